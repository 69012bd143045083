//! `ecm-lcd match`: each query image's place among database images, with no ground truth needed
//! (relocalising a new session against a map, merging two sessions): the database/query mode of
//! `eval`, its matches written as CSV instead of scored.

use super::replay::SourceArgs;
use anyhow::{Context, Result};
use ecm_lcd::eval::images_in_name_order;
use ecm_lcd::replay::run_database_queries;
use std::io::Write;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Folder of database images (name order, numbers by value: `2` before `10`).
    #[arg(long)]
    pub database: PathBuf,
    /// Folder of query images (name order, numbers by value). Where they look like a walk, they are
    /// aligned with the database as a whole walk, else matched one by one (as `eval --database`).
    #[arg(long)]
    pub queries: PathBuf,
    /// Write the matches here (CSV); default: print them.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub source_args: SourceArgs,
}

/// The CSV header: per query its index and image, its best database image (empty where none), the
/// match's score, and 1 where the score passes the threshold (`detector.min_score`, or
/// `detector.max_distance` as a score).
pub const HEADER: &str = "query,query_image,match,match_image,score,accepted";

pub fn run(args: Args) -> Result<()> {
    args.source_args.refuse_source_only()?;
    let inputs: Vec<&Path> =
        [args.source_args.config.as_deref(), args.source_args.weights.as_deref()].into_iter().flatten().collect();
    if let Some(output) = &args.output {
        ecm_lcd::io::output::ensure_not_an_input(output, &inputs)?;
    }
    let (database, queries) = (images_in_name_order(&args.database)?, images_in_name_order(&args.queries)?);
    let mut pipeline = args.source_args.pipeline()?;
    let (results, _) = run_database_queries(&mut pipeline, &database, &queries)?;
    let min_score = pipeline.detector().min_score();
    let sink: Box<dyn Write> = match &args.output {
        Some(path) => {
            Box::new(std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?)
        }
        None => Box::new(std::io::stdout().lock()),
    };
    // The csv crate quotes image names that hold commas or quotes.
    let mut csv = csv::Writer::from_writer(sink);
    csv.write_record(HEADER.split(','))?;
    let name = |path: &Path| path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    for result in &results {
        let (matched, match_image, score, accepted) = match result.best {
            Some((matched, score)) => (
                matched.to_string(),
                name(&database[matched]),
                format!("{score:.6}"),
                u8::from(score >= min_score).to_string(),
            ),
            None => (String::new(), String::new(), String::new(), "0".to_string()),
        };
        let query = result.query.to_string();
        csv.write_record([&query, &name(&queries[result.query]), &matched, &match_image, &score, &accepted])?;
    }
    csv.flush().context("cannot write the matches")?;
    let accepted = results.iter().filter(|r| r.best.is_some_and(|(_, score)| score >= min_score)).count();
    let policy = super::eval::policy_name(pipeline.params(), true);
    log::info!(
        "{} queries matched against {} database images ({policy}); {accepted} at or above the threshold {min_score}",
        queries.len(),
        database.len()
    );
    Ok(())
}
