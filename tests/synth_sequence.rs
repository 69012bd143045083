//! The synthetic sequence end to end: the `synth` command writes a TUM folder whose files agree
//! with each other and whose ground truth has loops exactly where the laps revisit places.

use ecm_lcd::eval::{loop_truth_from_poses, PoseLoopCriteria};
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::synth::{Scene, SynthConfig};
use ecm_lcd::types::Stamp;
use std::process::Command;

#[test]
fn synth_command_writes_a_consistent_tum_folder() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("seq");
    let status = Command::new(env!("CARGO_BIN_EXE_ecm-lcd"))
        .args(["synth", "-o"])
        .arg(&out)
        .args(["--frames", "24", "--laps", "2", "--seed", "5", "--width", "80", "--height", "60", "--rate", "10"])
        .status()
        .unwrap();
    assert!(status.success());
    let rgb = std::fs::read_to_string(out.join("rgb.txt")).unwrap();
    let entries: Vec<(&str, &str)> =
        rgb.lines().filter(|l| !l.starts_with('#')).map(|l| l.split_once(' ').unwrap()).collect();
    assert_eq!(entries.len(), 24);
    let scene = Scene::new(SynthConfig {
        frames: 24,
        laps: 2,
        seed: 5,
        width: 80,
        height: 60,
        rate_hz: 10.0,
        ..SynthConfig::default()
    })
    .unwrap();
    for (index, (stamp, path)) in entries.iter().enumerate() {
        assert_eq!(Stamp::parse_secs(stamp).unwrap(), scene.stamp(index));
        let image = image::open(out.join(path)).unwrap().to_rgb8();
        assert_eq!(image, scene.render(index), "frame {index} on disk differs from the renderer");
    }
    let truth = read_groundtruth(&out.join("groundtruth.txt")).unwrap();
    assert_eq!(truth.len(), 24);
    for (index, (stamp, pose)) in truth.iter().enumerate() {
        assert_eq!(*stamp, scene.stamp(index));
        let expected = scene.pose(index);
        assert!((pose.translation.vector - expected.translation.vector).norm() < 1e-12);
        assert!(pose.rotation.angle_to(&expected.rotation) < 1e-9);
    }
    // A second run into the same folder is refused rather than mixing two sequences.
    let again = Command::new(env!("CARGO_BIN_EXE_ecm-lcd")).args(["synth", "-o"]).arg(&out).output().unwrap();
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("already holds a sequence"));
}

#[test]
fn ground_truth_loops_join_the_laps() {
    // 3 laps of 300 frames at 30 Hz: 10 s per lap, so a 5 s gap keeps only other laps.
    let config = SynthConfig { frames: 900, laps: 3, ..SynthConfig::default() };
    let scene = Scene::new(config).unwrap();
    let stamps: Vec<Stamp> = (0..scene.len()).map(|i| scene.stamp(i)).collect();
    let poses: Vec<_> = (0..scene.len()).map(|i| (scene.stamp(i), scene.pose(i))).collect();
    let criteria =
        PoseLoopCriteria { max_distance_m: 0.5, max_angle_deg: 20.0, min_gap_s: 5.0, ..PoseLoopCriteria::default() };
    let truth = loop_truth_from_poses(&stamps, &poses, &criteria);
    // The first lap only revisits its own start at its very end (the path is closed).
    for q in 0..280 {
        assert!(truth.matches(q).unwrap().is_empty(), "first-lap frame {q} visits a new place");
    }
    assert!(truth.matches(299).unwrap().contains(&0), "the end of the first lap closes on its start");
    for q in 300..900 {
        let matches = truth.matches(q).unwrap();
        assert!(matches.contains(&(q - 300)), "frame {q} must match the same place one lap earlier");
        // Every match lies in an earlier lap, within a few frames of the same place.
        for &m in matches {
            let along = (q - m) % 300;
            assert!(along <= 15 || along >= 285, "frame {q} matched {m}, {along} frames off the same place");
        }
    }
}

/// The `hard` preset is hard for the default detector, and what makes it hard is the preset: the
/// same path, frames and seed without it are easy. Both written by the `synth` command, evaluated by
/// `eval --json` with the default configuration.
#[test]
fn the_hard_preset_is_hard_for_the_default_detector() {
    let dir = tempfile::tempdir().unwrap();
    let shared =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/models/mobilenet_v2_1.0_224_quant.tflite");
    assert!(shared.is_file(), "shared weights missing at {}: tests need ../shared (see README)", shared.display());
    let recall_at_1 = |preset: &str| {
        let out = dir.path().join(preset);
        let ecm_lcd = |args: &[&str]| {
            let output = Command::new(env!("CARGO_BIN_EXE_ecm-lcd"))
                .args(args)
                .env("ECM_LCD_CACHE", dir.path().join("cache"))
                .env("RUST_LOG", "warn")
                .output()
                .unwrap();
            assert!(output.status.success(), "{args:?}: {}", String::from_utf8_lossy(&output.stderr));
            String::from_utf8(output.stdout).unwrap()
        };
        let out_arg = out.to_str().unwrap();
        ecm_lcd(&[
            "synth", "-o", out_arg, "--preset", preset, "--frames", "450", "--laps", "3", "--rate", "5", "--width",
            "160", "--height", "120",
        ]);
        let json = ecm_lcd(&["eval", out_arg, "--json", "--quiet", "--weights", shared.to_str().unwrap()]);
        let summary: serde_json::Value = serde_json::from_str(&json).unwrap();
        assert!(summary["positives"].as_u64().unwrap() >= 90, "laps 2 and 3 revisit lap 1: {summary}");
        summary["recall_at_1"].as_f64().unwrap()
    };
    let (easy, hard) = (recall_at_1("easy"), recall_at_1("hard"));
    println!("default detector recall@1: easy {easy:.3}, hard {hard:.3}");
    assert!(easy >= 0.95, "the easy sequence should be easy: recall@1 {easy}");
    assert!(hard <= 0.8, "the hard preset should be hard: recall@1 {hard}");
}
