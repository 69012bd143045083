//! The persistent keyframe database end to end: `replay --db` killed (SIGKILL) at random moments and
//! restarted ends with the database and the CSV of an uninterrupted run, and always leaves a database
//! that loads;
//! a restarted pipeline continues ids and history; `db info|export|merge`; refusal of other descriptors.

mod support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use ecm_lcd::config::Params;
use ecm_lcd::detector::store::KeyframeStore;
use ecm_lcd::model::weights::resolve;
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::synth::{write_tum_folder, Scene, SynthConfig};
use nalgebra::Isometry3;

const FRAMES: usize = 40;

/// Small and fast, and loose enough that nearly every keyframe reports a candidate, so the CSV shows
/// what was emitted keyframe by keyframe.
const PARAMS: [&str; 5] = [
    "input_size=96",
    "detector.min_score=0",
    "detector.min_history=1",
    "detector.exclude_recent.count=1",
    "detector.exclude_recent.seconds=0",
];

fn shared() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared");
    assert!(dir.join("models").is_dir(), "shared data missing at {}: tests need ../shared (see README)", dir.display());
    dir
}

fn command() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_ecm-lcd"));
    command.env("ECM_LCD_CACHE", Path::new(env!("CARGO_TARGET_TMPDIR")).join("weights-cache")).env("RUST_LOG", "warn");
    command
}

fn ecm_lcd(args: &[&str]) -> Output {
    command().args(args).output().unwrap()
}

fn replay_args<'a>(source: &'a str, db: &'a str, csv: &'a str) -> Vec<&'a str> {
    let mut args = vec!["replay", source, "--db", db, "-o", csv, "--quiet", "--threads", "1"];
    for p in &PARAMS {
        args.extend(["--param", p]);
    }
    args
}

fn synthetic_sequence(dir: &Path) -> PathBuf {
    // 5 Hz against the default selection's 0.5 s: about every third frame is a keyframe, so a
    // restart must pick up the selection where the killed run left it.
    let config =
        SynthConfig { frames: FRAMES, laps: 2, width: 160, height: 120, rate_hz: 5.0, ..SynthConfig::default() };
    let seq = dir.join("seq");
    write_tum_folder(&Scene::new(config).unwrap(), &seq).unwrap();
    seq
}

/// The candidate lines of a replay CSV by query id (query id -> match id, distance); panics on a torn
/// or malformed line, or a query reported twice.
fn read_candidates(csv: &Path) -> BTreeMap<u64, (u64, f64)> {
    let text = std::fs::read_to_string(csv).unwrap_or_default();
    let mut lines = text.lines();
    let mut out = BTreeMap::new();
    if let Some(header) = lines.next() {
        assert!(
            header.starts_with(
                "query_id,query_stamp,match_id,match_stamp,distance,score,inliers,qx,qy,qz,qw,tx,ty,tz,metric,"
            ),
            "{header}"
        );
    }
    for line in lines {
        let fields: Vec<&str> = line.split(',').collect();
        assert_eq!(fields.len(), 15 + 21, "malformed line {line:?} in {}", csv.display());
        let query: u64 = fields[0].parse().unwrap();
        let previous = out.insert(query, (fields[2].parse().unwrap(), fields[4].parse().unwrap()));
        assert!(previous.is_none(), "query {query} reported twice in {}", csv.display());
    }
    out
}

fn stored_ids(db: &Path) -> Vec<u64> {
    let store = KeyframeStore::open_existing(db).unwrap_or_else(|e| panic!("{}: {e:#}", db.display()));
    let history = store.load_db(None).unwrap_or_else(|e| panic!("{}: {e:#}", db.display()));
    (0..history.len()).map(|p| history.id(p)).collect()
}

