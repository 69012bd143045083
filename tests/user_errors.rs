//! Commands a user mistypes: an output that names an input (or a file of a source folder, or another
//! output), a database path that is a device, a
//! FIFO, a directory or a symlink, read-only inspection of files that are not keyframe databases,
//! and numbers far out of range. Each must fail fast (within 2 s and 200 MB) with an error that says
//! what is wrong, and every file involved must keep its bytes (and its kind) afterwards.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use ecm_lcd::detector::store::{KeyframeStore, StoreIdentity};
use ecm_lcd::types::Stamp;

fn command() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_ecm-lcd"));
    command.env("ECM_LCD_CACHE", Path::new(env!("CARGO_TARGET_TMPDIR")).join("weights-cache")).env("RUST_LOG", "warn");
    command
}

/// Runs the binary; it must fail within 2 s (before any network is built) with every `expected`
/// piece in its error. Returns the error text.
fn refused(args: &[&str], expected: &[&str]) -> String {
    let started = Instant::now();
    let out: Output = command().args(args).output().unwrap();
    let elapsed = started.elapsed();
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "{args:?} succeeded:\n{err}");
    for piece in expected {
        assert!(err.contains(piece), "{args:?}: {piece:?} not in:\n{err}");
    }
    assert!(elapsed < Duration::from_secs(2), "{args:?} took {elapsed:?}");
    let peak = peak_child_rss_mb();
    assert!(peak > 1.0 && peak < 200.0, "{args:?}: a command of this test binary peaked at {peak:.0} MB");
    err
}

/// The largest resident set any finished child of this process reached, in MB (Linux reports KiB).
fn peak_child_rss_mb() -> f64 {
    // SAFETY: getrusage only writes into the zeroed struct it is given.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let status = unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage) };
    assert_eq!(status, 0, "getrusage failed");
    usage.ru_maxrss as f64 / 1024.0
}

/// Every file in `dir` with its length and a hash of its bytes (compared, and printed on a mismatch).
fn snapshot(dir: &Path) -> Vec<(PathBuf, usize, u64)> {
    use std::hash::{Hash, Hasher};
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| std::fs::symlink_metadata(p).unwrap().is_file())
        .map(|p| {
            let bytes = std::fs::read(&p).unwrap();
            let mut hasher = std::collections::hash_map::DefaultHasher::new();
            bytes.hash(&mut hasher);
            (p, bytes.len(), hasher.finish())
        })
        .collect();
    files.sort();
    files
}

/// A small valid keyframe store of 3 keyframes.
fn store(path: &Path) {
    let identity = StoreIdentity {
        weights_sha256: "0".repeat(64),
        arch: "mobilenetv2".into(),
        descriptor_mode: "l2".into(),
        input_size: 224,
        dim: 4,
    };
    let mut store = KeyframeStore::open_or_create(path, &identity).unwrap();
    for id in 0..3u64 {
        store.append(id, Stamp::from_sec_nsec(100 + id as i64, 0), &[0.5, 0.5, 0.5, id as f32]).unwrap();
    }
}

