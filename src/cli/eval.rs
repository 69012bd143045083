//! `ecm-lcd eval`: runs the detector over a source and scores its loop candidates against ground
//! truth (poses or a loops file), writing the PR curve (CSV, PNG) and a JSON summary.
//!
//! Only the step "run the pipeline over the source and collect one `QueryResult` per query" is
//! the pipeline's; everything before (truth) and after (metrics, outputs) is here.

use super::replay::SourceArgs;
use anyhow::{bail, Result};
use ecm_lcd::config::{ParamValue, Params};
use ecm_lcd::eval::{
    evaluate, loop_truth_from_poses, plot_pr_curve, read_loops, summary_json, write_curve_csv, LoopTruth, Metrics,
    PoseLoopCriteria, QueryResult,
};
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::replay::{run_database_queries, run_source};
use ecm_lcd::types::Stamp;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Sequence to replay (TUM folder, ROS 1 bag, ROS 2 bag); not used with --database/--queries.
    pub source: Option<PathBuf>,
    /// TUM ground-truth poses (`timestamp tx ty tz qx qy qz qw`); default: SOURCE/groundtruth.txt
    /// when SOURCE is a folder holding one.
    #[arg(long, conflicts_with = "loops")]
    pub groundtruth: Option<PathBuf>,
    /// Explicit loop truth instead of poses: lines `query_index,match_index match_index ...`.
    #[arg(long)]
    pub loops: Option<PathBuf>,
    /// Database/query mode: the database, an image folder (name order, numbers by value: `2` before
    /// `10`), a TUM folder, a ROS 1 / ROS 2 bag (`--topic` names a bag's image topic) or a keyframe
    /// database (`--db`); needs --queries and --loops, whose indexes count the frames of each from 0
    /// (a keyframe database's: its keyframe ids).
    #[arg(long, requires_all = ["queries", "loops"], conflicts_with = "source")]
    pub database: Option<PathBuf>,
    /// Database/query mode: the queries, from the same kinds of source. Where they look like a walk,
    /// they are aligned with the database as a whole walk (at any speed, along all or part of its
    /// route, either way), else matched one by one (`detector.sequence.length` 0; 1 or more sets it).
    #[arg(long, requires = "database")]
    pub queries: Option<PathBuf>,
    /// Print the summary as JSON (keys `queries`, `recall_at_1`, `recall_at_100_precision`,
    /// `average_precision`, ...) instead of text.
    #[arg(long)]
    pub json: bool,
    /// Write the precision-recall plot (PNG) here.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Write the precision-recall curve (CSV `threshold,precision,recall`) here.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Pose truth: largest distance between camera centres of the same place (metres).
    #[arg(long, default_value_t = PoseLoopCriteria::default().max_distance_m, conflicts_with = "loops")]
    pub max_distance: f64,
    /// Pose truth: largest angle between optical axes of the same place (degrees).
    #[arg(long, default_value_t = PoseLoopCriteria::default().max_angle_deg, conflicts_with = "loops")]
    pub max_angle: f64,
    /// Pose truth: smallest time between a query and its match (seconds).
    #[arg(long, default_value_t = PoseLoopCriteria::default().min_gap_s, conflicts_with = "loops")]
    pub min_gap: f64,
    #[command(flatten)]
    pub source_args: SourceArgs,
}

impl Args {
    pub fn criteria(&self) -> Result<PoseLoopCriteria> {
        for (name, value) in
            [("--max-distance", self.max_distance), ("--max-angle", self.max_angle), ("--min-gap", self.min_gap)]
        {
            if !(value.is_finite() && value >= 0.0) {
                bail!("{name} must be a non-negative number, got {value}");
            }
        }
        // The angle between two viewing axes is at most 180 degrees; a larger bound would wrap.
        if self.max_angle > 180.0 {
            bail!("--max-angle must be at most 180 (degrees between the viewing axes), got {}", self.max_angle);
        }
        Ok(PoseLoopCriteria {
            max_distance_m: self.max_distance,
            max_angle_deg: self.max_angle,
            min_gap_s: self.min_gap,
            ..PoseLoopCriteria::default()
        })
    }