#[test]
fn replay_killed_at_random_moments_ends_as_an_uninterrupted_run() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synthetic_sequence(dir.path());
    let seq_text = seq.to_str().unwrap();

    // Uninterrupted reference (this also imports the weights into the test cache once).
    let (ref_db, ref_csv) = (dir.path().join("ref.db"), dir.path().join("ref.csv"));
    let out = ecm_lcd(&replay_args(seq_text, ref_db.to_str().unwrap(), ref_csv.to_str().unwrap()));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // Timed on a second, warm run (the first imported the weights): kills land within this span.
    std::fs::remove_file(&ref_db).unwrap();
    let timed = Instant::now();
    let out = ecm_lcd(&replay_args(seq_text, ref_db.to_str().unwrap(), ref_csv.to_str().unwrap()));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let full_run_ms = (timed.elapsed().as_millis() as u64).clamp(100, 800);
    let reference = read_candidates(&ref_csv);
    let reference_ids = stored_ids(&ref_db);
    // A CSV line lost after its keyframe was committed (the window a kill can hit) is written again
    // from the database by the next run, which finds every frame stored.
    let full = std::fs::read_to_string(&ref_csv).unwrap();
    let cut = full.trim_end().rfind('\n').unwrap() + 1;
    std::fs::write(&ref_csv, &full[..cut]).unwrap();
    let out = ecm_lcd(&replay_args(seq_text, ref_db.to_str().unwrap(), ref_csv.to_str().unwrap()));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(std::fs::read_to_string(&ref_csv).unwrap(), full, "the lost line was not written again");
    // Printed rather than written, a resumed run's output is the whole run's too.
    let mut printed = replay_args(seq_text, ref_db.to_str().unwrap(), "");
    printed.retain(|arg| !["-o", ""].contains(arg));
    let out = ecm_lcd(&printed);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(String::from_utf8_lossy(&out.stdout), full, "a resumed run printed other candidates than it wrote");
    assert!(reference_ids.len() > 5 && reference_ids.len() < FRAMES / 2, "selection kept {reference_ids:?}");
    assert!(reference.len() >= reference_ids.len() - 2, "only {} candidates in the reference", reference.len());

    let seed = std::env::var("ECM_LCD_KILL_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or_else(|| {
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64 | 1
    });
    println!("kill test seed {seed} (ECM_LCD_KILL_SEED to repeat)");
    let mut random = support::Random(seed);
    let (db, csv) = (dir.path().join("kill.db"), dir.path().join("kill.csv"));
    let args = replay_args(seq_text, db.to_str().unwrap(), csv.to_str().unwrap());
    let started = Instant::now();
    let (mut kills, mut completions, mut checked, mut lost, mut kills_mid_sequence) = (0, 0, 0, 0, 0);
    let mut stored_before = 0;
    while kills < 20 || completions == 0 {
        assert!(started.elapsed() < Duration::from_secs(120), "kill test ran out of time after {kills} kills");
        let mut child = command().args(&args).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
        // Between 50 ms and one full run (at most 800 ms): from before the weights load to the end.
        let kill_after = Duration::from_millis(50 + random.below(full_run_ms - 49));
        let deadline = Instant::now() + kill_after;
        let finished = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break Some(status);
            }
            if Instant::now() >= deadline {
                break None;
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        let killed = finished.is_none();
        if killed {
            child.kill().unwrap(); // SIGKILL on Unix
            child.wait().unwrap();
            kills += 1;
        } else {
            assert!(finished.unwrap().success(), "replay failed after {kills} kills");
        }
        // The database always loads, and every keyframe with a candidate in the CSV is stored; the
        // emitted candidates are the reference's.
        let ids = if db.exists() { stored_ids(&db) } else { Vec::new() };
        assert!(reference_ids.starts_with(&ids), "stored ids {ids:?} are not a prefix of {reference_ids:?}");
        let emitted = read_candidates(&csv);
        for (query, (matched, distance)) in &emitted {
            assert!(
                ids.contains(query),
                "keyframe {query} has a candidate in the CSV but is not stored (stored: {ids:?})"
            );
            let (ref_match, ref_distance) = reference[query];
            assert_eq!(*matched, ref_match, "keyframe {query}");
            assert!((distance - ref_distance).abs() < 1e-4, "keyframe {query}: distance {distance} vs {ref_distance}");
        }
        checked += emitted.len();
        if killed && ids.len() > stored_before && ids.len() < reference_ids.len() {
            kills_mid_sequence += 1;
        }
        stored_before = ids.len();
        if !killed {
            // A complete run: the database and the CSV are the uninterrupted run's (a line a kill
            // kept from the CSV is written again from the database on restart).
            assert_eq!(ids, reference_ids);
            lost += reference.keys().filter(|q| !emitted.contains_key(q)).count();
            assert_eq!(emitted.keys().collect::<Vec<_>>(), reference.keys().collect::<Vec<_>>());
            completions += 1;
            stored_before = 0;
            for path in [&db, &csv] {
                std::fs::remove_file(path).unwrap();
            }
        }
    }
    println!(
        "kill test: {kills} kills within {full_run_ms} ms ({kills_mid_sequence} after some keyframes were stored and before the last), \
         {completions} complete sequences, {checked} emitted keyframes checked against the database, \
         {lost} candidates lost, {:.1} s",
        started.elapsed().as_secs_f64()
    );
    assert_eq!(lost, 0, "{lost} candidates lost in {kills} kills");
}

