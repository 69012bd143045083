//! Compares descriptor modes and networks on real and synthetic data: a program that measures
//! and prints (the README's table), not a test. The sets: `examples/common/mod.rs`.
//!
//!     cargo run --release --example compare_descriptors

mod common;

use anyhow::Result;
use ecm_lcd::model::weights::resolve;

fn main() -> Result<()> {
    let (_dir, sets) = common::start()?;
    let weights = resolve::resolve(None)?;
    println!("| data | network | descriptor | dim | queries (with loop) | recall@1 | recall@100%P | AP |");
    println!("|---|---|---|---|---|---|---|---|");
    for set in &sets {
        for arch in ["ecmobilenet", "mobilenetv2"] {
            for mode in ["paper", "l2", "spatial"] {
                let (m, dim) = common::evaluate_on(set, arch, Some(mode), &weights)?;
                let f = common::figure;
                println!(
                    "| {} | {arch} | {mode} | {dim} | {} ({}) | {} | {} | {} |",
                    set.name,
                    m.queries,
                    m.positives,
                    f(m.recall_at_1),
                    f(m.recall_at_100_precision),
                    f(m.average_precision)
                );
            }
        }
    }
    Ok(())
}
