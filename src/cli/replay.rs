//! `ecm-lcd replay`: runs every frame of a source through the pipeline offline and writes the
//! loop candidates as CSV.
//!
//! The CSV is written incrementally, flushed after each keyframe's candidates, so what a killed replay
//! emitted is on disk. With `--db`, keyframes are stored as they are accepted, and a replay of a source
//! whose frames are already stored skips them ([`ecm_lcd::replay`]) and appends to an existing output CSV
//! instead of replacing it, so a crashed replay restarted with the same arguments completes the file.

use std::path::{Path, PathBuf};

use anyhow::Result;

use ecm_lcd::config::{Params, NODE_NAME};
pub use ecm_lcd::io::candidates::write_candidates_csv;
use ecm_lcd::io::candidates::CandidateCsv;
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::replay::run_source_with;

/// Options every command that replays a source shares.
#[derive(clap::Args, Debug, Clone)]
pub struct SourceArgs {
    /// Image topic to read from a bag (default: the bag's one image topic).
    #[arg(long)]
    pub topic: Option<String>,
    /// Depth image topic of a bag (16UC1 millimetres or 32FC1 metres), paired with each image by the
    /// nearest stamp within 20 ms; with camera intrinsics, verified loops get metric poses.
    #[arg(long, value_name = "TOPIC")]
    pub depth_topic: Option<String>,
    /// The tracker's poses of the frames: a TUM trajectory (`timestamp tx ty tz qx qy qz qw`,
    /// camera-to-world), each frame taking the pose within 20 ms of its stamp. With
    /// `verification.max_drift` or `.max_rotation_drift`, loops that do not fit the tracker's
    /// trajectory are rejected.
    #[arg(long, value_name = "FILE")]
    pub poses: Option<PathBuf>,
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
    /// Persistent keyframe database (SQLite; created if missing): stored keyframes are the starting
    /// history, every new keyframe is committed before its candidates are written, and frames already
    /// stored are skipped. Must have been made with the same weights, arch, descriptor mode and input size.
    #[arg(long, value_name = "PATH")]
    pub db: Option<PathBuf>,
}

impl SourceArgs {
    pub fn topics(&self) -> ecm_lcd::io::Topics {
        ecm_lcd::io::Topics { image: self.topic.clone(), depth: self.depth_topic.clone(), poses: self.poses.clone() }
    }

    pub fn params(&self) -> Result<Params> {
        params_from(self.config.as_deref(), &self.params)
    }

    /// The files the options name for reading (not the sources, nor `--db`): `--config`,
    /// `--weights`, `--poses`.
    pub fn files_read(&self) -> Vec<&Path> {
        [self.config.as_deref(), self.weights.as_deref(), self.poses.as_deref()].into_iter().flatten().collect()
    }

    /// An error naming the first option given that only a replayed SOURCE uses, for commands that
    /// read other inputs (`what`: a database and queries, or images to learn from), which would
    /// otherwise ignore it (`--topic` serves all: the image topic of bags; `--depth-topic` a bag's).
    pub fn refuse_source_only(&self, what: &str) -> Result<()> {
        let source_only = [("--poses", self.poses.is_some()), ("--db", self.db.is_some())];
        match source_only.iter().find(|(_, given)| *given) {
            Some((flag, _)) => anyhow::bail!("{flag} applies to a replayed SOURCE, not to {what}"),
            None => Ok(()),
        }
    }

    pub fn pipeline(&self) -> Result<Pipeline> {
        self.pipeline_with(self.params()?)
    }

    /// [`SourceArgs::pipeline`] with `params` in place of the options' own.
    pub fn pipeline_with(&self, params: Params) -> Result<Pipeline> {
        let mut pipeline = Pipeline::new(params, self.weights.as_deref())?;
        pipeline.set_reference(self.reference);
        if let Some(db) = &self.db {
            pipeline.open_store(db)?;
        }
        Ok(pipeline)
    }
}