#[test]
fn restarted_pipeline_continues_ids_and_history() {
    let weights = || resolve::load_file(&shared().join("models/mobilenet_v2_1.0_224_quant.tflite")).unwrap();
    let mut params = Params::default();
    for p in PARAMS {
        let (name, value) = p.split_once('=').unwrap();
        params.set_from_str(name, value).unwrap();
    }
    let scene =
        Scene::new(SynthConfig { frames: 8, laps: 1, width: 160, height: 120, rate_hz: 2.0, ..SynthConfig::default() })
            .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("node.db");

    let mut first = Pipeline::with_weights(params.clone(), weights()).unwrap();
    first.open_store(&db).unwrap();
    for i in 0..5 {
        let (stamp, image, _) = scene.frame(i);
        assert_eq!(first.process_counted(stamp, &image).unwrap().keyframe, Some(i as u64));
    }
    drop(first);

    let mut second = Pipeline::with_weights(params.clone(), weights()).unwrap();
    second.open_store(&db).unwrap();
    assert_eq!(second.detector().db().len(), 5);
    let (stamp, image, _) = scene.frame(5);
    let outcome = second.process_counted(stamp, &image).unwrap();
    assert_eq!(outcome.keyframe, Some(5));
    assert!(outcome.candidates.iter().all(|c| c.match_id < 5) && !outcome.candidates.is_empty());
    // The tracker's own ids: a stored id is refused, the keyframe is neither stored nor matched.
    let err = format!("{:#}", second.process_keyframe(2, stamp, &image).unwrap_err());
    assert!(err.contains("keyframe id 2 is already stored"), "{err}");
    assert_eq!(second.detector().db().len(), 6);
    drop(second);

    // A memory budget loads only the newest keyframes; the store keeps all.
    params.set_from_str("detector.max_keyframes", "4").unwrap();
    let mut third = Pipeline::with_weights(params.clone(), weights()).unwrap();
    third.open_store(&db).unwrap();
    assert_eq!((third.detector().db().len(), third.detector().db().id(0)), (4, 2));
    let (stamp, image, _) = scene.frame(6);
    assert_eq!(third.process_counted(stamp, &image).unwrap().keyframe, Some(6));
    assert_eq!((third.detector().db().len(), third.store().unwrap().len()), (4, 7));
    drop(third);

    // Another descriptor mode is refused, naming both.
    params.set_from_str("descriptor.mode", "paper").unwrap();
    let mut other = Pipeline::with_weights(params, weights()).unwrap();
    let err = format!("{:#}", other.open_store(&db).unwrap_err());
    assert!(
        err.contains("descriptor regional-3x3-mac@blocks.16 (2880 values)")
            && err.contains("descriptor paper (128 values)")
            && err.contains("node.db"),
        "{err}"
    );
}

