//! Compares descriptor modes and networks on real and synthetic data: a program that measures
//! and prints (the README's table), not a test.
//!
//! Real: the 17 shared TUM fr3 frames as a two-pass revisit sequence (odd frames forward, even
//! frames backward; loops verified by the real poses: within 1 m and 30°, at least 2 s apart).
//! Synthetic: `ecm-lcd synth` defaults but 600 frames at 5 Hz, 3 laps (default pose criteria).
//!
//!     cargo run --release --example compare_descriptors

use std::path::Path;

use anyhow::Result;
use ecm_lcd::config::Params;
use ecm_lcd::eval::{evaluate, loop_truth_from_poses, revisit::write_two_pass, PoseLoopCriteria};
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::model::weights::resolve;
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::replay::run_source;
use ecm_lcd::synth::{write_tum_folder, Scene, SynthConfig};

fn main() -> Result<()> {
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    ecm_lcd::runtime::init_threads(None);
    let shared = ecm_lcd::runtime::shared_dirs().into_iter().next().expect("the shared data folder (../shared) is needed");
    let dir = tempfile::tempdir()?;
    let real = dir.path().join("fr3_two_pass");
    write_two_pass(&shared.join("data/tum/fr3_long_office_household"), &real, 1.0, 0.05)?;
    let synthetic = dir.path().join("synthetic");
    let scene = Scene::new(SynthConfig { frames: 600, laps: 3, rate_hz: 5.0, ..SynthConfig::default() })?;
    write_tum_folder(&scene, &synthetic)?;

    let weights = resolve::resolve(None)?;
    let datasets: [(&str, &Path, PoseLoopCriteria, &[(&str, &str)]); 2] = [
        (
            "TUM fr3 two-pass (real)",
            &real,
            PoseLoopCriteria { min_gap_s: 2.0, ..PoseLoopCriteria::default() },
            &[("detector.min_history", "2"), ("detector.exclude_recent.count", "1"), ("detector.exclude_recent.seconds", "2")],
        ),
        ("synthetic 600 frames, 3 laps", &synthetic, PoseLoopCriteria::default(), &[]),
    ];
    println!("| data | network | descriptor | dim | queries (with loop) | recall@1 | recall@100%P | AP |");
    println!("|---|---|---|---|---|---|---|---|");
    for (name, path, criteria, overrides) in datasets {
        let groundtruth = read_groundtruth(&path.join("groundtruth.txt"))?;
        for arch in ["ecmobilenet", "mobilenetv2"] {
            for mode in ["paper", "l2", "spatial"] {
                let mut params = Params::default();
                params.set_from_str("arch", arch).map_err(anyhow::Error::msg)?;
                params.set_from_str("descriptor.mode", mode).map_err(anyhow::Error::msg)?;
                for (k, v) in overrides {
                    params.set_from_str(k, v).map_err(anyhow::Error::msg)?;
                }
                let mut pipeline = Pipeline::with_weights(params, weights.clone())?;
                let run = run_source(&mut pipeline, path, None, false)?;
                let truth = loop_truth_from_poses(&run.frame_stamps, &groundtruth, &criteria);
                let m = evaluate(&run.query_results(), &truth)?;
                let f = |v: Option<f64>| v.map(|v| format!("{v:.3}")).unwrap_or_else(|| "-".into());
                println!(
                    "| {name} | {arch} | {mode} | {} | {} ({}) | {} | {} | {} |",
                    pipeline.descriptor().dim(),
                    m.queries,
                    m.positives,
                    f(m.recall_at_1),
                    f(m.recall_at_100_precision),
                    f(m.average_precision)
                );
            }
        }
    }
    Ok(())
}