#[test]
fn an_output_that_is_an_input_is_refused_and_the_input_kept() {
    let dir = tempfile::tempdir().unwrap();
    let d = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let image = image::RgbImage::from_fn(32, 24, |x, y| image::Rgb([x as u8 * 8, y as u8 * 10, 77]));
    image.save(d("frame.png")).unwrap();
    store(Path::new(&d("k.db")));
    std::fs::write(d("m.tflite"), b"not really a model").unwrap();
    std::fs::create_dir(dir.path().join("seq")).unwrap();
    image.save(d("seq/0.png")).unwrap();
    std::fs::write(d("loops.csv"), "0,0\n").unwrap();
    let before = snapshot(dir.path());
    let source_before = snapshot(&dir.path().join("seq"));

    refused(&["embed", &d("frame.png"), "-o", &d("frame.png")], &["frame.png", "destroy"]);
    refused(&["db", "export", &d("k.db"), "-o", &d("k.db")], &["k.db", "destroy"]);
    refused(&["replay", &d("seq"), "--db", &d("k.db"), "-o", &d("k.db")], &["k.db", "destroy"]);
    refused(&["import-weights", &d("m.tflite"), "-o", &d("m.tflite")], &["m.tflite", "destroy"]);
    // Another spelling of the same file.
    let spelled = dir.path().join(".").join("frame.png");
    refused(&["embed", &d("frame.png"), "-o", spelled.to_str().unwrap()], &["destroy"]);

    // A file the source folder holds, or the loop truth.
    refused(&["replay", &d("seq"), "-o", &d("seq/0.png")], &["seq/0.png", "file of the source folder"]);
    let (database, queries) = (["--database", &d("seq")], ["--queries", &d("seq")]);
    refused(&["match", database[0], database[1], queries[0], queries[1], "-o", &d("seq/0.png")], &["source folder"]);
    let eval = ["eval", database[0], database[1], queries[0], queries[1], "--loops", &d("loops.csv")];
    refused(&[&eval[..], &["-o", &d("loops.csv")]].concat(), &["loops.csv", "destroy"]);
    // eval's --db, which it reads and writes, as replay's.
    let eval_source = ["eval", &d("seq"), "--loops", &d("loops.csv")];
    refused(&[&eval_source[..], &["--db", &d("loops.csv")]].concat(), &["loops.csv", "destroy"]);
    refused(&[&eval_source[..], &["--db", &d("n.db"), "-o", &d("n.db")]].concat(), &["--db and -o both name"]);
    refused(&[&eval_source[..], &["--db", &d("n.db"), "-o", &d("n.db-wal")]].concat(), &["own -wal file"]);
    refused(&["eval", &d("seq"), "--max-angle", "200"], &["--max-angle must be at most 180"]);
    // Pose-truth options beside a loops file, which would be ignored.
    refused(&[&eval_source[..], &["--max-angle", "10"]].concat(), &["--max-angle", "cannot be used with"]);
    // A new image directly in an image folder would be read as one more frame.
    refused(&[&eval_source[..], &["--plot", &d("seq/pr.png")]].concat(), &["seq/pr.png", "source folder"]);
    // Two outputs under one name, whether the file exists yet or not.
    refused(&["replay", &d("seq"), "--db", &d("new.db"), "-o", &d("new.db")], &["--db and -o both name", "new.db"]);
    refused(&[&eval[..], &["-o", &d("pr.png"), "--plot", &d("pr.png")]].concat(), &["-o and --plot both name"]);
    let pose_graph = ["pose-graph", "--odometry", &d("o.txt"), "--candidates", &d("c.csv")];
    refused(&[&pose_graph[..], &["-o", &d("same.png"), "--plot", &d("same.png")]].concat(), &["both name"]);

    // synth writes new bags only, and checks before it renders anything.
    refused(&["synth", "-o", &d("synth"), "--frames", "4", "--ros1-bag", &d("k.db")], &["k.db", "already exists"]);
    refused(&["synth", "-o", &d("synth"), "--frames", "4", "--ros2-bag", &d("seq")], &["already exists"]);
    refused(&["synth", "-o", &d("synth"), "--frames", "4", "--ros2-bag", &d("synth")], &["is the output folder"]);
    let own_file = d("synth/rgb.txt");
    refused(&["synth", "-o", &d("synth"), "--frames", "4", "--ros1-bag", &own_file], &["a file of the sequence"]);
    let both = ["--ros1-bag", &d("b.bag"), "--ros2-bag", &d("b.bag")];
    refused(&[&["synth", "-o", &d("synth"), "--frames", "4"][..], &both].concat(), &["both", "choose two paths"]);
    assert!(!dir.path().join("synth").exists(), "a refused synth wrote its folder");
    // A bag inside the output folder, which synth makes.
    let inside = d("synth/synth.bag");
    let out = command()
        .args(["synth", "-o", &d("synth"), "--frames", "4", "--width", "32", "--height", "24", "--ros1-bag", &inside])
        .output()
        .unwrap();
    assert!(out.status.success() && Path::new(&inside).is_file(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(!Path::new(&format!("{inside}.writing")).exists());
    std::fs::remove_dir_all(d("synth")).unwrap();

    assert_eq!(snapshot(dir.path()), before, "a refused command changed a file");
    assert_eq!(snapshot(&dir.path().join("seq")), source_before, "a refused command changed a source file");
}

#[test]
fn a_database_path_that_is_not_a_regular_file_is_refused_not_replaced() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    std::fs::create_dir(&seq).unwrap();
    let seq = seq.to_str().unwrap();

    let folder = dir.path().join("a_folder.db");
    std::fs::create_dir(&folder).unwrap();
    refused(&["replay", seq, "--db", folder.to_str().unwrap(), "--quiet"], &["a_folder.db", "not a regular file"]);
    assert!(folder.is_dir());

    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        let fifo = dir.path().join("pipe.db");
        assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        refused(&["replay", seq, "--db", fifo.to_str().unwrap(), "--quiet"], &["pipe.db", "not a regular file"]);
        assert!(std::fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo(), "the FIFO was replaced");
        refused(&["db", "info", fifo.to_str().unwrap()], &["pipe.db", "not a regular file"]);
    }

    // A symlink to a valid store is read through and stays a symlink.
    #[cfg(unix)]
    {
        let real = dir.path().join("real.db");
        store(&real);
        let link = dir.path().join("link.db");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let out = command().args(["db", "info", link.to_str().unwrap()]).output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        assert!(String::from_utf8_lossy(&out.stdout).contains("keyframes:       3"));
        assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
    }
}

