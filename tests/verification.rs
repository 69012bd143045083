//! Geometric verification on real frames from ../shared: the TUM desk orbit's one revisit passes and
//! every wrong top-1 match is rejected; on the TUM fr3 two-pass, with the published fr3 intrinsics,
//! the verified relative poses agree with the ground-truth poses.

use std::path::{Path, PathBuf};

use ecm_lcd::config::Params;
use ecm_lcd::eval::revisit::write_two_pass;
use ecm_lcd::eval::{evaluate, loop_truth_from_poses, Metrics, PoseLoopCriteria, QueryResult};
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::model::weights::resolve;
use ecm_lcd::pipeline::{Input, Pipeline};
use ecm_lcd::replay::{run_source, ReplayRun};
use ecm_lcd::synth::{write_tum_folder, Scene, SynthConfig};
use ecm_lcd::types::{DepthImage, Stamp};

mod support;

fn shared() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared");
    assert!(
        dir.join("data/real").is_dir(),
        "shared data missing at {}: tests need ../shared (see README)",
        dir.display()
    );
    dir
}

fn pipeline(overrides: &[(&str, &str)]) -> Pipeline {
    let mut params = Params::default();
    for (name, value) in overrides {
        params.set_from_str(name, value).unwrap();
    }
    let weights = resolve::load_file(&shared().join("models/mobilenet_v2_1.0_224_quant.tflite")).unwrap();
    Pipeline::with_weights(params, weights).unwrap()
}

/// Every eligible top-1 match becomes a candidate (`min_score` 0), so verification alone decides.
const PERMISSIVE: (&str, &str) = ("detector.min_score", "0");

/// The desk orbit's ten frames (one revisit, frame 9 of frame 0): searched from the third frame on,
/// skipping only the three newest (no stamps: an image folder).
const ORBIT_RECENCY: [(&str, &str); 3] =
    [("detector.min_history", "2"), ("detector.exclude_recent.count", "3"), ("detector.exclude_recent.seconds", "0")];

/// The TUM fr3 two-pass sequence (frames one second apart) written into `dir`, its frame count, and
/// the parameters that verify it with every top-1 match a candidate.
fn two_pass(dir: &Path) -> (PathBuf, usize, [(&'static str, &'static str); 5]) {
    let seq = dir.join("two_pass");
    let frames = write_two_pass(&shared().join("data/tum/fr3_long_office_household"), &seq, 1.0, 0.05).unwrap();
    let overrides = [
        ("detector.min_history", "2"),
        ("detector.exclude_recent.count", "1"),
        ("detector.exclude_recent.seconds", "2"),
        PERMISSIVE,
        ("camera.preset", "tum_fr3"),
    ];
    (seq, frames, overrides)
}

#[test]
fn the_orbit_revisit_is_verified_and_the_wrong_matches_are_not() {
    let orbit = shared().join("data/real/tum_fr3_desk_orbit");
    let recency = ORBIT_RECENCY;
    let mut unverified = pipeline(&[recency[0], recency[1], recency[2], PERMISSIVE, ("verification.mode", "off")]);
    let appearance = run_source(&mut unverified, &orbit.join("rgb"), &Default::default(), false).unwrap();
    assert!(appearance.candidates.len() >= 4, "{:?}", appearance.candidates);
    assert!(appearance.candidates.iter().all(|c| c.verified.is_none()));
    assert!(appearance.candidates.iter().any(|c| (c.query_id, c.match_id) == (9, 0)));

    // auto: on, because the preset gives the intrinsics. Only each keyframe's best match is tried
    // first, to compare with the appearance candidates.
    let only_best = ("verification.candidates", "1");
    let preset = ("camera.preset", "tum_fr3");
    let mut verifying = pipeline(&[recency[0], recency[1], recency[2], PERMISSIVE, preset, only_best]);
    assert!(verifying.verifies());
    let verified = run_source(&mut verifying, &orbit.join("rgb"), &Default::default(), false).unwrap();
    let pairs: Vec<(u64, u64)> = verified.candidates.iter().map(|c| (c.query_id, c.match_id)).collect();
    assert_eq!(pairs, [(9, 0)], "only the true revisit survives");
    assert_eq!(verified.rejected, appearance.candidates.len() - 1);
    // Trying the next best matches of every keyframe whose best fails lets no wrong one through.
    let mut alternatives = pipeline(&[recency[0], recency[1], recency[2], PERMISSIVE, preset]);
    let tried = run_source(&mut alternatives, &orbit.join("rgb"), &Default::default(), false).unwrap();
    assert_eq!(tried.candidates.iter().map(|c| (c.query_id, c.match_id)).collect::<Vec<_>>(), [(9, 0)]);
    assert!(tried.rejected > verified.rejected, "alternatives were tried: {} rejected", tried.rejected);
    let found = verified.candidates[0].verified.expect("a verified candidate says so");
    assert!(found.inliers >= 30, "{found:?}");
    let pose = found.pose.expect("intrinsics known: a relative pose");
    assert!((pose.translation.norm() - 1.0).abs() < 1e-9, "translation is a direction");
    // Frame 9 is "nearly the same pose" as frame 0. The pair has no ground truth, and its baseline is
    // too short to fix the rotation to a degree: ORB at 500-2000 features, XFeat and a homography
    // give 6-11 degrees. A look-alike's pose would be tens of degrees off.
    assert!(pose.rotation.angle().to_degrees() < 15.0, "{pose:?}");
}