    /// The database and query sources in database/query mode, else `None`.
    pub fn database_and_queries(&self) -> Result<Option<(&Path, &Path)>> {
        match (&self.database, &self.queries) {
            (Some(database), Some(queries)) => {
                self.source_args.refuse_source_only("--database/--queries")?;
                Ok(Some((database, queries)))
            }
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
    let poses = ecm_lcd::io::tum::read_groundtruth(&path)?;
    if poses.is_empty() {
        bail!("ground truth {} holds no poses", path.display());
    }
    Ok(loop_truth_from_poses(query_stamps, &poses, &args.criteria()?))
}

/// Scores the results, writes the requested outputs and logs the summary; `timings_ms` are
/// per-stage timings to include in the JSON, `params` what the run used (the JSON names the
/// matching policy and every parameter).
/// `end`: how the sources' reading ended, which the JSON carries, so a script reading only the JSON
/// knows.
pub fn run_with_results(
    args: &Args,
    truth: &LoopTruth,
    results: &[QueryResult],
    timings_ms: &[(&str, f64)],
    params: &Params,
    end: &SourcesEnd,
) -> Result<Metrics> {
    let metrics = evaluate(results, truth)?;
    write_outputs(args, &metrics, timings_ms, params, end)?;
    Ok(metrics)
}

/// How the reading of a run's sources ended.
#[derive(Default)]
pub struct SourcesEnd<'a> {
    /// Why a source ended early, where it did (the figures count what was read): the JSON says
    /// `"complete": false` and carries it as `broke_off`.
    pub broke_off: Option<&'a str>,
    /// Frames (queries in the database/query mode) skipped because their images could not be
    /// decoded (`unreadable_frames` in the JSON): they are not scored.
    pub unreadable_frames: usize,
    /// In the database/query mode, database frames skipped so (`unreadable_database_frames`).
    pub unreadable_database_frames: Option<usize>,
    /// The replay's wall time in seconds, where there was one (`wall_s`).
    pub wall_secs: Option<f64>,
}

/// `walk`, `sequence` or `single-image`: how a query was matched under `params`. `database_mode`:
/// queries against a database (`--database`), where `detector.sequence.length` still 0 after the
/// run means that the queries were aligned as a walk (`run_database_queries`).
pub fn policy_name(params: &Params, database_mode: bool) -> &'static str {
    match params.get("detector.sequence.length") {
        Some(ParamValue::Integer(0)) if database_mode => "walk",
        Some(ParamValue::Integer(length)) if length > 1 => "sequence",
        _ => "single-image",
    }
}

fn write_outputs(
    args: &Args,
    metrics: &Metrics,
    timings_ms: &[(&str, f64)],
    params: &Params,
    end: &SourcesEnd,
) -> Result<()> {
    let mut summary = summary_json(metrics, timings_ms);
    summary["policy"] = serde_json::json!(policy_name(params, args.database.is_some()));
    summary["parameters"] = params.to_json();
    summary["complete"] = serde_json::json!(end.broke_off.is_none());
    summary["unreadable_frames"] = serde_json::json!(end.unreadable_frames);
    if let Some(frames) = end.unreadable_database_frames {
        summary["unreadable_database_frames"] = serde_json::json!(frames);
    }
    if let Some(why) = end.broke_off {
        summary["broke_off"] = serde_json::json!(why);
    }
    if let Some(seconds) = end.wall_secs {
        summary["wall_s"] = serde_json::json!(seconds);
    }
    if let Some(path) = &args.output {
        write_curve_csv(metrics, path)?;
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print_summary(metrics, timings_ms);
        if let Some(seconds) = end.wall_secs {
            println!("replay wall time        {seconds:.2} s");
        }
        let detector = params.detector();
        let policy = match policy_name(params, args.database.is_some()) {
            "sequence" => format!("sequence of {}", detector.sequence_length),
            other => other.to_string(),
        };
        println!(
            "policy                  {policy} (descriptor {}, threshold {:?})",
            params.descriptor_mode(),
            detector.threshold
        );
    }
    if let Some(path) = &args.plot {
        let title = args.source.as_deref().or(args.queries.as_deref()).map(display_name).unwrap_or_default();
        plot_pr_curve(metrics, &title, path)?;
    }
    Ok(())
}