#[test]
fn inspection_never_creates_converts_or_modifies_a_file() {
    let dir = tempfile::tempdir().unwrap();
    // An empty file, an SQLite database of another schema (rollback journal), and a valid store.
    let empty = dir.path().join("empty.db");
    std::fs::write(&empty, b"").unwrap();
    let other = dir.path().join("other.db");
    {
        let c = rusqlite::Connection::open(&other).unwrap();
        c.execute_batch("CREATE TABLE notes (t TEXT); INSERT INTO notes VALUES ('hello');").unwrap();
    }
    let valid = dir.path().join("valid.db");
    store(&valid);
    let before = snapshot(dir.path());

    refused(&["db", "info", empty.to_str().unwrap()], &["empty.db", "not a keyframe database"]);
    refused(&["db", "info", other.to_str().unwrap()], &["other.db", "not a keyframe database"]);
    refused(
        &["db", "export", other.to_str().unwrap(), "-o", dir.path().join("x.csv").to_str().unwrap()],
        &["other.db"],
    );
    let out = command().args(["db", "info", valid.to_str().unwrap()]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));

    // Same files, same bytes: nothing was created (no journal, no WAL), nothing converted.
    assert_eq!(snapshot(dir.path()), before, "inspection changed or created a file");
    let mode: String =
        rusqlite::Connection::open(&other).unwrap().query_row("PRAGMA journal_mode", [], |r| r.get(0)).unwrap();
    assert_eq!(mode, "delete", "the other database was switched to {mode}");
}

#[test]
fn numbers_far_out_of_range_are_refused_at_once() {
    let image = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/imagenet/cat.bmp");
    let image = image.to_str().unwrap();
    refused(&["classify", "--size", "65536", image], &["65536", "1024"]);
    refused(&["classify", "--size", "100", image], &["100", "multiple of 32"]);
    refused(&["--threads", "100000", "classify", image], &["100000", "--threads"]);
    refused(&["--threads", "0", "classify", image], &["--threads"]);
    refused(&["train", "--data", image, "-o", "x.safetensors", "--target-accuracy", "90"], &["'90'", "(0, 1]"]);
    // Values no schedule can use: they used to crash the batch loader into an epoch of no steps
    // reported as done, or to train to a loss of 0.
    refused(
        &["train", "--data", image, "-o", "x.safetensors", "--colour-jitter", "inf"],
        &["--colour-jitter", "[0, 1]"],
    );
    refused(&["distill", "--data", image, "-o", "x.safetensors", "--lr", "0"], &["--lr must be positive"]);
    refused(&["train-place", image, "-o", "x.safetensors", "--margin=-5"], &["--margin must be in (0, 4]"]);
    // A run's weights never replace the weights it starts from.
    let dir = tempfile::tempdir().unwrap();
    let tflite = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/models/mobilenet_v2_1.0_224_quant.tflite");
    let own = dir.path().join("teacher.tflite");
    std::fs::copy(&tflite, &own).unwrap();
    let own = own.to_str().unwrap();
    refused(&["distill", "--teacher", own, "--data", image, "-o", own], &["destroy"]);
    refused(&["train", "--init", own, "--data", image, "-o", own], &["destroy"]);
    refused(&["train-place", image, "--init", own, "-o", own], &["destroy"]);
    assert_eq!(std::fs::read(own).unwrap(), std::fs::read(&tflite).unwrap());
    #[cfg(unix)]
    refused(&["embed", image, "-o", "/dev/full"], &["cannot write /dev/full"]);
    #[cfg(unix)]
    {
        // Weights are written into the device, which fails (it is full), and never replace it.
        use std::os::unix::fs::FileTypeExt;
        let tflite = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/models/mobilenet_v2_1.0_224_quant.tflite");
        refused(&["import-weights", tflite.to_str().unwrap(), "-o", "/dev/full"], &["cannot write /dev/full"]);
        assert!(std::fs::symlink_metadata("/dev/full").unwrap().file_type().is_char_device(), "/dev/full was replaced");
    }
}