/// The median rotation and translation direction errors (degrees) of the verified relative poses
/// of the TUM fr3 two-pass, its frames resized to `width` x `height` (the published calibration is
/// the 640x480 camera's), and how many pairs they are over.
fn two_pass_pose_errors(width: u32, height: u32) -> (f64, f64, usize) {
    let dir = tempfile::tempdir().unwrap();
    let (seq, _, overrides) = two_pass(dir.path());
    for entry in std::fs::read_dir(seq.join("rgb")).unwrap() {
        let path = entry.unwrap().path();
        let frame = image::open(&path).unwrap();
        if frame.width() != width || frame.height() != height {
            frame.resize_exact(width, height, image::imageops::FilterType::Triangle).save(&path).unwrap();
        }
    }
    let mut pipeline = pipeline(&overrides);
    let run = run_source(&mut pipeline, &seq, &Default::default(), false).unwrap();
    let groundtruth = read_groundtruth(&seq.join("groundtruth.txt")).unwrap();
    let pose_at = |stamp: Stamp| groundtruth.iter().find(|(s, _)| s.nanos == stamp.nanos).map(|(_, pose)| *pose);
    let (mut rotation, mut direction) = (Vec::new(), Vec::new());
    for c in &run.candidates {
        let pose = c.verified.and_then(|v| v.pose).expect("with intrinsics every verified candidate has a pose");
        let (Some(query), Some(matched)) = (pose_at(c.query_stamp), pose_at(c.match_stamp)) else { continue };
        let truth = matched.inverse() * query;
        rotation.push(pose.rotation.angle_to(&truth.rotation).to_degrees());
        direction.push(pose.translation.angle(&truth.translation.vector).to_degrees());
    }
    let pairs = rotation.len();
    assert!(pairs > 0, "{width}x{height}: no verified pair with a pose");
    let (rotation_error, direction_error) = (median_of(rotation), median_of(direction));
    println!(
        "{width}x{height}: {pairs} pairs: median rotation error {rotation_error:.2} deg, translation direction \
         {direction_error:.2} deg"
    );
    (rotation_error, direction_error, pairs)
}

/// [`two_pass_pose_errors`] at `width` x `height`, over at least `min_pairs` pairs, within the median
/// bounds (degrees).
fn check_two_pass_poses(width: u32, height: u32, min_pairs: usize, max_rotation: f64, max_direction: f64) {
    let (rotation_error, direction_error, pairs) = two_pass_pose_errors(width, height);
    assert!(pairs >= min_pairs, "{pairs} verified pairs with poses");
    assert!(rotation_error <= max_rotation, "median rotation error {rotation_error} deg");
    assert!(direction_error <= max_direction, "median translation direction error {direction_error} deg");
}

#[test]
fn verified_relative_poses_agree_with_the_ground_truth() {
    check_two_pass_poses(640, 480, 6, 1.0, 5.0);
}

/// A tracker that publishes its keyframes at half size, with the full frame's calibration: the
/// intrinsics are scaled to the frames, so the poses stay near the full frames' (the calibration
/// taken unscaled puts them several times farther off).
#[test]
fn half_size_frames_with_the_full_frame_calibration_get_right_poses() {
    check_two_pass_poses(320, 240, 4, 4.0, 10.0);
}

/// One verified row of `match`'s CSV: the frames' names, the inliers and the relative pose.
struct MatchedPose {
    query_frame: String,
    match_frame: String,
    inliers: usize,
    rotation: nalgebra::UnitQuaternion<f64>,
    translation: nalgebra::Vector3<f64>,
    metric: bool,
    has_covariance: bool,
}

