//! `ecm-lcd-bench load-test`: a load test program (not a test) for the node under a keyframe burst.
//!
//! It re-runs itself in a private network namespace (loopback only, see [`ecm_lcd::ros::netns`]), starts
//! `ecm-lcd node` there as a separate process with the real pipeline, and plays the tracker, the back
//! end and a parameter client in this process. After a warm-up it publishes ecm_lcd_msgs/Keyframe at
//! `--factor` (default 10) times the nominal keyframe rate for `--seconds` (default 60), while another
//! thread calls the node's `get_parameters`/`set_parameters` services every `--param-period` seconds
//! (the set toggles `selection.every_nth`, which does not touch Keyframe messages) and a third samples
//! the node's resident memory. Then it waits for the node to drain, stops it with SIGTERM and prints:
//! published, received, processed, dropped (the node's counters), publish -> candidate latency
//! percentiles, parameter call latencies and failures, and the node's peak RSS (VmHWM).
//!
//! Nominal rate (interpretation): the keyframe rate the configuration implies, `1 / selection.min_period`
//! (default 0.5 s -> 2 Hz, so the burst is 20 Hz); `--nominal-rate` overrides it.
//! The node runs with the threshold at 0 and no history/recency limits, so every processed keyframe
//! after the first yields exactly one candidate: the candidates received measure what was processed.

use anyhow::{bail, Context as _, Result};
use serde::Serialize;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::node::{
    every_keyframe_matches_args, frames_for_benchmark, quantile, rerun_in_private_netns, start_node, stop_node,
};
use ecm_lcd::config::Params;
use ecm_lcd::ros::node::InputQos;
use ecm_lcd::ros::peer::{CandidateListener, FramePublisher, ParamClient, SendAs};
use ecm_lcd::types::{Frame, Stamp};

const NAMESPACE: &str = "/load";

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Seconds of burst.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// Burst rate as a multiple of the nominal keyframe rate.
    #[arg(long, default_value_t = 10.0)]
    pub factor: f64,
    /// Nominal keyframe rate in Hz (default: 1 / selection.min_period of the default configuration).
    #[arg(long)]
    pub nominal_rate: Option<f64>,
    /// Capacity of the node's queue (`ecm-lcd node --queue`).
    #[arg(long, default_value_t = 4)]
    pub queue: usize,
    /// Seconds between parameter service calls (one get and one set each time) during the burst.
    #[arg(long, default_value_t = 0.5)]
    pub param_period: f64,
    #[command(flatten)]
    pub frames: super::node::FrameArgs,
    /// Extra node parameters, `name:=value` (as `-p` after --ros-args).
    #[arg(long = "node-param", value_name = "NAME:=VALUE")]
    pub node_params: Vec<String>,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Percentiles of a set of latencies, in milliseconds.
#[derive(Serialize, Debug, Default, Clone, Copy)]
pub struct Percentiles {
    pub count: usize,
    pub p50_ms: f64,
    pub p90_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
}

impl Percentiles {
    fn of(mut samples: Vec<f64>) -> Percentiles {
        if samples.is_empty() {
            return Percentiles::default();
        }
        samples.sort_by(f64::total_cmp);
        Percentiles {
            count: samples.len(),
            p50_ms: quantile(&samples, 0.5),
            p90_ms: quantile(&samples, 0.9),
            p99_ms: quantile(&samples, 0.99),
            max_ms: samples[samples.len() - 1],
        }
    }
}

impl std::fmt::Display for Percentiles {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "n {}  p50 {:.1} ms  p90 {:.1} ms  p99 {:.1} ms  max {:.1} ms",
            self.count, self.p50_ms, self.p90_ms, self.p99_ms, self.max_ms
        )
    }
}

#[derive(Serialize, Debug)]
pub struct LoadReport {
    pub seconds: f64,
    pub nominal_rate_hz: f64,
    pub burst_rate_hz: f64,
    pub width: u32,
    pub height: u32,
    pub queue_capacity: usize,
    /// Keyframes this program published during the burst.
    pub published: u64,
    /// The node's final counters (whole run, warm-up included).
    pub received: u64,
    pub processed: u64,
    pub dropped: u64,
    pub malformed: u64,
    pub failed: u64,
    /// Candidates that reached this program (one per processed keyframe after the first).
    pub candidates_received: u64,
    /// Publish -> candidate receipt, burst keyframes only.
    pub latency: Percentiles,
    pub param_get: Percentiles,
    pub param_set: Percentiles,
    pub param_failures: u64,
    /// Resident memory of the node after the warm-up, and its peak (VmHWM) over the whole run, MiB.
    pub rss_after_warmup_mib: f64,
    pub peak_rss_mib: f64,
    /// The node's final counters line.
    pub node_counters: String,
}

