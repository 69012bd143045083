//! `ecm-lcd synth`: renders a synthetic looping indoor sequence into a TUM RGB-D folder.

use crate::synth::{write_tum_folder, Scene, SynthConfig};
use anyhow::{bail, Result};
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Output folder (created; must not already hold an rgb.txt).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Number of frames.
    #[arg(long, default_value_t = SynthConfig::default().frames)]
    pub frames: usize,
    /// Number of laps of the closed path, spread over the frames.
    #[arg(long, default_value_t = SynthConfig::default().laps)]
    pub laps: usize,
    /// Seed of textures, furniture, posters, per-lap perturbation and lighting.
    #[arg(long, default_value_t = SynthConfig::default().seed)]
    pub seed: u64,
    #[arg(long, default_value_t = SynthConfig::default().width)]
    pub width: u32,
    #[arg(long, default_value_t = SynthConfig::default().height)]
    pub height: u32,
    /// Frame rate of the stamps (frames per second).
    #[arg(long, default_value_t = SynthConfig::default().rate_hz)]
    pub rate: f64,
}

pub fn run(args: Args) -> Result<()> {
    if args.output.join("rgb.txt").exists() {
        bail!("{} already holds a sequence (rgb.txt); choose an empty folder", args.output.display());
    }
    let config = SynthConfig {
        frames: args.frames,
        laps: args.laps,
        seed: args.seed,
        width: args.width,
        height: args.height,
        rate_hz: args.rate,
        ..SynthConfig::default()
    };
    let scene = Scene::new(config)?;
    let started = Instant::now();
    write_tum_folder(&scene, &args.output)?;
    let seconds = started.elapsed().as_secs_f64();
    log::info!(
        "wrote {} frames ({} laps of {:.1} m) to {} in {:.1} s ({:.1} ms/frame including PNG encoding)",
        scene.len(),
        args.laps,
        scene.lap_length(),
        args.output.display(),
        seconds,
        seconds * 1e3 / scene.len() as f64
    );
    Ok(())
}
