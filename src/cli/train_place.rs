//! `ecm-lcd train-place`: the loop-closure objective (see [`ecm_lcd::train::place`]).

use std::path::PathBuf;

use anyhow::Result;

use ecm_lcd::model::weights::resolve;
use ecm_lcd::train::data::Augment;
use ecm_lcd::train::place::{train_place, PlaceConfig};
use ecm_lcd::train::{check_device, Optimisation, OptimizerKind};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Sequences with ground-truth poses (TUM folders with groundtruth.txt, e.g. `ecm-lcd synth` output).
    #[arg(required = true)]
    pub data: Vec<PathBuf>,
    /// Trained weights (inference form, usable as --weights); the report goes beside it as `.json`.
    #[arg(short, long)]
    pub out: PathBuf,
    /// Initial weights (default: see README "Weights").
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Parameters whose `arch` and `descriptor.*` say which descriptor is trained (default: the
    /// built-in defaults, i.e. what the detector runs).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override a parameter: `--param arch=ecmobilenet` (repeatable).
    #[arg(long = "param", value_name = "NAME=VALUE")]
    pub params: Vec<String>,
    /// Input size to train at (default: the parameters' `input_size`, which the trained weights are
    /// then used at).
    #[arg(long)]
    pub size: Option<usize>,
    /// Each epoch takes every frame that has a revisit once as an anchor.
    #[arg(long, default_value_t = 2)]
    pub epochs: usize,
    /// Anchors per step (each brings its revisit and one random frame: three images per anchor).
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    #[arg(long, value_enum, default_value_t = OptimizerKind::Adamw)]
    pub optimizer: OptimizerKind,
    #[arg(long, default_value_t = 1e-4)]
    pub lr: f64,
    #[arg(long, default_value_t = 0.9)]
    pub momentum: f64,
    #[arg(long, default_value_t = 0.0)]
    pub weight_decay: f64,
    #[arg(long, default_value_t = 0.2)]
    pub warmup_epochs: f64,
    /// Triplet margin on squared descriptor distances (unit vectors: in [0, 4]).
    #[arg(long, default_value_t = 0.1)]
    pub margin: f64,
    /// Same place: centres at most this far apart (metres) ...
    #[arg(long, default_value_t = 1.0)]
    pub max_distance: f64,
    /// ... optical axes at most this many degrees apart ...
    #[arg(long, default_value_t = 30.0)]
    pub max_angle: f64,
    /// ... and at least this many seconds apart (a revisit, not a neighbour).
    #[arg(long, default_value_t = 20.0)]
    pub min_gap: f64,
    #[arg(long, default_value_t = 0.7)]
    pub min_crop_area: f64,
    #[arg(long, default_value_t = 0.3)]
    pub colour_jitter: f64,
    /// Seeds the order, the augmentation and the weights drawn afresh.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// No progress bar (progress is logged instead).
    #[arg(long)]
    pub quiet: bool,
    /// Compute device; only `cpu` is built in.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

pub fn run(args: Args) -> Result<()> {
    check_device(&args.device)?;
    let params = super::replay::params_from(args.config.as_deref(), &args.params)?;
    let init = resolve::resolve(args.init.as_deref())?;
    let sources: Vec<&std::path::Path> = args.data.iter().map(PathBuf::as_path).collect();
    ecm_lcd::io::output::ensure_not_an_input(&args.out, &[&[init.path.as_path()], &sources[..]].concat())?;
    ecm_lcd::io::output::ensure_not_in_source(&args.out, &sources)?;
    let descriptor = params.descriptor()?;
    let tap = params.tap()?;
    let config = PlaceConfig {
        data: args.data,
        arch: params.arch().parse()?,
        tap: tap.to_string(),
        descriptor: descriptor.name(),
        size: args.size.unwrap_or(params.input_size()),
        opt: Optimisation {
            epochs: args.epochs,
            batch: args.batch,
            optimizer: args.optimizer,
            lr: args.lr,
            momentum: args.momentum,
            weight_decay: args.weight_decay,
            warmup_epochs: args.warmup_epochs,
            augment: Augment { min_crop_area: args.min_crop_area, flip: false, colour_jitter: args.colour_jitter },
            seed: args.seed,
        },
        margin: args.margin,
        max_distance_m: args.max_distance,
        max_angle_deg: args.max_angle,
        min_gap_s: args.min_gap,
        out: args.out,
        progress: !args.quiet,
    };
    let report = train_place(&init.weights, &init.describe(), &descriptor, tap, &config)?;
    println!(
        "{} frames, {} anchors, {} steps in {:.0} s; triplet loss per epoch {:?}, revisit nearer than the hardest negative {:?} -> {}",
        report.frames,
        report.anchors,
        report.steps,
        report.seconds,
        report.epoch_loss.iter().map(|l| format!("{l:.4}")).collect::<Vec<_>>(),
        report.epoch_triplet_accuracy.iter().map(|a| format!("{a:.3}")).collect::<Vec<_>>(),
        config.out.display()
    );
    Ok(())
}