pub fn run(args: Args) -> Result<()> {
    let nominal = match args.nominal_rate {
        Some(rate) => rate,
        None => {
            let period = Params::default().selection().min_period_secs;
            if period <= 0.0 {
                bail!("selection.min_period is 0 by default, so no nominal rate follows: give --nominal-rate");
            }
            1.0 / period
        }
    };
    let burst = nominal * args.factor;
    for (name, value) in [
        ("--seconds", args.seconds),
        ("--factor", args.factor),
        ("--nominal-rate", nominal),
        ("--param-period", args.param_period),
    ] {
        if !(value.is_finite() && value > 0.0) {
            bail!("{name} must be a positive number, got {value}");
        }
    }
    if !(burst <= 1000.0 && args.seconds <= 3600.0) {
        bail!(
            "the load test is bounded: at most 1000 keyframes/s for at most 3600 s (asked {burst} Hz for {} s)",
            args.seconds
        );
    }
    if rerun_in_private_netns("load test")? {
        return Ok(());
    }
    let frames = frames_for_benchmark(args.frames.source.as_deref(), 30, args.frames.width, args.frames.height)?;
    let log_path = std::env::temp_dir().join(format!("ecm-lcd-load-test-{}.log", std::process::id()));
    let mut node_args = vec!["--queue".to_string(), args.queue.to_string()];
    if let Some(weights) = &args.frames.weights {
        node_args.extend(["--weights".to_string(), weights.display().to_string()]);
    }
    node_args.extend(every_keyframe_matches_args(NAMESPACE));
    for param in &args.node_params {
        node_args.extend(["-p".to_string(), param.clone()]);
    }
    let mut node = start_node(&node_args, &log_path)?;
    let measured = measure(&args, burst, &frames, node.id());
    let counters = stop_node(&mut node, &log_path);
    let (measured, counters) = match (measured, counters) {
        (Ok(m), Ok(c)) => (m, c),
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("node log kept at {}", log_path.display());
            return Err(e);
        }
    };
    let _ = std::fs::remove_file(&log_path);
    let counter = |name: &str| -> Result<u64> {
        let mut words = counters.split_whitespace();
        while let Some(word) = words.next() {
            if word == name {
                return words
                    .next()
                    .and_then(|v| v.parse().ok())
                    .with_context(|| format!("counter {name} in {counters:?}"));
            }
        }
        bail!("no counter {name} in the node's final line {counters:?}")
    };
    let (width, height) = frames[0].image.dimensions();
    let report = LoadReport {
        seconds: args.seconds,
        nominal_rate_hz: nominal,
        burst_rate_hz: burst,
        width,
        height,
        queue_capacity: args.queue,
        published: measured.published,
        received: counter("received")?,
        processed: counter("processed")?,
        dropped: counter("dropped")?,
        malformed: counter("malformed")?,
        failed: counter("failed")?,
        candidates_received: measured.candidates,
        latency: Percentiles::of(measured.latencies_ms),
        param_get: Percentiles::of(measured.param_get_ms),
        param_set: Percentiles::of(measured.param_set_ms),
        param_failures: measured.param_failures,
        rss_after_warmup_mib: measured.rss_after_warmup_kib as f64 / 1024.0,
        peak_rss_mib: measured.peak_rss_kib as f64 / 1024.0,
        node_counters: counters,
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "burst of {:.0} keyframes/s ({}x the nominal {:.1} Hz) for {:.0} s, {}x{} rgb8, node queue {} (drop oldest), DDS on loopback:",
            report.burst_rate_hz, args.factor, report.nominal_rate_hz, report.seconds, width, height, report.queue_capacity
        );
        println!(
            "published {}  received {}  processed {}  dropped {}  malformed {}  failed {}  candidates received {}",
            report.published,
            report.received,
            report.processed,
            report.dropped,
            report.malformed,
            report.failed,
            report.candidates_received
        );
        println!("latency publish -> candidate: {}", report.latency);
        println!("parameter get: {}", report.param_get);
        println!("parameter set: {}", report.param_set);
        println!("parameter calls failed: {}", report.param_failures);
        println!(
            "node RSS after warm-up {:.1} MiB, peak (VmHWM) {:.1} MiB",
            report.rss_after_warmup_mib, report.peak_rss_mib
        );
    }
    Ok(())
}

