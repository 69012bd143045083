//! Distillation: ECMobileNet (ECA included) learns to reproduce a teacher's (MobileNetV2's)
//! pooled 1280-d descriptor on unlabelled images, so the loop-closure descriptor survives the
//! removed bottlenecks.
//!
//! The student starts as `Weights::for_arch(EcMobileNet)` of the teacher (kept blocks copied,
//! every ECA gate a constant 0.5 compensated in the projection). Its BatchNorm layers run in
//! inference form with frozen statistics (the running mean 0 and variance 1 - eps of
//! [`super::training_form`], so the student starts exactly at the converted network); gamma,
//! beta, convolution and ECA weights are trained. Freezing the statistics is our choice: training-
//! mode batch statistics would replace the teacher's calibrated normalisation by a different
//! function at step 0, and fine-tuning with small batches is customarily done with frozen BN.
//!
//! Loss on L2-normalised pooled descriptors `s`, `t`: `mse` is the mean over the batch of
//! `|s - t|²`, `cosine` the mean of `1 - s·t`; for unit vectors `|s - t|² = 2 (1 - s·t)`, so the two
//! differ by a factor of 2 (which matters for SGD's step size, not for AdamW's). The reported error
//! is the mean `|s - t|²` on held-out images (no augmentation).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{ensure, Context, Result};
use candle_core::Tensor;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use serde::{Deserialize, Serialize};

use super::data::{load_unlabelled, Augment, ImageSet, Loader, MemorySet};
use super::{learning_rate, progress_bar, trainable_params, training_form, write_json, Optimisation, Trainable};
use crate::model::layers::Mode;
use crate::model::weights::Weights;
use crate::model::{check_input_size, Arch, Network};

/// The distillation loss.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum DistillLoss {
    Mse,
    Cosine,
}

/// A distillation run.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DistillConfig {
    pub data: PathBuf,
    pub size: usize,
    #[serde(flatten)]
    pub opt: Optimisation,
    pub loss: DistillLoss,
    pub val_fraction: f64,
    pub max_images: usize,
    pub out: PathBuf,
    #[serde(skip)]
    pub progress: bool,
}

/// What a distillation did.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DistillReport {
    pub command: String,
    pub teacher: String,
    pub config: DistillConfig,
    pub train_images: usize,
    pub heldout_images: usize,
    pub steps: usize,
    /// Mean held-out `|s - t|²` of the L2-normalised descriptors before and after.
    pub heldout_error_before: f64,
    pub heldout_error_after: f64,
    pub epoch_train_loss: Vec<f64>,
    pub seconds: f64,
}

/// L2-normalised pooled descriptors `[B, C]` of `network` for `x`.
fn descriptors(network: &Network, x: &Tensor, mode: Mode) -> Result<Tensor> {
    let pooled = network.features(x, mode)?.mean((2, 3))?;
    let norm = pooled.sqr()?.sum_keepdim(1)?.sqrt()?.clamp(1e-12, f64::MAX)?;
    Ok(pooled.broadcast_div(&norm)?)
}

/// The teacher's descriptors of `x` (images at `size` pixels), refused where one is zero: at small
/// sizes the teacher's pooled features can vanish altogether, and a student taught zeros learns
/// nothing of places while its error reads 0.
fn teacher_descriptors(teacher: &Network, x: &Tensor, size: usize) -> Result<Tensor> {
    let t = descriptors(teacher, x, Mode::Inference)?;
    let zero = t.sqr()?.sum(1)?.to_vec1::<f32>()?.iter().filter(|norm| **norm < 0.5).count();
    ensure!(
        zero == 0,
        "the teacher's descriptor is zero for {zero} of {} images at --size {size}: its features vanish at this \
         input size (try --size 64 or more)",
        x.dim(0)?
    );
    Ok(t)
}

fn loss_of(student: &Tensor, teacher: &Tensor, loss: DistillLoss) -> Result<Tensor> {
    Ok(match loss {
        DistillLoss::Mse => (student - teacher)?.sqr()?.sum(1)?.mean_all()?,
        DistillLoss::Cosine => (student * teacher)?.sum(1)?.affine(-1.0, 1.0)?.mean_all()?,
    })
}

/// Mean `|s - t|²` over `set` (no augmentation), `student` in inference form.
pub fn descriptor_error(
    student: &Network,
    teacher: &Network,
    set: Arc<dyn ImageSet>,
    size: usize,
    batch: usize,
) -> Result<f64> {
    let (mut sum, mut n) = (0.0, 0usize);
    let loader = Loader::spawn(set, batch, size, Augment::NONE, false, 0);
    for b in loader.batches.iter() {
        let b = b?;
        let x = b.tensor(size)?;
        let e =
            (descriptors(student, &x, Mode::Inference)? - teacher_descriptors(teacher, &x, size)?)?.sqr()?.sum(1)?;
        sum += e.sum_all()?.to_scalar::<f32>()? as f64;
        n += b.len();
    }
    ensure!(n > 0, "no held-out images");
    Ok(sum / n as f64)
}