/// Runs `match` with `args` (after the command) and reads the verified rows of its CSV, checking
/// that each carries replay's verification columns: at least the default 15 inliers and a unit
/// quaternion. Returns them and the number of queries.
fn matched_poses(dir: &Path, args: &[&str]) -> (Vec<MatchedPose>, usize) {
    let csv = dir.join("matches.csv");
    support::ecm_lcd_ok(&[&["match", "-o", csv.to_str().unwrap()], args].concat());
    let mut reader = csv::Reader::from_path(&csv).unwrap();
    let header = reader.headers().unwrap().clone();
    let column = |name: &str| header.iter().position(|h| h == name).unwrap_or_else(|| panic!("no column {name}"));
    let (mut poses, mut queries) = (Vec::new(), 0);
    for row in reader.records() {
        let row = row.unwrap();
        queries += 1;
        let field = |name: &str| row.get(column(name)).unwrap().to_string();
        if field("inliers").is_empty() {
            continue;
        }
        let value = |name: &str| field(name).parse::<f64>().unwrap();
        let q = nalgebra::Quaternion::new(value("qw"), value("qx"), value("qy"), value("qz"));
        assert!((q.norm() - 1.0).abs() < 1e-5, "{row:?}");
        let pose = MatchedPose {
            query_frame: field("query_frame"),
            match_frame: field("match_frame"),
            inliers: field("inliers").parse().unwrap(),
            rotation: nalgebra::UnitQuaternion::from_quaternion(q),
            translation: nalgebra::Vector3::new(value("tx"), value("ty"), value("tz")),
            metric: field("metric") == "1",
            has_covariance: !field("cov_x_x").is_empty(),
        };
        assert!(pose.inliers >= 15, "{row:?}");
        poses.push(pose);
    }
    (poses, queries)
}

/// The median of `values`.
fn median_of(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// `match` with verification on (the fr3 intrinsics): the real fr3 frames split into a map (every
/// other frame) and queries (the frames between), each query's match carries its inliers and the
/// query camera's pose in the match camera's frame, up to scale, in `replay`'s columns, and the poses
/// agree with the ground truth as a replay's do.
#[test]
fn match_reports_each_querys_verified_pose_in_the_maps_frame() {
    let fr3 = shared().join("data/tum/fr3_long_office_household");
    let dir = tempfile::tempdir().unwrap();
    let (map, queries) = (dir.path().join("map"), dir.path().join("queries"));
    for (i, path) in ecm_lcd::eval::images_in_name_order(&fr3.join("rgb")).unwrap().iter().enumerate() {
        let to = if i % 2 == 0 { &map } else { &queries };
        std::fs::create_dir_all(to).unwrap();
        std::fs::copy(path, to.join(path.file_name().unwrap())).unwrap();
    }
    let (map, queries) = (map.to_str().unwrap(), queries.to_str().unwrap());
    let (poses, count) =
        matched_poses(dir.path(), &["--database", map, "--queries", queries, "--param", "camera.preset=tum_fr3"]);
    let groundtruth = read_groundtruth(&fr3.join("groundtruth.txt")).unwrap();
    let pose_of = |file: &str| {
        let stamp = Stamp::parse_secs(file.trim_end_matches(".png")).unwrap();
        ecm_lcd::eval::poses_at_stamps(&[stamp], &groundtruth, 0.05)[0]
    };
    let (mut rotation, mut direction) = (Vec::new(), Vec::new());
    for pose in &poses {
        assert!(!pose.metric && !pose.has_covariance, "up to scale, without a covariance");
        assert!((pose.translation.norm() - 1.0).abs() < 1e-5, "a unit direction");
        let (Some(query), Some(matched)) = (pose_of(&pose.query_frame), pose_of(&pose.match_frame)) else { continue };
        let truth = matched.inverse() * query;
        rotation.push(pose.rotation.angle_to(&truth.rotation).to_degrees());
        direction.push(pose.translation.angle(&truth.translation.vector).to_degrees());
    }
    assert!(
        poses.len() >= 6 && rotation.len() >= 5,
        "{} of {count} verified, {} with truth",
        poses.len(),
        rotation.len()
    );
    let (rotation, direction) = (median_of(rotation), median_of(direction));
    println!(
        "{} of {count} queries verified: median rotation error {rotation:.2} deg, direction {direction:.2} deg",
        poses.len()
    );
    assert!(rotation <= 1.0 && direction <= 5.0, "median errors {rotation} deg, {direction} deg");
}

/// `match` against a map with depth (a synthetic TUM folder of the first lap with `depth.txt`) gives
/// the second lap's queries metric poses with a covariance, within the metric goals of the
/// ground truth.
#[test]
fn match_against_a_map_with_depth_reports_metric_poses() {
    let dir = tempfile::tempdir().unwrap();
    let full = dir.path().join("full");
    let config = SynthConfig { frames: 120, laps: 2, depth: true, ..SynthConfig::default() };
    let scene = Scene::new(config.clone()).unwrap();
    write_tum_folder(&scene, &full).unwrap();
    // The map: the first lap as a TUM folder with depth; the queries: the second lap's images.
    let (map, queries) = (dir.path().join("map"), dir.path().join("queries"));
    support::split_into_map_and_queries(&full, &map, &queries);
    let focal = scene.focal_length().to_string();
    let (cx, cy) = ((config.width as f64 / 2.0 - 0.5).to_string(), (config.height as f64 / 2.0 - 0.5).to_string());
    let camera = [
        format!("camera.fx={focal}"),
        format!("camera.fy={focal}"),
        format!("camera.cx={cx}"),
        format!("camera.cy={cy}"),
    ];
    let mut args = vec!["--database", map.to_str().unwrap(), "--queries", queries.to_str().unwrap()];
    camera.iter().for_each(|c| args.extend(["--param", c.as_str()]));
    let (poses, count) = matched_poses(dir.path(), &args);
    let groundtruth = read_groundtruth(&full.join("groundtruth.txt")).unwrap();
    let pose_of = |name: &str| {
        let stamp = Stamp::parse_secs(name.trim_end_matches(".png")).unwrap();
        ecm_lcd::eval::poses_at_stamps(&[stamp], &groundtruth, 0.001)[0].unwrap()
    };
    let (mut rotation, mut translation) = (Vec::new(), Vec::new());
    for pose in &poses {
        assert!(pose.metric && pose.has_covariance, "metric, with a covariance");
        let truth = pose_of(&pose.match_frame).inverse() * pose_of(&pose.query_frame);
        rotation.push(pose.rotation.angle_to(&truth.rotation).to_degrees());
        translation.push((pose.translation - truth.translation.vector).norm());
    }
    assert!(poses.len() >= 54, "{} of {count} queries verified", poses.len());
    let (rotation, translation) = (median_of(rotation), median_of(translation));
    println!(
        "{} of {count} queries metric: median rotation error {rotation:.2} deg, translation {translation:.3} m",
        poses.len()
    );
    assert!(rotation <= 1.0 && translation <= 0.05, "median errors {rotation} deg, {translation} m");
}

/// A folder named as the TUM benchmark names its fr3 sequences gives the fr3 intrinsics by itself:
/// replayed without `camera.*` parameters, it verifies as the same frames do with the preset.
#[test]
fn a_tum_folder_name_gives_verification_its_intrinsics() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, _, overrides) = two_pass(dir.path());
    let named = dir.path().join("rgbd_dataset_freiburg3_two_pass");
    write_two_pass(&shared().join("data/tum/fr3_long_office_household"), &named, 1.0, 0.05).unwrap();
    let without_preset: Vec<_> = overrides.iter().copied().filter(|(name, _)| *name != "camera.preset").collect();
    let mut plain = pipeline(&without_preset);
    assert!(!plain.verifies(), "no intrinsics in the parameters");
    let from_name = run_source(&mut plain, &named, &Default::default(), false).unwrap();
    assert!(plain.verifies(), "the folder name turned verification on");
    let from_preset = run_source(&mut pipeline(&overrides), &seq, &Default::default(), false).unwrap();
    let summary = |run: &ReplayRun| -> Vec<_> {
        run.candidates.iter().map(|c| (c.query_id, c.match_id, c.verified.and_then(|v| v.pose))).collect()
    };
    assert!(from_preset.candidates.len() >= 6, "{} verified candidates", from_preset.candidates.len());
    assert_eq!(summary(&from_name), summary(&from_preset));
    assert_eq!(from_name.rejected, from_preset.rejected);
    // Under another name the same frames have no intrinsics, so nothing is verified.
    let unnamed = run_source(&mut pipeline(&without_preset), &seq, &Default::default(), false).unwrap();
    assert!(unnamed.candidates.iter().all(|c| c.verified.is_none()) && unnamed.rejected == 0);
}

