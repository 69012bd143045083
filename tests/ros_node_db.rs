//! `ecm-lcd node --db` over DDS: the node receives the first lap of a looped synthetic sequence, is
//! killed with SIGKILL, and a new node started on the same database loads that history; the second
//! lap (the revisit) published to it then closes loops on keyframes of the first run, exactly as the
//! offline run of the whole sequence does. The tracker and the back end are RustDDS participants in
//! this process; the whole test re-runs itself in a private network namespace (see `ros_support`).

mod ros_support;
mod support;

use ecm_lcd::config::Params;
use ecm_lcd::detector::store::KeyframeStore;
use ecm_lcd::io::open_source;
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::ros::msgs::{Marker, Point, Pose};
use ecm_lcd::ros::node::InputQos;
use ecm_lcd::ros::peer::{CandidateListener, FramePublisher, Listener, SendAs};
use ecm_lcd::types::Frame;
use nalgebra::Isometry3;
use ros_support::NodeProcess;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

const FRAMES: usize = 60;
const FIRST_LAP: usize = FRAMES / 2;
/// A lap is 30 keyframes: loops are searched early and only a few keyframes back are excluded.
const PARAMS: &[(&str, &str)] = &[
    ("detector.min_history", "5"),
    ("detector.exclude_recent.count", "8"),
    ("detector.exclude_recent.seconds", "0.0"),
    // The threshold is for this descriptor, uncentred.
    // The thresholds below are for this network and descriptor, uncentred.
    ("arch", "ecmobilenet"),
    ("descriptor.mode", "l2"),
    ("detector.centre_on_history", "false"),
    ("detector.min_score", "0.975"),
];

fn weights() -> PathBuf {
    let path = support::shared_dir().join("models/mobilenet_v2_1.0_224_quant.tflite");
    assert!(path.is_file(), "{} missing", path.display());
    path
}

/// The node on `db` with the test's weights and parameters, logging to `node{run}.log`.
fn start_node(dir: &Path, db: &Path, run: usize) -> NodeProcess {
    let mut args: Vec<OsString> = vec!["--weights".into(), weights().into(), "--db".into(), db.into()];
    args.extend(["--ros-args", "-r", "__ns:=/dbtest"].map(OsString::from));
    for (name, value) in PARAMS {
        args.extend(["-p".into(), format!("{name}:={value}").into()]);
    }
    NodeProcess::start(dir, dir.join(format!("node{run}.log")), args)
}

/// The test sequence (`ros_support::looped_sequence`) and its frames.
fn looped_sequence(dir: &Path) -> (PathBuf, Vec<Frame>) {
    let seq = ros_support::looped_sequence(dir, FRAMES);
    let frames = open_source(&seq, None).unwrap().map(|f| f.unwrap()).collect();
    (seq, frames)
}

/// The candidates `(query, match)` of the offline run of the whole sequence.
fn offline(frames: &[Frame]) -> Vec<(u64, u64)> {
    let mut params = Params::default();
    for (name, value) in PARAMS {
        params.set_from_str(name, value).unwrap();
    }
    let mut pipeline = Pipeline::new(params, Some(&weights())).unwrap();
    let mut rows = Vec::new();
    for frame in frames {
        let outcome = pipeline.process_keyframe(frame.index as u64, frame.stamp, &frame.image).unwrap();
        rows.extend(outcome.candidates.iter().map(|c| (c.query_id, c.match_id)));
    }
    rows
}

