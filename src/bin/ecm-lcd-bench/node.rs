//! `ecm-lcd-bench node`: a benchmark program (not a test) for the node's end-to-end latency: the time
//! from publishing an ecm_lcd_msgs/Keyframe to receiving its LoopCandidate, over DDS on loopback.
//!
//! It re-runs itself in a private network namespace (see [`ecm_lcd::ros::netns`]), starts `ecm-lcd node`
//! there as a separate process (the real pipeline; the threshold at 0 and no history/recency limits, so
//! every keyframe after the first yields exactly one candidate), and plays the tracker and the back end
//! in this process. Keyframes go one at a time (closed loop: the next is published once the previous
//! one's candidate arrived), so the figure is the latency of an idle node, not of a queue. The node is
//! stopped with SIGTERM at the end and its final counters are printed.
//! Frames: a synthetic sequence rendered in memory (default) or any replay source (`--source`), cycled.

use anyhow::{bail, Context as _, Result};
use serde::Serialize;
use std::io::{BufRead as _, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use ecm_lcd::ros::netns::{inside_private_netns, private_netns_command};
use ecm_lcd::ros::node::InputQos;
use ecm_lcd::ros::peer::{CandidateListener, FramePublisher, SendAs};
use ecm_lcd::synth::{Scene, SynthConfig};
use ecm_lcd::types::Frame;

/// What the benchmark publishes and the node runs with (shared by `bench-node` and `load-test`).
#[derive(clap::Args, Debug)]
pub struct FrameArgs {
    /// Frames from this replay source instead of the synthetic sequence (cycled if shorter).
    #[arg(long)]
    pub source: Option<PathBuf>,
    /// Size of the synthetic frames.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Weights for the node (default: the usual resolution).
    #[arg(long)]
    pub weights: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Keyframes timed (after the warm-up).
    #[arg(long, default_value_t = 100)]
    pub keyframes: usize,
    /// Keyframes sent first and not timed.
    #[arg(long, default_value_t = 5)]
    pub warmup: usize,
    #[command(flatten)]
    pub frames: FrameArgs,
    /// Seconds to wait for one keyframe's candidate before giving up on the run.
    #[arg(long, default_value_t = 10.0)]
    pub timeout: f64,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize, Debug)]
pub struct Latency {
    pub keyframes: usize,
    pub width: u32,
    pub height: u32,
    pub median_ms: f64,
    pub p90_ms: f64,
    pub p99_ms: f64,
    pub min_ms: f64,
    pub max_ms: f64,
    pub mean_ms: f64,
    /// The node's final counters line.
    pub node_counters: String,
}

/// The `q`-quantile of sorted samples (nearest rank).
pub(crate) fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

pub fn run(args: Args) -> Result<()> {
    if args.keyframes == 0 {
        bail!("--keyframes must be at least 1");
    }
    if !(args.timeout.is_finite() && args.timeout > 0.0) {
        bail!("--timeout must be a positive number of seconds, got {}", args.timeout);
    }
    if rerun_in_private_netns("benchmark")? {
        return Ok(());
    }
    let frames = load_frames(&args)?;
    let log_path = std::env::temp_dir().join(format!("ecm-lcd-bench-node-{}.log", std::process::id()));
    let mut node_args = Vec::new();
    if let Some(weights) = &args.frames.weights {
        node_args.extend(["--weights".to_string(), weights.display().to_string()]);
    }
    node_args.extend(every_keyframe_matches_args("/bench"));
    let mut node = start_node(&node_args, &log_path)?;
    let result = measure(&args, &frames);
    let counters = stop_node(&mut node, &log_path);
    let (mut samples, counters) = match (result, counters) {
        (Ok(samples), Ok(counters)) => (samples, counters),
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("node log kept at {}", log_path.display());
            return Err(e);
        }
    };
    let _ = std::fs::remove_file(&log_path);
    samples.sort_by(f64::total_cmp);
    let (width, height) = frames.first().map_or((0, 0), |f| f.image.dimensions());
    let latency = Latency {
        keyframes: samples.len(),
        width,
        height,
        median_ms: quantile(&samples, 0.5),
        p90_ms: quantile(&samples, 0.9),
        p99_ms: quantile(&samples, 0.99),
        min_ms: samples[0],
        max_ms: samples[samples.len() - 1],
        mean_ms: samples.iter().sum::<f64>() / samples.len() as f64,
        node_counters: counters,
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&latency)?);
    } else {
        println!(
            "keyframe publish -> loop candidate receipt, {} keyframes of {}x{} (after {} warm-up), one at a time, \
             DDS on loopback:",
            latency.keyframes, width, height, args.warmup
        );
        println!(
            "median {:.1} ms  p90 {:.1} ms  p99 {:.1} ms  min {:.1} ms  max {:.1} ms  mean {:.1} ms",
            latency.median_ms, latency.p90_ms, latency.p99_ms, latency.min_ms, latency.max_ms, latency.mean_ms
        );
        println!("node: {}", latency.node_counters);
    }
    Ok(())
}

