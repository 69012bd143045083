//! `ecm-lcd match`: each query frame's place among database frames, with no ground truth needed
//! (relocalising a new session against a map, merging two sessions): the database/query mode of
//! `eval`, its matches written as CSV instead of scored.

use super::replay::SourceArgs;
use anyhow::{Context, Result};
use ecm_lcd::eval::images_in_name_order;
use ecm_lcd::replay::run_database_queries;
use ecm_lcd::types::Stamp;
use std::io::Write;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The map: an image folder (name order, numbers by value: `2` before `10`), a TUM folder, a
    /// ROS 1 / ROS 2 bag (`--topic` names the image topic where a bag has several), or a keyframe
    /// database made with `--db` (read only; its keyframes are named by id and stamp).
    #[arg(long)]
    pub database: PathBuf,
    /// The frames to place on it, from the same kinds of source. Where they look like a walk, they
    /// are aligned with the database as a whole walk, else matched one by one (as `eval --database`).
    #[arg(long)]
    pub queries: PathBuf,
    /// Write the matches here (CSV); default: print them.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub source_args: SourceArgs,
}

/// The CSV columns: per query its index and frame, its best database frame (empty where none), the
/// match's score, and 1 where the score passes the threshold (`detector.min_score`, or
/// `detector.max_distance` as a score); then, where verification is on and the match passed it,
/// its inliers and the query camera's pose in the match camera's frame, as in `replay`'s CSV
/// (`inliers,qx,qy,qz,qw,tx,ty,tz,metric,cov_x_x,...`; with verification a match that fails it is
/// no match). A frame is named by its file in an image folder, elsewhere by its stamp in seconds (a
/// TUM folder's `rgb.txt` stamp, a bag message's header stamp).
pub fn header() -> Vec<String> {
    let matched = ["query", "query_frame", "match", "match_frame", "score", "accepted"];
    matched.into_iter().map(str::to_string).chain(ecm_lcd::io::candidates::verification_columns()).collect()
}

pub fn run(args: Args) -> Result<()> {
    args.source_args.refuse_source_only("--database/--queries")?;
    let sources = [args.database.as_path(), args.queries.as_path()];
    let outputs: Vec<(&str, &std::path::Path)> =
        args.output.as_deref().map(|output| ("-o", output)).into_iter().collect();
    ecm_lcd::io::output::ensure_outputs(&sources, &args.source_args.files_read(), None, &outputs)?;
    let mut pipeline = args.source_args.pipeline()?;
    let run = run_database_queries(
        &mut pipeline,
        &args.database,
        &args.queries,
        &args.source_args.topics(),
        !args.source_args.quiet,
    )?;
    let database_names: std::collections::HashMap<u64, String> =
        run.database.iter().map(|&(id, _)| id).zip(frame_names(&args.database, &run.database)?).collect();
    let queries: Vec<(u64, Stamp)> = run.query_stamps.iter().enumerate().map(|(i, &s)| (i as u64, s)).collect();
    let query_names = frame_names(&args.queries, &queries)?;
    if let Some(unreadable) = run.unreadable_database.summary(("database frame", "database frames")) {
        log::warn!("{}: {unreadable}; no query can match them", args.database.display());
    }
    if let Some(unreadable) = run.unreadable_queries.summary(("query", "queries")) {
        log::warn!("{}: {unreadable}; they have no row", args.queries.display());
    }
    let min_score = pipeline.detector().min_score();
    if let (Some(error), true) = (&run.error, run.results.is_empty()) {
        anyhow::bail!("{error} (no query was matched; the output was left as it was)");
    }
    let sink: Box<dyn Write> = match &args.output {
        Some(path) => {
            Box::new(std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?)
        }
        None => Box::new(std::io::stdout().lock()),
    };
    // The csv crate quotes image names that hold commas or quotes.
    let mut csv = csv::Writer::from_writer(sink);
    csv.write_record(header())?;
    for (result, verified) in run.results.iter().zip(&run.verified) {
        let (matched, match_frame, score, accepted) = match result.best {
            Some((matched, score)) => (
                matched.to_string(),
                database_names[&(matched as u64)].clone(),
                format!("{score:.6}"),
                u8::from(score >= min_score).to_string(),
            ),
            None => (String::new(), String::new(), String::new(), "0".to_string()),
        };
        let query = result.query.to_string();
        let record = [query, query_names[result.query].clone(), matched, match_frame, score, accepted];
        csv.write_record(record.into_iter().chain(ecm_lcd::io::candidates::verification_fields(*verified)))?;
    }
    csv.flush().context("cannot write the matches")?;
    let accepted = run.results.iter().filter(|r| r.best.is_some_and(|(_, score)| score >= min_score)).count();
    let policy = super::eval::policy_name(pipeline.params(), true);
    let verified = run.verified.iter().flatten().count();
    let verified = match pipeline.verifies() {
        true => format!("; {verified} verified ({} no match)", run.results.len() - verified),
        false => String::new(),
    };
    log::info!(
        "{} queries matched against {} database frames ({policy}){verified}; {accepted} at or above the threshold {min_score}",
        run.results.len(),
        run.database.len()
    );
    match run.error {
        Some(error) => anyhow::bail!("{error} (the matches of the queries before it were written)"),
        None => Ok(()),
    }
}

/// The names of `source`'s `frames` ([`header`]), each its index in the source and the stamp it
/// was read with.
fn frame_names(source: &Path, frames: &[(u64, Stamp)]) -> Result<Vec<String>> {
    if ecm_lcd::io::is_image_folder(source) {
        // A frame's index is its image's place in name order.
        let files = images_in_name_order(source)?;
        let name = |index: u64| {
            let path =
                files.get(index as usize).with_context(|| format!("{} changed while it was read", source.display()))?;
            Ok(path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default())
        };
        return frames.iter().map(|&(index, _)| name(index)).collect();
    }
    Ok(frames.iter().map(|(_, stamp)| stamp.to_string()).collect())
}