/// The parameters of `--config FILE` (or the defaults) with each `--param NAME=VALUE` applied.
pub fn params_from(config: Option<&Path>, assignments: &[String]) -> Result<Params> {
    let mut params = match config {
        Some(path) => Params::load(path, NODE_NAME)?,
        None => Params::default(),
    };
    for assignment in assignments {
        params.set_assignment(assignment)?;
    }
    Ok(params)
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
    // Before anything is opened: neither output may be one of the inputs (or the other output).
    let outputs: Vec<(&str, &Path)> = args.output.as_deref().map(|output| ("-o", output)).into_iter().collect();
    ecm_lcd::io::output::ensure_outputs(
        &[&args.source],
        &args.source_args.files_read(),
        args.source_args.db.as_deref(),
        &outputs,
    )?;
    let mut pipeline = args.source_args.pipeline()?;
    let resuming = pipeline.store().is_some_and(|store| !store.is_empty());
    let stored = match pipeline.store() {
        Some(store) if resuming => store.stored_candidates()?,
        _ => None,
    };
    // The CSV is opened at the first keyframe (or at the end of a source that yields none), so a
    // source that cannot be opened or read from its first frame leaves an existing file as it was.
    let open_csv = |stored: Option<Vec<_>>| match (&args.output, stored) {
        // Resuming a store that holds every emitted candidate: the CSV is rewritten from it, so a
        // line lost to a kill between a keyframe's commit and its write comes back.
        (Some(path), Some(stored)) => CandidateCsv::rewrite(path, &stored),
        (Some(path), None) if resuming => CandidateCsv::to_file(path, true),
        (Some(path), None) => CandidateCsv::rewrite(path, &[]),
        // Printed, the earlier run's candidates come first, so the output is the whole run's too.
        (None, stored) => {
            let mut out = CandidateCsv::to_stdout()?;
            out.write(stored.as_deref().unwrap_or_default())?;
            Ok(out)
        }
    };
    let mut stored = Some(stored);
    let mut csv: Option<CandidateCsv> = None;
    let run = run_source_with(
        &mut pipeline,
        &args.source,
        &args.source_args.topics(),
        !args.source_args.quiet,
        |_, candidates| {
            let out = match &mut csv {
                Some(out) => out,
                None => csv.insert(open_csv(stored.take().flatten())?),
            };
            out.write(candidates)
        },
    )?;
    // Nothing decoded before the source broke off: an earlier output stays as it was.
    let untouched = csv.is_none() && run.frames == run.unreadable.count() && run.error.is_some();
    if csv.is_none() && !untouched {
        open_csv(stored.take().flatten())?;
    }
    let t = run.mean();
    let verification = if pipeline.verifies() {
        let odometry = match pipeline.params().verification(None).and_then(|v| v.drift) {
            Some(_) if args.source_args.poses.is_none() => format!(
                " (an odometry check is set, but without --poses this run's frames have no tracker pose{})",
                match run.unchecked_by_odometry {
                    0 => String::new(),
                    n => format!("; {n} candidates were not checked by it"),
                }
            ),
            Some(_) => format!(
                " ({} of them by the odometry check; {} candidates were not checked by it, for want of a tracker pose)",
                run.rejected_by_odometry, run.unchecked_by_odometry
            ),
            None => String::new(),
        };
        format!(", verification {:.2} ms; {} candidates failed verification{odometry}", t.verification_ms, run.rejected)
    } else {
        String::new()
    };
    eprintln!(
        "{} frames{}, {} keyframes, {} loop candidates in {:.1} s (per keyframe: network {:.1} ms, descriptor {:.2} ms, detector {:.2} ms{verification}){}",
        run.frames,
        if run.skipped > 0 { format!(" ({} processed by the earlier run, skipped)", run.skipped) } else { String::new() },
        run.keyframes.len(),
        run.candidates.len(),
        run.wall_secs,
        t.network_ms,
        t.descriptor_ms,
        t.detector_ms,
        args.output.as_ref().filter(|_| !untouched).map(|p| format!("; wrote {}", p.display())).unwrap_or_default()
    );
    if let Some(unreadable) = run.unreadable.summary(ecm_lcd::io::FRAMES) {
        log::warn!("{}: {unreadable}", args.source.display());
    }
    if let Some(why) = run.why_nothing_could_match(pipeline.params()) {
        log::warn!("{}: {why}", args.source.display());
    }
    if let Some(error) = run.error {
        anyhow::bail!(
            "{} broke off after {} frames ({}): {error}",
            args.source.display(),
            run.frames,
            if untouched { "the output was left as it was" } else { "results for those were written" }
        );
    }
    Ok(())
}
