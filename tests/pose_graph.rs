//! The paper's Fig. 11, end to end through the binary: a drifted two-lap synthetic sequence with depth
//! is replayed with verification on (metric relative poses by PnP), and `pose-graph` corrects the
//! odometry with the loops. Checks: the relative poses against the exact ground truth, the ATE at
//! least 5x lower after the back end, and our ATE equal to `evo_ape`'s (the standard tool, PyPI, in a
//! test virtualenv) within 1e-6 m. And a real case: the shared TUM fr3 frames as a two-pass revisit,
//! with their ground-truth poses plus injected drift as the odometry and no depth, corrected with
//! loops verified up to scale.

mod support;

use std::path::Path;
use std::process::Command;

use ecm_lcd::eval::revisit::write_two_pass;
use ecm_lcd::io::candidates::read_candidates_csv;
use ecm_lcd::io::tum::{read_groundtruth, write_trajectory};
use ecm_lcd::synth::OdometryDrift;

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// evo's APE RMSE (translation part, SE(3) Umeyama alignment: `evo_ape tum GT EST -a`), printed with
/// full precision through evo's Python API.
const EVO_APE: &str = r#"
import sys
from evo.core import metrics, sync
from evo.tools import file_interface
ref = file_interface.read_tum_trajectory_file(sys.argv[1])
for path in sys.argv[2:]:
    est = file_interface.read_tum_trajectory_file(path)
    ref_synced, est_synced = sync.associate_trajectories(ref, est, max_diff=0.01)
    est_synced.align(ref_synced, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref_synced, est_synced))
    print(repr(ape.get_statistic(metrics.StatisticsType.rmse)))
"#;

/// The renderer's camera: focal 0.82 * width, principal point at the centre.
const SYNTHETIC_CAMERA: [&str; 8] = [
    "--param",
    "camera.fx=262.4",
    "--param",
    "camera.fy=262.4",
    "--param",
    "camera.cx=160",
    "--param",
    "camera.cy=120",
];

/// `pose-graph --json` on these files, with `more` arguments; its summary.
fn pose_graph(
    odometry: &Path,
    candidates: &Path,
    groundtruth: &Path,
    corrected: &Path,
    more: &[&str],
) -> serde_json::Value {
    let mut args = vec![
        "pose-graph",
        "--odometry",
        odometry.to_str().unwrap(),
        "--candidates",
        candidates.to_str().unwrap(),
        "--groundtruth",
        groundtruth.to_str().unwrap(),
        "-o",
        corrected.to_str().unwrap(),
        "--json",
    ];
    args.extend(more);
    serde_json::from_slice(&support::ecm_lcd_ok(&args).stdout).unwrap()
}