#[test]
fn db_info_export_and_merge_commands() {
    let dir = tempfile::tempdir().unwrap();
    let scene =
        Scene::new(SynthConfig { frames: 6, laps: 1, width: 160, height: 120, rate_hz: 2.0, ..SynthConfig::default() })
            .unwrap();
    let seq = dir.path().join("seq");
    write_tum_folder(&scene, &seq).unwrap();
    let (db, csv) = (dir.path().join("a.db"), dir.path().join("a.csv"));
    let out = ecm_lcd(&replay_args(seq.to_str().unwrap(), db.to_str().unwrap(), csv.to_str().unwrap()));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // A second replay of the same source finds everything stored and adds nothing.
    let out = ecm_lcd(&replay_args(seq.to_str().unwrap(), db.to_str().unwrap(), csv.to_str().unwrap()));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("6 processed by the earlier run, skipped"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    // Continued with another threshold: the loops found before keep theirs, and the log says so.
    let mut args = replay_args(seq.to_str().unwrap(), db.to_str().unwrap(), csv.to_str().unwrap());
    args.extend(["--param", "detector.min_score=0.97"]);
    let out = ecm_lcd(&args);
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && log.contains("processed with other parameters (detector.min_score"), "{log}");

    let out = ecm_lcd(&["db", "info", db.to_str().unwrap()]);
    let info = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for expected in [
        "keyframes:       6",
        "ids:             0 .. 5",
        "arch:            mobilenetv2",
        "descriptor:      regional-3x3-mac@blocks.16 (2880 values)",
        "input size:      96",
    ] {
        assert!(info.contains(expected), "{expected:?} not in\n{info}");
    }
    let sha = KeyframeStore::open_existing(&db).unwrap().identity().weights_sha256.clone();
    assert!(info.contains(&sha) && sha.len() == 64, "{info}");

    let export = dir.path().join("export.csv");
    let out = ecm_lcd(&["db", "export", db.to_str().unwrap(), "-o", export.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(&export).unwrap();
    let rows: Vec<Vec<&str>> = text.lines().map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 7);
    assert_eq!(&rows[0][..3], ["id", "stamp", "d0"]);
    assert!(rows.iter().all(|r| r.len() == 2 + 2880));
    let stored = KeyframeStore::open_existing(&db).unwrap().keyframes().unwrap();
    let exported: Vec<f32> = rows[4][2..].iter().map(|v| v.parse().unwrap()).collect();
    assert_eq!((rows[4][0], exported), ("3", stored[3].descriptor.clone()));

    let merged = dir.path().join("merged.db");
    let out = ecm_lcd(&["db", "merge", db.to_str().unwrap(), db.to_str().unwrap(), "-o", merged.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success()
            && err.contains("6 keyframe id(s)")
            && err.contains("0, 1, 2, 3, 4, 5")
            && err.contains("--offset 6"),
        "{err}"
    );
    let out = ecm_lcd(&[
        "db",
        "merge",
        db.to_str().unwrap(),
        db.to_str().unwrap(),
        "-o",
        merged.to_str().unwrap(),
        "--offset",
        "6",
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(stored_ids(&merged), (0..12).collect::<Vec<_>>());

    // Replaying with another descriptor mode into this database is refused, naming both.
    let mut args = replay_args(seq.to_str().unwrap(), db.to_str().unwrap(), csv.to_str().unwrap());
    args.extend(["--param", "descriptor.mode=paper"]);
    let out = ecm_lcd(&args);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success()
            && err.contains("descriptor regional-3x3-mac@blocks.16")
            && err.contains("descriptor paper")
            && err.contains("a.db"),
        "{err}"
    );
}

/// A replay stopped after any frame and restarted under the default selection (frames at 10 Hz,
/// keyframes at most every 0.5 s) stores exactly the keyframes of an uninterrupted run: selection
/// continues from the newest stored keyframe rather than taking the first frame after the restart.
#[test]
fn a_restarted_replay_selects_the_keyframes_of_an_uninterrupted_one() {
    let dir = tempfile::tempdir().unwrap();
    let config = SynthConfig { frames: 30, laps: 1, width: 96, height: 72, rate_hz: 10.0, ..SynthConfig::default() };
    let seq = dir.path().join("seq");
    write_tum_folder(&Scene::new(config).unwrap(), &seq).unwrap();
    let frames: Vec<_> = ecm_lcd::io::open_source(&seq, None).unwrap().map(|f| f.unwrap()).collect();
    let mut params = Params::default();
    params.set_from_str("input_size", "64").unwrap();
    let weights = resolve::load_file(&shared().join("models/mobilenet_v2_1.0_224_quant.tflite")).unwrap();
    let pipeline = |db: &Path| {
        let mut p = Pipeline::with_weights(params.clone(), weights.clone()).unwrap();
        p.open_store(db).unwrap();
        p
    };
    let reference_db = dir.path().join("reference.db");
    ecm_lcd::replay::run_source(&mut pipeline(&reference_db), &seq, &Default::default(), false).unwrap();
    let reference = stored_ids(&reference_db);
    assert!(reference.len() >= 5 && reference.len() < frames.len() / 2, "selection kept {reference:?}");
    for stop_after in [0, 3, 5, 6, 12, 17] {
        let db = dir.path().join(format!("stopped{stop_after}.db"));
        {
            let mut first = pipeline(&db);
            for frame in &frames[..=stop_after] {
                first.process_frame(frame.index as u64, frame.stamp, &frame.image).unwrap();
            }
        }
        let run = ecm_lcd::replay::run_source(&mut pipeline(&db), &seq, &Default::default(), false).unwrap();
        assert!(run.skipped > 0);
        assert_eq!(stored_ids(&db), reference, "stopped after frame {stop_after}");
    }
}

/// A database is continued only with the source it was built from: another sequence (same stamps,
/// other images), one with other stamps, or a shorter one is refused with a clear error.
#[test]
fn a_database_refuses_to_continue_another_source() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, seed: u64, rate_hz: f64, frames: usize| {
        let config = SynthConfig { frames, laps: 1, seed, width: 96, height: 72, rate_hz, ..SynthConfig::default() };
        let seq = dir.path().join(name);
        write_tum_folder(&Scene::new(config).unwrap(), &seq).unwrap();
        seq.to_str().unwrap().to_string()
    };
    let (a, other_images, other_stamps, shorter) =
        (write("a", 1, 2.0, 8), write("b", 2, 2.0, 8), write("c", 1, 3.0, 8), write("d", 1, 2.0, 4));
    let db = dir.path().join("a.db");
    let csv = dir.path().join("a.csv");
    let run = |source: &str| ecm_lcd(&replay_args(source, db.to_str().unwrap(), csv.to_str().unwrap()));
    assert!(run(&a).status.success());
    for (source, expected) in
        [(&other_images, "differs from its keyframe"), (&other_stamps, "has stamp"), (&shorter, "has only 4 frames")]
    {
        let out = run(source);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains("built from another source") && err.contains(expected),
            "{source}: {err}"
        );
    }
    // The same source again is fine.
    assert!(run(&a).status.success());
    // Where the frame of the newest stored keyframe cannot be read now, its stamp still tells
    // another source apart, and the same source goes on with a warning.
    let newest = *stored_ids(&db).last().unwrap() as usize;
    for source in [&a, &other_stamps] {
        let mut images: Vec<PathBuf> =
            std::fs::read_dir(Path::new(source).join("rgb")).unwrap().map(|e| e.unwrap().path()).collect();
        images.sort();
        std::fs::write(&images[newest], b"cut").unwrap();
    }
    let out = run(&other_stamps);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("built from another source") && err.contains("(unreadable)"),
        "{err}"
    );
    let out = run(&a);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains(&format!("frame {newest}, the keyframe database's newest")), "{err}");
}

