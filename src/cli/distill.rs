//! `ecm-lcd distill`: ECMobileNet learns a teacher's descriptor (see [`ecm_lcd::train::distill`]).

use std::path::PathBuf;

use anyhow::Result;

use ecm_lcd::model::weights::resolve;
use ecm_lcd::train::data::Augment;
use ecm_lcd::train::distill::{distill, DistillConfig, DistillLoss};
use ecm_lcd::train::{check_device, Optimisation, OptimizerKind};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Teacher weights (safetensors or .tflite), or `default` for the project's MobileNetV2.
    #[arg(long, default_value = "default")]
    pub teacher: String,
    /// Unlabelled images: an image folder, a folder of such folders or replay sources (TUM folders,
    /// ROS 2 bag folders), or any replay source.
    #[arg(long)]
    pub data: PathBuf,
    /// Student weights (inference form); the report goes beside it as `.json`.
    #[arg(short, long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 224)]
    pub size: usize,
    #[arg(long, default_value_t = 10)]
    pub epochs: usize,
    #[arg(long, default_value_t = 32)]
    pub batch: usize,
    #[arg(long, value_enum, default_value_t = OptimizerKind::Adamw)]
    pub optimizer: OptimizerKind,
    #[arg(long, default_value_t = 1e-4)]
    pub lr: f64,
    #[arg(long, default_value_t = 0.9)]
    pub momentum: f64,
    #[arg(long, default_value_t = 0.0)]
    pub weight_decay: f64,
    #[arg(long, default_value_t = 0.5)]
    pub warmup_epochs: f64,
    #[arg(long, value_enum, default_value_t = DistillLoss::Mse)]
    pub loss: DistillLoss,
    #[arg(long, default_value_t = 0.5)]
    pub min_crop_area: f64,
    #[arg(long, default_value_t = 0.2)]
    pub colour_jitter: f64,
    /// Held-out fraction of the images, on which the error is reported.
    #[arg(long, default_value_t = 0.1)]
    pub val_fraction: f64,
    /// Use at most this many images, evenly spread over the source.
    #[arg(long, default_value_t = 20000)]
    pub max_images: usize,
    /// Seeds the split, the order and the augmentation.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Compute device; only `cpu` is built in.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

pub fn run(args: Args) -> Result<()> {
    check_device(&args.device)?;
    let teacher = if args.teacher == "default" {
        resolve::resolve(None)?
    } else {
        resolve::load_file(std::path::Path::new(&args.teacher))?
    };
    ecm_lcd::io::output::ensure_not_an_input(&args.out, &[&teacher.path])?;
    // The student learns MobileNetV2's descriptor; another network's (a student of an earlier run,
    // through --teacher or $ECM_LCD_WEIGHTS) would teach it something else under that name.
    anyhow::ensure!(
        teacher.weights.arch == ecm_lcd::model::Arch::MobileNetV2,
        "the teacher {} is {}, not MobileNetV2: distillation teaches MobileNetV2's descriptor",
        teacher.path.display(),
        teacher.weights.arch
    );
    let config = DistillConfig {
        data: args.data,
        size: args.size,
        opt: Optimisation {
            epochs: args.epochs,
            batch: args.batch,
            optimizer: args.optimizer,
            lr: args.lr,
            momentum: args.momentum,
            weight_decay: args.weight_decay,
            warmup_epochs: args.warmup_epochs,
            augment: Augment { min_crop_area: args.min_crop_area, flip: true, colour_jitter: args.colour_jitter },
            seed: args.seed,
        },
        loss: args.loss,
        val_fraction: args.val_fraction,
        max_images: args.max_images,
        out: args.out,
        progress: true,
    };
    let report = distill(&teacher.weights, &teacher.describe(), &config)?;
    println!(
        "held-out descriptor error |s - t|^2: {:.5} -> {:.5} ({} steps, {:.0} s) -> {}",
        report.heldout_error_before,
        report.heldout_error_after,
        report.steps,
        report.seconds,
        config.out.display()
    );
    Ok(())
}
