//! `ecm-lcd train`: the paper's classification recipe on an image folder (see [`ecm_lcd::train`]).

use std::path::PathBuf;

use anyhow::{bail, Result};

use ecm_lcd::model::Arch;
use ecm_lcd::train::data::Augment;
use ecm_lcd::train::{check_device, train, Hyper, Optimisation, OptimizerKind, RunFiles, TrainConfig};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Image folder: one sub-folder per class; optional TrainImages.txt / TestImages.txt split lists.
    #[arg(long)]
    pub data: PathBuf,
    #[arg(long, default_value = "ecmobilenet")]
    pub arch: Arch,
    /// Initial weights (inference form, e.g. the imported MobileNetV2); default: random init.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Number of classes: `auto` (as many as the data has) or a number the data must match.
    #[arg(long, default_value = "auto")]
    pub classes: String,
    /// Best weights go here; `.last.safetensors`, `.train.safetensors` and `.json` beside it.
    #[arg(short, long)]
    pub out: PathBuf,
    /// Continue the run that wrote this checkpoint (any of its files); its settings are reused.
    #[arg(long)]
    pub resume: Option<PathBuf>,
    /// Input size (a multiple of 32).
    #[arg(long, default_value_t = 224)]
    pub size: usize,
    #[arg(long, default_value_t = 30)]
    pub epochs: usize,
    /// Stop after the first epoch whose validation accuracy reaches this fraction (0-1]; the
    /// schedule still spans --epochs, so --resume continues it.
    #[arg(long, value_parser = accuracy_fraction)]
    pub target_accuracy: Option<f64>,
    #[arg(long, default_value_t = 32)]
    pub batch: usize,
    #[arg(long, value_enum, default_value_t = OptimizerKind::Sgd)]
    pub optimizer: OptimizerKind,
    /// Peak learning rate (reached after the warm-up).
    #[arg(long, default_value_t = 0.05)]
    pub lr: f64,
    #[arg(long, default_value_t = 0.9)]
    pub momentum: f64,
    #[arg(long, default_value_t = 4e-5)]
    pub weight_decay: f64,
    #[arg(long, default_value_t = 1.0)]
    pub warmup_epochs: f64,
    #[arg(long, default_value_t = 0.1)]
    pub label_smoothing: f64,
    /// Smallest area fraction of the random resized crop.
    #[arg(long, default_value_t = 0.25)]
    pub min_crop_area: f64,
    /// Colour jitter strength (brightness, contrast, saturation in [1 - j, 1 + j]).
    #[arg(long, default_value_t = 0.3)]
    pub colour_jitter: f64,
    #[arg(long)]
    pub no_flip: bool,
    /// Held-out fraction per class when the folder has no split lists.
    #[arg(long, default_value_t = 0.2)]
    pub val_fraction: f64,
    /// Seeds the split, the order, the augmentation and the weights drawn afresh: the same seed
    /// and data repeat a run exactly.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Keep BatchNorm's loaded statistics while training (the default with --init: pretrained
    /// weights are folded, and batch statistics would renormalise every pretrained layer).
    #[arg(long, conflicts_with = "train_bn")]
    pub freeze_bn: bool,
    /// Normalise by each batch's statistics (the default without --init, training from scratch).
    #[arg(long)]
    pub train_bn: bool,
    /// Learning rate of the body (everything but the classifier) as a multiple of --lr; default
    /// 0.1 with --init (a new head on a pretrained body), 1 from scratch.
    #[arg(long)]
    pub body_lr_scale: Option<f64>,
    /// Compute device; only `cpu` is built in.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

/// A fraction in (0, 1], for `--target-accuracy`.
fn accuracy_fraction(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(value) if value > 0.0 && value <= 1.0 => Ok(value),
        _ => Err(format!("'{text}' is not a fraction in (0, 1]")),
    }
}

pub fn run(args: Args) -> Result<()> {
    check_device(&args.device)?;
    let classes = match args.classes.as_str() {
        "auto" => None,
        n => match n.parse::<usize>() {
            Ok(k) if k >= 2 => Some(k),
            _ => bail!("--classes '{n}' is neither 'auto' nor a number of at least 2"),
        },
    };
    // The run's weights must not replace those it starts from.
    let inputs: Vec<&std::path::Path> = args.init.iter().map(PathBuf::as_path).collect();
    ecm_lcd::io::output::ensure_not_an_input(&args.out, &inputs)?;
    let hyper = Hyper {
        size: args.size,
        opt: Optimisation {
            epochs: args.epochs,
            batch: args.batch,
            optimizer: args.optimizer,
            lr: args.lr,
            momentum: args.momentum,
            weight_decay: args.weight_decay,
            warmup_epochs: args.warmup_epochs,
            augment: Augment {
                min_crop_area: args.min_crop_area,
                flip: !args.no_flip,
                colour_jitter: args.colour_jitter,
            },
            seed: args.seed,
        },
        label_smoothing: args.label_smoothing,
        freeze_batch_norm: args.freeze_bn || (args.init.is_some() && !args.train_bn),
        body_lr_scale: args.body_lr_scale.unwrap_or(if args.init.is_some() { 0.1 } else { 1.0 }),
    };
    let config = TrainConfig {
        data: args.data,
        arch: args.arch,
        init: args.init,
        classes,
        val_fraction: args.val_fraction,
        hyper,
        out: args.out.clone(),
        resume: args.resume,
        progress: true,
        stop_after: None,
        target_accuracy: args.target_accuracy,
    };
    let record = train(&config)?;
    let files = RunFiles::new(&args.out);
    println!(
        "best validation accuracy {:.2}% (epoch {}) -> {}; last -> {}; training form -> {}; record -> {}",
        100.0 * record.best_val_accuracy,
        record.best_epoch,
        files.best.display(),
        files.last.display(),
        files.training.display(),
        files.json.display()
    );
    Ok(())
}
