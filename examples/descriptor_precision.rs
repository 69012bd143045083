//! What storing descriptors in f16 or int8 instead of f32 would cost in loop-closure accuracy: a
//! program that measures and prints (the README's precision table), not a test. The sets are
//! `compare_descriptors`' own (`examples/common/mod.rs`), with ECMobileNet.
//!
//!     cargo run --release --example descriptor_precision
//!
//! Each set is replayed once in f32 with every keyframe stored (`--db`). The stored keyframes then
//! go, in their order, through a fresh detector with the same parameters, each descriptor rounded
//! to the storage format and back, queries included: a store in that format would compute these
//! very distances (f32 sums over the decoded values), so the figures are what it would give. The
//! f32 pass through the fresh detector must reproduce the replay exactly, which checks the method.
//!
//! int8 is symmetric with one f32 scale per descriptor (largest magnitude -> 127): 4 bytes more
//! per keyframe, and no per-dimension statistics that would have to be trained and kept.

mod common;

use anyhow::{ensure, Result};
use ecm_lcd::detector::store::KeyframeStore;
use ecm_lcd::detector::Detector;
use ecm_lcd::eval::{evaluate, QueryResult};
use ecm_lcd::model::weights::resolve;

/// A storage format: its name, bytes per stored descriptor of `dim` values, and the round trip.
struct Format {
    name: &'static str,
    bytes: fn(usize) -> usize,
    round_trip: fn(&[f32]) -> Vec<f32>,
}

const FORMATS: [Format; 3] = [
    Format { name: "f32", bytes: |dim| 4 * dim, round_trip: |v| v.to_vec() },
    Format { name: "f16", bytes: |dim| 2 * dim, round_trip: f16_round_trip },
    Format { name: "int8 + scale", bytes: |dim| dim + 4, round_trip: int8_round_trip },
];

fn f16_round_trip(v: &[f32]) -> Vec<f32> {
    v.iter().map(|&x| half::f16::from_f32(x).to_f32()).collect()
}

fn int8_round_trip(v: &[f32]) -> Vec<f32> {
    let max = v.iter().fold(0f32, |m, x| m.max(x.abs()));
    if max == 0.0 {
        return v.to_vec();
    }
    let scale = max / 127.0;
    v.iter().map(|&x| (x / scale).round().clamp(-127.0, 127.0) * scale).collect()
}

fn main() -> Result<()> {
    let (dir, sets) = common::start()?;
    let weights = resolve::resolve(None)?;
    println!("| data | descriptor | stored as | bytes | recall@1 | recall@100%P | AP | same best match as f32 | largest score change |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for (s, set) in sets.iter().enumerate() {
        for mode in ["paper", "l2"] {
            let db_path = dir.path().join(format!("set{s}_{mode}.db"));
            let replayed = common::replay_on(set, "ecmobilenet", Some(mode), &weights, Some(&db_path))?;
            let keyframes = KeyframeStore::open_existing(&db_path)?.keyframes()?;
            let replay_results = replayed.run.query_results();
            let dim = replayed.pipeline.descriptor().dim();
            let mut f32_results: Vec<QueryResult> = Vec::new();
            for format in &FORMATS {
                let mut detector =
                    Detector::new(*replayed.pipeline.descriptor(), replayed.pipeline.params().detector());
                let mut results = Vec::with_capacity(keyframes.len());
                for keyframe in &keyframes {
                    let (nearest, _) = detector.process_ranked(
                        keyframe.id,
                        keyframe.stamp,
                        &(format.round_trip)(&keyframe.descriptor),
                        1,
                    )?;
                    results.push(QueryResult {
                        query: keyframe.id as usize,
                        best: nearest.first().map(|m| (m.id as usize, m.score)),
                    });
                }
                if format.name == "f32" {
                    ensure!(results == replay_results, "the f32 pass differs from the replay: the method is wrong");
                    f32_results = results.clone();
                }
                let same_best = results
                    .iter()
                    .zip(&f32_results)
                    .filter(|(a, b)| a.best.map(|m| m.0) == b.best.map(|m| m.0))
                    .count();
                let largest_score_change = results
                    .iter()
                    .zip(&f32_results)
                    .filter_map(|(a, b)| Some((a.best?.1 - b.best?.1).abs()))
                    .fold(0f32, f32::max);
                let m = evaluate(&results, &replayed.truth)?;
                let f = common::figure;
                println!(
                    "| {} | {mode} | {} | {} | {} | {} | {} | {same_best} of {} | {largest_score_change:.1e} |",
                    set.name,
                    format.name,
                    (format.bytes)(dim),
                    f(m.recall_at_1),
                    f(m.recall_at_100_precision),
                    f(m.average_precision),
                    results.len(),
                );
            }
        }
    }
    Ok(())
}
