//! `ecm-lcd-bench speed`: a benchmark program (not a test) that prints, in one run, the figures of the project's speed goals
//! side by side: network forward (ECMobileNet and MobileNetV2, per thread count), the same networks in
//! ONNX Runtime with the same weights, preprocessing, search at growing database sizes (exact and
//! indexed, with the index's recall), one keyframe end to end with a large database, and peak memory
//! with a million stored descriptors. `--json` prints one object with every section; `--only` picks
//! sections (the million-descriptor ones take a while).
//!
//! Interpretations, written down once:
//! - Forward times the network alone on a prepared `[1, 3, S, S]` tensor (preprocessing has its own
//!   section), which is also exactly what the ONNX Runtime script times, so their ratio compares like
//!   with like. Median and p90 of `--runs` runs after 5 warm-up runs.
//! - ONNX Runtime: the weights the bench runs are folded by the project (BatchNorm into the convolutions,
//!   [`ecm_lcd::model::Network::visit_units`]), saved with the project's safetensors writer, and turned into an
//!   ONNX graph by `benches/ort/export_onnx.py`; `benches/ort/time_ort.py` checks the output equals ours
//!   (max abs difference reported, goal 1e-4) and times it. Both run in a virtualenv the bench creates
//!   (`target/bench-venv`, reused).
//! - Search uses synthetic clustered unit vectors (see [`ClusteredVectors`]), stored through
//!   [`KeyframeDb::insert`] as the node stores them, so the index is built the way the node builds it.
//!   Queries exclude the newest 100 keyframes, as the detector's recency rule does. Recall is recall@k
//!   of the automatic search against the exact scan of the same rows; for six-level codes
//!   (`--search-coded-dims`) also against the exact search of the `f32` vectors they code, worked
//!   out while inserting (the `f32` rows are never all held).
//! - End to end: a real TUM frame, as a raw rgb8 `Image` (what `ecm_lcd/Keyframe` carries) and as a
//!   JPEG `CompressedImage` in alternation, goes through decode -> preprocessing -> network ->
//!   descriptor -> search -> candidates in a [`Pipeline`] whose detector already holds
//!   `--e2e-stored` synthetic descriptors of the pipeline's descriptor length.
//! - Verification: ORB extraction on the bench frame, and [`ecm_lcd::verification::verify`] of the
//!   frame against the next TUM frame (the same desk, 1 s later: a pair that verifies) and against
//!   the last one (another view: a pair that does not, where RANSAC runs its full budget). The end to
//!   end section runs once more with verification on (TUM fr3 intrinsics); there each keyframe's
//!   best match is an earlier copy of the same frame, so its check is the cheap, all-inlier case and
//!   the figure is extraction plus matching.
//! - Memory: a child process (this program, hidden `--memory-child`) inserts the descriptors into a
//!   [`Detector`] one by one, as a node does, queries it, and reports its peak RSS (`VmHWM`) and the
//!   RSS before inserting, so the figure is the real process peak, not an estimate.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use image::RgbImage;
use serde::Serialize;

use ecm_lcd::config::Params;
use ecm_lcd::detector::index::{ClusteredVectors, IndexPolicy};
use ecm_lcd::detector::{Detector, IndexInfo, KeyframeDb, RowFormat};
use ecm_lcd::io::image_msg::{decode_compressed_image, decode_image, jpeg_message, rgb8_message};
use ecm_lcd::model::embedder::Embedder;
use ecm_lcd::model::layers::Mode;
use ecm_lcd::model::weights::resolve;
use ecm_lcd::model::Arch;
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::preprocess::Preprocessor;
use ecm_lcd::types::Stamp;

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Section {
    Forward,
    Ort,
    Preprocess,
    Search,
    E2e,
    Memory,
    /// Time per stage of ECMobileNet's forward pass: where the time goes.
    Profile,
    /// Geometric verification: ORB extraction and one check of a matching and a non-matching pair.
    Verification,
}

#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// Weights (default resolution as for every command).
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// Input size.
    #[arg(long, default_value_t = 224)]
    pub size: usize,
    /// Timed runs per configuration (after warm-up).
    #[arg(long, default_value_t = 50)]
    pub runs: usize,
    /// Thread counts to measure (each 1 to 1024; the top-level --threads sets the other sections').
    #[arg(long, value_delimiter = ',', default_value = "1,2", value_parser = ecm_lcd::runtime::parse_threads)]
    pub thread_counts: Vec<usize>,
    /// Also time the stock-candle reference path.
    #[arg(long)]
    pub reference: bool,
    /// Sections to run (default: all).
    #[arg(long, value_delimiter = ',', value_enum)]
    pub only: Vec<Section>,
    /// Database sizes for the search section.
    #[arg(long, value_delimiter = ',', default_value = "1000,10000,100000,1000000")]
    pub search_sizes: Vec<usize>,
    /// Descriptor lengths for the search section (128: `paper`; 1280: `l2`).
    #[arg(long, value_delimiter = ',', default_value = "128,1280")]
    pub search_dims: Vec<usize>,
    /// Descriptor lengths searched as six-level codes (`detector.storage` levels6; 2880: the default
    /// descriptor).
    #[arg(long, value_delimiter = ',', default_value = "2880")]
    pub search_coded_dims: Vec<usize>,
    /// Skip search configurations whose stored rows take more than this many MB.
    #[arg(long, default_value_t = 1024)]
    pub search_max_mb: usize,
    /// Queries per search configuration.
    #[arg(long, default_value_t = 100)]
    pub queries: usize,
    /// Fraction of the index's lists a query scans (default: the database's).
    #[arg(long)]
    pub probe_fraction: Option<f64>,
    /// Neighbours per query (recall is recall@k).
    #[arg(long, default_value_t = 10)]
    pub k: usize,
    /// A pipeline parameter for the end-to-end and verification sections: `--param
    /// verification.features=1000` (repeatable).
    #[arg(long = "param", value_name = "NAME=VALUE")]
    pub params: Vec<String>,
    /// Descriptors stored before the end-to-end runs.
    #[arg(long, default_value_t = 100_000)]
    pub e2e_stored: usize,
    /// `stored:dim` pairs for the memory section.
    #[arg(long, value_delimiter = ',', default_value = "1000000:128,100000:1280,1000000:2880")]
    pub memory: Vec<String>,
    /// Virtualenv for ONNX Runtime (created when missing).
    #[arg(long)]
    pub venv: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
    /// Internal: run one memory measurement (`stored:dim`) and print it as JSON.
    #[arg(long, hide = true)]
    pub memory_child: Option<String>,
}

