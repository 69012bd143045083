//! `ecm-lcd bench`: a benchmark program (not a test). Measures network forward time per image at
//! batch 1 for each architecture and thread count, after warm-up, and prints median and p90.

use std::time::Instant;

use anyhow::Result;
use image::RgbImage;
use serde::Serialize;

use super::model::NetworkArgs;
use crate::model::Arch;

#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// Weights (default resolution as for every command).
    #[arg(long)]
    pub weights: Option<std::path::PathBuf>,
    /// Input size.
    #[arg(long, default_value_t = 224)]
    pub size: usize,
    /// Timed runs per configuration (after warm-up).
    #[arg(long, default_value_t = 50)]
    pub runs: usize,
    /// Thread counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    pub threads: Vec<usize>,
    /// Also time the stock-candle reference path.
    #[arg(long)]
    pub reference: bool,
    #[arg(long)]
    pub json: bool,
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

/// Median and 90th percentile of `samples` (ms).
pub fn median_p90(samples: &mut [f64]) -> (f64, f64) {
    samples.sort_by(f64::total_cmp);
    let at = |q: f64| samples[((samples.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.9))
}

pub fn run(args: BenchArgs) -> Result<()> {
    // A fixed pseudo-random 640x480 frame: the content does not change the arithmetic.
    let mut seed = 0x2545F491u32;
    let image = RgbImage::from_fn(640, 480, |_, _| {
        seed ^= seed << 13;
        seed ^= seed >> 17;
        seed ^= seed << 5;
        image::Rgb([seed as u8, (seed >> 8) as u8, (seed >> 16) as u8])
    });
    let mut timings = Vec::new();
    for arch in [Arch::EcMobileNet, Arch::MobileNetV2] {
        let paths: &[bool] = if args.reference { &[false, true] } else { &[false] };
        for &reference in paths {
            let network = NetworkArgs { weights: args.weights.clone(), arch: Some(arch), size: args.size, reference };
            let (mut embedder, _) = network.embedder(arch, false)?;
            let cost = arch.spec().cost(None, args.size);
            for &threads in &args.threads {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
                // candle sizes its matmul split by this variable on every call.
                std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
                let mut samples = pool.install(|| -> Result<Vec<f64>> {
                    for _ in 0..5 {
                        embedder.feature_map(&image)?;
                    }
                    (0..args.runs.max(1))
                        .map(|_| {
                            let start = Instant::now();
                            embedder.feature_map(&image)?;
                            Ok(start.elapsed().as_secs_f64() * 1e3)
                        })
                        .collect()
                })?;
                let (median_ms, p90_ms) = median_p90(&mut samples);
                let path = if reference { "stock candle" } else { "fast" };
                timings.push(Timing { arch, path, threads, params: cost.params, macs: cost.macs, runs: samples.len(), median_ms, p90_ms });
            }
        }
    }
    std::env::set_var("RAYON_NUM_THREADS", crate::runtime::init_threads(None).to_string());
    if args.json {
        println!("{}", serde_json::to_string_pretty(&timings)?);
        return Ok(());
    }
    println!("forward, batch 1, {0}x{0} input incl. preprocessing of a 640x480 frame, {1} runs after 5 warm-up", args.size, args.runs);
    println!("{:<12} {:<13} {:>7} {:>10} {:>12} {:>10} {:>9}", "arch", "path", "threads", "params", "MACs", "median ms", "p90 ms");
    for t in &timings {
        println!(
            "{:<12} {:<13} {:>7} {:>10} {:>12} {:>10.2} {:>9.2}",
            t.arch.name(),
            t.path,
            t.threads,
            t.params,
            t.macs,
            t.median_ms,
            t.p90_ms
        );
    }
    for &threads in &args.threads {
        let find = |arch| timings.iter().find(|t| t.arch == arch && t.threads == threads && t.path == "fast");
        if let (Some(e), Some(m)) = (find(Arch::EcMobileNet), find(Arch::MobileNetV2)) {
            println!("ratio ecmobilenet/mobilenetv2 at {threads} thread(s): {:.2}", e.median_ms / m.median_ms);
        }
    }
    Ok(())
}