#[test]
fn camera_info_turns_verification_on_in_auto_mode_only() {
    let fr3 = ecm_lcd::verification::Intrinsics::preset("tum_fr3").unwrap();
    let mut auto = pipeline(&[]);
    assert!(!auto.verifies(), "auto without intrinsics: off");
    assert!(auto.set_camera_info(fr3).unwrap());
    assert!(auto.verifies());
    let mut off = pipeline(&[("verification.mode", "off")]);
    assert!(!off.set_camera_info(fr3).unwrap(), "off stays off");
    // Parameters win over camera_info: a preset-configured pipeline keeps its intrinsics.
    let mut configured = pipeline(&[("camera.preset", "tum_fr1")]);
    assert!(configured.set_camera_info(fr3).unwrap());
    assert_eq!(configured.params().intrinsics(), ecm_lcd::verification::Intrinsics::preset("tum_fr1"));

    // Keyframes seen before the intrinsics have no features: their matches are rejected, later ones
    // verify.
    let orbit = shared().join("data/real/tum_fr3_desk_orbit/rgb");
    let frames: Vec<_> = ecm_lcd::eval::images_in_name_order(&orbit).unwrap();
    let mut late = pipeline(&[&ORBIT_RECENCY[..], &[PERMISSIVE]].concat());
    let mut reported = Vec::new();
    for (i, path) in frames.iter().enumerate() {
        if i == 1 {
            late.set_camera_info(fr3).unwrap();
        }
        let image = ecm_lcd::preprocess::read_image(path).unwrap();
        let outcome = late.process_keyframe(i as u64, Stamp::from_nanos(i as i64 * 1_000_000_000), &image).unwrap();
        reported.extend(outcome.candidates.iter().map(|c| (c.query_id, c.match_id)));
    }
    // Frame 9 revisits frame 0, whose features were never extracted: nothing is reported.
    assert!(!reported.contains(&(9, 0)), "{reported:?}");
}