/// Publishes `frames` as keyframes carrying their ground-truth poses, from fresh participants (so
/// that no match with a killed node lingers), and collects the candidates until `expected` arrived or
/// nothing came for a while, and the loop-edge markers.
fn publish_and_listen(frames: &[Frame], poses: &[Isometry3<f64>], expected: usize) -> (Vec<(u64, u64)>, Vec<Marker>) {
    let tracker = ros2_client::Context::new().unwrap();
    let back_end = ros2_client::Context::new().unwrap();
    let publisher =
        FramePublisher::new(&tracker, "/dbtest/keyframes", SendAs::Keyframe, InputQos::Reliable, "camera").unwrap();
    let listener = CandidateListener::new(&back_end, "/dbtest/loop_candidates").unwrap();
    let viewer = ros2_client::Context::new().unwrap();
    let markers = Listener::markers(&viewer, "/dbtest/loop_markers").unwrap();
    assert!(publisher.wait_for_subscriber(Duration::from_secs(60)), "the node did not subscribe");
    assert!(listener.wait_for_publisher(Duration::from_secs(60)), "the node did not publish");
    assert!(markers.wait_for_publisher(Duration::from_secs(60)), "the node did not publish markers");
    std::thread::sleep(Duration::from_millis(500));
    let mut got = Vec::new();
    for frame in frames {
        publisher.publish_with_pose(frame, Some(Pose::from_isometry(&poses[frame.index]))).unwrap();
        std::thread::sleep(Duration::from_millis(50));
        got.extend(listener.take_all().unwrap().iter().map(|c| (c.query_id, c.match_id)));
    }
    let mut last = Instant::now();
    while got.len() < expected && last.elapsed() < Duration::from_secs(10) {
        let more = listener.wait(Duration::from_millis(200)).unwrap();
        if !more.is_empty() {
            last = Instant::now();
        }
        got.extend(more.iter().map(|c| (c.query_id, c.match_id)));
    }
    // Anything late would show as a difference from the offline run.
    std::thread::sleep(Duration::from_millis(300));
    got.extend(listener.take_all().unwrap().iter().map(|c| (c.query_id, c.match_id)));
    let edges = markers.take_all().unwrap().into_iter().flat_map(|array| array.markers).collect();
    (got, edges)
}

/// Each candidate is one line from the match keyframe's position to the query's, in the map frame.
fn check_markers(markers: &[Marker], candidates: &[(u64, u64)], poses: &[Isometry3<f64>]) {
    assert_eq!(markers.len(), candidates.len(), "one loop-edge marker per candidate");
    for (marker, &(query, matched)) in markers.iter().zip(candidates) {
        assert_eq!((marker.marker_type, marker.header.frame_id.as_str()), (Marker::LINE_LIST, "map"));
        let at = |p: &Point| nalgebra::Vector3::new(p.x, p.y, p.z);
        assert!((at(&marker.points[0]) - poses[matched as usize].translation.vector).norm() < 1e-9);
        assert!((at(&marker.points[1]) - poses[query as usize].translation.vector).norm() < 1e-9);
    }
}