/// A two-lap synthetic sequence (240 frames at 5 Hz, seed 5) written into a folder, its frames, and
/// pipelines for the renderer's camera (focal 0.82 * width, principal point at the centre) with
/// some parameters more, each on a given store.
struct RestartCase {
    scene: Scene,
    frames: Vec<ecm_lcd::types::Frame>,
    params: Params,
    weights: ecm_lcd::model::weights::resolve::Resolved,
}

impl RestartCase {
    fn new(dir: &Path, depth: bool, extra: &[(&str, &str)]) -> Self {
        let seq = dir.join("seq");
        let config = SynthConfig { frames: 240, laps: 2, seed: 5, rate_hz: 5.0, depth, ..SynthConfig::default() };
        let scene = Scene::new(config).unwrap();
        write_tum_folder(&scene, &seq).unwrap();
        let frames = ecm_lcd::io::open_source(&seq, None).unwrap().map(|f| f.unwrap()).collect();
        let mut params = Params::default();
        let camera = [("camera.fx", "262.4"), ("camera.fy", "262.4"), ("camera.cx", "160"), ("camera.cy", "120")];
        for (name, value) in camera.iter().chain(extra) {
            params.set_from_str(name, value).unwrap();
        }
        let weights = resolve::load_file(&shared().join("models/mobilenet_v2_1.0_224_quant.tflite")).unwrap();
        RestartCase { scene, frames, params, weights }
    }