#[test]
fn endless_garbage_and_truth_outside_the_data_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    // A TUM folder whose rgb.txt has one 5 MB line: the error quotes a short excerpt.
    std::fs::create_dir(d("seq")).unwrap();
    std::fs::write(d("seq/rgb.txt"), format!("1.0 a {}\n", "x/".repeat(2_500_000))).unwrap();
    let err = refused(&["replay", &d("seq"), "--quiet"], &["rgb.txt:1", "expected `timestamp path`", "bytes)"]);
    assert!(err.len() < 2000, "the error echoes the line: {} bytes", err.len());
    std::fs::write(d("seq/rgb.txt"), format!("1.0 {}\n", "x/".repeat(2_500_000))).unwrap();
    let err = refused(&["replay", &d("seq"), "--quiet"], &["rgb.txt:1", "does not exist", "bytes)"]);
    assert!(err.len() < 2000, "the error echoes the path: {} bytes", err.len());
    // An image path that is a directory, or a symlink loop, says so.
    std::fs::create_dir(d("seq/rgb")).unwrap();
    std::fs::write(d("seq/rgb.txt"), "1.0 rgb\n").unwrap();
    refused(&["replay", &d("seq"), "--quiet"], &["rgb.txt:1", "is a directory"]);
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(d("seq/loop.png"), d("seq/loop.png")).unwrap();
        std::fs::write(d("seq/rgb.txt"), "1.0 loop.png\n").unwrap();
        refused(&["replay", &d("seq"), "--quiet"], &["rgb.txt:1", "symlink that cannot be followed"]);
        std::fs::remove_file(d("seq/loop.png")).unwrap();
    }
    std::fs::remove_dir(d("seq/rgb")).unwrap();
    std::fs::write(d("seq/rgb.txt"), "1.0 a.png\n").unwrap();
    #[cfg(unix)]
    {
        refused(&["replay", &d("seq"), "--config", "/dev/zero"], &["params file", "/dev/zero", "MiB"]);
        refused(&["replay", &d("seq"), "--weights", "/dev/zero"], &["/dev/zero", "MiB"]);
        refused(&["import-weights", "/dev/zero", "-o", &d("w.safetensors")], &["/dev/zero", "MiB"]);
        assert!(!dir.path().join("w.safetensors").exists(), "nothing written");
    }
    // Brackets nested 100 000 deep in a params file.
    std::fs::write(d("deep.yaml"), format!("ecm_lcd:\n  ros__parameters:\n    x: {}\n", "[".repeat(100_000))).unwrap();
    refused(&["replay", &d("seq"), "--config", &d("deep.yaml")], &["deep.yaml", "nested deeper"]);

    // Loops that name images past the folders' ends.
    for folder in ["db", "q"] {
        std::fs::create_dir(d(folder)).unwrap();
        for i in 0..3u8 {
            let image = image::RgbImage::from_fn(32, 32, |x, y| image::Rgb([x as u8 * 7 + i * 40, y as u8 * 5, 60]));
            image.save(d(&format!("{folder}/{i}.png"))).unwrap();
        }
    }
    std::fs::write(d("loops.csv"), "0,0\n1,7\n").unwrap();
    refused(
        &["eval", "--database", &d("db"), "--queries", &d("q"), "--loops", &d("loops.csv")],
        &["7", "only 3 references"],
    );
    std::fs::write(d("loops.csv"), "5,0\n").unwrap();
    refused(
        &["eval", "--database", &d("db"), "--queries", &d("q"), "--loops", &d("loops.csv")],
        &["query 5", "only 3 queries"],
    );
}

