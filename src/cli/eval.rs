//! `ecm-lcd eval`: runs the detector over a source and scores its loop candidates against ground
//! truth (poses or a loops file), writing the PR curve (CSV, PNG) and a JSON summary.
//!
//! Only the step "run the pipeline over the source and collect one `QueryResult` per query" is
//! the pipeline's; everything before (truth) and after (metrics, outputs) is here.
//! Not yet wired as a sub-command: the lead adds the `Command::Eval` variant together with that
//! pipeline step (see `run_with_results`).

use crate::eval::{
    evaluate, images_in_name_order, loop_truth_from_poses, plot_pr_curve, read_loops, read_tum_groundtruth,
    summary_json, write_curve_csv, write_summary_json, LoopTruth, Metrics, PoseLoopCriteria, QueryResult,
};
use crate::types::Stamp;
use anyhow::{bail, Result};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Sequence to replay (TUM folder, ROS 1 bag, ROS 2 bag); not used with --database/--queries.
    pub source: Option<PathBuf>,
    /// TUM ground-truth poses (`timestamp tx ty tz qx qy qz qw`); default: SOURCE/groundtruth.txt
    /// when SOURCE is a folder holding one.
    #[arg(long)]
    pub groundtruth: Option<PathBuf>,
    /// Explicit loop truth instead of poses: lines `query_index,match_index match_index ...`.
    #[arg(long)]
    pub loops: Option<PathBuf>,
    /// Database/query mode: folder of database images (name order); needs --queries and --loops.
    #[arg(long, requires_all = ["queries", "loops"], conflicts_with = "source")]
    pub database: Option<PathBuf>,
    /// Database/query mode: folder of query images (name order).
    #[arg(long, requires = "database")]
    pub queries: Option<PathBuf>,
    /// Write the JSON summary here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write the precision-recall plot (PNG) here.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Write the precision-recall curve (CSV `threshold,precision,recall`) here.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Pose truth: largest distance between camera centres of the same place (metres).
    #[arg(long, default_value_t = PoseLoopCriteria::default().max_distance_m)]
    pub max_distance: f64,
    /// Pose truth: largest angle between optical axes of the same place (degrees).
    #[arg(long, default_value_t = PoseLoopCriteria::default().max_angle_deg)]
    pub max_angle: f64,
    /// Pose truth: smallest time between a query and its match (seconds).
    #[arg(long, default_value_t = PoseLoopCriteria::default().min_gap_s)]
    pub min_gap: f64,
    /// Detector parameters (ROS 2 params YAML).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Image topic to read from a bag.
    #[arg(long)]
    pub topic: Option<String>,
}

impl Args {
    pub fn criteria(&self) -> Result<PoseLoopCriteria> {
        for (name, value) in [("--max-distance", self.max_distance), ("--max-angle", self.max_angle), ("--min-gap", self.min_gap)] {
            if !(value.is_finite() && value >= 0.0) {
                bail!("{name} must be a non-negative number, got {value}");
            }
        }
        Ok(PoseLoopCriteria {
            max_distance_m: self.max_distance,
            max_angle_deg: self.max_angle,
            min_gap_s: self.min_gap,
            ..PoseLoopCriteria::default()
        })
    }

    /// Database and query image paths in database/query mode, else `None`.
    pub fn database_and_queries(&self) -> Result<Option<(Vec<PathBuf>, Vec<PathBuf>)>> {
        match (&self.database, &self.queries) {
            (Some(database), Some(queries)) => Ok(Some((images_in_name_order(database)?, images_in_name_order(queries)?))),
            (None, None) => Ok(None),
            _ => bail!("--database and --queries go together"),
        }
    }

    /// Ground-truth file for sequence mode: --groundtruth, or SOURCE/groundtruth.txt.
    fn groundtruth_path(&self) -> Option<PathBuf> {
        self.groundtruth.clone().or_else(|| {
            let candidate = self.source.as_deref()?.join("groundtruth.txt");
            candidate.is_file().then_some(candidate)
        })
    }
}

/// The loop truth for these arguments. `query_stamps` are the stamps of the replayed frames in
/// replay order (sequence mode with poses; ignored with --loops).
pub fn load_truth(args: &Args, query_stamps: &[Stamp]) -> Result<LoopTruth> {
    if let Some(loops) = &args.loops {
        return read_loops(loops);
    }
    if args.database.is_some() {
        bail!("database/query mode needs --loops");
    }
    let Some(path) = args.groundtruth_path() else {
        bail!("no loop truth: give --loops FILE or --groundtruth FILE (or a SOURCE folder with groundtruth.txt)");
    };
    let poses = read_tum_groundtruth(&path)?;
    if poses.is_empty() {
        bail!("ground truth {} holds no poses", path.display());
    }
    Ok(loop_truth_from_poses(query_stamps, &poses, &args.criteria()?))
}

/// Scores the results, writes the requested outputs and logs the summary; `timings_ms` are
/// per-stage timings to include in the JSON.
pub fn run_with_results(args: &Args, truth: &LoopTruth, results: &[QueryResult], timings_ms: &[(&str, f64)]) -> Result<Metrics> {
    let metrics = evaluate(results, truth)?;
    write_outputs(args, &metrics, timings_ms)?;
    Ok(metrics)
}

fn write_outputs(args: &Args, metrics: &Metrics, timings_ms: &[(&str, f64)]) -> Result<()> {
    let summary = summary_json(metrics, timings_ms);
    if let Some(path) = &args.output {
        write_curve_csv(metrics, path)?;
    }
    if let Some(path) = &args.json {
        write_summary_json(path, &summary)?;
    }
    if let Some(path) = &args.plot {
        let title = args.source.as_deref().or(args.queries.as_deref()).map(display_name).unwrap_or_default();
        plot_pr_curve(metrics, &title, path)?;
    }
    log::info!("{summary}");
    Ok(())
}

fn display_name(path: &Path) -> String {
    path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| path.display().to_string())
}