impl BenchArgs {
    /// Refuses values that would measure nothing or abort, before any work.
    fn check(&self) -> Result<()> {
        ecm_lcd::model::check_input_size(self.size)?;
        anyhow::ensure!(self.runs >= 1, "--runs must be at least 1");
        anyhow::ensure!(self.queries >= 1 && self.k >= 1, "--queries and --k must be at least 1");
        let dims = self.search_dims.iter().chain(&self.search_coded_dims);
        anyhow::ensure!(dims.clone().all(|&d| d >= 1), "--search-dims and --search-coded-dims must be at least 1");
        if let Some(&small) = self.search_sizes.iter().find(|&&n| n <= BENCH_EXCLUDE_RECENT) {
            anyhow::bail!(
                "--search-sizes {small}: a search excludes the newest {BENCH_EXCLUDE_RECENT} rows, so give more than that"
            );
        }
        Ok(())
    }
}

#[derive(Serialize, Debug)]
pub struct Timing {
    pub arch: Arch,
    pub path: &'static str,
    pub threads: usize,
    pub params: usize,
    pub macs: usize,
    pub runs: usize,
    pub median_ms: f64,
    pub p90_ms: f64,
}

/// Order statistics of timed runs (ms).
#[derive(Serialize, Debug, Clone, Copy)]
pub struct Stats {
    pub runs: usize,
    pub median_ms: f64,
    pub p90_ms: f64,
    pub p99_ms: f64,
}

impl Stats {
    pub fn of(samples: &mut [f64]) -> Stats {
        samples.sort_by(f64::total_cmp);
        let at = |q: f64| {
            if samples.is_empty() {
                f64::NAN
            } else {
                samples[((samples.len() - 1) as f64 * q).round() as usize]
            }
        };
        Stats { runs: samples.len(), median_ms: at(0.5), p90_ms: at(0.9), p99_ms: at(0.99) }
    }

    /// Times `runs` calls of `f` after `warmup` untimed ones.
    fn time(warmup: usize, runs: usize, mut f: impl FnMut() -> Result<()>) -> Result<Stats> {
        for _ in 0..warmup {
            f()?;
        }
        let mut samples = (0..runs.max(1))
            .map(|_| {
                let start = Instant::now();
                f()?;
                Ok(start.elapsed().as_secs_f64() * 1e3)
            })
            .collect::<Result<Vec<f64>>>()?;
        Ok(Stats::of(&mut samples))
    }
}

#[derive(Serialize, Debug)]
pub struct Machine {
    pub cpu: String,
    pub logical_cores: usize,
    pub os: String,
}

impl Machine {
    fn this() -> Machine {
        let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
        let cpu = cpuinfo
            .lines()
            .find_map(|l| {
                l.strip_prefix("model name").and_then(|r| r.split_once(':')).map(|(_, v)| v.trim().to_string())
            })
            .unwrap_or_else(|| std::env::consts::ARCH.to_string());
        let logical_cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
        Machine { cpu, logical_cores, os: std::env::consts::OS.to_string() }
    }
}

#[derive(Serialize, Debug)]
pub struct OrtArch {
    pub arch: Arch,
    /// Largest |ONNX Runtime - ecm-lcd| over the feature map of the bench frame.
    pub max_abs_diff: f64,
    pub timings: Vec<OrtTiming>,
}

#[derive(Serialize, Debug, serde::Deserialize)]
pub struct OrtTiming {
    pub threads: usize,
    pub runs: usize,
    pub median_ms: f64,
    pub p90_ms: f64,
}

#[derive(Serialize, Debug)]
pub struct Ort {
    pub onnxruntime: String,
    pub archs: Vec<OrtArch>,
}

#[derive(Serialize, Debug)]
pub struct PreprocessRow {
    pub input: &'static str,
    #[serde(flatten)]
    pub stats: Stats,
}

#[derive(Serialize, Debug)]
pub struct SearchRow {
    pub dim: usize,
    /// `f32` or `levels6`.
    pub storage: &'static str,
    pub stored: usize,
    /// Seconds to insert everything (index training included).
    pub build_s: f64,
    /// The slowest single insert, in ms: an index (re)training, which holds up that keyframe.
    pub slowest_insert_ms: f64,
    pub exact: Stats,
    /// The automatic choice: `exact` below the index threshold, `ivf` above.
    pub auto_method: &'static str,
    pub auto: Stats,
    /// The automatic search from a worker of a 2-thread pool, as the pipeline runs it (the probed
    /// lists are scanned in parallel there).
    pub auto_on_two_threads: Stats,
    pub index: Option<IndexInfo>,
    pub k: usize,
    /// recall@k of the automatic search against the exact scan.
    pub recall: f64,
    /// For coded rows: recall@k of the automatic search against the exact search of the `f32` vectors.
    pub recall_vs_f32: Option<f64>,
}

#[derive(Serialize, Debug)]
pub struct EndToEnd {
    /// What the keyframe arrives as: `rgb8` (a raw `sensor_msgs/Image`, as `ecm_lcd/Keyframe`
    /// carries it) or `jpeg` (a `sensor_msgs/CompressedImage`, quality 90).
    pub input: String,
    pub stored: usize,
    pub dim: usize,
    pub descriptor: String,
    pub arch: Arch,
    pub frame: String,
    /// Message decode through candidates, per keyframe.
    pub total: Stats,
    pub network: Stats,
    pub detector: Stats,
    /// Feature extraction and checks, when verification is on.
    pub verification: Option<Stats>,
    pub index: Option<IndexInfo>,
}

#[derive(Serialize, Debug, serde::Deserialize)]
pub struct MemoryRow {
    pub stored: usize,
    pub dim: usize,
    /// RSS before any descriptor was stored.
    pub baseline_mb: f64,
    /// Peak RSS of the process (VmHWM) after storing and querying.
    pub peak_mb: f64,
    /// What the stored rows alone take (`f32`, or codes where `detector.storage` picks them).
    pub descriptors_mb: f64,
    pub storage: String,
    pub indexed: bool,
}

#[derive(Serialize, Debug)]
pub struct Goal {
    pub goal: String,
    pub measured: String,
    pub met: bool,
}

#[derive(Serialize, Debug, Default)]
pub struct Report {
    pub machine: Option<Machine>,
    pub forward: Option<Vec<Timing>>,
    pub ort: Option<Ort>,
    pub preprocess: Option<Vec<PreprocessRow>>,
    pub search: Option<Vec<SearchRow>>,
    pub end_to_end: Option<Vec<EndToEnd>>,
    pub memory: Option<Vec<MemoryRow>>,
    pub profile: Option<Vec<ProfileRow>>,
    pub verification: Option<VerificationTiming>,
    pub goals: Vec<Goal>,
}

/// Times of the verification stage ([`Section::Verification`]).
#[derive(Serialize, Debug)]
pub struct VerificationTiming {
    pub frames: String,
    /// ORB features of one 640x480 frame.
    pub extract: Stats,
    /// One check of a pair that verifies, and its inliers.
    pub matching_pair: Stats,
    pub matching_inliers: usize,
    /// One check of a pair that does not, and its inliers.
    pub other_pair: Stats,
    pub other_inliers: usize,
}