/// A depth image of another size than its colour image (a depth camera not registered to the colour
/// one) cannot give a keyframe a metric pose, but it costs the keyframe nothing: the desk orbit with
/// such depth images gives the candidates, verified up to scale, that it gives without depth. A
/// second keyframe under an id already taken is refused and leaves the history as it was.
#[test]
fn a_depth_image_of_another_size_is_left_out_and_a_taken_id_is_refused() {
    let orbit = shared().join("data/real/tum_fr3_desk_orbit/rgb");
    let frames: Vec<_> = ecm_lcd::eval::images_in_name_order(&orbit).unwrap();
    let images: Vec<_> = frames.iter().map(|path| ecm_lcd::preprocess::read_image(path).unwrap()).collect();
    let misfit = DepthImage { width: 320, height: 240, metres: vec![1.5; 320 * 240] };
    let run = |depth: Option<&DepthImage>| {
        let mut pipeline = pipeline(&[&ORBIT_RECENCY[..], &[("camera.preset", "tum_fr3"), PERMISSIVE]].concat());
        let mut candidates = Vec::new();
        for (i, image) in images.iter().enumerate() {
            let stamp = Stamp::from_nanos(i as i64 * 1_000_000_000);
            let input = Input { depth, ..Input::keyframe(i as u64, stamp, image) };
            let outcome = pipeline.process_input(&input).unwrap();
            assert_eq!(outcome.keyframe, Some(i as u64));
            candidates.extend(outcome.candidates);
        }
        (pipeline, candidates)
    };
    let (_, without_depth) = run(None);
    let (mut with_misfits, candidates) = run(Some(&misfit));
    assert_eq!(candidates, without_depth);
    let revisit = candidates.iter().find(|c| (c.query_id, c.match_id) == (9, 0)).expect("the revisit is reported");
    let pose = revisit.verified.and_then(|v| v.pose).expect("verified, with a pose");
    assert!(!pose.metric, "up to scale: no depth was used");

    let err =
        format!("{:#}", with_misfits.process_keyframe(4, Stamp::from_nanos(20_000_000_000), &images[0]).unwrap_err());
    assert!(err.contains("keyframe id 4 was taken by an earlier keyframe"), "{err}");
    assert_eq!(with_misfits.detector().db().len(), images.len());
}

#[test]
fn a_node_checks_candidates_only_and_evaluation_checks_every_best_match() {
    let orbit = shared().join("data/real/tum_fr3_desk_orbit/rgb");
    let frames = ecm_lcd::eval::images_in_name_order(&orbit).unwrap();
    // No candidate passes 0.999, so only evaluation's best-match check runs.
    let overrides = [&ORBIT_RECENCY[..], &[("detector.min_score", "0.999"), ("camera.preset", "tum_fr3")]].concat();
    let checked = |verify_best: bool| {
        let mut pipeline = pipeline(&overrides);
        pipeline.set_verify_best(verify_best);
        let mut checked = 0;
        for (i, path) in frames.iter().enumerate() {
            let image = ecm_lcd::preprocess::read_image(path).unwrap();
            let outcome =
                pipeline.process_keyframe(i as u64, Stamp::from_nanos(i as i64 * 1_000_000_000), &image).unwrap();
            assert!(outcome.candidates.is_empty());
            checked += outcome.best_verified.is_some() as usize;
        }
        checked
    };
    assert_eq!(checked(true), 6, "queries 4..9 have a best match");
    assert_eq!(checked(false), 0);
}