struct Measured {
    published: u64,
    candidates: u64,
    latencies_ms: Vec<f64>,
    param_get_ms: Vec<f64>,
    param_set_ms: Vec<f64>,
    param_failures: u64,
    rss_after_warmup_kib: u64,
    peak_rss_kib: u64,
}

/// A `kB` field of /proc/PID/status (VmRSS, VmHWM).
fn status_kib(pid: u32, field: &str) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = text.lines().find(|l| l.starts_with(field))?;
    line[field.len()..].trim_start_matches(':').split_whitespace().next()?.parse().ok()
}

fn keyframe(frames: &[Frame], id: usize) -> Frame {
    // Keyframe id = position in the run; 100 ms apart in stamps whatever the real rate.
    Frame {
        index: id,
        stamp: Stamp::from_sec_nsec(1_000 + id as i64 / 10, (id % 10) as u32 * 100_000_000),
        image: frames[id % frames.len()].image.clone(),
        depth: None,
    }
}

fn measure(args: &Args, burst_hz: f64, frames: &[Frame], node_pid: u32) -> Result<Measured> {
    // One participant each: ros2-client hands a participant's discovery events to one node only.
    let tracker = ros2_client::Context::new().context("creating the DDS participant")?;
    let back_end = ros2_client::Context::new().context("creating the DDS participant")?;
    let publisher = FramePublisher::new(
        &tracker,
        &format!("{NAMESPACE}/keyframes"),
        SendAs::Keyframe,
        InputQos::Reliable,
        "camera",
    )?;
    let listener = CandidateListener::new(&back_end, &format!("{NAMESPACE}/loop_candidates"))?;
    let ready = Duration::from_secs(60);
    if !publisher.wait_for_subscriber(ready) || !listener.wait_for_publisher(ready) {
        bail!(
            "the node did not appear on {NAMESPACE}/keyframes and {NAMESPACE}/loop_candidates within {} s",
            ready.as_secs()
        );
    }
    std::thread::sleep(Duration::from_millis(500));

    // Warm-up: two keyframes one at a time; the second one's candidate shows the node is ready.
    let mut next_id = 0usize;
    let mut candidates = 0u64;
    for _ in 0..2 {
        publisher.publish(&keyframe(frames, next_id))?;
        next_id += 1;
        std::thread::sleep(Duration::from_millis(300));
    }
    let warm_deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let got = listener.wait(Duration::from_millis(100))?;
        candidates += got.len() as u64;
        if got.iter().any(|c| c.query_id == 1) {
            break;
        }
        if Instant::now() > warm_deadline {
            bail!("no candidate for the warm-up keyframe within 30 s");
        }
    }
    let rss_after_warmup_kib = status_kib(node_pid, "VmRSS").context("reading the node's VmRSS")?;

    // The parameter client: its own participant and thread; first call before the burst (discovery).
    let burst_on = Arc::new(AtomicBool::new(true));
    let param_failures = Arc::new(AtomicU64::new(0));
    let param_samples = Arc::new(Mutex::new((Vec::new(), Vec::new())));
    let client_ready = Arc::new(AtomicBool::new(false));
    let param_thread = {
        let (burst_on, failures, samples, ready) =
            (burst_on.clone(), param_failures.clone(), param_samples.clone(), client_ready.clone());
        let period = Duration::from_secs_f64(args.param_period);
        std::thread::Builder::new().name("param-client".into()).spawn(move || -> Result<()> {
            let context = ros2_client::Context::new().context("creating the DDS participant")?;
            let client = ParamClient::new(
                &context,
                &format!("{NAMESPACE}/{}", ecm_lcd::config::NODE_NAME),
                Duration::from_secs(10),
            )?;
            client.get("detector.min_score").context("first parameter call, before the burst")?;
            ready.store(true, Ordering::SeqCst);
            let mut every_nth = 1;
            while burst_on.load(Ordering::SeqCst) {
                let started = Instant::now();
                match client.get("detector.min_score") {
                    Ok(ros2_client::ParameterValue::Double(_)) => {
                        samples.lock().unwrap().0.push(started.elapsed().as_secs_f64() * 1e3)
                    }
                    Ok(other) => {
                        log::warn!("get detector.min_score answered {other:?}");
                        failures.fetch_add(1, Ordering::SeqCst);
                    }
                    Err(e) => {
                        log::warn!("get_parameters during the burst: {e:#}");
                        failures.fetch_add(1, Ordering::SeqCst);
                    }
                }
                every_nth = 3 - every_nth; // 1, 2, 1, ...
                let started = Instant::now();
                match client.set("selection.every_nth", ros2_client::ParameterValue::Integer(every_nth)) {
                    Ok(Ok(())) => samples.lock().unwrap().1.push(started.elapsed().as_secs_f64() * 1e3),
                    Ok(Err(reason)) => {
                        log::warn!("set selection.every_nth refused: {reason}");
                        failures.fetch_add(1, Ordering::SeqCst);
                    }
                    Err(e) => {
                        log::warn!("set_parameters during the burst: {e:#}");
                        failures.fetch_add(1, Ordering::SeqCst);
                    }
                }
                std::thread::sleep(period.saturating_sub(started.elapsed()));
            }
            Ok(())
        })?
    };
    let ready_deadline = Instant::now() + Duration::from_secs(30);
    while !client_ready.load(Ordering::SeqCst) {
        if param_thread.is_finished() || Instant::now() > ready_deadline {
            burst_on.store(false, Ordering::SeqCst);
            return Err(match param_thread.join() {
                Ok(Err(e)) => e.context("the parameter client failed before the burst"),
                _ => anyhow::anyhow!("the parameter services did not answer within 30 s before the burst"),
            });
        }
        std::thread::sleep(Duration::from_millis(20));
    }

    // Resident memory sampler.
    let peak_sampled = Arc::new(AtomicU64::new(rss_after_warmup_kib));
    let sampling = Arc::new(AtomicBool::new(true));
    let sampler = {
        let (peak, sampling) = (peak_sampled.clone(), sampling.clone());
        std::thread::spawn(move || {
            while sampling.load(Ordering::SeqCst) {
                if let Some(rss) = status_kib(node_pid, "VmRSS") {
                    peak.fetch_max(rss, Ordering::SeqCst);
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        })
    };

    // The burst: keyframes at `burst_hz`, candidates taken between sends.
    let period = Duration::from_secs_f64(1.0 / burst_hz);
    let mut sent: HashMap<u64, Instant> = HashMap::new();
    let mut latencies = Vec::new();
    let mut take = |got: Vec<ecm_lcd::ros::msgs::LoopCandidate>, sent: &HashMap<u64, Instant>, candidates: &mut u64| {
        let now = Instant::now();
        for c in got {
            *candidates += 1;
            if let Some(at) = sent.get(&c.query_id) {
                latencies.push((now - *at).as_secs_f64() * 1e3);
            }
        }
    };
    let start = Instant::now();
    let length = Duration::from_secs_f64(args.seconds);
    let first_burst_id = next_id;
    while start.elapsed() < length {
        let due = start + period.mul_f64((next_id - first_burst_id) as f64);
        let now = Instant::now();
        if now >= due {
            publisher.publish(&keyframe(frames, next_id))?;
            sent.insert(next_id as u64, Instant::now());
            next_id += 1;
        } else {
            let got = listener.wait((due - now).min(Duration::from_millis(20)))?;
            take(got, &sent, &mut candidates);
        }
    }
    burst_on.store(false, Ordering::SeqCst);
    let published = (next_id - first_burst_id) as u64;

    // Drain: the queue holds at most `queue` keyframes; wait until candidates stop coming.
    let mut quiet_since = Instant::now();
    let drain_deadline = Instant::now() + Duration::from_secs(30);
    while quiet_since.elapsed() < Duration::from_secs(2) && Instant::now() < drain_deadline {
        let got = listener.wait(Duration::from_millis(100))?;
        if !got.is_empty() {
            quiet_since = Instant::now();
        }
        take(got, &sent, &mut candidates);
    }
    let peak_rss_kib =
        status_kib(node_pid, "VmHWM").context("reading the node's VmHWM")?.max(peak_sampled.load(Ordering::SeqCst));
    sampling.store(false, Ordering::SeqCst);
    let _ = sampler.join();
    match param_thread.join() {
        Ok(result) => result?,
        Err(_) => bail!("the parameter client thread panicked"),
    }
    let (param_get_ms, param_set_ms) = std::mem::take(&mut *param_samples.lock().unwrap());
    Ok(Measured {
        published,
        candidates,
        latencies_ms: latencies,
        param_get_ms,
        param_set_ms,
        param_failures: param_failures.load(Ordering::SeqCst),
        rss_after_warmup_kib,
        peak_rss_kib,
    })
}