/// One stage of ECMobileNet at one thread count.
#[derive(Serialize, Debug)]
pub struct ProfileRow {
    pub stage: String,
    pub threads: usize,
    pub macs: usize,
    pub ms: f64,
}

fn profile(args: &BenchArgs, image: &RgbImage) -> Result<Vec<ProfileRow>> {
    let x = Preprocessor::new(args.size).tensor(image)?;
    let (embedder, _) =
        Embedder::from_weights(args.weights.as_deref(), Some(Arch::EcMobileNet), Arch::EcMobileNet, args.size, false)?;
    let costs = Arch::EcMobileNet.spec().stage_costs(None, args.size);
    let mut rows = Vec::new();
    for &threads in &args.thread_counts {
        let stages = with_threads(threads, || Ok(embedder.network.profile(&x, Mode::Inference, args.runs)?))?;
        for (stage, time) in stages {
            // A fused stage ("stem+blocks.0") costs what its parts do.
            let macs = stage.split('+').map(|part| costs.iter().find(|c| c.name == part).map_or(0, |c| c.macs)).sum();
            rows.push(ProfileRow { stage, threads, macs, ms: time.as_secs_f64() * 1e3 });
        }
    }
    Ok(rows)
}

pub fn run(args: BenchArgs) -> Result<()> {
    if let Some(spec) = &args.memory_child {
        let (stored, dim) = parse_memory_spec(spec)?;
        println!("{}", serde_json::to_string(&memory_child(stored, dim)?)?);
        return Ok(());
    }
    args.check()?;
    let wanted = |s: Section| args.only.is_empty() || args.only.contains(&s);
    let mut report = Report { machine: Some(Machine::this()), ..Default::default() };
    let frame = bench_frame()?;
    if wanted(Section::Forward) {
        report.forward = Some(forward(&args, &frame.0)?);
    }
    if wanted(Section::Ort) {
        report.ort = Some(ort(&args, &frame.0)?);
    }
    if wanted(Section::Preprocess) {
        report.preprocess = Some(preprocess(&args, &frame.0)?);
    }
    if wanted(Section::Search) {
        report.search = Some(search(&args)?);
    }
    if wanted(Section::E2e) {
        // A node runs its keyframes on a rayon worker (runtime::on_worker); so does this.
        let mut rows = ecm_lcd::runtime::on_worker(|| end_to_end(&args, &frame, false))?;
        rows.extend(ecm_lcd::runtime::on_worker(|| end_to_end(&args, &frame, true))?);
        report.end_to_end = Some(rows);
    }
    if wanted(Section::Verification) {
        report.verification = Some(verification(&args, &frame)?);
    }
    if wanted(Section::Memory) {
        report.memory = Some(args.memory.iter().map(|spec| memory(spec)).collect::<Result<_>>()?);
    }
    if wanted(Section::Profile) {
        report.profile = Some(profile(&args, &frame.0)?);
    }
    report.goals = goals(&report);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&args, &report);
    }
    Ok(())
}

/// A real 640x480 TUM frame from the shared data when present, else a fixed pseudo-random frame (the
/// forward pass does not depend on the content; the JPEG size does).
fn bench_frame() -> Result<(RgbImage, String)> {
    for dir in ecm_lcd::runtime::shared_dirs() {
        let rgb = dir.join("data/tum/fr3_long_office_household/rgb");
        if let Ok(entries) = std::fs::read_dir(&rgb) {
            let mut paths: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
            paths.sort();
            if let Some(path) = paths.first() {
                return Ok((ecm_lcd::preprocess::read_image(path)?, path.display().to_string()));
            }
        }
    }
    let mut seed = 0x2545F491u32;
    let image = RgbImage::from_fn(640, 480, |_, _| {
        seed ^= seed << 13;
        seed ^= seed >> 17;
        seed ^= seed << 5;
        image::Rgb([seed as u8, (seed >> 8) as u8, (seed >> 16) as u8])
    });
    Ok((image, "synthetic 640x480 noise (shared TUM frames not found)".into()))
}

/// Runs `f` in a pool of `threads` threads, with candle's matmul split set to match.
fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> Result<T> + Send) -> Result<T> {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    // candle sizes its matmul split by this variable on every call.
    std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
    let out = pool.install(f);
    std::env::set_var("RAYON_NUM_THREADS", ecm_lcd::runtime::init_threads(None).to_string());
    out
}

fn forward(args: &BenchArgs, image: &RgbImage) -> Result<Vec<Timing>> {
    let x = Preprocessor::new(args.size).tensor(image)?;
    let mut timings = Vec::new();
    for arch in [Arch::EcMobileNet, Arch::MobileNetV2] {
        let paths: &[bool] = if args.reference { &[false, true] } else { &[false] };
        for &reference in paths {
            let (embedder, _) = Embedder::from_weights(args.weights.as_deref(), Some(arch), arch, args.size, false)?;
            let mode = if reference { Mode::Reference } else { Mode::Inference };
            let cost = arch.spec().cost(None, args.size);
            for &threads in &args.thread_counts {
                let stats = with_threads(threads, || {
                    Stats::time(5, args.runs, || embedder.network.features(&x, mode).map(drop).map_err(Into::into))
                })?;
                let path = if reference { "stock candle" } else { "fast" };
                timings.push(Timing {
                    arch,
                    path,
                    threads,
                    params: cost.params,
                    macs: cost.macs,
                    runs: stats.runs,
                    median_ms: stats.median_ms,
                    p90_ms: stats.p90_ms,
                });
            }
        }
    }
    Ok(timings)
}

fn repo_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The bench's Python: a virtualenv with onnxruntime, onnx, numpy and safetensors, created when missing.
fn bench_python(venv: &Path) -> Result<PathBuf> {
    let python = venv.join("bin/python");
    let check = |python: &Path| {
        Command::new(python)
            .args(["-c", "import onnxruntime, onnx, numpy, safetensors"])
            .status()
            .is_ok_and(|s| s.success())
    };
    if python.exists() && check(&python) {
        return Ok(python);
    }
    eprintln!("creating the ONNX Runtime virtualenv {} (once)", venv.display());
    let status = Command::new("python3")
        .args(["-m", "venv"])
        .arg(venv)
        .status()
        .context("cannot run python3 (needed for the ONNX Runtime comparison)")?;
    ensure!(status.success(), "python3 -m venv {} failed", venv.display());
    let status = Command::new(venv.join("bin/pip"))
        .args(["install", "--quiet", "onnxruntime", "onnx", "numpy", "safetensors"])
        .status()
        .with_context(|| format!("cannot run {}/bin/pip", venv.display()))?;
    ensure!(
        status.success() && check(&python),
        "pip could not install onnxruntime, onnx, numpy and safetensors into {} (is PyPI reachable?); \
         run `ecm-lcd-bench speed --only forward,preprocess,search,e2e,memory` to skip the ONNX Runtime comparison",
        venv.display()
    );
    Ok(python)
}