fn load_frames(args: &Args) -> Result<Vec<Frame>> {
    // Enough distinct frames that the descriptors differ; more would only cost rendering time.
    let wanted = (args.keyframes + args.warmup + 1).min(60);
    frames_for_benchmark(args.frames.source.as_deref(), wanted, args.frames.width, args.frames.height)
}

/// `wanted` frames from a replay source (fewer if it is shorter), or rendered synthetic frames.
pub(crate) fn frames_for_benchmark(
    source: Option<&std::path::Path>,
    wanted: usize,
    width: u32,
    height: u32,
) -> Result<Vec<Frame>> {
    if let Some(path) = source {
        let source = ecm_lcd::io::open_source(path, None).with_context(|| format!("opening {}", path.display()))?;
        let frames: Vec<Frame> = ecm_lcd::io::skip_unreadable(source.take(wanted), path)
            .collect::<Result<_>>()
            .with_context(|| format!("reading {}", path.display()))?;
        if frames.is_empty() {
            bail!("{} holds no frames", path.display());
        }
        return Ok(frames);
    }
    let scene = Scene::new(SynthConfig { frames: wanted, laps: 1, width, height, ..SynthConfig::default() })?;
    Ok((0..wanted)
        .map(|index| {
            let (stamp, image, _) = scene.frame(index);
            Frame { index, stamp, image, depth: None }
        })
        .collect())
}

/// Outside a private network namespace, runs this program again with the same arguments inside one
/// and returns true once it succeeded (DDS discovery must not reach other programs on this machine);
/// inside, returns false: the caller does its work.
pub(crate) fn rerun_in_private_netns(what: &str) -> Result<bool> {
    if inside_private_netns() {
        return Ok(false);
    }
    let exe = std::env::current_exe().context("finding this program to run it in a private network namespace")?;
    let status = private_netns_command(&exe)
        .args(std::env::args_os().skip(1))
        .status()
        .context("running unshare (util-linux) for a private network namespace")?;
    if !status.success() {
        bail!("the {what} in the private network namespace failed ({status})");
    }
    Ok(true)
}

/// The node's arguments for the benchmarks: namespace `ns`, and parameters under which every keyframe
/// after the first yields exactly one candidate (threshold 0, no history or recency limits).
pub(crate) fn every_keyframe_matches_args(ns: &str) -> Vec<String> {
    let mut args: Vec<String> = vec!["--ros-args".into(), "-r".into(), format!("__ns:={ns}")];
    for param in [
        "detector.min_score:=0.0",
        "detector.min_history:=1",
        "detector.exclude_recent.count:=0",
        "detector.exclude_recent.seconds:=0.0",
    ] {
        args.extend(["-p".to_string(), param.to_string()]);
    }
    args
}