#[test]
fn loops_with_metric_poses_remove_the_drift_and_the_ate_agrees_with_evo() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    let seq_arg = seq.to_str().unwrap();
    support::ecm_lcd_ok(&["synth", "-o", seq_arg, "--frames", "400", "--laps", "2", "--rate", "5", "--depth"]);
    let candidates = dir.path().join("candidates.csv");
    let mut replay = vec!["replay", seq_arg, "-o", candidates.to_str().unwrap()];
    replay.extend(SYNTHETIC_CAMERA);
    support::ecm_lcd_ok(&replay);

    // Every reported candidate is verified with a metric pose; the poses are close to the truth.
    let found = read_candidates_csv(&candidates).unwrap();
    assert!(found.len() >= 30, "{} candidates", found.len());
    let truth = read_groundtruth(&seq.join("groundtruth.txt")).unwrap();
    let pose_at =
        |stamp| truth.iter().find(|(s, _)| *s == stamp).map(|(_, p)| *p).expect("a ground-truth pose at every frame");
    let (mut rotation_deg, mut translation_m) = (Vec::new(), Vec::new());
    let (mut rotation_nees, mut translation_nees) = (Vec::new(), Vec::new());
    for c in &found {
        let pose = c.verified.and_then(|v| v.pose).expect("verified with a pose");
        assert!(pose.metric, "depth given: metric pose for {} -> {}", c.query_id, c.match_id);
        let exact = pose_at(c.match_stamp).inverse() * pose_at(c.query_stamp);
        rotation_deg.push(exact.rotation.angle_to(&pose.rotation).to_degrees());
        translation_m.push((exact.translation.vector - pose.translation).norm());
        // The CSV carries each metric pose's covariance; the errors in its units.
        let (r, t) = pose.normalised_squared_errors(&exact).expect("a covariance read back from the CSV");
        rotation_nees.push(r);
        translation_nees.push(t);
    }
    let (rotation, translation) = (median(rotation_deg), median(translation_m));
    let (rotation_nees, translation_nees) = (median(rotation_nees), median(translation_nees));
    println!(
        "{} metric loops: median rotation error {rotation:.3} deg, translation error {translation:.4} m; \
         median normalised squared error {rotation_nees:.1} / {translation_nees:.1} (2.4 if the covariance is right)",
        found.len()
    );
    assert!(rotation <= 1.0 && translation <= 0.05, "median errors {rotation} deg, {translation} m");
    // Standard deviations within 2x of the errors' (a right covariance's median is 2.4, so under
    // 4 x 2.4): it understates the errors of rendered views somewhat, but not by more.
    assert!(
        rotation_nees < 4.0 * 2.4 && translation_nees < 4.0 * 2.4,
        "median normalised squared errors {rotation_nees:.1} / {translation_nees:.1}"
    );

    let corrected = dir.path().join("corrected.txt");
    let plot = dir.path().join("fig11.png");
    let odometry = seq.join("odometry.txt");
    let groundtruth = seq.join("groundtruth.txt");
    let summary = pose_graph(&odometry, &candidates, &groundtruth, &corrected, &["--plot", plot.to_str().unwrap()]);
    println!("{summary}");
    let before = summary["ate_rmse_before_m"].as_f64().unwrap();
    let after = summary["ate_rmse_after_m"].as_f64().unwrap();
    assert!(before > 0.2, "the odometry drifts: ATE {before} m");
    assert!(after * 5.0 <= before, "ATE {before} m -> {after} m: not 5x lower");
    assert_eq!(summary["poses"].as_u64(), Some(400));
    assert!(summary["loops_kept"].as_u64().unwrap() * 10 >= summary["loops"].as_u64().unwrap() * 9, "{summary}");
    assert!(image::open(&plot).unwrap().width() == 900);

    let python = support::venv_python("test-venv-evo", &["evo==1.38.1"]);
    let script = dir.path().join("evo_ape.py");
    std::fs::write(&script, EVO_APE).unwrap();
    // evo writes its settings under $HOME; keep them out of the user's.
    let evo = Command::new(python)
        .arg(&script)
        .arg(&groundtruth)
        .arg(&odometry)
        .arg(&corrected)
        .env("HOME", dir.path())
        .output()
        .unwrap();
    assert!(evo.status.success(), "evo failed:\n{}", String::from_utf8_lossy(&evo.stderr));
    let evo_rmse: Vec<f64> =
        String::from_utf8(evo.stdout).unwrap().lines().map(|l| l.trim().parse().unwrap()).collect();
    println!("evo_ape RMSE: odometry {}, corrected {}", evo_rmse[0], evo_rmse[1]);
    assert!((evo_rmse[0] - before).abs() <= 1e-6, "odometry ATE: ours {before}, evo {}", evo_rmse[0]);
    assert!((evo_rmse[1] - after).abs() <= 1e-6, "corrected ATE: ours {after}, evo {}", evo_rmse[1]);
}

/// A monocular camera's case on real imagery: no depth, so every verified loop is up to scale. The 17
/// shared TUM fr3 frames replayed odd-forward then even-backward (their folder named as TUM names fr3
/// sequences, so the fr3 intrinsics come from the name), the odometry their ground truth with
/// `synth`'s drift on every step, and `pose-graph` with its defaults.
#[test]
fn loops_up_to_scale_correct_a_drifted_odometry_on_real_tum_frames() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("rgbd_dataset_freiburg3_two_pass");
    write_two_pass(&support::shared_dir().join("data/tum/fr3_long_office_household"), &seq, 1.0, 0.05).unwrap();
    let candidates = dir.path().join("candidates.csv");
    support::ecm_lcd_ok(&[
        "replay",
        seq.to_str().unwrap(),
        "-o",
        candidates.to_str().unwrap(),
        // Keyframes one second apart: a short history, and only the previous keyframe too recent.
        "--param",
        "detector.min_history=2",
        "--param",
        "detector.exclude_recent.count=1",
        "--param",
        "detector.exclude_recent.seconds=2",
    ]);
    let found = read_candidates_csv(&candidates).unwrap();
    let verified = found.iter().filter(|c| c.verified.and_then(|v| v.pose).is_some_and(|p| !p.metric)).count();
    println!("{verified} of {} candidates verified up to scale", found.len());
    assert!(verified >= 5, "{verified} of {} candidates verified up to scale", found.len());
    let groundtruth = seq.join("groundtruth.txt");
    let truth = read_groundtruth(&groundtruth).unwrap();
    let poses: Vec<_> = truth.iter().map(|(_, p)| *p).collect();
    let drift = OdometryDrift { yaw_deg_per_m: DRIFT_DEG_PER_M, ..OdometryDrift::default() };
    for seed in 1..=3 {
        let odometry: Vec<_> = truth.iter().map(|(s, _)| *s).zip(drift.apply(&poses, seed)).collect();
        let odometry_path = dir.path().join(format!("odometry{seed}.txt"));
        write_trajectory(&odometry_path, &odometry).unwrap();
        let summary = pose_graph(&odometry_path, &candidates, &groundtruth, &dir.path().join("corrected.txt"), &[]);
        println!("seed {seed}: {summary}");
        let before = summary["ate_rmse_before_m"].as_f64().unwrap();
        let after = summary["ate_rmse_after_m"].as_f64().unwrap();
        // Every loop edge is up to scale, and every verified candidate is an edge or counted out.
        assert_eq!(summary["loops_up_to_scale"], summary["loops"], "{summary}");
        let accounted: u64 = ["loops", "loops_unmatched", "loops_on_one_pose", "loops_implausible"]
            .iter()
            .map(|key| summary[key].as_u64().unwrap())
            .sum();
        assert_eq!(accounted, verified as u64, "{summary}");
        assert!(after * 3.0 <= before, "seed {seed}: ATE {before} m -> {after} m");
    }
}

