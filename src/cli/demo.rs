//! `ecm-lcd demo`: the README's main command. Replays the bundled sample in `bags/`, prints the
//! loop candidates and the precision-recall summary against the sample's ground truth, and writes
//! the candidates, the curve and its plot.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use super::eval::{pipeline_for_pose_truth, print_summary, refuse_stored_keyframes};
use super::replay::{write_candidates_csv, SourceArgs};
use ecm_lcd::eval::{evaluate, loop_truth_from_poses, plot_pr_curve, write_curve_csv, PoseLoopCriteria};
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::replay::run_source;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Sequence to replay.
    #[arg(long, default_value = "bags/sample_loop.bag")]
    pub source: PathBuf,
    /// Its ground-truth poses (TUM format).
    #[arg(long, default_value = "bags/sample_loop_groundtruth.txt")]
    pub groundtruth: PathBuf,
    /// Folder for demo_candidates.csv, demo_pr.csv and demo_pr.png.
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    #[command(flatten)]
    pub source_args: SourceArgs,
}

/// `path` as given, or inside the source tree this binary was built from (so `demo` works from
/// any folder of a checkout).
fn bundled(path: &Path) -> PathBuf {
    if path.exists() || path.is_absolute() {
        return path.to_path_buf();
    }
    let in_tree = Path::new(env!("CARGO_MANIFEST_DIR")).join(path);
    if in_tree.exists() {
        in_tree
    } else {
        path.to_path_buf()
    }
}

pub fn run(args: Args) -> Result<()> {
    let (source, groundtruth) = (bundled(&args.source), bundled(&args.groundtruth));
    // Before anything is read: the outputs can all be written, and none is an input.
    if args.out.exists() && !args.out.is_dir() {
        bail!("--out {} is a file; demo writes three files into a folder of that name", args.out.display());
    }
    let (candidates, curve, plot) =
        (args.out.join("demo_candidates.csv"), args.out.join("demo_pr.csv"), args.out.join("demo_pr.png"));
    let outputs = [("demo_candidates.csv", candidates.as_path()), ("demo_pr.csv", &curve), ("demo_pr.png", &plot)];
    let mut inputs = vec![groundtruth.as_path()];
    inputs.extend(args.source_args.files_read());
    ecm_lcd::io::output::ensure_outputs(&[&source], &inputs, args.source_args.db.as_deref(), &outputs)?;
    let criteria = PoseLoopCriteria::default();
    let mut pipeline = pipeline_for_pose_truth(&args.source_args, &criteria)?;
    refuse_stored_keyframes(&pipeline, "demo")?;
    let run = run_source(&mut pipeline, &source, &args.source_args.topics(), !args.source_args.quiet)?;
    if let Some(error) = &run.error {
        anyhow::bail!("{} broke off after {} frames: {error}", source.display(), run.frames);
    }
    if let Some(unreadable) = run.unreadable.summary(ecm_lcd::io::FRAMES) {
        log::warn!("{}: {unreadable}", source.display());
    }
    println!("{} frames, {} keyframes from {}", run.frames, run.keyframes.len(), source.display());
    println!("{} loop candidates (query -> match, score):", run.candidates.len());
    for c in &run.candidates {
        println!(
            "  keyframe {:>4} at {} -> keyframe {:>4} at {}  distance {:.3}  score {:.3}",
            c.query_id, c.query_stamp, c.match_id, c.match_stamp, c.distance, c.score
        );
    }
    let poses = read_groundtruth(&groundtruth).context("the demo's ground truth")?;
    let truth = loop_truth_from_poses(&run.frame_stamps, &poses, &criteria);
    let metrics = evaluate(&run.query_results(), &truth)?;
    let false_loops = run
        .candidates
        .iter()
        .filter(|c| truth.matches(c.query_id as usize).is_some_and(|m| !m.contains(&(c.match_id as usize))))
        .count();
    println!("\nagainst the ground-truth poses (same place: within 1 m and 30 degrees, at least 20 s apart):");
    println!("reported candidates      {} ({} false)", run.candidates.len(), false_loops);
    print_summary(&metrics, &run.mean_timings());
    write_candidates_csv(&run.candidates, &candidates)?;
    write_curve_csv(&metrics, &curve)?;
    plot_pr_curve(&metrics, &format!("ecm-lcd demo: {}", args.source.display()), &plot)?;
    println!("wrote {}, {} and {}", candidates.display(), curve.display(), plot.display());
    Ok(())
}
