//! `ecm-lcd learn-projection`: learns a PCA projection (optionally whitened) of the configured
//! descriptor from the frames of one or more sources, without labels, and saves it for
//! `descriptor.projection` ([`ecm_lcd::descriptor::Projection`]).

use std::path::PathBuf;

use anyhow::{ensure, Context, Result};

use super::replay::SourceArgs;
use ecm_lcd::descriptor::Projection;
use ecm_lcd::io::open_source_topics;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Sources to learn from (TUM folders, image folders, bags): images of the kind the robot will
    /// see, e.g. `synth` output or a recording of the building; no labels needed.
    #[arg(required = true)]
    pub sources: Vec<PathBuf>,
    #[command(flatten)]
    pub source_args: SourceArgs,
    /// Output file (safetensors).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Dimensions to keep (at most the number of frames used minus one).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=8192))]
    pub dims: u32,
    /// Scale each axis to unit variance (PCA-whitening).
    #[arg(long)]
    pub whiten: bool,
    /// Use every N-th frame of each source.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub every: u32,
    /// Use at most this many frames in all, shared out over the sources and spread over each.
    #[arg(long, default_value_t = 4000, value_parser = clap::value_parser!(u32).range(2..=20_000))]
    pub max_frames: u32,
}

pub fn run(args: Args) -> Result<()> {
    let inputs: Vec<&std::path::Path> = args.sources.iter().map(PathBuf::as_path).collect();
    args.source_args.refuse_source_only("learn-projection (it reads only images)")?;
    ecm_lcd::io::output::ensure_outputs(&inputs, &args.source_args.files_read(), None, &[("-o", &args.output)])?;
    let mut params = args.source_args.params()?;
    // Learned on the descriptor itself, never on a projection of it.
    params.set_from_str("descriptor.projection", "").map_err(anyhow::Error::msg)?;
    let mut pipeline = args.source_args.pipeline_with(params)?;
    let name = pipeline.descriptor_name();
    let mut samples = Vec::new();
    // --max-frames is shared out over the sources (what one leaves unused goes to those after it),
    // and spread over each source's length where it is known: a long first source does not take
    // the whole budget from its first minutes.
    for (k, source) in args.sources.iter().enumerate() {
        let share = (args.max_frames as usize).saturating_sub(samples.len()).div_ceil(args.sources.len() - k);
        let frames = open_source_topics(source, &args.source_args.topics())?;
        let every = args.every as usize;
        // Of every `--every`th frame, `share` evenly spread where the length is known.
        let picked: Option<std::collections::BTreeSet<usize>> = frames.len_hint().map(|len| {
            let candidates: Vec<usize> = (0..len).step_by(every).collect();
            let n = share.min(candidates.len());
            (0..n).map(|i| candidates[i * candidates.len() / n]).collect()
        });
        log::info!("learning from {} (at most {share} frames)", frames.describe());
        let before = samples.len();
        for frame in ecm_lcd::io::skip_unreadable(frames, source) {
            let frame = frame.with_context(|| format!("reading {}", source.display()))?;
            let wanted = match &picked {
                Some(picked) => picked.contains(&frame.index),
                None => frame.index % every == 0,
            };
            if wanted {
                samples.push(pipeline.describe(&frame.image)?);
            }
            if samples.len() - before >= share {
                break;
            }
        }
    }
    ensure!(
        samples.len() > args.dims as usize,
        "{} frames give at most {} dimensions; asked for {} (give more frames or fewer --dims)",
        samples.len(),
        samples.len().saturating_sub(1),
        args.dims
    );
    let started = std::time::Instant::now();
    let mut projection = Projection::learn(&samples, args.dims as usize, args.whiten, &name)?;
    projection.network = Some(pipeline.network_name());
    projection.save(&args.output)?;
    println!(
        "learned {} -> {} dimensions{} from {} frames in {:.1} s; wrote {} (use --param descriptor.projection={})",
        projection.in_dim(),
        projection.out_dim(),
        if args.whiten { ", whitened" } else { "" },
        samples.len(),
        started.elapsed().as_secs_f64(),
        args.output.display(),
        args.output.display()
    );
    Ok(())
}