/// Starts `ecm-lcd node ARGS` (the user binary beside this program) with its log in `log_path`.
pub(crate) fn start_node(args: &[String], log_path: &std::path::Path) -> Result<Child> {
    let exe = super::user_binary()?;
    let log = std::fs::File::create(log_path).with_context(|| format!("creating {}", log_path.display()))?;
    let mut command = Command::new(exe);
    command
        .arg("node")
        .args(args)
        // The final counters line is logged at info: keep it whatever RUST_LOG says (later directives win).
        .env(
            "RUST_LOG",
            format!(
                "ecm_lcd::ros::node=info,{}",
                std::env::var("RUST_LOG").unwrap_or_else(|_| "info,rustdds=error".into())
            ),
        )
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(log);
    command.spawn().context("starting `ecm-lcd node`")
}

/// Publishes the keyframes one at a time and returns the timed latencies in milliseconds.
fn measure(args: &Args, frames: &[Frame]) -> Result<Vec<f64>> {
    // One participant each: ros2-client hands a participant's discovery events to one node only.
    let tracker = ros2_client::Context::new().context("creating the DDS participant")?;
    let back_end = ros2_client::Context::new().context("creating the DDS participant")?;
    let publisher = FramePublisher::new(&tracker, "/bench/keyframes", SendAs::Keyframe, InputQos::Reliable, "camera")?;
    let listener = CandidateListener::new(&back_end, "/bench/loop_candidates")?;
    // The node loads its weights first; then discovery matches both sides.
    let ready = Duration::from_secs(60);
    if !publisher.wait_for_subscriber(ready) || !listener.wait_for_publisher(ready) {
        bail!("the node did not appear on /bench/keyframes and /bench/loop_candidates within {} s", ready.as_secs());
    }
    std::thread::sleep(Duration::from_millis(500)); // both directions of the match settle
    let timeout = Duration::from_secs_f64(args.timeout);
    let mut samples = Vec::with_capacity(args.keyframes);
    for id in 0..=(args.warmup + args.keyframes) {
        let source = &frames[id % frames.len()];
        // Keyframe id = frame index; one second apart, whatever the source's stamps.
        let stamp = ecm_lcd::types::Stamp::from_sec_nsec(1_000 + id as i64, 0);
        let frame = Frame { index: id, stamp, image: source.image.clone(), depth: None };
        let sent = Instant::now();
        publisher.publish(&frame)?;
        if id == 0 {
            // The first keyframe only fills the database; let it be processed before timing the next.
            std::thread::sleep(Duration::from_secs(1));
            listener.take_all()?;
            continue;
        }
        let received = loop {
            let got = listener.wait(Duration::from_millis(50))?;
            if got.iter().any(|c| c.query_id == id as u64) {
                break Instant::now();
            }
            if sent.elapsed() > timeout {
                bail!("no candidate for keyframe {id} within {} s", args.timeout);
            }
        };
        if id > args.warmup {
            samples.push((received - sent).as_secs_f64() * 1e3);
        }
    }
    Ok(samples)
}

/// Stops the node with SIGTERM and returns its final counters line.
pub(crate) fn stop_node(node: &mut Child, log_path: &std::path::Path) -> Result<String> {
    let _ = Command::new("kill").args(["-TERM", &node.id().to_string()]).status();
    let deadline = Instant::now() + Duration::from_secs(15);
    let status = loop {
        if let Some(status) = node.try_wait().context("waiting for the node")? {
            break status;
        }
        if Instant::now() > deadline {
            let _ = node.kill();
            bail!("the node did not stop within 15 s of SIGTERM");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    if !status.success() {
        bail!("the node exited with {status}");
    }
    let log = std::fs::File::open(log_path).with_context(|| format!("reading {}", log_path.display()))?;
    BufReader::new(log)
        .lines()
        .map_while(Result::ok)
        .find_map(|line| line.split_once("stopped: ").map(|(_, counters)| counters.to_string()))
        .context("the node's log has no final counters line")
}