/// The TUM fr3 two-pass replayed with the odometry check `check` on, once with the true poses as the
/// tracker's and once with the tracker's second pass changed by `displace`; asserts that loops
/// between the passes are kept with the true poses and all rejected with the displaced ones. Returns
/// the run with the true poses and the replay, for more checks.
fn odometry_check_across_passes(
    dir: &Path,
    check: (&'static str, &'static str),
    displace: impl Fn(&mut nalgebra::Isometry3<f64>),
) -> (ReplayRun, impl Fn(&Path) -> anyhow::Result<ReplayRun>) {
    let (seq, frames, two_pass_overrides) = two_pass(dir);
    // One match tried per keyframe, so both runs try the same candidates (the count below).
    let only_best = ("verification.candidates", "1");
    let overrides: Vec<(&str, &str)> = two_pass_overrides.iter().copied().chain([check, only_best]).collect();
    let replay = move |poses: &Path| {
        let topics = ecm_lcd::io::Topics { poses: Some(poses.to_path_buf()), ..Default::default() };
        run_source(&mut pipeline(&overrides), &seq, &topics, false)
    };
    // The true poses as the tracker's: every revisit fits them.
    let truth = dir.join("two_pass/groundtruth.txt");
    let consistent = replay(&truth).unwrap();
    assert!(consistent.candidates.len() >= 6, "{:?}", consistent.candidates);

    // A tracker that got the second pass (from frame `frames / 2` on) wrong: no loop between the
    // passes fits it. (A frame without a ground-truth pose has none here either and is not checked.)
    let second_pass = consistent.frame_stamps[frames / 2];
    let mut poses = read_groundtruth(&truth).unwrap();
    for (stamp, pose) in &mut poses {
        if *stamp >= second_pass {
            displace(pose);
        }
    }
    let displaced = dir.join("displaced.txt");
    ecm_lcd::io::tum::write_trajectory(&displaced, &poses).unwrap();
    let inconsistent = replay(&displaced).unwrap();
    let posed = |stamp: Stamp| poses.iter().any(|(s, _)| *s == stamp);
    let across = |run: &ReplayRun| -> Vec<(u64, u64)> {
        run.candidates
            .iter()
            .filter(|c| c.match_stamp < second_pass && c.query_stamp >= second_pass)
            .filter(|c| posed(c.query_stamp) && posed(c.match_stamp))
            .map(|c| (c.query_id, c.match_id))
            .collect()
    };
    assert!(across(&consistent).len() >= 4, "{:?}", consistent.candidates);
    assert_eq!(across(&inconsistent), [], "loops between the passes");
    assert!(inconsistent.rejected_by_odometry >= across(&consistent).len(), "{}", inconsistent.rejected_by_odometry);
    assert!(inconsistent.candidates.len() < consistent.candidates.len());
    assert_eq!(
        inconsistent.rejected + inconsistent.candidates.len(),
        consistent.rejected + consistent.candidates.len(),
        "a candidate the odometry check drops is counted as rejected"
    );
    (consistent, replay)
}

#[test]
fn the_odometry_check_rejects_loops_the_tracker_puts_elsewhere() {
    let dir = tempfile::tempdir().unwrap();
    // As if the second pass were a look-alike room 10 m away.
    let (consistent, replay) = odometry_check_across_passes(dir.path(), ("verification.max_drift", "0.1"), |pose| {
        pose.translation.vector.x += 10.0
    });
    assert_eq!(consistent.rejected_by_odometry, 0, "the true poses fit every true loop");
    let missing = dir.path().join("no_such_poses.txt");
    let error = format!("{:#}", replay(&missing).unwrap_err());
    assert!(error.contains("no_such_poses.txt") && error.contains("--poses"), "{error}");
}

#[test]
fn the_rotation_check_rejects_verified_rotations_the_tracker_contradicts() {
    let dir = tempfile::tempdir().unwrap();
    // Positions kept, every second-pass camera turned 60 degrees about its optical axis: each verified
    // relative rotation between the passes is about 60 degrees off the tracker's, far beyond
    // 10 + 1.5 degrees per metre of the few metres walked.
    let turn = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 60f64.to_radians());
    let (checked, _) = odometry_check_across_passes(dir.path(), ("verification.max_rotation_drift", "1.5"), |pose| {
        pose.rotation *= turn
    });

    // With the true poses as the tracker's, it drops exactly the verified loops whose relative
    // rotation is off the truth by more than the bound: wrong poses, not drift.
    let unchecked_dir = tempfile::tempdir().unwrap();
    let (seq, _, overrides) = two_pass(unchecked_dir.path());
    let unchecked = run_source(&mut pipeline(&overrides), &seq, &Default::default(), false).unwrap();
    let mut truth = read_groundtruth(&seq.join("groundtruth.txt")).unwrap();
    truth.sort_by_key(|(stamp, _)| *stamp);
    let path_to = |stamp: Stamp| -> f64 {
        let before: Vec<_> =
            truth.iter().filter(|(s, _)| *s <= stamp).map(|(_, pose)| pose.translation.vector).collect();
        before.windows(2).map(|w| (w[1] - w[0]).norm()).sum()
    };
    let pose_at = |stamp: Stamp| truth.iter().find(|(s, _)| *s == stamp).map(|(_, pose)| *pose);
    let wrong: Vec<(u64, u64)> = unchecked
        .candidates
        .iter()
        .filter(|c| {
            let (Some(query), Some(matched)) = (pose_at(c.query_stamp), pose_at(c.match_stamp)) else { return false };
            let verified = c.verified.as_ref().and_then(|v| v.pose.as_ref()).unwrap().rotation;
            let error = verified.angle_to(&(matched.rotation.inverse() * query.rotation)).to_degrees();
            error > 10.0 + 1.5 * (path_to(c.query_stamp) - path_to(c.match_stamp))
        })
        .map(|c| (c.query_id, c.match_id))
        .collect();
    assert!(wrong.len() <= 2, "{wrong:?}: most verified TUM poses are right");
    assert_eq!(checked.rejected_by_odometry, wrong.len());
    let kept: Vec<(u64, u64)> = checked.candidates.iter().map(|c| (c.query_id, c.match_id)).collect();
    assert!(wrong.iter().all(|pair| !kept.contains(pair)), "{wrong:?} kept");
    assert_eq!(kept.len() + wrong.len(), unchecked.candidates.len());
}