    fn pipeline(&self, db: &Path) -> Pipeline {
        let mut p = Pipeline::with_weights(self.params.clone(), self.weights.clone()).unwrap();
        p.open_store(db).unwrap();
        p
    }
}

/// With verification on, a pipeline restarted on its database verifies loops to keyframes stored
/// before the restart as an uninterrupted one does: their local features (with depth) come back from
/// the database. The candidates after the restart, their inliers and metric poses, equal the
/// uninterrupted run's.
#[test]
fn a_restart_keeps_verifying_loops_to_keyframes_stored_before_it() {
    let dir = tempfile::tempdir().unwrap();
    let case = RestartCase::new(dir.path(), true, &[]);
    let (frames, pipeline) = (&case.frames, |db: &Path| case.pipeline(db));
    // (query, match, inliers, metric, translation) of every candidate from frame `from` on.
    type Row = (u64, u64, u32, bool, [f64; 3]);
    let run = |p: &mut Pipeline, frames: &[ecm_lcd::types::Frame]| -> Vec<Row> {
        let mut rows = Vec::new();
        for frame in frames {
            for c in p.process_source_frame(frame, None).unwrap().candidates {
                let verified = c.verified.expect("verification is on");
                let pose = verified.pose.expect("intrinsics given: a pose");
                let t = pose.translation;
                rows.push((c.query_id, c.match_id, verified.inliers, pose.metric, [t.x, t.y, t.z]));
            }
        }
        rows
    };
    let restart_at = 150; // in the second lap: loops to the first lap from before and after the restart
    let uninterrupted = run(&mut pipeline(&dir.path().join("whole.db")), frames);
    let db = dir.path().join("restarted.db");
    let before = run(&mut pipeline(&db), &frames[..restart_at]);
    let after = run(&mut pipeline(&db), &frames[restart_at..]);
    let expected_after: Vec<Row> = uninterrupted.iter().filter(|r| r.0 >= restart_at as u64).cloned().collect();
    assert!(expected_after.len() >= 20, "{} loops after the restart point", expected_after.len());
    assert!(expected_after.iter().all(|r| r.3), "every loop metric (depth)");
    assert_eq!(before.len() + after.len(), uninterrupted.len());
    let key = |rows: &[Row]| rows.iter().map(|r| (r.0, r.1, r.2, r.3)).collect::<Vec<_>>();
    assert_eq!(key(&after), key(&expected_after), "candidates, inliers and metric flags after the restart");
    for (got, want) in after.iter().zip(&expected_after) {
        let apart = (0..3).map(|i| (got.4[i] - want.4[i]).powi(2)).sum::<f64>().sqrt();
        assert!(apart < 1e-9, "{} -> {}: translation {apart} m from the uninterrupted run's", got.0, got.1);
    }
    println!("{} candidates after the restart, all verified and metric as without it", after.len());
}

