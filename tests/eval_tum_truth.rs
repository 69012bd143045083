//! Pose-based loop truth on the real TUM frames in ../shared: stamp matching against the
//! 100 Hz ground truth, including a frame taken before the ground truth starts.

use ecm_lcd::eval::{loop_truth_from_poses, poses_at_stamps, PoseLoopCriteria};
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::types::Stamp;
use std::path::PathBuf;

fn shared_dir() -> PathBuf {
    let beside = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared");
    if beside.is_dir() {
        return beside;
    }
    match std::env::var_os("ECM_LCD_SHARED") {
        Some(dir) => PathBuf::from(dir),
        None => panic!("shared test data missing: neither {} nor $ECM_LCD_SHARED exists", beside.display()),
    }
}

#[test]
fn tum_frames_take_the_nearest_ground_truth_pose() {
    let dir = shared_dir().join("data/tum/fr3_long_office_household");
    let rgb = std::fs::read_to_string(dir.join("rgb.txt"))
        .unwrap_or_else(|e| panic!("{}: {e}", dir.join("rgb.txt").display()));
    let stamps: Vec<Stamp> = rgb
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| Stamp::parse_secs(l.split_whitespace().next().unwrap()).unwrap())
        .collect();
    assert_eq!(stamps.len(), 17);
    let groundtruth = read_groundtruth(&dir.join("groundtruth.txt")).unwrap();
    let poses = poses_at_stamps(&stamps, &groundtruth, 0.05);
    // The first image (…980.72) precedes the first pose (…981.02) by 0.3 s: no pose.
    assert!(poses[0].is_none());
    assert!(poses[1..].iter().all(Option::is_some));
    // Image …981.726650 is 3.4 ms from the pose at …981.7300 and 6 ms from …981.7206.
    assert!((poses[1].unwrap().translation.x - -0.5947).abs() < 1e-12);
    // 17 s of frames: no pair is 20 s apart, so no loops; frame 0 is unknown.
    let truth = loop_truth_from_poses(&stamps, &groundtruth, &PoseLoopCriteria::default());
    assert_eq!(truth.positive_queries().count(), 0);
    assert_eq!(truth.unknown_queries().iter().copied().collect::<Vec<_>>(), vec![0]);
}