/// The figures as text.
pub fn print_summary(metrics: &Metrics, timings_ms: &[(&str, f64)]) {
    let why_none = match metrics.queries {
        0 => "n/a (no query scored)",
        _ => "n/a (no loops in the truth)",
    };
    let show = |v: Option<f64>| v.map(|v| format!("{v:.3}")).unwrap_or_else(|| why_none.into());
    let unknown_matches = match metrics.unknown_matches {
        0 => String::new(),
        n => format!(", {n} whose best match has none"),
    };
    println!(
        "queries                 {} ({} with a true loop, {} without ground truth{unknown_matches})",
        metrics.queries, metrics.positives, metrics.unknown
    );
    println!("recall@1                {}", show(metrics.recall_at_1));
    println!("recall at 100% precision {}", show(metrics.recall_at_100_precision));
    println!("average precision       {}", show(metrics.average_precision));
    let timings: Vec<String> = timings_ms.iter().map(|(name, ms)| format!("{name} {ms:.2}")).collect();
    println!("per keyframe            {}", timings.join(", "));
}

/// Refuses a `--db` that already holds keyframes: frames stored by an earlier run are skipped, not
/// replayed, so they would not be scored and the figures would be of part of the sequence.
pub fn refuse_stored_keyframes(pipeline: &Pipeline, command: &str) -> Result<()> {
    if let Some(store) = pipeline.store().filter(|store| !store.is_empty()) {
        bail!(
            "{} already holds {} keyframes, which {command} would skip and not score; give a new database (or none)",
            store.path().display(),
            store.len()
        );
    }
    Ok(())
}

/// `ecm-lcd eval`: replays the source (or embeds the database and query folders), then scores.
pub fn run(args: Args) -> Result<()> {
    if let Some(plot) = &args.plot {
        ecm_lcd::io::output::ensure_png(plot, "--plot")?;
    }
    // Before anything is opened: no output may be an input, a source's file or the other output.
    let sources: Vec<&Path> =
        [&args.source, &args.database, &args.queries].into_iter().flatten().map(PathBuf::as_path).collect();
    let mut inputs: Vec<&Path> = [&args.loops, &args.groundtruth].into_iter().flatten().map(PathBuf::as_path).collect();
    inputs.extend(args.source_args.files_read());
    let outputs: Vec<(&str, &Path)> = [("-o", &args.output), ("--plot", &args.plot)]
        .into_iter()
        .filter_map(|(flag, path)| Some((flag, path.as_deref()?)))
        .collect();
    ecm_lcd::io::output::ensure_outputs(&sources, &inputs, args.source_args.db.as_deref(), &outputs)?;
    // Before the pipeline opens (and creates) a --db that database/query mode refuses.
    let database_and_queries = args.database_and_queries()?;
    let mut pipeline = match (&args.source, &args.loops) {
        (Some(_), None) => pipeline_for_pose_truth(&args.source_args, &args.criteria()?)?,
        _ => args.source_args.pipeline()?,
    };
    refuse_stored_keyframes(&pipeline, "eval")?;
    if let Some((database, queries)) = database_and_queries {
        let mut truth = load_truth(&args, &[])?;
        let run = run_database_queries(
            &mut pipeline,
            database,
            queries,
            &args.source_args.topics(),
            !args.source_args.quiet,
        )?;
        // Every database frame read counts, unreadable ones too: a loops file names them.
        let unreadable_ids = &run.unreadable_database.indexes;
        let read_ids = run.database.iter().map(|&(id, _)| id as usize).chain(unreadable_ids.iter().copied());
        let references = read_ids.map(|id| id + 1).max().unwrap_or(0);
        if let Some(error) = &run.error {
            if run.results.is_empty() {
                bail!("{error}");
            }
            // As a replay that broke off: the queries read are evaluated, the truth cut to them.
            log::warn!("{error}; evaluating the {} queries read", run.results.len());
            truth = truth.between(0..run.query_stamps.len(), 0..references);
        }
        if let Some(unreadable) = run.unreadable_database.summary(("database frame", "database frames")) {
            log::warn!("{}: {unreadable}; no query can match them", database.display());
        }
        if let Some(unreadable) = run.unreadable_queries.summary(("query", "queries")) {
            log::warn!("{}: {unreadable}; they are not scored", queries.display());
        }
        truth.check_within(run.query_stamps.len(), references)?;
        truth.without_references(unreadable_ids);
        let end = SourcesEnd {
            broke_off: run.error.as_deref(),
            unreadable_frames: run.unreadable_queries.count(),
            unreadable_database_frames: Some(run.unreadable_database.count()),
            wall_secs: None,
        };
        run_with_results(&args, &truth, &run.results, &run.timings(), pipeline.params(), &end)?;
        return match &run.error {
            Some(error) => Err(broke_off(error, run.results.len())),
            None => Ok(()),
        };
    }
    let Some(source) = &args.source else { bail!("give a SOURCE to replay, or --database and --queries") };
    let run = run_source(&mut pipeline, source, &args.source_args.topics(), !args.source_args.quiet)?;
    if let Some(error) = &run.error {
        log::warn!("{} broke off after {} frames; evaluating those: {error}", source.display(), run.frames);
    }
    if let Some(unreadable) = run.unreadable.summary(ecm_lcd::io::FRAMES) {
        log::warn!("{}: {unreadable}; they are neither scored nor matched", source.display());
    }
    if let Some(why) = run.why_nothing_could_match(pipeline.params()) {
        log::warn!("{}: {why}", source.display());
    }
    let mut truth = load_truth(&args, &run.frame_stamps)?;
    truth.check_within(run.frame_stamps.len(), run.frame_stamps.len())?;
    truth.without_references(&run.unreadable.indexes);
    let results = run.query_results();
    if let Some(loops) = &args.loops {
        warn_unscored_loops(loops, &truth, &results, &run.unreadable.indexes);
    }
    let timings = run.mean_timings();
    let end = SourcesEnd {
        broke_off: run.error.as_deref(),
        unreadable_frames: run.unreadable.count(),
        unreadable_database_frames: None,
        wall_secs: Some(run.wall_secs),
    };
    run_with_results(&args, &truth, &results, &timings, pipeline.params(), &end)?;
    match &run.error {
        Some(error) => Err(broke_off(error, run.frames)),
        None => Ok(()),
    }
}

