//! What the measuring examples share: the two evaluation sets and one evaluation run.
//!
//! Real: the 17 shared TUM fr3 frames as a two-pass revisit sequence (odd frames forward, even
//! frames backward; loops verified by the real poses: within 1 m and 30°, at least 2 s apart).
//! Synthetic: `ecm-lcd synth` defaults (seed 1) but 600 frames at 5 Hz, 3 laps (default pose criteria),
//! and the same with the `hard` preset (identical rooms, night laps, offset laps, 160x120 grayscale,
//! noise and blur).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use ecm_lcd::config::Params;
use ecm_lcd::eval::{evaluate, loop_truth_from_poses, revisit::write_two_pass, LoopTruth, Metrics, PoseLoopCriteria};
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::model::weights::resolve::Resolved;
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::replay::{run_source, ReplayRun};
use ecm_lcd::synth::{write_tum_folder, Scene, SynthConfig};

/// One evaluation sequence with its loop criteria and detector overrides.
pub struct EvalSet {
    pub name: &'static str,
    pub path: PathBuf,
    pub criteria: PoseLoopCriteria,
    pub overrides: &'static [(&'static str, &'static str)],
}

/// What every measuring example starts with: logging (warnings), the thread pool, and both sets
/// written to a temporary folder, which lives as long as the returned guard.
pub fn start() -> Result<(tempfile::TempDir, Vec<EvalSet>)> {
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    ecm_lcd::runtime::init_threads(None);
    let dir = tempfile::tempdir()?;
    let sets = eval_sets(dir.path())?;
    Ok((dir, sets))
}

/// Writes both sets under `dir`.
fn eval_sets(dir: &Path) -> Result<Vec<EvalSet>> {
    let shared =
        ecm_lcd::runtime::shared_dirs().into_iter().next().context("the shared data folder (../shared) is needed")?;
    let real = dir.join("fr3_two_pass");
    write_two_pass(&shared.join("data/tum/fr3_long_office_household"), &real, 1.0, 0.05)?;
    let synthetic = dir.join("synthetic");
    let scene = Scene::new(synthetic_sequence(SynthConfig::default()))?;
    write_tum_folder(&scene, &synthetic)?;
    let hard = dir.join("synthetic_hard");
    write_tum_folder(&Scene::new(synthetic_sequence(SynthConfig::hard()))?, &hard)?;
    Ok(vec![
        EvalSet {
            name: "TUM fr3 two-pass (real)",
            path: real,
            criteria: PoseLoopCriteria { min_gap_s: 2.0, ..PoseLoopCriteria::default() },
            overrides: &[
                ("detector.min_history", "2"),
                ("detector.exclude_recent.count", "1"),
                ("detector.exclude_recent.seconds", "2"),
            ],
        },
        EvalSet {
            name: "synthetic 600 frames, 3 laps",
            path: synthetic,
            criteria: PoseLoopCriteria::default(),
            overrides: &[],
        },
        EvalSet {
            name: "synthetic hard preset, 600 frames, 3 laps",
            path: hard,
            criteria: PoseLoopCriteria::default(),
            overrides: &[],
        },
    ])
}

/// The synthetic sequences' renderer settings: `base` (`synth`'s defaults or its hard preset) but
/// 600 frames at 5 Hz, 3 laps.
pub fn synthetic_sequence(base: SynthConfig) -> SynthConfig {
    SynthConfig { frames: 600, laps: 3, rate_hz: 5.0, ..base }
}

/// Replays `set` with `weights` as `arch` and the descriptor `mode` (`None`: the default);
/// returns the metrics and the descriptor's dimension.
#[allow(dead_code)] // each example builds this module for itself, and not every one calls this
pub fn evaluate_on(set: &EvalSet, arch: &str, mode: Option<&str>, weights: &Resolved) -> Result<(Metrics, usize)> {
    let replayed = replay_on(set, arch, mode, weights, None)?;
    Ok((evaluate(&replayed.run.query_results(), &replayed.truth)?, replayed.pipeline.descriptor().dim()))
}

/// One replay of a set: the pipeline after it, what it found, and the set's loop truth.
pub struct Replayed {
    pub pipeline: Pipeline,
    pub run: ReplayRun,
    pub truth: LoopTruth,
}

/// Replays `set` as [`evaluate_on`] does; with `db`, every keyframe is also stored there.
pub fn replay_on(
    set: &EvalSet,
    arch: &str,
    mode: Option<&str>,
    weights: &Resolved,
    db: Option<&Path>,
) -> Result<Replayed> {
    let groundtruth = read_groundtruth(&set.path.join("groundtruth.txt"))?;
    let mut params = Params::default();
    params.set_from_str("arch", arch).map_err(anyhow::Error::msg)?;
    // These programs study descriptors, so the database keeps them exactly.
    params.set_from_str("detector.storage", "f32").map_err(anyhow::Error::msg)?;
    if let Some(mode) = mode {
        params.set_from_str("descriptor.mode", mode).map_err(anyhow::Error::msg)?;
    }
    for (k, v) in set.overrides {
        params.set_from_str(k, v).map_err(anyhow::Error::msg)?;
    }
    // As `ecm-lcd eval` scores: no match younger than the truth's gap.
    set.criteria.exclude_younger_than_the_gap(&mut params)?;
    let mut pipeline = Pipeline::with_weights(params, weights.clone())?;
    if let Some(db) = db {
        pipeline.open_store(db)?;
    }
    let run = run_source(&mut pipeline, &set.path, &Default::default(), false)?;
    let truth = loop_truth_from_poses(&run.frame_stamps, &groundtruth, &set.criteria);
    Ok(Replayed { pipeline, run, truth })
}

/// A figure with three decimals, `-` when undefined.
pub fn figure(v: Option<f64>) -> String {
    v.map(|v| format!("{v:.3}")).unwrap_or_else(|| "-".into())
}