#[test]
fn node_with_a_database_killed_and_restarted_detects_the_revisit() {
    if !ros_support::inside() {
        return ros_support::check_inner_run("node_with_a_database_killed_and_restarted_detects_the_revisit");
    }
    let dir = tempfile::tempdir().unwrap();
    let (seq, frames) = looped_sequence(dir.path());
    let expected = offline(&frames);
    let (before, after): (Vec<_>, Vec<_>) = expected.iter().partition(|(query, _)| (*query as usize) < FIRST_LAP);
    assert!(after.len() >= 5, "the second lap should close loops on the first offline: {expected:?}");
    assert!(after.iter().all(|(_, matched)| (*matched as usize) < FIRST_LAP), "{after:?}");

    // First run: the first lap, then SIGKILL once the last keyframe was processed.
    let db = dir.path().join("keyframes.db");
    let mut first = start_node(dir.path(), &db, 1);
    let poses: Vec<Isometry3<f64>> =
        read_groundtruth(&seq.join("groundtruth.txt")).unwrap().into_iter().map(|(_, p)| p).collect();
    let (got, markers) = publish_and_listen(&frames[..FIRST_LAP], &poses, before.len());
    assert_eq!(got, before, "first lap over DDS vs offline");
    check_markers(&markers, &got, &poses);
    first.wait_for_log(&format!(" id {} stamp", FIRST_LAP - 1), Duration::from_secs(30));
    first.child.kill().unwrap(); // SIGKILL
    first.child.wait().unwrap();
    let store = KeyframeStore::open_existing(&db).unwrap();
    let stored: Vec<u64> = store.keyframes().unwrap().iter().map(|k| k.id).collect();
    assert_eq!(stored, (0..FIRST_LAP as u64).collect::<Vec<_>>(), "keyframes stored by the killed node");
    drop(store);

    // Second run on the same database: the history is loaded and the revisit closes loops on it.
    let second = start_node(dir.path(), &db, 2);
    second.wait_for_log(&format!("{FIRST_LAP} keyframes stored, {FIRST_LAP} loaded"), Duration::from_secs(60));
    let (got, markers) = publish_and_listen(&frames[FIRST_LAP..], &poses, after.len());
    assert_eq!(got, after, "second lap after the restart vs the offline run of the whole sequence");
    // The matches are keyframes of the first run: their tracker poses come back from the database, so
    // every loop edge is drawn between the right positions.
    check_markers(&markers, &got, &poses);
    let mut second = second;
    Command::new("kill").args(["-TERM", &second.child.id().to_string()]).status().unwrap();
    assert!(second.child.wait().unwrap().success(), "{}", second.log_text());
    let counters =
        second.log_text().lines().find_map(|l| l.split_once("stopped: ").map(|(_, c)| c.to_string())).unwrap();
    assert!(
        counters.starts_with(&format!("received {0} processed {0} candidates {1} ", FRAMES - FIRST_LAP, after.len())),
        "{counters}"
    );
    let stored = KeyframeStore::open_existing(&db).unwrap().keyframes().unwrap().len();
    assert_eq!(stored, FRAMES);
    println!("INNER-DONE first lap {} candidates, after the restart {} candidates, all on the first run's keyframes; {counters}", before.len(), after.len());
}