/// Says how many queries with a loop in the loops file are not keyframes: a replay scores the
/// keyframes the detector selects, so those frames' truth goes unused.
/// Frames skipped as `unreadable` are warned about on their own.
fn warn_unscored_loops(
    loops: &std::path::Path,
    truth: &LoopTruth,
    results: &[ecm_lcd::eval::QueryResult],
    unreadable: &[usize],
) {
    let scored: std::collections::BTreeSet<usize> =
        results.iter().map(|r| r.query).chain(unreadable.iter().copied()).collect();
    let listed = truth.positive_queries().count();
    let unscored = truth.positive_queries().filter(|q| !scored.contains(q)).count();
    if unscored > 0 {
        log::warn!(
            "{unscored} of the {listed} queries with a loop in {} are not keyframes and are not scored: eval scores \
             the keyframes the detector selects (every frame is one with selection.min_period 0, \
             selection.every_nth 1 and selection.novelty_max_score 1)",
            loops.display()
        );
    }
}

/// The error of a run whose source broke off after `read` frames or queries, once their figures are
/// out: the command fails, as a replay or `match` does, so that a script does not take a part for
/// the whole.
fn broke_off(error: &dyn std::fmt::Display, read: usize) -> anyhow::Error {
    anyhow::anyhow!("{error} (the figures above count the {read} read before)")
}

/// The pipeline of `source_args` for scoring against loop truth from poses under `criteria`: it does
/// not look for matches younger than the truth's gap
/// ([`PoseLoopCriteria::exclude_younger_than_the_gap`]; logged where that raises the setting).
pub fn pipeline_for_pose_truth(source_args: &SourceArgs, criteria: &PoseLoopCriteria) -> Result<Pipeline> {
    let mut params = source_args.params()?;
    let excluded = params.detector().exclude_recent_secs;
    if excluded > criteria.min_gap_s {
        log::warn!(
            "the loop truth counts matches from {} s apart (--min-gap), but the detector excludes keyframes younger \
             than {excluded} s (detector.exclude_recent.seconds): loops between the two cannot be found, and recall \
             counts them as missed",
            criteria.min_gap_s
        );
    }
    if let Some(configured) = criteria.exclude_younger_than_the_gap(&mut params)? {
        log::info!(
            "the loop truth counts no match younger than {} s, so the detector does not look there either \
             (detector.exclude_recent.seconds {configured} -> {})",
            criteria.min_gap_s,
            criteria.min_gap_s
        );
    }
    source_args.pipeline_with(params)
}