fn write_f32(path: &Path, values: &[f32]) -> Result<()> {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(path, bytes).with_context(|| format!("cannot write {}", path.display()))
}

fn run_python(python: &Path, script: &Path, args: &[&std::ffi::OsStr]) -> Result<String> {
    let output = Command::new(python)
        .arg(script)
        .args(args)
        .output()
        .with_context(|| format!("cannot run {}", script.display()))?;
    if !output.status.success() {
        bail!("{} failed: {}", script.display(), String::from_utf8_lossy(&output.stderr).trim());
    }
    Ok(String::from_utf8_lossy(&output.stdout).into_owned())
}

fn ort(args: &BenchArgs, image: &RgbImage) -> Result<Ort> {
    let venv = args.venv.clone().unwrap_or_else(|| repo_dir().join("target/bench-venv"));
    let python = bench_python(&venv)?;
    let scripts = repo_dir().join("benches/ort");
    let work = tempfile_dir()?;
    let resolved = resolve::resolve(args.weights.as_deref())?;
    let x = Preprocessor::new(args.size).tensor(image)?;
    write_f32(&work.join("input.f32"), &x.flatten_all()?.to_vec1::<f32>()?)?;
    let mut archs = Vec::new();
    let mut version = String::new();
    for arch in [Arch::MobileNetV2, Arch::EcMobileNet] {
        let network = resolved.weights.for_arch(arch)?.network(false)?;
        // The exact weights our fast path runs, BatchNorm folded, in the project's own file format.
        let mut tensors = std::collections::HashMap::new();
        network.visit_units(&mut |name, weight, bias| {
            tensors.insert(format!("{name}.weight"), weight.clone());
            if let Some(b) = bias {
                tensors.insert(format!("{name}.bias"), b.clone());
            }
        })?;
        let folded = ecm_lcd::model::weights::Weights {
            arch,
            classes: None,
            source: "ecm-lcd-bench speed (folded)".into(),
            tensors,
        };
        let weights_path = work.join(format!("{}.safetensors", arch.name()));
        folded.save(&weights_path)?;
        let blocks: Vec<serde_json::Value> = arch
            .spec()
            .blocks()
            .iter()
            .map(|b| serde_json::json!({"input": b.input, "hidden": b.hidden, "output": b.output, "stride": b.stride, "eca_kernel": b.eca_kernel}))
            .collect();
        let spec_path = work.join(format!("{}.json", arch.name()));
        std::fs::write(
            &spec_path,
            serde_json::json!({"input_size": args.size, "stem_stride": 2, "blocks": blocks}).to_string(),
        )?;
        let expected = network.features(&x, Mode::Inference)?.flatten_all()?.to_vec1::<f32>()?;
        let expected_path = work.join(format!("{}.expected.f32", arch.name()));
        write_f32(&expected_path, &expected)?;
        let onnx_path = work.join(format!("{}.onnx", arch.name()));
        run_python(
            &python,
            &scripts.join("export_onnx.py"),
            &[
                "--weights".as_ref(),
                weights_path.as_ref(),
                "--spec".as_ref(),
                spec_path.as_ref(),
                "--out".as_ref(),
                onnx_path.as_ref(),
            ],
        )?;
        let threads = args.thread_counts.iter().map(|t| t.to_string()).collect::<Vec<_>>().join(",");
        let (size, runs) = (args.size.to_string(), args.runs.to_string());
        let out = run_python(
            &python,
            &scripts.join("time_ort.py"),
            &[
                "--model".as_ref(),
                onnx_path.as_ref(),
                "--input".as_ref(),
                work.join("input.f32").as_ref(),
                "--expected".as_ref(),
                expected_path.as_ref(),
                "--size".as_ref(),
                size.as_ref(),
                "--threads".as_ref(),
                threads.as_ref(),
                "--runs".as_ref(),
                runs.as_ref(),
            ],
        )?;
        #[derive(serde::Deserialize)]
        struct OrtOut {
            onnxruntime: String,
            max_abs_diff: f64,
            timings: Vec<OrtTiming>,
        }
        let parsed: OrtOut =
            serde_json::from_str(out.trim()).with_context(|| format!("time_ort.py printed {out:?}"))?;
        version = parsed.onnxruntime;
        archs.push(OrtArch { arch, max_abs_diff: parsed.max_abs_diff, timings: parsed.timings });
    }
    std::fs::remove_dir_all(&work).ok();
    Ok(Ort { onnxruntime: version, archs })
}

/// A fresh scratch folder under the system temp dir.
fn tempfile_dir() -> Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!("ecm-lcd-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    Ok(dir)
}

fn preprocess(args: &BenchArgs, image: &RgbImage) -> Result<Vec<PreprocessRow>> {
    let runs = args.runs.max(200);
    let mut pre = Preprocessor::new(args.size);
    let rgb8 = rgb8_message(Stamp::default(), "camera", image);
    let jpeg = jpeg_message(Stamp::default(), "camera", image, 90)?;
    let mut rows = Vec::new();
    let mut row = |input, f: &mut dyn FnMut() -> Result<()>| -> Result<()> {
        rows.push(PreprocessRow { input, stats: Stats::time(10, runs, f)? });
        Ok(())
    };
    row("rgb8 Image 640x480 -> tensor (direct)", &mut || pre.tensor_from_image_msg(&rgb8).map(drop))?;
    row("rgb8 Image 640x480 -> RgbImage -> tensor", &mut || pre.tensor(&decode_image(&rgb8)?).map(drop))?;
    row("JPEG CompressedImage (q90) -> tensor", &mut || pre.tensor_from_compressed(&jpeg).map(drop))?;
    row("JPEG decode alone", &mut || decode_compressed_image(&jpeg).map(drop))?;
    Ok(rows)
}

/// Clusters for `stored` synthetic descriptors: about 50 views per place.
fn clusters_for(stored: usize) -> usize {
    (stored / 50).clamp(10, 20_000)
}

/// Newest keyframes a bench query may not match (the detector's recency rule).
const BENCH_EXCLUDE_RECENT: usize = 100;

fn search(args: &BenchArgs) -> Result<Vec<SearchRow>> {
    let mut rows = Vec::new();
    let plain = args.search_dims.iter().map(|&dim| (dim, RowFormat::F32));
    let coded = args.search_coded_dims.iter().map(|&dim| (dim, RowFormat::Levels6));
    for (dim, format) in plain.chain(coded) {
        for &stored in &args.search_sizes {
            let mb = stored * format.row_bytes(dim) / 1_000_000;
            let storage = format.name();
            if mb > args.search_max_mb {
                eprintln!(
                    "search: skipping {stored} x {dim}-d {storage} ({mb} MB > --search-max-mb {})",
                    args.search_max_mb
                );
                continue;
            }
            eprintln!("search: {stored} x {dim}-d {storage} ...");
            rows.push(search_one(args, dim, stored, format)?);
        }
    }
    Ok(rows)
}

