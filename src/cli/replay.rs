//! `ecm-lcd replay`: runs every frame of a source through the pipeline offline and writes the
//! loop candidates as CSV.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::config::{Params, NODE_NAME};
use crate::pipeline::Pipeline;
use crate::replay::run_source;
use crate::types::LoopCandidate;

/// Options every command that replays a source shares.
#[derive(clap::Args, Debug, Clone)]
pub struct SourceArgs {
    /// Image topic to read from a bag (default: the bag's one image topic).
    #[arg(long)]
    pub topic: Option<String>,
    /// Parameters (a ROS 2 params file, section `ecm_lcd`); default: built-in defaults, which
    /// equal config/ecm_lcd.yaml.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override a parameter: `--param detector.min_score=0.9` (repeatable).
    #[arg(long = "param", value_name = "NAME=VALUE")]
    pub params: Vec<String>,
    /// Weights file (default: see README "Weights").
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// Run stock candle operations instead of the fast kernels (verification).
    #[arg(long)]
    pub reference: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

impl SourceArgs {
    pub fn params(&self) -> Result<Params> {
        let mut params = match &self.config {
            Some(path) => Params::load(path, NODE_NAME)?,
            None => Params::default(),
        };
        for assignment in &self.params {
            let (name, value) = assignment
                .split_once('=')
                .with_context(|| format!("--param {assignment}: expected NAME=VALUE"))?;
            params.set_from_str(name.trim(), value.trim()).map_err(|e| anyhow::anyhow!("--param {assignment}: {e}"))?;
        }
        Ok(params)
    }

    pub fn pipeline(&self) -> Result<Pipeline> {
        let mut pipeline = Pipeline::new(self.params()?, self.weights.as_deref())?;
        pipeline.set_reference(self.reference);
        Ok(pipeline)
    }
}

/// Writes candidates as CSV: `query_id,query_stamp,match_id,match_stamp,distance,score`.
pub fn write_candidates_csv(candidates: &[LoopCandidate], path: &Path) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let mut out = csv::Writer::from_path(path).with_context(|| format!("cannot write {}", path.display()))?;
    out.write_record(["query_id", "query_stamp", "match_id", "match_stamp", "distance", "score"])?;
    for c in candidates {
        out.write_record([
            c.query_id.to_string(),
            c.query_stamp.to_string(),
            c.match_id.to_string(),
            c.match_stamp.to_string(),
            format!("{:.6}", c.distance),
            format!("{:.6}", c.score),
        ])?;
    }
    out.flush().with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct Args {
    /// TUM folder, ROS 1 bag, ROS 2 bag (folder, .db3 or .mcap), or a folder of images.
    pub source: PathBuf,
    #[command(flatten)]
    pub source_args: SourceArgs,
    /// Output CSV of loop candidates (default: print them).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
}

pub fn run(args: Args) -> Result<()> {
    let mut pipeline = args.source_args.pipeline()?;
    let run = run_source(&mut pipeline, &args.source, args.source_args.topic.as_deref(), !args.source_args.quiet)?;
    match &args.output {
        Some(path) => write_candidates_csv(&run.candidates, path)?,
        None => {
            println!("query_id,query_stamp,match_id,match_stamp,distance,score");
            for c in &run.candidates {
                println!("{},{},{},{},{:.6},{:.6}", c.query_id, c.query_stamp, c.match_id, c.match_stamp, c.distance, c.score);
            }
        }
    }
    let t = run.mean_timings();
    eprintln!(
        "{} frames, {} keyframes, {} loop candidates in {:.1} s (per keyframe: network {:.1} ms, descriptor {:.2} ms, detector {:.2} ms){}",
        run.frames,
        run.keyframes.len(),
        run.candidates.len(),
        run.wall_secs,
        t[0].1,
        t[1].1,
        t[2].1,
        args.output.as_ref().map(|p| format!("; wrote {}", p.display())).unwrap_or_default()
    );
    if let Some(error) = run.error {
        anyhow::bail!("{} broke off after {} frames (results for those were written): {error}", args.source.display(), run.frames);
    }
    Ok(())
}