#[test]
fn plots_must_be_png_and_empty_sources_and_foreign_databases_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    std::fs::create_dir(d("seq")).unwrap();
    let image = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8 * 3, y as u8 * 5, 90]));
    image.save(d("seq/0.png")).unwrap();
    image.save(d("seq/1.png")).unwrap();
    refused(&["eval", &d("seq"), "--plot", &d("pr.txt")], &["pr.txt", "PNG", ".png"]);
    std::fs::write(d("odometry.txt"), "1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n").unwrap();
    std::fs::write(d("c.csv"), "query_id,query_stamp,match_id,match_stamp,distance,score\n").unwrap();
    let refused_pose_graph = |output: &str, more: &[&str], expected: &[&str]| {
        let (odometry, candidates, output) = (d("odometry.txt"), d("c.csv"), d(output));
        let mut args = vec!["pose-graph", "--odometry", &odometry, "--candidates", &candidates, "-o", &output];
        args.extend(more);
        refused(&args, expected);
    };
    refused_pose_graph("out.txt", &["--plot", &d("f.jpg")], &["f.jpg", "PNG"]);
    refused_pose_graph("c.csv", &[], &["destroy"]);
    refused_pose_graph("out.txt", &["--robust-rotation-scale", "0"], &["--robust-rotation-scale", "positive"]);
    // What fails after the work, fails before any output is written: a ground truth that cannot
    // be read or pairs with no pose, a plot in a folder that does not exist.
    std::fs::write(d("other.txt"), "100.0 0 0 0 0 0 0 1\n101.0 1 0 0 0 0 0 1\n").unwrap();
    refused_pose_graph("out.txt", &["--groundtruth", &d("missing.txt")], &["missing.txt"]);
    refused_pose_graph("out.txt", &["--groundtruth", &d("other.txt")], &["ground-truth pose within"]);
    // A plot in a folder that cannot be made (its parent is a file).
    refused_pose_graph("out.txt", &["--plot", &d("c.csv/p.png")], &["--plot", "cannot create"]);
    refused(&["eval", &d("seq"), "-o", &d("pr.csv"), "--plot", &d("c.csv/x.png")], &["--plot", "cannot create"]);
    // Candidates of which none gives a loop edge would leave the odometry as it was, unsaid: no
    // relative pose (not verified), or keyframes stamped in another time base than the odometry.
    let header = "query_id,query_stamp,match_id,match_stamp,distance,score";
    std::fs::write(d("c.csv"), format!("{header}\n1,2.0,0,1.0,0.5,0.9\n")).unwrap();
    refused_pose_graph("out.txt", &[], &["none of the 1 candidates", "1 carry no relative pose"]);
    let posed = "inliers,qx,qy,qz,qw,tx,ty,tz,metric";
    std::fs::write(d("c.csv"), format!("{header},{posed}\n1,102.0,0,101.0,0.5,0.9,30,0,0,0,1,1,0,0,1\n")).unwrap();
    refused_pose_graph("out.txt", &[], &["1 name keyframes with no odometry pose", "101.000000000 to 102.000000000"]);
    std::fs::write(d("c.csv"), format!("{header}\n")).unwrap();
    assert!(!Path::new(&d("out.txt")).exists() && !Path::new(&d("pr.csv")).exists());
    // Options that only a replayed source uses are refused where they would be ignored.
    refused(&["learn-projection", &d("seq"), "-o", &d("p.safetensors"), "--db", &d("k.db")], &["--db"]);
    assert!(!Path::new(&d("k.db")).exists());
    std::fs::write(d("loops.csv"), "1,0\n").unwrap();
    let database_and_queries = ["eval", "--database", &d("seq"), "--queries", &d("seq"), "--loops", &d("loops.csv")];
    refused(&[&database_and_queries[..], &["--db", &d("k.db")]].concat(), &["--db applies to a replayed SOURCE"]);
    assert!(!Path::new(&d("k.db")).exists(), "a refused --db is not created");
    // eval skips the frames a database already holds, so it would score part of the sequence.
    let out = command().args(["replay", &d("seq"), "--quiet", "--db", &d("k.db")]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    refused(&["eval", &d("seq"), "--quiet", "--db", &d("k.db")], &["k.db already holds", "not score"]);

    // A ROS 2 bag with its image topic and no message in it.
    let bag = dir.path().join("empty_bag");
    let written = ecm_lcd::io::ros2bag::write_ros2_bag(
        &bag,
        ecm_lcd::io::ros2bag::Ros2Storage::Sqlite3,
        "/camera/rgb/image_color",
        std::iter::empty(),
        ecm_lcd::io::image_msg::WireEncoding::Rgb8,
    )
    .unwrap();
    assert_eq!(written, 0);
    refused(&["replay", bag.to_str().unwrap(), "--quiet"], &["empty_bag", "no images"]);

    // A database whose newest keyframe has id i64::MAX cannot have come from a two-frame folder.
    let weights = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/models/mobilenet_v2_1.0_224_quant.tflite");
    let pipeline = ecm_lcd::pipeline::Pipeline::new(ecm_lcd::config::Params::default(), Some(&weights)).unwrap();
    let identity = pipeline.store_identity();
    let before = snapshot(dir.path());
    let mut store = KeyframeStore::open_or_create(Path::new(&d("max.db")), &identity).unwrap();
    store.append(i64::MAX as u64, Stamp::from_sec_nsec(5, 0), &vec![0.0; identity.dim]).unwrap();
    drop(store);
    let out = command()
        .args(["replay", &d("seq"), "--db", &d("max.db"), "--quiet", "--weights", weights.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "a foreign database was continued:\n{err}");
    assert!(err.contains("max.db") && err.contains(&i64::MAX.to_string()), "{err}");
    assert!(store_ids_unchanged(&d("max.db")));
    assert!(before.iter().all(|f| snapshot(dir.path()).contains(f)), "an input changed");
}

/// The one keyframe of the i64::MAX store is all it holds.
fn store_ids_unchanged(path: &str) -> bool {
    let store = KeyframeStore::open_read_only(Path::new(path)).unwrap();
    store.len() == 1
}

/// Stamps that repeat or go back are replayed in file order, and said with their counts.
#[test]
fn repeated_and_decreasing_stamps_are_warned_with_counts() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    std::fs::create_dir_all(seq.join("rgb")).unwrap();
    for i in 0..4u8 {
        let image = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8 * 3 + i * 50, y as u8 * 5, 90]));
        image.save(seq.join(format!("rgb/{i}.png"))).unwrap();
    }
    // 2.0 repeats 2.0; 1.5 goes back.
    std::fs::write(seq.join("rgb.txt"), "1.0 rgb/0.png\n2.0 rgb/1.png\n2.0 rgb/2.png\n1.5 rgb/3.png\n").unwrap();
    let weights = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/models/mobilenet_v2_1.0_224_quant.tflite");
    let out = command()
        .args(["replay", seq.to_str().unwrap(), "--quiet", "--weights", weights.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("1 stamp(s) repeat") && err.contains("1 go back in time"), "{err}");
}

/// Durations the ROS helper commands take that no duration holds (negative, infinite, or a rate so
/// low that its period overflows) are refused, naming the option, before any DDS participant starts.
/// They run in a private network namespace all the same, should one start.
#[test]
fn durations_out_of_range_are_refused_before_any_participant_starts() {
    let bag = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags/sample_loop.bag");
    let bag = bag.to_str().unwrap();
    let exe = Path::new(env!("CARGO_BIN_EXE_ecm-lcd"));
    for (args, expected) in [
        (&["listen", "--idle-timeout=-1"][..], "--idle-timeout"),
        (&["listen", "--wait-publisher", "inf"], "--wait-publisher"),
        (&["param", "--timeout", "1e30", "get", "/ecm_lcd", "detector.min_score"], "--timeout"),
        (&["play-keyframes", bag, "--rate", "1e-300"], "1 / --rate"),
        (&["play-keyframes", bag, "--linger", "inf"], "--linger"),
    ] {
        let out = ecm_lcd::ros::netns::private_netns_command(exe).args(args).env("RUST_LOG", "warn").output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}:\n{err}");
        assert!(err.contains(expected) && err.contains("seconds"), "{args:?}: {expected:?} not in:\n{err}");
    }
}