/// The `k` nearest eligible rows to each query by exact `f32` distance, offered one row at a time.
struct StreamedExact {
    queries: Vec<f32>,
    dim: usize,
    k: usize,
    /// Per query, up to `k` (squared distance, position), nearest first.
    best: Vec<Vec<(f32, usize)>>,
}

impl StreamedExact {
    fn new(queries: &[f32], dim: usize, k: usize) -> Self {
        StreamedExact { queries: queries.to_vec(), dim, k, best: vec![Vec::new(); queries.len() / dim] }
    }

    fn offer(&mut self, position: usize, row: &[f32]) {
        use rayon::prelude::*;
        let (dim, k) = (self.dim, self.k);
        self.best.par_iter_mut().zip(self.queries.par_chunks_exact(dim)).for_each(|(best, q)| {
            let d2 = ecm_lcd::descriptor::squared_distance(q, row);
            if best.len() == k && best.last().is_some_and(|&(worst, _)| worst <= d2) {
                return;
            }
            let at = best.partition_point(|&(d, _)| d <= d2);
            best.insert(at, (d2, position));
            best.truncate(k);
        });
    }
}

fn search_one(args: &BenchArgs, dim: usize, stored: usize, format: RowFormat) -> Result<SearchRow> {
    let mut generator = ClusteredVectors::new(dim, clusters_for(stored), 42);
    let mut queries_gen = generator.clone().reseed(7);
    let mut db = KeyframeDb::with_format(format, dim, stored);
    if let Some(probe_fraction) = args.probe_fraction {
        db.set_index_policy(IndexPolicy { probe_fraction, ..db.index_policy() })?;
    }
    let queries = queries_gen.take(args.queries.max(1));
    let eligible = |p: usize| p + BENCH_EXCLUDE_RECENT < stored;
    let mut f32_exact = (format != RowFormat::F32).then(|| StreamedExact::new(&queries, dim, args.k));
    let mut v = vec![0f32; dim];
    let mut build_s = 0f64;
    let mut slowest_insert_ms = 0f64;
    for i in 0..stored {
        generator.next_into(&mut v);
        let insert_started = Instant::now();
        db.insert(i as u64, Stamp::from_nanos(i as i64), &v)?;
        let insert_s = insert_started.elapsed().as_secs_f64();
        build_s += insert_s;
        slowest_insert_ms = slowest_insert_ms.max(insert_s * 1e3);
        if let Some(exact) = f32_exact.as_mut().filter(|_| eligible(i)) {
            exact.offer(i, &v);
        }
    }
    let mut exact_results = Vec::new();
    let mut exact_samples = Vec::new();
    for q in queries.chunks_exact(dim) {
        let start = Instant::now();
        exact_results.push(db.nearest_exact(q, args.k, eligible)?);
        exact_samples.push(start.elapsed().as_secs_f64() * 1e3);
    }
    let mut auto_samples = Vec::new();
    let mut auto_results = Vec::new();
    let mut hits = 0;
    let mut wanted = 0;
    for (q, exact) in queries.chunks_exact(dim).zip(&exact_results) {
        let start = Instant::now();
        let got = db.nearest(q, args.k, eligible)?;
        auto_samples.push(start.elapsed().as_secs_f64() * 1e3);
        hits += got.iter().filter(|n| exact.iter().any(|e| e.position == n.position)).count();
        wanted += exact.len();
        auto_results.push(got);
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build()?;
    let mut pooled_samples = Vec::new();
    for q in queries.chunks_exact(dim) {
        let start = Instant::now();
        pool.install(|| db.nearest(q, args.k, eligible))?;
        pooled_samples.push(start.elapsed().as_secs_f64() * 1e3);
    }
    let recall_vs_f32 = f32_exact.map(|exact| {
        let (mut hits, mut wanted) = (0, 0);
        for (got, want) in auto_results.iter().zip(&exact.best) {
            hits += got.iter().filter(|n| want.iter().any(|&(_, p)| p == n.position)).count();
            wanted += want.len();
        }
        hits as f64 / wanted.max(1) as f64
    });
    let index = db.index_info();
    Ok(SearchRow {
        dim,
        storage: format.name(),
        stored,
        build_s,
        slowest_insert_ms,
        exact: Stats::of(&mut exact_samples),
        auto_method: if index.is_some() { "ivf" } else { "exact" },
        auto: Stats::of(&mut auto_samples),
        auto_on_two_threads: Stats::of(&mut pooled_samples),
        index,
        k: args.k,
        recall: hits as f64 / wanted.max(1) as f64,
        recall_vs_f32,
    })
}

/// The end-to-end runs; with `verify`, geometric verification is on (TUM fr3 intrinsics) and only
/// the rgb8 input runs.
fn end_to_end(args: &BenchArgs, frame: &(RgbImage, String), verify: bool) -> Result<Vec<EndToEnd>> {
    let mut params = Params::default();
    if verify {
        params.set_from_str("camera.preset", "tum_fr3").map_err(anyhow::Error::msg)?;
    }
    for assignment in &args.params {
        params.set_assignment(assignment)?;
    }
    let mut pipeline = Pipeline::new(params, args.weights.as_deref())?;
    let dim = pipeline.descriptor().dim();
    let stored = args.e2e_stored;
    eprintln!("end to end: storing {stored} synthetic {dim}-d descriptors ...");
    let mut generator = ClusteredVectors::new(dim, clusters_for(stored), 43);
    let mut v = vec![0f32; dim];
    for i in 0..stored {
        generator.next_into(&mut v);
        // Stamped a day before the live frames, so the recency rule leaves them all eligible.
        pipeline.detector_mut().insert(i as u64, Stamp::from_nanos(i as i64 * 1_000_000), &v)?;
    }
    // The two inputs alternate keyframe by keyframe, so that both see the same machine.
    let raw = rgb8_message(Stamp::default(), "camera", &frame.0);
    let jpeg = jpeg_message(Stamp::default(), "camera", &frame.0, 90)?;
    let all: [(&str, &dyn Fn() -> Result<RgbImage>); 2] =
        [("rgb8", &|| decode_image(&raw)), ("jpeg", &|| decode_compressed_image(&jpeg))];
    let inputs = if verify { &all[..1] } else { &all[..] };
    let mut next_id = stored as u64;
    let base = 86_400_000_000_000i64;
    let mut samples = vec![(Vec::new(), Vec::new(), Vec::new(), Vec::new()); inputs.len()];
    for i in 0..(5 + args.runs.max(100)) {
        for ((_, decode), (total, network, detector, verification)) in inputs.iter().zip(samples.iter_mut()) {
            let start = Instant::now();
            let image = decode()?;
            let outcome =
                pipeline.process_keyframe(next_id, Stamp::from_nanos(base + next_id as i64 * 1_000_000_000), &image)?;
            let elapsed = start.elapsed().as_secs_f64() * 1e3;
            next_id += 1;
            if i >= 5 {
                total.push(elapsed);
                network.push(outcome.timings.network_ms);
                detector.push(outcome.timings.detector_ms);
                verification.push(outcome.timings.verification_ms);
            }
        }
    }
    let mut out = Vec::new();
    for ((input, _), (mut total, mut network, mut detector, mut verification)) in inputs.iter().zip(samples) {
        out.push(EndToEnd {
            input: if verify { format!("{input}, verified") } else { input.to_string() },
            stored,
            dim,
            descriptor: pipeline.descriptor_name(),
            arch: pipeline.params().arch().parse()?,
            frame: frame.1.clone(),
            total: Stats::of(&mut total),
            network: Stats::of(&mut network),
            detector: Stats::of(&mut detector),
            verification: verify.then(|| Stats::of(&mut verification)),
            index: pipeline.detector().db().index_info(),
        });
    }
    Ok(out)
}

fn verification(args: &BenchArgs, frame: &(RgbImage, String)) -> Result<VerificationTiming> {
    use ecm_lcd::verification::{verify, Verifier};
    let mut pipeline_params = Params::default();
    pipeline_params.set_from_str("camera.preset", "tum_fr3").map_err(anyhow::Error::msg)?;
    for assignment in &args.params {
        pipeline_params.set_assignment(assignment)?;
    }
    let params = pipeline_params.verification(None).context("the verification section needs verification.mode on")?;
    let verifier = Verifier::new(params.clone())?;
    let mut paths: Vec<PathBuf> = ecm_lcd::runtime::shared_dirs()
        .into_iter()
        .filter_map(|dir| std::fs::read_dir(dir.join("data/tum/fr3_long_office_household/rgb")).ok())
        .flat_map(|entries| entries.filter_map(|e| e.ok().map(|e| e.path())).collect::<Vec<_>>())
        .collect();
    paths.sort();
    ensure!(
        paths.len() >= 3,
        "the verification section needs the TUM fr3 frames of ../shared (data/tum/fr3_long_office_household)"
    );
    let next = ecm_lcd::preprocess::read_image(&paths[1])?;
    let last = ecm_lcd::preprocess::read_image(&paths[paths.len() - 1])?;
    let runs = args.runs.max(20);
    let mut samples = Vec::new();
    let mut features = None;
    for _ in 0..runs {
        let start = Instant::now();
        features = Some(verifier.extract(&frame.0, None)?);
        samples.push(start.elapsed().as_secs_f64() * 1e3);
    }
    let features = features.expect("at least one run");
    let extract_stats = Stats::of(&mut samples);
    let check = |other: &RgbImage| -> Result<(Stats, usize)> {
        let theirs = verifier.extract(other, None)?;
        let mut samples = Vec::new();
        let mut inliers = 0;
        for _ in 0..runs {
            let start = Instant::now();
            inliers = verify(&features, &theirs, &params).inliers;
            samples.push(start.elapsed().as_secs_f64() * 1e3);
        }
        Ok((Stats::of(&mut samples), inliers))
    };
    let (matching_pair, matching_inliers) = check(&next)?;
    let (other_pair, other_inliers) = check(&last)?;
    Ok(VerificationTiming {
        frames: format!("{} against {} and {}", frame.1, paths[1].display(), paths[paths.len() - 1].display()),
        extract: extract_stats,
        matching_pair,
        matching_inliers,
        other_pair,
        other_inliers,
    })
}

fn parse_memory_spec(spec: &str) -> Result<(usize, usize)> {
    let (stored, dim) =
        spec.split_once(':').with_context(|| format!("memory spec {spec:?}: expected stored:dim, e.g. 1000000:128"))?;
    Ok((
        stored.trim().parse().with_context(|| format!("memory spec {spec:?}: bad count"))?,
        dim.trim().parse().with_context(|| format!("memory spec {spec:?}: bad dim"))?,
    ))
}

/// Runs one memory measurement in a child process, so each peak is its own.
fn memory(spec: &str) -> Result<MemoryRow> {
    parse_memory_spec(spec)?;
    eprintln!("memory: {spec} in a child process ...");
    let exe = std::env::current_exe().context("cannot find this program to run the memory child")?;
    let output =
        Command::new(exe).args(["speed", "--memory-child", spec]).output().context("cannot run the memory child")?;
    ensure!(output.status.success(), "memory child {spec} failed: {}", String::from_utf8_lossy(&output.stderr).trim());
    let out = String::from_utf8_lossy(&output.stdout);
    serde_json::from_str(out.trim()).with_context(|| format!("memory child printed {out:?}"))
}

/// `VmRSS` and `VmHWM` (MB) of this process.
fn rss_mb() -> Result<(f64, f64)> {
    let status = std::fs::read_to_string("/proc/self/status").context("reading /proc/self/status (Linux only)")?;
    let field = |name: &str| -> Result<f64> {
        let line =
            status.lines().find(|l| l.starts_with(name)).with_context(|| format!("no {name} in /proc/self/status"))?;
        let kb: f64 =
            line[name.len()..].trim().trim_end_matches("kB").trim().parse().with_context(|| format!("bad {line:?}"))?;
        Ok(kb * 1024.0 / 1e6)
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

fn memory_child(stored: usize, dim: usize) -> Result<MemoryRow> {
    let (baseline_mb, _) = rss_mb()?;
    // Any unit-vector mode whose length is its channel count: only the length and the score matter here.
    let descriptor = ecm_lcd::descriptor::Descriptor::new(ecm_lcd::descriptor::DescriptorMode::L2, dim);
    let params = ecm_lcd::detector::DetectorParams { min_history: 1, ..ecm_lcd::config::Params::default().detector() };
    let mut detector = Detector::new(descriptor, params);
    let mut generator = ClusteredVectors::new(dim, clusters_for(stored), 44);
    let mut v = vec![0f32; dim];
    for i in 0..stored {
        generator.next_into(&mut v);
        detector.insert(i as u64, Stamp::from_nanos(i as i64), &v)?;
    }
    for i in 0..10 {
        generator.next_into(&mut v);
        detector.best_match(Stamp::from_nanos((stored + i) as i64), &v)?;
    }
    let (_, peak_mb) = rss_mb()?;
    Ok(MemoryRow {
        stored,
        dim,
        baseline_mb,
        peak_mb,
        descriptors_mb: (stored * detector.row_bytes()) as f64 / 1e6,
        storage: detector.db().format().name().into(),
        indexed: detector.db().index_info().is_some(),
    })
}

fn goals(report: &Report) -> Vec<Goal> {
    let mut goals = Vec::new();
    let mut goal = |goal: &str, measured: String, met: bool| goals.push(Goal { goal: goal.into(), measured, met });
    let ours = |arch: Arch, threads: usize| {
        report
            .forward
            .as_ref()?
            .iter()
            .find(|t| t.arch == arch && t.threads == threads && t.path == "fast")
            .map(|t| t.median_ms)
    };
    let theirs = |arch: Arch, threads: usize| {
        report
            .ort
            .as_ref()?
            .archs
            .iter()
            .find(|a| a.arch == arch)?
            .timings
            .iter()
            .find(|t| t.threads == threads)
            .map(|t| t.median_ms)
    };
    if let (Some(e), Some(o)) = (ours(Arch::EcMobileNet, 2), theirs(Arch::MobileNetV2, 2)) {
        goal("ECMobileNet forward <= 1.0 x ORT MobileNetV2 (2 threads)", format!("{:.2} x", e / o), e / o <= 1.0);
    }
    if let (Some(m), Some(o)) = (ours(Arch::MobileNetV2, 2), theirs(Arch::MobileNetV2, 2)) {
        goal("MobileNetV2 forward <= 1.3 x ORT MobileNetV2 (2 threads)", format!("{:.2} x", m / o), m / o <= 1.3);
    }
    if let Some(ort) = &report.ort {
        for a in &ort.archs {
            goal(
                &format!("ORT {} output equals ecm-lcd's within 1e-4", a.arch.name()),
                format!("max abs diff {:.2e}", a.max_abs_diff),
                a.max_abs_diff <= 1e-4,
            );
        }
    }
    if let Some(p) = report.preprocess.as_ref().and_then(|rows| rows.first()) {
        goal(
            "preprocessing 640x480 rgb8 -> tensor <= 1.5 ms",
            format!("{:.3} ms median", p.stats.median_ms),
            p.stats.median_ms <= 1.5,
        );
    }
    for e in report.end_to_end.iter().flatten() {
        let limit = if e.input.ends_with("verified") { 25.0 } else { 15.0 };
        goal(
            &format!("keyframe ({}) -> candidate p99 <= {limit} ms with {} stored ({}-d)", e.input, e.stored, e.dim),
            format!("{:.1} ms p99", e.total.p99_ms),
            e.total.p99_ms <= limit,
        );
    }
    if let Some(v) = &report.verification {
        for (pair, stats) in [("matching", &v.matching_pair), ("non-matching", &v.other_pair)] {
            goal(
                &format!("verification of a {pair} pair <= 10 ms"),
                format!("{:.2} ms median, {:.2} ms p99", stats.median_ms, stats.p99_ms),
                stats.p99_ms <= 10.0,
            );
        }
    }
    if let Some(rows) = &report.search {
        for r in rows.iter().filter(|r| r.stored >= 1_000_000) {
            // Coded rows are judged against the exact search of the vectors they code.
            let recall = r.recall_vs_f32.unwrap_or(r.recall);
            goal(
                &format!("query at 1M ({}-d {}) <= 5 ms with recall >= 0.99", r.dim, r.storage),
                format!("{:.2} ms median, recall@{} {:.4}", r.auto.median_ms, r.k, recall),
                r.auto.median_ms <= 5.0 && recall >= 0.99,
            );
        }
    }
    if let Some(rows) = &report.memory {
        for r in rows.iter().filter(|r| r.stored >= 1_000_000) {
            // The paper's 128-d descriptor: 600 MB; the default descriptor, coded: 1.5 GB.
            let limit = if r.dim <= 128 { 600.0 } else { 1500.0 };
            goal(
                &format!("1M stored ({}-d {}) <= {limit:.0} MB RSS", r.dim, r.storage),
                format!("{:.0} MB peak", r.peak_mb),
                r.peak_mb <= limit,
            );
        }
    }
    goals
}

fn print_report(args: &BenchArgs, report: &Report) {
    if let Some(m) = &report.machine {
        println!("machine: {} ({} logical cores, {})", m.cpu, m.logical_cores, m.os);
    }
    if let Some(rows) = &report.profile {
        println!("\nprofile: ECMobileNet stage by stage, mean of {} runs", args.runs);
        println!("{:<10} {:>7} {:>10} {:>9} {:>8} {:>7}", "stage", "threads", "MACs", "ms", "GMAC/s", "share");
        for &threads in &args.thread_counts {
            let total: f64 = rows.iter().filter(|r| r.threads == threads).map(|r| r.ms).sum();
            for r in rows.iter().filter(|r| r.threads == threads) {
                let rate = r.macs as f64 / r.ms / 1e6;
                println!(
                    "{:<10} {:>7} {:>10} {:>9.3} {:>8.1} {:>6.1}%",
                    r.stage,
                    threads,
                    r.macs,
                    r.ms,
                    rate,
                    100.0 * r.ms / total
                );
            }
            println!("{:<10} {:>7} {:>10} {:>9.3}", "total", threads, "", total);
        }
    }
    let ort_time = |arch: Arch, threads: usize| {
        report
            .ort
            .as_ref()
            .and_then(|o| o.archs.iter().find(|a| a.arch == arch))
            .and_then(|a| a.timings.iter().find(|t| t.threads == threads))
    };
    if report.forward.is_some() || report.ort.is_some() {
        println!("\nforward, batch 1, {0}x{0} tensor (network only), {1} runs after 5 warm-up", args.size, args.runs);
        println!(
            "{:<12} {:<14} {:>7} {:>10} {:>12} {:>10} {:>9}",
            "arch", "runtime", "threads", "params", "MACs", "median ms", "p90 ms"
        );
        for t in report.forward.iter().flatten() {
            let runtime = if t.path == "fast" { "ecm-lcd" } else { "ecm-lcd stock" };
            println!(
                "{:<12} {:<14} {:>7} {:>10} {:>12} {:>10.2} {:>9.2}",
                t.arch.name(),
                runtime,
                t.threads,
                t.params,
                t.macs,
                t.median_ms,
                t.p90_ms
            );
        }
        if let Some(o) = &report.ort {
            for a in &o.archs {
                for t in &a.timings {
                    let runtime = format!("ORT {}", o.onnxruntime);
                    println!(
                        "{:<12} {:<14} {:>7} {:>10} {:>12} {:>10.2} {:>9.2}",
                        a.arch.name(),
                        runtime,
                        t.threads,
                        "",
                        "",
                        t.median_ms,
                        t.p90_ms
                    );
                }
                println!("  ORT {} output vs ecm-lcd: max abs diff {:.2e}", a.arch.name(), a.max_abs_diff);
            }
        }
        for &threads in &args.thread_counts {
            let ours = |arch| {
                report
                    .forward
                    .iter()
                    .flatten()
                    .find(|t| t.arch == arch && t.threads == threads && t.path == "fast")
                    .map(|t| t.median_ms)
            };
            let mut ratios = Vec::new();
            if let (Some(e), Some(m)) = (ours(Arch::EcMobileNet), ours(Arch::MobileNetV2)) {
                ratios.push(format!("ecmobilenet/mobilenetv2 {:.2}", e / m));
            }
            if let Some(o) = ort_time(Arch::MobileNetV2, threads) {
                if let Some(m) = ours(Arch::MobileNetV2) {
                    ratios.push(format!("mobilenetv2/ORT mobilenetv2 {:.2}", m / o.median_ms));
                }
                if let Some(e) = ours(Arch::EcMobileNet) {
                    ratios.push(format!("ecmobilenet/ORT mobilenetv2 {:.2}", e / o.median_ms));
                }
            }
            if let (Some(e), Some(o)) = (ours(Arch::EcMobileNet), ort_time(Arch::EcMobileNet, threads)) {
                ratios.push(format!("ecmobilenet/ORT ecmobilenet {:.2}", e / o.median_ms));
            }
            if !ratios.is_empty() {
                println!("ratios at {threads} thread(s): {}", ratios.join(", "));
            }
        }
    }
    if let Some(rows) = &report.preprocess {
        println!("\npreprocessing to a [1, 3, {0}, {0}] tensor (1 thread)", args.size);
        println!("{:<42} {:>6} {:>10} {:>9} {:>9}", "input", "runs", "median ms", "p90 ms", "p99 ms");
        for r in rows {
            println!(
                "{:<42} {:>6} {:>10.3} {:>9.3} {:>9.3}",
                r.input, r.stats.runs, r.stats.median_ms, r.stats.p90_ms, r.stats.p99_ms
            );
        }
    }
    if let Some(rows) = &report.search {
        println!("\nsearch: top-{} of clustered unit vectors, newest {BENCH_EXCLUDE_RECENT} excluded, {} queries, 1 thread per query (2-thr: from a 2-thread pool's worker, as the pipeline runs it)", args.k, args.queries);
        println!(
            "{:>5} {:>8} {:>8} {:>8} {:>11} {:>10} {:>9} {:>6} {:>10} {:>9} {:>11} {:>22} {:>8} {:>10}",
            "dim",
            "storage",
            "stored",
            "build s",
            "slowest ins",
            "exact med",
            "exact p90",
            "auto",
            "auto med",
            "auto p90",
            "2-thr med",
            "lists/probed, largest",
            "recall",
            "vs f32"
        );
        for r in rows {
            let lists = r
                .index
                .map(|i| format!("{}/{} max {}", i.nlist, i.nprobe, i.largest_list))
                .unwrap_or_else(|| "-".into());
            println!(
                "{:>5} {:>8} {:>8} {:>8.1} {:>8.0} ms {:>10.3} {:>9.3} {:>6} {:>10.3} {:>9.3} {:>11.3} {:>22} {:>8.4} {:>10}",
                r.dim,
                r.storage,
                r.stored,
                r.build_s,
                r.slowest_insert_ms,
                r.exact.median_ms,
                r.exact.p90_ms,
                r.auto_method,
                r.auto.median_ms,
                r.auto.p90_ms,
                r.auto_on_two_threads.median_ms,
                lists,
                r.recall,
                r.recall_vs_f32.map(|r| format!("{r:.4}")).unwrap_or_else(|| "-".into())
            );
        }
    }
    for e in report.end_to_end.iter().flatten() {
        let input = match e.input.as_str() {
            "jpeg" => "JPEG CompressedImage",
            "rgb8" => "rgb8 Image (as ecm_lcd/Keyframe carries it)",
            _ => "rgb8 Image with geometric verification (TUM fr3 intrinsics)",
        };
        println!(
            "\nend to end: {input} -> decode -> {} -> {} descriptor ({}-d) -> search among {} stored -> candidates",
            e.arch.name(),
            e.descriptor,
            e.dim,
            e.stored
        );
        println!(
            "  frame: {}; index: {}",
            e.frame,
            e.index.map(|i| format!("ivf {}/{}", i.nlist, i.nprobe)).unwrap_or_else(|| "exact".into())
        );
        // With verification, ORB extraction runs beside the forward pass, which then ends when both do.
        let network =
            if e.verification.is_some() { "network (beside ORB extraction)" } else { "network (preprocess + forward)" };
        for (what, s) in [("total", e.total), (network, e.network), ("detector (search + insert)", e.detector)] {
            println!(
                "  {what:<32} median {:>7.2} ms  p90 {:>7.2} ms  p99 {:>7.2} ms  ({} runs)",
                s.median_ms, s.p90_ms, s.p99_ms, s.runs
            );
        }
        if let Some(v) = e.verification {
            let what = "verification (ORB + check)";
            println!(
                "  {what:<32} median {:>7.2} ms  p90 {:>7.2} ms  p99 {:>7.2} ms  ({} runs)",
                v.median_ms, v.p90_ms, v.p99_ms, v.runs
            );
        }
    }
    if let Some(v) = &report.verification {
        println!("\nverification: {}", v.frames);
        for (what, s) in [
            ("ORB extraction (640x480)".to_string(), v.extract),
            (format!("check, matching pair ({} inliers)", v.matching_inliers), v.matching_pair),
            (format!("check, non-matching pair ({} inliers)", v.other_inliers), v.other_pair),
        ] {
            println!(
                "  {what:<40} median {:>7.2} ms  p90 {:>7.2} ms  p99 {:>7.2} ms  ({} runs)",
                s.median_ms, s.p90_ms, s.p99_ms, s.runs
            );
        }
    }
    if let Some(rows) = &report.memory {
        println!("\npeak memory (VmHWM of a child process that stores descriptors in a Detector, then queries)");
        println!(
            "{:>8} {:>5} {:>8} {:>12} {:>10} {:>13} {:>8}",
            "stored", "dim", "storage", "baseline MB", "peak MB", "rows MB", "indexed"
        );
        for r in rows {
            println!(
                "{:>8} {:>5} {:>8} {:>12.0} {:>10.0} {:>13.0} {:>8}",
                r.stored, r.dim, r.storage, r.baseline_mb, r.peak_mb, r.descriptors_mb, r.indexed
            );
        }
    }
    if !report.goals.is_empty() {
        println!("\ngoals");
        for g in &report.goals {
            println!("  [{}] {:<62} {}", if g.met { "met" } else { "NOT met" }, g.goal, g.measured);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn order_statistics_and_memory_specs() {
        let mut samples: Vec<f64> = (1..=100).rev().map(f64::from).collect();
        let s = Stats::of(&mut samples);
        assert_eq!((s.runs, s.median_ms, s.p90_ms, s.p99_ms), (100, 51.0, 90.0, 99.0));
        assert!(Stats::of(&mut []).median_ms.is_nan());
        assert_eq!(parse_memory_spec("1000000:128").unwrap(), (1_000_000, 128));
        for bad in ["1000000", "x:128", "10:"] {
            assert!(format!("{:#}", parse_memory_spec(bad).unwrap_err()).contains(bad), "{bad}");
        }
    }
}