/// Heading drift injected into the TUM odometry, degrees per metre.
const DRIFT_DEG_PER_M: f64 = 5.0;

/// The synthetic two-lap sequence without depth, as a monocular camera sees it: every loop is verified
/// up to scale, and the back end still removes most of the drift.
#[test]
fn loops_up_to_scale_remove_the_drift_of_the_synthetic_sequence() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    support::ecm_lcd_ok(&["synth", "-o", seq.to_str().unwrap(), "--frames", "400", "--laps", "2", "--rate", "5"]);
    let candidates = dir.path().join("candidates.csv");
    let mut replay = vec!["replay", seq.to_str().unwrap(), "-o", candidates.to_str().unwrap()];
    replay.extend(SYNTHETIC_CAMERA);
    support::ecm_lcd_ok(&replay);
    let found = read_candidates_csv(&candidates).unwrap();
    assert!(found.iter().all(|c| c.verified.and_then(|v| v.pose).is_some_and(|p| !p.metric)));
    let corrected = dir.path().join("corrected.txt");
    let summary = pose_graph(&seq.join("odometry.txt"), &candidates, &seq.join("groundtruth.txt"), &corrected, &[]);
    println!("{summary}");
    let before = summary["ate_rmse_before_m"].as_f64().unwrap();
    let after = summary["ate_rmse_after_m"].as_f64().unwrap();
    assert_eq!(summary["loops_up_to_scale"].as_u64(), Some(found.len() as u64));
    assert!(found.len() >= 40, "{} loops", found.len());
    assert!(after * 4.0 <= before, "ATE {before} m -> {after} m");
}

/// The hard preset with depth: identical rooms, so some wrong loops pass verification with metric
/// poses metres off. The robust back end still lowers the drift instead of bending the map to them,
/// with the loops up to scale and without them.
#[test]
fn wrong_metric_loops_of_look_alike_rooms_do_not_bend_the_map() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    let seq_arg = seq.to_str().unwrap();
    let synth = ["synth", "--preset", "hard", "-o", seq_arg, "--frames", "600", "--laps", "3", "--rate", "5"];
    support::ecm_lcd_ok(&[&synth[..], &["--depth"]].concat());
    let candidates = dir.path().join("candidates.csv");
    support::ecm_lcd_ok(&[
        "replay",
        seq_arg,
        "-o",
        candidates.to_str().unwrap(),
        // The hard preset's 160x120 camera.
        "--param",
        "camera.fx=131.2",
        "--param",
        "camera.fy=131.2",
        "--param",
        "camera.cx=79.5",
        "--param",
        "camera.cy=59.5",
    ]);
    let (odometry, groundtruth) = (seq.join("odometry.txt"), seq.join("groundtruth.txt"));
    for metric_only in [false, true] {
        let more: &[&str] = if metric_only { &["--metric-only"] } else { &[] };
        let summary = pose_graph(&odometry, &candidates, &groundtruth, &dir.path().join("corrected.txt"), more);
        println!("metric only {metric_only}: {summary}");
        let before = summary["ate_rmse_before_m"].as_f64().unwrap();
        let after = summary["ate_rmse_after_m"].as_f64().unwrap();
        assert!(summary["loops"].as_u64().unwrap() >= 15, "{summary}");
        assert!(after * 2.0 <= before, "ATE {before} m -> {after} m");
    }
}