/// The odometry check goes on through a restart: the tracker poses of keyframes stored before it come
/// back from the database, so a loop to one of them that the tracker puts elsewhere is still rejected.
#[test]
fn a_restart_keeps_checking_loops_against_the_stored_tracker_poses() {
    let dir = tempfile::tempdir().unwrap();
    let case = RestartCase::new(dir.path(), false, &[("verification.max_drift", "0.1")]);
    let (scene, frames, pipeline) = (&case.scene, &case.frames, |db: &Path| case.pipeline(db));
    let second_lap = frames.len() / 2;
    // Loops from the second lap to the first, with the tracker's pose of each frame from `pose`.
    let loops = |p: &mut Pipeline, frames: &[ecm_lcd::types::Frame], pose: &dyn Fn(usize) -> Isometry3<f64>| {
        let mut loops = Vec::new();
        for frame in frames {
            let outcome = p.process_source_frame(frame, Some(pose(frame.index))).unwrap();
            loops.extend(
                outcome.candidates.iter().filter(|c| c.match_id < second_lap as u64).map(|c| (c.query_id, c.match_id)),
            );
        }
        loops
    };
    let truth = |i: usize| scene.pose(i);
    let found = loops(&mut pipeline(&dir.path().join("truth.db")), frames, &truth);
    assert!(found.len() >= 10, "{found:?}: loops that fit the true trajectory pass");
    // A tracker that put the second lap 10 m away: before and after a restart in that lap, no loop
    // to the first lap passes.
    let elsewhere = |i: usize| {
        let mut pose = scene.pose(i);
        if i >= second_lap {
            pose.translation.vector.x += 10.0;
        }
        pose
    };
    let restart_at = second_lap + 30;
    let db = dir.path().join("restarted.db");
    let before = loops(&mut pipeline(&db), &frames[..restart_at], &elsewhere);
    let after = loops(&mut pipeline(&db), &frames[restart_at..], &elsewhere);
    assert_eq!(before, [], "before the restart");
    assert_eq!(after, [], "after the restart");
    assert!(found.iter().filter(|(q, _)| *q >= restart_at as u64).count() >= 5, "{found:?}");

    // The first lap stored by a run without poses, the second continued with them (the elsewhere
    // ones): loops to the first lap cannot be checked, and each reported one is counted as such.
    let db = dir.path().join("half_posed.db");
    let mut unposed = pipeline(&db);
    for frame in &frames[..second_lap] {
        let outcome = unposed.process_source_frame(frame, None).unwrap();
        assert_eq!(outcome.unchecked_by_odometry, 0, "no keyframe has a pose yet");
    }
    drop(unposed);
    let mut continued = pipeline(&db);
    let (mut reported, mut unchecked) = (0, 0);
    for frame in &frames[second_lap..] {
        let outcome = continued.process_source_frame(frame, Some(elsewhere(frame.index))).unwrap();
        reported += outcome.candidates.iter().filter(|c| c.match_id < second_lap as u64).count();
        unchecked += outcome.unchecked_by_odometry;
    }
    assert!(reported >= 5 && unchecked >= reported, "{reported} loops to the first lap, {unchecked} counted unchecked");
}

/// Temporal consistency (delayed, with verification) and the sequence policy remember the last
/// keyframes' matches and descriptors; a restart resumes both from the database, so restarts in the
/// middle of a revisit report exactly the loops of an uninterrupted run, late ones included.
#[test]
fn restarts_in_a_revisit_keep_temporal_consistency_and_the_sequence_policy() {
    let dir = tempfile::tempdir().unwrap();
    let extra = [("detector.consistency.queries", "2"), ("detector.sequence.length", "3")];
    let case = RestartCase::new(dir.path(), false, &extra);
    let (frames, pipeline) = (&case.frames, |db: &Path| case.pipeline(db));
    // (keyframe that reported it, query, match, rank, inliers, score) of every candidate.
    type Row = (u64, u64, u64, u32, u32, f32);
    let run = |p: &mut Pipeline, frames: &[ecm_lcd::types::Frame]| -> Vec<Row> {
        let mut rows = Vec::new();
        for frame in frames {
            let outcome = p.process_source_frame(frame, None).unwrap();
            for c in outcome.candidates {
                let inliers = c.verified.expect("verification is on").inliers;
                rows.push((outcome.keyframe.unwrap(), c.query_id, c.match_id, c.rank, inliers, c.score));
            }
        }
        rows
    };
    let uninterrupted = run(&mut pipeline(&dir.path().join("whole.db")), frames);
    let late = |rows: &[Row]| rows.iter().filter(|r| r.1 != r.0).count();
    assert!(uninterrupted.len() >= 20 && late(&uninterrupted) >= 1, "{uninterrupted:?}");
    // A restart before every frame of the second lap, so each late loop's query was held back
    // before a restart and confirmed after one.
    let db = dir.path().join("restarted.db");
    let mut restarted = run(&mut pipeline(&db), &frames[..100]);
    let mut late_after_restart = 0;
    for chunk in frames[100..].chunks(1) {
        let rows = run(&mut pipeline(&db), chunk);
        // Held back before this restart, confirmed after it (ids are frame indices).
        late_after_restart += rows.iter().filter(|r| r.1 < chunk[0].index as u64).count();
        restarted.extend(rows);
    }
    assert_eq!(restarted, uninterrupted, "candidates with a restart before every frame");
    assert_eq!(late_after_restart, late(&uninterrupted));
    println!(
        "{} candidates ({} late, {late_after_restart} held back before a restart and confirmed after it)",
        uninterrupted.len(),
        late(&uninterrupted)
    );
}
