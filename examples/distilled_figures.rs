//! Loop-closure figures of ECMobileNet initialised from MobileNetV2 (no training), of a
//! distilled ECMobileNet (the weights file given as the argument, written by `ecm-lcd distill`),
//! and of MobileNetV2 itself, with the default `l2` descriptor: a program that measures and prints
//! (the README's distillation table), not a test. The sets are `compare_descriptors`' own
//! (`examples/common/mod.rs`).
//!
//!     cargo run --release --example distilled_figures -- student.safetensors

mod common;

use std::path::PathBuf;

use anyhow::{Context, Result};
use ecm_lcd::model::weights::resolve;

fn main() -> Result<()> {
    let student_path = PathBuf::from(std::env::args().nth(1).context("usage: distilled_figures STUDENT.safetensors")?);
    let (_dir, sets) = common::start()?;
    let mnv2 = resolve::resolve(None)?;
    let student = resolve::load_file(&student_path)?;
    let networks = [
        ("ECMobileNet from MobileNetV2, no training", "ecmobilenet", &mnv2),
        ("ECMobileNet distilled", "ecmobilenet", &student),
        ("MobileNetV2", "mobilenetv2", &mnv2),
    ];
    println!("student: {}", student.describe());
    println!("| data | network | queries (with loop) | recall@1 | recall@100%P | AP |");
    println!("|---|---|---|---|---|---|");
    for set in &sets {
        for (label, arch, weights) in networks {
            let (m, _) = common::evaluate_on(set, arch, None, weights)?;
            let f = common::figure;
            println!(
                "| {} | {label} | {} ({}) | {} | {} | {} |",
                set.name,
                m.queries,
                m.positives,
                f(m.recall_at_1),
                f(m.recall_at_100_precision),
                f(m.average_precision)
            );
        }
    }
    Ok(())
}