/// The hard synthetic preset (600 frames, 3 laps, at 5 Hz) written into `dir`, with the parameters of its
/// renderer's camera: principal point at the image centre (pixel index coordinates).
fn hard_preset(dir: &Path) -> (PathBuf, [(&'static str, String); 4]) {
    let seq = dir.join("hard");
    let config = SynthConfig { frames: 600, laps: 3, rate_hz: 5.0, ..SynthConfig::hard() };
    let scene = Scene::new(config.clone()).unwrap();
    write_tum_folder(&scene, &seq).unwrap();
    let focal = scene.focal_length().to_string();
    let (cx, cy) = ((config.width as f64 / 2.0 - 0.5).to_string(), (config.height as f64 / 2.0 - 0.5).to_string());
    (seq, [("camera.fx", focal.clone()), ("camera.fy", focal), ("camera.cx", cx), ("camera.cy", cy)])
}

/// Sets of results of one replayed sequence `seq`, scored against the loop truth of its ground-truth
/// poses (`criteria`).
fn score_against_poses<const N: usize>(
    seq: &Path,
    run: &ReplayRun,
    criteria: &PoseLoopCriteria,
    results: [&[QueryResult]; N],
) -> [Metrics; N] {
    let groundtruth = read_groundtruth(&seq.join("groundtruth.txt")).unwrap();
    let truth = loop_truth_from_poses(&run.frame_stamps, &groundtruth, criteria);
    results.map(|r| evaluate(r, &truth).unwrap())
}

/// On the hard synthetic preset (three identical rooms, night laps, 160x120) a look-alike room often
/// outranks the true place. Verifying the next best match too (`verification.candidates` 2, the
/// default) and reporting the one with the most inliers finds loops the look-alike hid, keeps a true
/// loop for every keyframe whose best match alone was one, and lets no more wrong matches through.
#[test]
fn trying_the_next_best_matches_finds_loops_a_look_alike_hid() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, camera) = hard_preset(dir.path());
    let replay = |tried: &str| {
        let mut overrides = vec![PERMISSIVE, ("verification.candidates", tried)];
        overrides.extend(camera.iter().map(|(name, value)| (*name, value.as_str())));
        run_source(&mut pipeline(&overrides), &seq, &Default::default(), false).unwrap()
    };
    let (best_only, alternatives) = (replay("1"), replay("2"));
    let [before, after] = score_against_poses(
        &seq,
        &best_only,
        &PoseLoopCriteria::default(),
        [&best_only.query_results(), &alternatives.query_results()],
    );
    println!(
        "best only: {} true, {} wrong; with alternatives: {} true, {} wrong ({} positives)",
        before.true_reports, before.false_reports, after.true_reports, after.false_reports, before.positives
    );
    let groundtruth = read_groundtruth(&seq.join("groundtruth.txt")).unwrap();
    let truth = loop_truth_from_poses(&best_only.frame_stamps, &groundtruth, &PoseLoopCriteria::default());
    let true_loops = |run: &ReplayRun| -> Vec<u64> {
        let is_true = |q: u64, m: u64| truth.matches(q as usize).is_some_and(|ms| ms.contains(&(m as usize)));
        run.candidates.iter().filter(|c| is_true(c.query_id, c.match_id)).map(|c| c.query_id).collect()
    };
    let with_alternatives = true_loops(&alternatives);
    assert_eq!(true_loops(&best_only).len(), before.true_reports);
    for query in true_loops(&best_only) {
        assert!(with_alternatives.contains(&query), "keyframe {query} lost its true loop");
    }
    assert!(
        after.true_reports >= before.true_reports + 5,
        "{} -> {} true loops",
        before.true_reports,
        after.true_reports
    );
    assert!(after.false_reports <= before.false_reports, "{} -> {} wrong", before.false_reports, after.false_reports);
    // With two reported a keyframe (`detector.top_k` 2), both verified, ranked most inliers first.
    let mut overrides = vec![PERMISSIVE, ("verification.candidates", "2"), ("detector.top_k", "2")];
    overrides.extend(camera.iter().map(|(name, value)| (*name, value.as_str())));
    let both = run_source(&mut pipeline(&overrides), &seq, &Default::default(), false).unwrap();
    let inliers = |c: &ecm_lcd::types::LoopCandidate| c.verified.expect("verified").inliers;
    let pairs: Vec<_> = both.candidates.windows(2).filter(|w| w[0].query_id == w[1].query_id).collect();
    assert!(pairs.len() >= 10, "{} keyframes with two loops", pairs.len());
    for w in pairs {
        assert_eq!((w[0].rank, w[1].rank), (0, 1));
        assert!(inliers(&w[0]) >= inliers(&w[1]), "{:?}", (w[0].query_id, inliers(&w[0]), inliers(&w[1])));
    }
}

