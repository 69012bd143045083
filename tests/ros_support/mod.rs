//! Helpers shared by the ROS integration tests: re-running one test inside a private network namespace
//! (every DDS participant of the test then lives there; the outer run only checks the inner one's
//! result), `ecm-lcd node` and `ecm-lcd listen` as child processes, and the test-only Python
//! virtualenv with Eclipse Cyclone DDS.
#![allow(dead_code)] // each test binary uses a different subset

use ecm_lcd::ros::netns::{inside_private_netns, private_netns_command};
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

/// True inside the re-run (then the logger is set up for the test too).
pub fn inside() -> bool {
    let inside = inside_private_netns();
    if inside {
        let _ = env_logger::builder().is_test(true).filter_level(log::LevelFilter::Info).try_init();
    }
    inside
}

/// Re-runs this binary's test `name` in a private network namespace; checks that it passed and reached
/// its end (it prints `INNER-DONE`).
pub fn check_inner_run(name: &str) {
    let exe = std::env::current_exe().unwrap();
    let out = private_netns_command(&exe)
        .args([name, "--exact", "--nocapture", "--test-threads=1"])
        .output()
        .expect("running unshare (util-linux) for a private network namespace");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "inner run failed:\n{text}");
    assert!(text.contains("INNER-DONE"), "inner run did not complete:\n{text}");
    // What the inner run measured, for the outer run's --nocapture.
    text.lines().filter(|l| l.contains("INNER-DONE") || l.contains("seed")).for_each(|l| println!("{l}"));
}

/// The Python virtualenv with Cyclone DDS (created once under target/, reused afterwards). Call it
/// outside the namespace: the first call needs PyPI.
pub fn cyclone_python() -> PathBuf {
    static BUILDING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = BUILDING.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/test-venv-dds");
    let python = venv.join("bin/python");
    let has = |py: &Path| {
        std::process::Command::new(py)
            .args(["-c", "import cyclonedds.domain"])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !has(&python) {
        let status = std::process::Command::new("python3").arg("-m").arg("venv").arg(&venv).status();
        assert!(status.is_ok_and(|s| s.success()), "python3 -m venv {} failed", venv.display());
        let status = std::process::Command::new(&python).args(["-m", "pip", "install", "-q", "cyclonedds"]).status();
        assert!(status.is_ok_and(|s| s.success()), "pip install cyclonedds failed");
    }
    assert!(has(&python), "cyclonedds not importable from {}", python.display());
    python
}

/// The peer script beside this file.
pub fn cyclone_peer_script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/ros_support/cyclone_peer.py")
}

/// `ecm-lcd listen` as a child process, started once it matched the node's publisher, so that no
/// candidate is published before anyone listens.
pub struct Listener {
    child: Child,
    stdout: BufReader<ChildStdout>,
    pub header: String,
}

impl Listener {
    pub fn start(count: usize) -> Listener {
        let mut child = Command::new(env!("CARGO_BIN_EXE_ecm-lcd"))
            .args(["listen", "--wait-publisher", "60", "--idle-timeout", "60", "--count", &count.to_string()])
            .env("RUST_LOG", "warn,rustdds=error")
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        let mut header = String::new();
        stdout.read_line(&mut header).unwrap();
        // The replay's candidate columns, then the message's rank and type.
        assert_eq!(
            header.trim(),
            [ecm_lcd::io::candidates::columns(), vec!["rank".into(), "loop_type".into()]].concat().join(","),
            "listener failed to start"
        );
        // The writer side of the match may lag the reader side a little.
        std::thread::sleep(Duration::from_millis(500));
        Listener { child, stdout, header }
    }

    /// Waits for the listener to end; returns its CSV rows (no header: that is in `header`).
    pub fn finish(mut self) -> String {
        let mut csv = String::new();
        self.stdout.read_to_string(&mut csv).unwrap();
        assert!(self.child.wait().unwrap().success(), "listen failed:\n{csv}");
        csv
    }
}

/// `ecm-lcd node` as a child process, its log (debug lines of the node module) in a file.
pub struct NodeProcess {
    pub child: Child,
    pub log: PathBuf,
}

impl NodeProcess {
    /// Starts `ecm-lcd node --queue 128 ARGS...`, with its weights cache under `dir` and its log at `log`.
    pub fn start<S: AsRef<std::ffi::OsStr>>(
        dir: &Path,
        log: PathBuf,
        args: impl IntoIterator<Item = S>,
    ) -> NodeProcess {
        Self::start_logging(dir, log, args, Some("info,ecm_lcd::ros::node=debug,rustdds=error"))
    }

    /// As [`NodeProcess::start`], with `RUST_LOG` set to `filter`, or unset (the node's default) for `None`.
    pub fn start_logging<S: AsRef<std::ffi::OsStr>>(
        dir: &Path,
        log: PathBuf,
        args: impl IntoIterator<Item = S>,
        filter: Option<&str>,
    ) -> NodeProcess {
        let mut command = Command::new(env!("CARGO_BIN_EXE_ecm-lcd"));
        match filter {
            Some(filter) => command.env("RUST_LOG", filter),
            None => command.env_remove("RUST_LOG"),
        };
        let child = command
            .args(["node", "--queue", "128"])
            .args(args)
            .env("ECM_LCD_CACHE", dir.join("cache"))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        NodeProcess { child, log }
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Waits until the node logged `needle` (e.g. a keyframe's debug line).
    pub fn wait_for_log(&self, needle: &str, within: Duration) {
        let end = Instant::now() + within;
        while !self.log_text().contains(needle) {
            assert!(Instant::now() < end, "node never logged {needle:?}:\n{}", self.log_text());
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// Writes the node tests' sequence to `dir/seq` as a TUM folder: `frames` frames of two laps of a
/// small synthetic scene at 10 Hz.
#[allow(dead_code)] // each test crate builds this module for itself, and not every one calls this
pub fn looped_sequence(dir: &Path, frames: usize) -> PathBuf {
    let config = ecm_lcd::synth::SynthConfig {
        frames,
        laps: 2,
        seed: 3,
        width: 160,
        height: 120,
        rate_hz: 10.0,
        ..ecm_lcd::synth::SynthConfig::default()
    };
    let seq = dir.join("seq");
    ecm_lcd::synth::write_tum_folder(&ecm_lcd::synth::Scene::new(config).unwrap(), &seq).unwrap();
    seq
}
