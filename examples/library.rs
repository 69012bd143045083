//! The library used directly, without the command line: every frame of a source (a folder of
//! images, a TUM folder or a bag) through one [`Pipeline`], loop candidates printed as they are found.
//!
//!     cargo run --release --example library -- bags/sample_loop.bag
//!
//! The weights are found as the commands find them (`../shared`, the cache, or a checked download).

use std::path::PathBuf;

use anyhow::{Context, Result};
use ecm_lcd::config::Params;
use ecm_lcd::io::open_source;
use ecm_lcd::pipeline::Pipeline;

fn main() -> Result<()> {
    ecm_lcd::runtime::init_threads(None);
    let source: PathBuf =
        std::env::args().nth(1).context("usage: library SOURCE (image folder, TUM folder or bag)")?.into();
    // The built-in defaults, which equal config/ecm_lcd.yaml; any parameter can be set by name.
    let mut params = Params::default();
    params.set_from_str("detector.top_k", "1")?;
    let mut pipeline = Pipeline::new(params, None)?;
    let mut keyframes = 0;
    for frame in open_source(&source, None)? {
        let frame = frame?;
        let outcome = pipeline.process_source_frame(&frame, None)?;
        keyframes += usize::from(outcome.keyframe.is_some());
        for candidate in outcome.candidates {
            println!(
                "frame {} revisits frame {} (score {:.3}, {} s apart)",
                candidate.query_id,
                candidate.match_id,
                candidate.score,
                (candidate.query_stamp.nanos - candidate.match_stamp.nanos) / 1_000_000_000
            );
        }
    }
    println!("{keyframes} keyframes in {}", source.display());
    Ok(())
}