/// Distils `teacher` into ECMobileNet; writes the student (inference form) to `config.out` and
/// the report as JSON beside it.
pub fn distill(teacher: &Weights, teacher_name: &str, config: &DistillConfig) -> Result<DistillReport> {
    let started = Instant::now();
    let report_path = super::report_beside(&config.out)?;
    check_input_size(config.size)?;
    ensure!(config.opt.batch >= 2, "batch size {} is below 2", config.opt.batch);
    config.opt.check()?;
    ensure!(
        (0.0..1.0).contains(&config.val_fraction) && config.val_fraction > 0.0,
        "--val-fraction {} is not in (0, 1)",
        config.val_fraction
    );
    let teacher_net = teacher.network(false)?;
    let student_init = teacher.for_arch(Arch::EcMobileNet)?;
    let mut init = training_form(&student_init.tensors)?;
    init.retain(|n, _| !n.starts_with("classifier."));
    let student = Trainable::new(Arch::EcMobileNet, None, &init, config.opt.seed)?;

    let mut images = load_unlabelled(&config.data, (config.size as u32 * 5).div_ceil(4), config.max_images)?;
    images.shuffle(&mut StdRng::seed_from_u64(config.opt.seed));
    let heldout = ((images.len() as f64 * config.val_fraction).round() as usize).clamp(1, images.len() - 2);
    let train_images = images.split_off(heldout);
    let (train_set, heldout_set): (Arc<dyn ImageSet>, Arc<dyn ImageSet>) =
        (Arc::new(MemorySet(train_images)), Arc::new(MemorySet(images)));

    let before = descriptor_error(
        &student_init.network(false)?,
        &teacher_net,
        heldout_set.clone(),
        config.size,
        config.opt.batch,
    )?;
    let mut optimizer = config.opt.optimizer(trainable_params(&student.varmap))?;
    let steps_per_epoch = config.opt.steps_per_epoch(train_set.len());
    let total = steps_per_epoch * config.opt.epochs;
    let warmup = config.opt.warmup_steps(steps_per_epoch);
    let mut step = 0;
    let mut epoch_train_loss = Vec::new();
    for epoch in 0..config.opt.epochs {
        let bar = progress_bar(
            config.progress,
            steps_per_epoch as u64,
            &format!("epoch {}/{}", epoch + 1, config.opt.epochs),
        );
        let loader = config.opt.epoch_loader(train_set.clone(), config.size, epoch);
        let (mut sum, mut seen) = (0.0, 0usize);
        let epoch_start = Instant::now();
        for b in loader.batches.iter() {
            let b = b?;
            let x = b.tensor(config.size)?;
            let target = teacher_descriptors(&teacher_net, &x, config.size)?.detach();
            let s = descriptors(&student.network, &x, Mode::FineTune)?;
            let loss = loss_of(&s, &target, config.loss)?;
            let lr = learning_rate(step, total, warmup, config.opt.lr);
            optimizer.step(&loss.backward()?, lr)?;
            step += 1;
            let l = loss.to_scalar::<f32>()? as f64;
            ensure!(l.is_finite(), "the distillation loss diverged at step {step}");
            sum += l * b.len() as f64;
            seen += b.len();
            bar.set_message(format!(
                "loss {:.4} {:.1} img/s lr {lr:.2e}",
                sum / seen as f64,
                seen as f64 / epoch_start.elapsed().as_secs_f64()
            ));
            bar.inc(1);
        }
        bar.finish();
        epoch_train_loss.push(sum / seen.max(1) as f64);
    }
    let weights =
        student.inference_weights(&format!("ecm-lcd distill of {teacher_name} on {}", config.data.display()))?;
    let after =
        descriptor_error(&weights.network(false)?, &teacher_net, heldout_set.clone(), config.size, config.opt.batch)?;
    weights.check_finite().context("training diverged; nothing is saved (try a lower --lr)")?;
    weights.save(&config.out)?;
    let report = DistillReport {
        command: "distill".into(),
        teacher: teacher_name.to_string(),
        config: config.clone(),
        train_images: train_set.len(),
        heldout_images: heldout_set.len(),
        steps: step,
        heldout_error_before: before,
        heldout_error_after: after,
        epoch_train_loss,
        seconds: started.elapsed().as_secs_f64(),
    };
    write_json(&report_path, &report)?;
    Ok(report)
}