/// The node on a database, SIGKILLed again and again at random moments while keyframes arrive; each
/// new node is sent the keyframes its database does not hold yet. In the end the database holds
/// exactly what an uninterrupted run stores: the same keyframes (ids, stamps, descriptors within 1e-4)
/// and the same candidates (pairs identical, distances within 1e-4).
#[test]
fn node_with_a_database_killed_at_random_ends_with_an_uninterrupted_runs_database() {
    if !ros_support::inside() {
        return ros_support::check_inner_run(
            "node_with_a_database_killed_at_random_ends_with_an_uninterrupted_runs_database",
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let (_, frames) = looped_sequence(dir.path());

    // The uninterrupted run, offline, into its own database.
    let reference_db = dir.path().join("reference.db");
    let mut params = Params::default();
    for (name, value) in PARAMS {
        params.set_from_str(name, value).unwrap();
    }
    let mut pipeline = Pipeline::new(params, Some(&weights())).unwrap();
    pipeline.open_store(&reference_db).unwrap();
    for frame in &frames {
        pipeline.process_keyframe(frame.index as u64, frame.stamp, &frame.image).unwrap();
    }
    drop(pipeline);
    let reference = KeyframeStore::open_existing(&reference_db).unwrap();
    let (reference_keyframes, reference_candidates) =
        (reference.keyframes().unwrap(), reference.stored_candidates().unwrap().expect("all candidates stored"));
    assert!(reference_candidates.len() >= 5, "the sequence closes loops: {}", reference_candidates.len());

    let seed = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64 | 1;
    println!("kill schedule seed {seed}");
    let mut random = support::Random(seed);
    let db = dir.path().join("keyframes.db");
    let stored_ids = || -> Vec<u64> {
        if !db.exists() {
            return Vec::new();
        }
        KeyframeStore::open_existing(&db).unwrap().keyframes().unwrap().iter().map(|k| k.id).collect()
    };
    let (mut kills, mut run) = (0, 0);
    loop {
        let stored = stored_ids();
        assert_eq!(stored, (0..stored.len() as u64).collect::<Vec<_>>(), "stored ids have a gap (seed {seed})");
        let next = stored.len();
        if next == FRAMES {
            break;
        }
        run += 1;
        assert!(run < 60, "no progress (seed {seed})");
        let node = start_node(dir.path(), &db, run);
        node.wait_for_log("keyframes stored", Duration::from_secs(60));
        let tracker = ros2_client::Context::new().unwrap();
        let publisher =
            FramePublisher::new(&tracker, "/dbtest/keyframes", SendAs::Keyframe, InputQos::Reliable, "camera").unwrap();
        assert!(publisher.wait_for_subscriber(Duration::from_secs(60)), "the node did not subscribe");
        std::thread::sleep(Duration::from_millis(300));
        // Up to 8 keyframes, then SIGKILL after 0-150 ms: mid-keyframe, mid-commit or idle.
        let count = 1 + random.below(8) as usize;
        let end = (next + count).min(FRAMES);
        for frame in &frames[next..end] {
            publisher.publish(frame).unwrap();
            std::thread::sleep(Duration::from_millis(40));
        }
        let mut node = node;
        if end == FRAMES && random.below(2) == 0 {
            // Let the last run finish cleanly now and then.
            node.wait_for_log(&format!(" id {} stamp", FRAMES - 1), Duration::from_secs(30));
            Command::new("kill").args(["-TERM", &node.child.id().to_string()]).status().unwrap();
            assert!(node.child.wait().unwrap().success(), "{}", node.log_text());
        } else {
            std::thread::sleep(Duration::from_millis(random.below(150)));
            node.child.kill().unwrap(); // SIGKILL
            node.child.wait().unwrap();
            kills += 1;
        }
    }
    println!("INNER-DONE {kills} SIGKILLs over {run} runs (seed {seed})");
    assert!(kills >= 10, "only {kills} kills (seed {seed})");

    let store = KeyframeStore::open_existing(&db).unwrap();
    let keyframes = store.keyframes().unwrap();
    assert_eq!(keyframes.len(), reference_keyframes.len());
    for (got, want) in keyframes.iter().zip(&reference_keyframes) {
        assert_eq!((got.id, got.stamp), (want.id, want.stamp), "seed {seed}");
        let difference = ecm_lcd::descriptor::distance(&got.descriptor, &want.descriptor);
        assert!(difference <= 1e-4, "keyframe {} descriptor differs by {difference} (seed {seed})", got.id);
    }
    let candidates = store.stored_candidates().unwrap().expect("all candidates stored");
    let pairs = |c: &[ecm_lcd::types::LoopCandidate]| c.iter().map(|c| (c.query_id, c.match_id)).collect::<Vec<_>>();
    assert_eq!(pairs(&candidates), pairs(&reference_candidates), "candidates differ (seed {seed})");
    for (got, want) in candidates.iter().zip(&reference_candidates) {
        assert!((got.distance - want.distance).abs() <= 1e-4, "{got:?} vs {want:?} (seed {seed})");
    }
}

/// Keyframes that carry their poses: every candidate is also drawn as a loop edge for RViz.
#[test]
fn loop_edges_are_published_as_markers_when_keyframes_carry_poses() {
    if !ros_support::inside() {
        return ros_support::check_inner_run("loop_edges_are_published_as_markers_when_keyframes_carry_poses");
    }
    let dir = tempfile::tempdir().unwrap();
    let (seq, frames) = looped_sequence(dir.path());
    let poses: Vec<Isometry3<f64>> =
        read_groundtruth(&seq.join("groundtruth.txt")).unwrap().into_iter().map(|(_, p)| p).collect();
    let expected = offline(&frames);
    let node = start_node(dir.path(), &dir.path().join("keyframes.db"), 1);
    let (got, markers) = publish_and_listen(&frames, &poses, expected.len());
    assert_eq!(got, expected);
    assert!(got.len() >= 5, "{got:?}");
    check_markers(&markers, &got, &poses);
    drop(node);
    println!("INNER-DONE {} candidates, {} loop-edge markers", got.len(), markers.len());
}