/// Prints the true and wrong loops reported without temporal consistency, dropping and delaying.
fn print_true_and_wrong([before, dropped, delayed]: &[&Metrics; 3]) {
    println!(
        "true/wrong loops: without consistency {}/{}, dropping {}/{}, delaying {}/{}",
        before.true_reports,
        before.false_reports,
        dropped.true_reports,
        dropped.false_reports,
        delayed.true_reports,
        delayed.false_reports
    );
}

/// On the hard preset, equalised ORB with both odometry bounds (the synthetic drifted odometry as the
/// tracker's poses) still passes a few wrong loops: the same scene just outside the place rule, and
/// wrong relative poses. Those are seldom consistent with the keyframe before, so temporal consistency
/// (`detector.consistency.queries` 2, before verification) removes most of them. Dropping what it
/// holds back, as DBoW2 does, leaves at most one and keeps most true loops; delaying it (the default)
/// loses no loop that dropping reports, keeps nearly every true loop, and still removes at least half
/// of the wrong ones. Scored on what is reported, as a node would publish it. The detector looks back
/// from 10 s, as when these bounds were set, so that matches to the identical room one room back are
/// tried too (with the default 20 s: 122 / 4 without consistency, 104 / 2 dropping, 118 / 2 delaying;
/// docs/verification.md).
#[test]
fn temporal_consistency_removes_the_wrong_loops_that_pass_verification() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, camera) = hard_preset(dir.path());
    let topics = ecm_lcd::io::Topics { poses: Some(seq.join("odometry.txt")), ..Default::default() };
    let replay = |queries: &str, delayed: &str| {
        let mut overrides = vec![
            PERMISSIVE,
            ("verification.equalise", "true"),
            ("verification.max_drift", "0.1"),
            ("verification.max_rotation_drift", "1.5"),
            ("detector.consistency.queries", queries),
            ("detector.consistency.delayed", delayed),
            ("detector.exclude_recent.seconds", "10"),
        ];
        overrides.extend(camera.iter().map(|(name, value)| (*name, value.as_str())));
        run_source(&mut pipeline(&overrides), &seq, &topics, false).unwrap()
    };
    let plain = replay("1", "true");
    let (dropping, delaying) = (replay("2", "false").reported_results(), replay("2", "true").reported_results());
    let [before, dropped, delayed] = score_against_poses(
        &seq,
        &plain,
        &PoseLoopCriteria::default(),
        [&plain.reported_results(), &dropping, &delaying],
    );
    print_true_and_wrong(&[&before, &dropped, &delayed]);
    assert!(before.false_reports >= 3, "{} wrong loops without consistency", before.false_reports);
    assert!(dropped.false_reports <= 1, "{} wrong loops with consistency", dropped.false_reports);
    assert!(
        dropped.true_reports * 100 >= before.true_reports * 85,
        "{} -> {} true loops",
        before.true_reports,
        dropped.true_reports
    );
    for (held, late) in dropping.iter().zip(&delaying) {
        assert!(held.best.is_none() || held.best == late.best, "{held:?} lost when delayed: {late:?}");
    }
    assert!(
        delayed.true_reports * 100 >= before.true_reports * 95,
        "{} -> {} true loops when delayed",
        before.true_reports,
        delayed.true_reports
    );
    assert!(
        delayed.false_reports * 2 <= before.false_reports,
        "{} -> {} wrong loops when delayed",
        before.false_reports,
        delayed.false_reports
    );
}

/// On the real TUM two-pass, temporal consistency removes the wrong loop that passes verification.
/// Delayed (the default), it keeps every true loop verification keeps; dropped, as DBoW2 does, it
/// loses the revisit's first keyframe, which no earlier keyframe's match confirms.
#[test]
fn temporal_consistency_removes_the_wrong_verified_loop_of_the_real_two_pass() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, _, overrides) = two_pass(dir.path());
    let replay = |queries: &'static str, delayed: &'static str| {
        let mut all = overrides.to_vec();
        all.extend([("detector.consistency.queries", queries), ("detector.consistency.delayed", delayed)]);
        run_source(&mut pipeline(&all), &seq, &Default::default(), false).unwrap()
    };
    let (plain, dropping, delaying) = (replay("1", "true"), replay("2", "false"), replay("2", "true"));
    let criteria = PoseLoopCriteria { min_gap_s: 2.0, ..PoseLoopCriteria::default() };
    let [before, dropped, delayed] = score_against_poses(
        &seq,
        &plain,
        &criteria,
        [&plain.reported_results(), &dropping.reported_results(), &delaying.reported_results()],
    );
    print_true_and_wrong(&[&before, &dropped, &delayed]);
    assert!(before.false_reports >= 1, "the wrong loop that passes verification is gone: {before:?}");
    assert_eq!((dropped.true_reports, dropped.false_reports), (before.true_reports - 1, 0), "{dropped:?}");
    assert_eq!((delayed.true_reports, delayed.false_reports), (before.true_reports, 0), "{delayed:?}");
}