fn display_name(path: &Path) -> String {
    path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| path.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct TestCli {
        #[command(flatten)]
        args: Args,
    }

    fn parse(argv: &[&str]) -> Result<Args, clap::Error> {
        TestCli::try_parse_from(std::iter::once("eval").chain(argv.iter().copied())).map(|c| c.args)
    }

    #[test]
    fn truth_comes_from_loops_or_the_source_folders_groundtruth() {
        let dir = tempfile::tempdir().unwrap();
        let loops = dir.path().join("loops.csv");
        std::fs::write(&loops, "3,0 1\n").unwrap();
        let args = parse(&["seq", "--loops", loops.to_str().unwrap()]).unwrap();
        let truth = load_truth(&args, &[]).unwrap();
        assert_eq!(truth.positive_queries().collect::<Vec<_>>(), vec![3]);

        // Without --loops: SOURCE/groundtruth.txt, with the distance/angle/gap options applied.
        std::fs::write(dir.path().join("groundtruth.txt"), "10.0 0 0 0 0 0 0 1\n15.0 0.3 0 0 0 0 0 1\n").unwrap();
        let stamps = [Stamp::from_secs_f64(10.0), Stamp::from_secs_f64(15.0)];
        let source = dir.path().to_str().unwrap();
        let truth = load_truth(&parse(&[source]).unwrap(), &stamps).unwrap();
        assert_eq!(truth.positive_queries().count(), 0, "default 20 s gap");
        let truth = load_truth(&parse(&[source, "--min-gap", "4"]).unwrap(), &stamps).unwrap();
        assert_eq!(truth.positive_queries().collect::<Vec<_>>(), vec![1]);
        let truth = load_truth(&parse(&[source, "--min-gap", "4", "--max-distance", "0.2"]).unwrap(), &stamps).unwrap();
        assert_eq!(truth.positive_queries().count(), 0);

        let err = load_truth(&parse(&["/nonexistent-folder"]).unwrap(), &stamps).unwrap_err();
        assert!(err.to_string().contains("no loop truth"), "{err:#}");
        let err = load_truth(&parse(&[source, "--min-gap=-1"]).unwrap(), &stamps).unwrap_err();
        assert!(err.to_string().contains("--min-gap"), "{err:#}");
    }

    #[test]
    fn database_mode_needs_queries_and_loops_and_refuses_what_only_a_replay_uses() {
        assert!(parse(&["--database", "db"]).is_err());
        assert!(parse(&["--database", "db", "--queries", "q"]).is_err(), "needs --loops");
        assert!(parse(&["seq", "--database", "db", "--queries", "q", "--loops", "l"]).is_err(), "not with SOURCE");
        let args = parse(&["--database", "db", "--queries", "q", "--loops", "l", "--topic", "/camera/image"]).unwrap();
        let (database, queries) = args.database_and_queries().unwrap().unwrap();
        assert_eq!((database, queries), (Path::new("db"), Path::new("q")));
        let with_poses = ["--database", "db", "--queries", "q", "--loops", "l", "--poses", "odometry.txt"];
        let err = parse(&with_poses).unwrap().database_and_queries().unwrap_err();
        assert!(err.to_string().contains("--poses applies to a replayed SOURCE"), "{err:#}");
        assert!(parse(&["seq"]).unwrap().database_and_queries().unwrap().is_none());
    }

    #[test]
    fn results_are_scored_and_written() {
        let dir = tempfile::tempdir().unwrap();
        let (csv, png) = (dir.path().join("pr.csv"), dir.path().join("pr.png"));
        let args = parse(&["seq", "-o", csv.to_str().unwrap(), "--json", "--plot", png.to_str().unwrap()]).unwrap();
        let truth = ecm_lcd::eval::parse_loops("2,0\n3,1\n").unwrap();
        let results = [QueryResult { query: 2, best: Some((0, 0.8)) }, QueryResult { query: 3, best: Some((0, 0.6)) }];
        let metrics =
            run_with_results(&args, &truth, &results, &[("total", 5.0)], &Params::default(), &SourcesEnd::default())
                .unwrap();
        assert_eq!(metrics.recall_at_1, Some(0.5));
        assert!(std::fs::read_to_string(&csv).unwrap().starts_with("threshold,precision,recall\n0.8,1,0.5\n"));
        let summary = summary_json(&metrics, &[("total", 5.0)]);
        assert_eq!(summary["average_precision"], 0.5);
        assert_eq!(summary["timing_ms"]["total"], 5.0);
        assert!(png.is_file());
    }
}
