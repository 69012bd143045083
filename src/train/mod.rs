//! Training: the paper's recipe (classification on an image folder such as indoorCVPR) for
//! ECMobileNet or MobileNetV2, and distillation of a MobileNetV2 teacher's descriptor into
//! ECMobileNet ([`distill`]).
//!
//! - The network is built in its training form (`Network::load(.., batch_norm = true)`) from a
//!   `VarMap`. [`Mode::Train`] runs differentiable ops: stock candle ops, plus two custom ops with
//!   hand-written backward passes, the depthwise convolution ([`crate::model::kernels::depthwise_grad`])
//!   and training-mode BatchNorm ([`crate::model::kernels::batch_norm_train`]), both tested against
//!   finite differences and candle's stock ops. Distillation uses [`Mode::FineTune`] (BatchNorm
//!   frozen). The inference kernels have no backward.
//! - `--init` loads folded (inference-form) weights into the training form: convolution weight as
//!   is, BatchNorm gamma = 1, beta = the folded bias, running mean 0, running variance 1 - eps, so
//!   the initial network computes exactly the folded one ([`training_form`]) in inference and in
//!   [`Mode::FineTune`].
//! - Fine-tuning from such weights freezes the BatchNorm statistics ([`Hyper::freeze_batch_norm`],
//!   the CLI's default with `--init`). Folded weights carry no statistics: in [`Mode::Train`] every
//!   layer would be renormalised by its batch's mean and variance, which are nowhere near the 0 and 1
//!   the folding assumes, so the network at step 0 is no longer the pretrained one and the features
//!   the weights know are gone before the first update (on two real indoor scenes the loss stayed at
//!   ln 2 and the model predicted one class). Frozen, the network starts as the pretrained function
//!   and gamma and beta still train as a per-channel affine map. Training from scratch keeps
//!   training-mode BatchNorm.
//! - Optimizers: SGD with (PyTorch-style) momentum and AdamW, written here (in-place updates,
//!   [`update`]) rather than with candle's `Optimizer` trait because candle's SGD has no momentum
//!   and candle's AdamW keeps its moments private; owning the state lets `--resume` restore it exactly. Weight decay applies to
//!   convolution, ECA and classifier weights, not to BatchNorm parameters or biases.
//! - Learning rate: linear warm-up from 0, then a cosine decay to 0 over the remaining steps.
//! - Loss: cross-entropy with label smoothing.
//! - BatchNorm statistics: candle's running averages move slowly (momentum 0.01), far too slowly
//!   for short runs, so before each validation and save the running statistics are recomputed
//!   exactly over up to [`PRECISE_BN_IMAGES`] training images ("precise BN", Wu & Johnson 2021):
//!   with the running values set to 0, one training-mode forward leaves `momentum x` the batch
//!   statistic in them, which is read back and averaged over batches.
//!
//! Outputs for `-o run.safetensors`: `run.safetensors` (best validation accuracy, inference form
//! via [`inference_tensors`], usable as `--weights` anywhere), `run.last.safetensors` (last epoch,
//! inference form), `run.train.safetensors` (training form: every `VarMap` tensor plus the
//! optimizer state under `optimizer.`, for `--resume`), and `run.json` (settings, per-epoch
//! results, where the schedule stands).

pub mod data;
pub mod distill;
pub mod place;
mod update;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var, D};
use candle_nn::{VarBuilder, VarMap};
use serde::{Deserialize, Serialize};

use crate::model::layers::{Mode, BN_EPS, BN_MOMENTUM};
use crate::model::weights::fetch::sha256_hex;
use crate::model::weights::{inference_tensors, Weights};
use crate::model::{check_input_size, Arch, Network};
use data::{Augment, FileSet, ImageFolder, ImageSet, Loader};

/// Images used to recompute BatchNorm statistics before each validation and save. 256 images
/// give each channel's mean and variance from 256 x (map size) values; at 512 the recomputation
/// took a quarter of each epoch of the 64 px texture test (640 training images).
pub const PRECISE_BN_IMAGES: usize = 256;

/// Which optimizer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum OptimizerKind {
    Sgd,
    Adamw,
}

/// The optimisation settings classification training and distillation share.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Optimisation {
    pub epochs: usize,
    pub batch: usize,
    pub optimizer: OptimizerKind,
    /// Peak learning rate (reached after the warm-up).
    pub lr: f64,
    /// SGD momentum (unused by AdamW).
    pub momentum: f64,
    pub weight_decay: f64,
    pub warmup_epochs: f64,
    pub augment: Augment,
    pub seed: u64,
}

impl Optimisation {
    /// Refuses values no schedule can use (they used to train to a loss of 0, or crash the loader
    /// into an epoch of no steps that was reported as done).
    pub fn check(&self) -> Result<()> {
        ensure!(self.epochs >= 1, "--epochs must be at least 1");
        ensure!(self.lr.is_finite() && self.lr > 0.0, "--lr must be positive and finite, got {}", self.lr);
        ensure!((0.0..1.0).contains(&self.momentum), "--momentum must be in [0, 1), got {}", self.momentum);
        ensure!(
            self.weight_decay.is_finite() && self.weight_decay >= 0.0,
            "--weight-decay must be finite and not negative, got {}",
            self.weight_decay
        );
        ensure!(
            self.warmup_epochs.is_finite() && self.warmup_epochs >= 0.0,
            "--warmup-epochs must be finite and not negative, got {}",
            self.warmup_epochs
        );
        let augment = &self.augment;
        ensure!(
            augment.min_crop_area > 0.0 && augment.min_crop_area <= 1.0,
            "--min-crop-area must be in (0, 1], got {}",
            augment.min_crop_area
        );
        ensure!(
            (0.0..=1.0).contains(&augment.colour_jitter),
            "--colour-jitter must be in [0, 1], got {}",
            augment.colour_jitter
        );
        Ok(())
    }

    /// Steps in an epoch of `images` (a last batch of one image is dropped: BatchNorm needs two).
    pub fn steps_per_epoch(&self, images: usize) -> usize {
        images / self.batch + usize::from(images % self.batch >= 2)
    }

    /// Warm-up steps for `steps_per_epoch`.
    pub fn warmup_steps(&self, steps_per_epoch: usize) -> usize {
        (self.warmup_epochs * steps_per_epoch as f64).round() as usize
    }

    /// The optimizer over `params` with these settings.
    pub fn optimizer(&self, params: Vec<Param>) -> Result<Optimizer> {
        Optimizer::new(self.optimizer, params, self.momentum, self.weight_decay)
    }

    /// A loader over one epoch of `set` (shuffled with a seed of this epoch, augmented).
    pub fn epoch_loader(&self, set: Arc<dyn ImageSet>, size: usize, epoch: usize) -> Loader {
        Loader::spawn(set, self.batch, size, self.augment, true, self.seed.wrapping_add(1 + epoch as u64))
    }
}

/// Everything a classification run needs besides the data (serialised flat, as before the
/// shared [`Optimisation`] existed, so older run records still resume).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hyper {
    pub size: usize,
    #[serde(flatten)]
    pub opt: Optimisation,
    pub label_smoothing: f64,
    /// BatchNorm keeps the statistics it was loaded with ([`Mode::FineTune`]) instead of
    /// normalising by each batch's: what fine-tuning from pretrained weights needs (module doc).
    #[serde(default)]
    pub freeze_batch_norm: bool,
    /// The learning rate of everything but the classifier, as a multiple of the classifier's
    /// (below 1 when fine-tuning: a new head learns fast, a pretrained body must move slowly).
    #[serde(default = "full_rate")]
    pub body_lr_scale: f64,
}

fn full_rate() -> f64 {
    1.0
}

/// Learning rate at `step` (from 0) of `total` steps: linear warm-up over `warmup` steps to
/// `base`, then cosine decay to 0 at `total`.
pub fn learning_rate(step: usize, total: usize, warmup: usize, base: f64) -> f64 {
    if step < warmup {
        return base * (step + 1) as f64 / warmup as f64;
    }
    let span = total.saturating_sub(warmup).max(1) as f64;
    let progress = ((step - warmup) as f64 / span).min(1.0);
    0.5 * base * (1.0 + (std::f64::consts::PI * progress).cos())
}

/// Cross-entropy of `logits` `[B, K]` against `labels` `[B]` (u32) with label smoothing `eps`:
/// the target is `1 - eps` on the label plus `eps / K` everywhere.
pub fn smoothed_cross_entropy(logits: &Tensor, labels: &Tensor, eps: f64) -> Result<Tensor> {
    let log_p = candle_nn::ops::log_softmax(logits, D::Minus1)?;
    let nll = log_p.gather(&labels.unsqueeze(1)?, 1)?.squeeze(1)?.neg()?;
    let uniform = log_p.mean(D::Minus1)?.neg()?;
    Ok(((nll * (1.0 - eps))? + (uniform * eps)?)?.mean_all()?)
}

/// A trainable tensor with its name.
pub struct Param {
    pub name: String,
    pub var: Var,
    pub decay: bool,
    /// This parameter's learning rate as a multiple of the schedule's.
    pub lr_scale: f64,
}

/// The trainable variables of a training-form `VarMap` (running statistics excluded), sorted by name.
pub fn trainable_params(varmap: &VarMap) -> Vec<Param> {
    let data = varmap.data().lock().expect("VarMap lock");
    let mut params: Vec<Param> = data
        .iter()
        .filter(|(n, _)| !n.ends_with("running_mean") && !n.ends_with("running_var"))
        .map(|(n, v)| Param {
            name: n.clone(),
            var: v.clone(),
            decay: n.ends_with(".weight") && !n.ends_with("bn.weight"),
            lr_scale: 1.0,
        })
        .collect();
    params.sort_by(|a, b| a.name.cmp(&b.name));
    params
}

/// SGD with momentum or AdamW, with its state in tensors it can save and restore.
pub struct Optimizer {
    pub kind: OptimizerKind,
    params: Vec<Param>,
    /// Per parameter: SGD momentum buffer / AdamW first moment, and AdamW second moment.
    state: Vec<(Tensor, Tensor)>,
    pub steps: usize,
    momentum: f64,
    weight_decay: f64,
}

const ADAM_BETAS: (f64, f64) = (0.9, 0.999);
const ADAM_EPS: f64 = 1e-8;

impl Optimizer {
    pub fn new(kind: OptimizerKind, params: Vec<Param>, momentum: f64, weight_decay: f64) -> Result<Self> {
        let state =
            params.iter().map(|p| Ok((p.var.zeros_like()?, p.var.zeros_like()?))).collect::<Result<Vec<_>>>()?;
        Ok(Optimizer { kind, params, state, steps: 0, momentum, weight_decay })
    }

    /// One update with learning rate `lr`; parameters without a gradient are left alone.
    /// Parameters and state are updated in place ([`update`]).
    pub fn step(&mut self, grads: &GradStore, lr: f64) -> Result<()> {
        self.steps += 1;
        let t = self.steps as i32;
        for (p, (m, v)) in self.params.iter().zip(self.state.iter_mut()) {
            let Some(g) = grads.get(p.var.as_tensor()) else { continue };
            let g = g.contiguous()?;
            let w = p.var.as_tensor();
            let wd = if p.decay { self.weight_decay } else { 0.0 };
            let lr = lr * p.lr_scale;
            match self.kind {
                OptimizerKind::Sgd => {
                    m.inplace_op3(
                        &g,
                        w,
                        &update::SgdMomentum { momentum: self.momentum as f32, weight_decay: wd as f32 },
                    )?;
                    w.inplace_op2(m, &update::SgdStep { lr: lr as f32 })?;
                }
                OptimizerKind::Adamw => {
                    let (b1, b2) = ADAM_BETAS;
                    m.inplace_op2(&g, &update::Moment { decay: b1 as f32, squared: false })?;
                    v.inplace_op2(&g, &update::Moment { decay: b2 as f32, squared: true })?;
                    let step = update::AdamWStep {
                        lr: lr as f32,
                        weight_decay: wd as f32,
                        correction1: (1.0 - b1.powi(t)) as f32,
                        correction2: (1.0 - b2.powi(t)) as f32,
                        eps: ADAM_EPS as f32,
                    };
                    w.inplace_op3(m, v, &step)?;
                }
            }
        }
        Ok(())
    }

    /// The state as named tensors (`optimizer.<param>.m` / `.v`).
    pub fn state_tensors(&self) -> Result<HashMap<String, Tensor>> {
        let mut out = HashMap::new();
        for (p, (m, v)) in self.params.iter().zip(&self.state) {
            // Copies: the state is updated in place.
            out.insert(format!("optimizer.{}.m", p.name), m.copy()?);
            if self.kind == OptimizerKind::Adamw {
                out.insert(format!("optimizer.{}.v", p.name), v.copy()?);
            }
        }
        Ok(out)
    }

    /// Restores the state saved by [`Optimizer::state_tensors`].
    pub fn restore(&mut self, tensors: &HashMap<String, Tensor>, steps: usize) -> Result<()> {
        for (p, (m, v)) in self.params.iter().zip(self.state.iter_mut()) {
            let get = |suffix: &str| {
                tensors
                    .get(&format!("optimizer.{}.{suffix}", p.name))
                    .with_context(|| format!("the checkpoint has no optimizer state for {}", p.name))
            };
            *m = update::owned(get("m")?)?;
            if self.kind == OptimizerKind::Adamw {
                *v = update::owned(get("v")?)?;
            }
        }
        self.steps = steps;
        Ok(())
    }
}

/// Folded (inference-form) tensors turned into the training form: every unit `X` with `X.bias`
/// gets `X.bn.weight = 1`, `X.bn.bias = bias`, `X.bn.running_mean = 0`,
/// `X.bn.running_var = 1 - eps`, so BatchNorm in inference computes the folded unit exactly.
/// The classifier keeps its bias; ECA kernels pass through; training-form tensors pass through.
pub fn training_form(tensors: &HashMap<String, Tensor>) -> Result<HashMap<String, Tensor>> {
    let mut out = HashMap::new();
    for (name, t) in tensors {
        match name.strip_suffix(".bias") {
            Some(unit) if unit != "classifier" && !unit.ends_with(".bn") => {
                out.insert(format!("{unit}.bn.bias"), t.clone());
                out.insert(format!("{unit}.bn.weight"), t.ones_like()?);
                out.insert(format!("{unit}.bn.running_mean"), t.zeros_like()?);
                out.insert(format!("{unit}.bn.running_var"), (t.ones_like()? * (1.0 - BN_EPS))?);
            }
            _ => {
                out.insert(name.clone(), t.clone());
            }
        }
    }
    Ok(out)
}

/// A training-form network and the `VarMap` holding its variables.
pub struct Trainable {
    pub varmap: VarMap,
    pub network: Network,
}

/// The variables of a network being built: those already in `varmap` as they are, the others
/// drawn from `rng` with the distribution the layer asks for (candle's `VarMap` draws them from an
/// unseeded generator, so a run from scratch could not be repeated).
struct SeededVariables {
    varmap: VarMap,
    rng: std::sync::Mutex<rand::rngs::StdRng>,
}

impl candle_nn::var_builder::SimpleBackend for SeededVariables {
    fn get(
        &self,
        shape: candle_core::Shape,
        name: &str,
        init: candle_nn::Init,
        dtype: DType,
        device: &Device,
    ) -> candle_core::Result<Tensor> {
        use candle_nn::init::{Init, NormalOrUniform};
        use rand_distr::{Distribution, Normal, Uniform};
        let mut data = self.varmap.data().lock().expect("VarMap lock");
        if let Some(var) = data.get(name) {
            if var.shape() != &shape {
                candle_core::bail!("{name} has the shape {:?}, not {shape:?}", var.shape());
            }
            return Ok(var.as_tensor().clone());
        }
        let count = shape.elem_count();
        let mut rng = self.rng.lock().expect("generator lock");
        let uniform = |lo: f64, up: f64, rng: &mut rand::rngs::StdRng| -> candle_core::Result<Vec<f32>> {
            let uniform = Uniform::new(lo, up).map_err(candle_core::Error::wrap)?;
            Ok((0..count).map(|_| uniform.sample(rng) as f32).collect())
        };
        let normal = |mean: f64, stdev: f64, rng: &mut rand::rngs::StdRng| -> candle_core::Result<Vec<f32>> {
            let normal = Normal::new(mean, stdev).map_err(candle_core::Error::wrap)?;
            Ok((0..count).map(|_| normal.sample(rng) as f32).collect())
        };
        let values = match init {
            Init::Const(value) => vec![value as f32; count],
            Init::Uniform { lo, up } => uniform(lo, up, &mut rng)?,
            Init::Randn { mean, stdev } => normal(mean, stdev, &mut rng)?,
            Init::Kaiming { dist, fan, non_linearity } => {
                let stdev = non_linearity.gain() / (fan.for_shape(&shape) as f64).sqrt();
                match dist {
                    NormalOrUniform::Uniform => uniform(-(3f64.sqrt()) * stdev, 3f64.sqrt() * stdev, &mut rng)?,
                    NormalOrUniform::Normal => normal(0.0, stdev, &mut rng)?,
                }
            }
        };
        let var = Var::from_tensor(&Tensor::from_vec(values, shape, device)?.to_dtype(dtype)?)?;
        data.insert(name.to_string(), var.clone());
        Ok(var.as_tensor().clone())
    }

    fn get_unchecked(&self, name: &str, _dtype: DType, _device: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("{name}: a variable needs its shape")
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.varmap.data().lock().expect("VarMap lock").contains_key(name)
    }
}

impl Trainable {
    /// `arch` with `classes` outputs (or none), its variables taken from `init` where present
    /// (in training form: see [`training_form`]) and drawn afresh otherwise, from a generator
    /// seeded with `seed`: the same seed gives the same network.
    pub fn new(arch: Arch, classes: Option<usize>, init: &HashMap<String, Tensor>, seed: u64) -> Result<Self> {
        use rand::SeedableRng;
        let varmap = VarMap::new();
        {
            let mut data = varmap.data().lock().expect("VarMap lock");
            for (name, t) in init {
                data.insert(name.clone(), Var::from_tensor(&t.to_dtype(DType::F32)?.contiguous()?)?);
            }
        }
        let variables = SeededVariables {
            varmap: varmap.clone(),
            rng: std::sync::Mutex::new(rand::rngs::StdRng::seed_from_u64(seed)),
        };
        let vb = VarBuilder::from_backend(Box::new(variables), DType::F32, Device::Cpu);
        let network = Network::load(arch.spec(), vb, classes, true)
            .with_context(|| format!("the initial weights do not fit {arch}"))?;
        Ok(Trainable { varmap, network })
    }

    /// Every variable as a named tensor (training form).
    pub fn tensors(&self) -> HashMap<String, Tensor> {
        let data = self.varmap.data().lock().expect("VarMap lock");
        data.iter().map(|(n, v)| (n.clone(), v.as_tensor().detach())).collect()
    }

    /// The inference-form weights (BatchNorm folded with the current running statistics).
    pub fn inference_weights(&self, source: &str) -> Result<Weights> {
        Ok(Weights {
            arch: self.network.arch(),
            classes: self.network.classes(),
            source: source.to_string(),
            tensors: inference_tensors(&self.network)?,
        })
    }

    /// Recomputes every BatchNorm's running mean and variance as the average of the batch
    /// statistics over `batches` (see the module doc).
    pub fn precise_batch_norm(&self, batches: &[Tensor]) -> Result<()> {
        if batches.is_empty() {
            return Ok(());
        }
        let stats: Vec<(String, Var)> = {
            let data = self.varmap.data().lock().expect("VarMap lock");
            data.iter()
                .filter(|(n, _)| n.ends_with("running_mean") || n.ends_with("running_var"))
                .map(|(n, v)| (n.clone(), v.clone()))
                .collect()
        };
        let mut sums: Vec<Tensor> = stats.iter().map(|(_, v)| v.zeros_like()).collect::<candle_core::Result<_>>()?;
        for x in batches {
            for (_, v) in &stats {
                v.set(&v.zeros_like()?)?;
            }
            self.network.features(x, Mode::Train)?;
            for (sum, (_, v)) in sums.iter_mut().zip(&stats) {
                *sum = (&*sum + (v.as_tensor().detach() / BN_MOMENTUM)?)?;
            }
        }
        for (sum, (_, v)) in sums.into_iter().zip(&stats) {
            v.set(&(sum / batches.len() as f64)?)?;
        }
        Ok(())
    }
}

/// Top-1 accuracy of an inference-form network over a labelled set at `size`.
pub fn accuracy(network: &Network, set: Arc<dyn ImageSet>, size: usize, batch: usize) -> Result<f64> {
    let total = set.len();
    ensure!(total > 0, "no validation images");
    let mut correct = 0usize;
    let loader = Loader::spawn(set, batch, size, Augment::NONE, false, 0);
    for b in loader.batches.iter() {
        let b = b?;
        let predicted = network.logits(&b.tensor(size)?, Mode::Inference)?.argmax(D::Minus1)?.to_vec1::<u32>()?;
        correct += predicted.iter().zip(&b.labels).filter(|(p, l)| p == l).count();
    }
    Ok(correct as f64 / total as f64)
}

/// Up to `max_images` of `set` without augmentation, as batches (for [`Trainable::precise_batch_norm`]).
pub fn calibration_batches(
    set: Arc<dyn ImageSet>,
    size: usize,
    batch: usize,
    max_images: usize,
    seed: u64,
) -> Result<Vec<Tensor>> {
    let loader = Loader::spawn(set, batch, size, Augment::NONE, true, seed);
    let mut out = Vec::new();
    let mut seen = 0;
    for b in loader.batches.iter() {
        let b = b?;
        seen += b.len();
        out.push(b.tensor(size)?);
        if seen >= max_images {
            break;
        }
    }
    Ok(out)
}

/// One epoch's results.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EpochResult {
    pub epoch: usize,
    pub train_loss: f64,
    pub train_accuracy: f64,
    pub val_accuracy: f64,
    pub learning_rate: f64,
    pub images_per_second: f64,
    pub seconds: f64,
}

/// The run's JSON: settings, results, and where the schedule stands (for `--resume`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunRecord {
    pub command: String,
    pub data: PathBuf,
    pub arch: Arch,
    pub classes: Vec<String>,
    pub split: String,
    pub train_images: usize,
    pub val_images: usize,
    pub init: Option<String>,
    pub hyper: Hyper,
    pub steps_per_epoch: usize,
    pub epochs_done: usize,
    pub steps_done: usize,
    pub best_val_accuracy: f64,
    pub best_epoch: usize,
    pub history: Vec<EpochResult>,
    /// SHA-256 of the training form saved with `epochs_done` (records from before it have none): a
    /// resume checks that the training form is the record's, not one of an epoch whose record a
    /// kill kept from being written.
    #[serde(default)]
    pub training_sha256: Option<String>,
}

/// The files of a run whose best weights go to `out`.
#[derive(Clone, Debug)]
pub struct RunFiles {
    pub best: PathBuf,
    pub last: PathBuf,
    pub training: PathBuf,
    pub json: PathBuf,
}

impl RunFiles {
    pub fn new(out: &Path) -> Self {
        let stem = weights_stem(out);
        let with = |suffix: &str| {
            let mut path = stem.as_os_str().to_owned();
            path.push(suffix);
            PathBuf::from(path)
        };
        RunFiles {
            best: out.to_path_buf(),
            last: with(".last.safetensors"),
            training: with(".train.safetensors"),
            json: with(".json"),
        }
    }

    /// Makes the run's folder and refuses files that could not all be written, before any
    /// training ([`crate::io::output::ensure_writable_outputs`]): an `-o` that is a folder, or a
    /// run file that is one.
    pub fn check(&self) -> Result<()> {
        crate::io::output::ensure_writable_outputs(&[
            ("-o", &self.best),
            ("the last epoch's weights", &self.last),
            ("the training form", &self.training),
            ("the run record", &self.json),
        ])
    }

    /// The training form written before its record names it ([`RunRecord::training_sha256`]).
    pub fn training_next(&self) -> PathBuf {
        let mut path = self.training.as_os_str().to_owned();
        path.push(".next");
        PathBuf::from(path)
    }

    /// The training form that belongs to `record`: the one in place, or the one written just before
    /// the record where a kill came before it was renamed into place. A form of another epoch (a
    /// kill after the form, before its record) is refused: resuming from it would train an epoch
    /// twice under a schedule that does not know it.
    pub fn training_of(&self, record: &RunRecord) -> Result<PathBuf> {
        let Some(wanted) = &record.training_sha256 else { return Ok(self.training.clone()) };
        let hash = |path: &Path| std::fs::read(path).ok().map(|bytes| sha256_hex(&bytes));
        if hash(&self.training).as_ref() == Some(wanted) {
            return Ok(self.training.clone());
        }
        if hash(&self.training_next()).as_ref() == Some(wanted) {
            std::fs::rename(self.training_next(), &self.training)
                .with_context(|| format!("renaming {} into place", self.training_next().display()))?;
            return Ok(self.training.clone());
        }
        bail!(
            "{} is not the training form its run record {} names (epoch {}): the run was stopped while saving \
             an epoch; it cannot be resumed exactly (train anew, or from {} with --init)",
            self.training.display(),
            self.json.display(),
            record.epochs_done,
            self.last.display()
        )
    }

    /// The files of the run that wrote `checkpoint` (any of its files, or `-o` of that run).
    pub fn of_checkpoint(checkpoint: &Path) -> Self {
        let s = checkpoint.display().to_string();
        let base = [".train.safetensors", ".last.safetensors", ".safetensors", ".json"]
            .iter()
            .find_map(|suffix| s.strip_suffix(suffix))
            .unwrap_or(&s)
            .to_string();
        // The run's -o: `base.safetensors`, or `base` itself for an -o without that extension.
        let with_extension = PathBuf::from(format!("{base}.safetensors"));
        let bare = PathBuf::from(&base);
        match !with_extension.exists() && RunFiles::new(&bare).json.exists() {
            true => RunFiles::new(&bare),
            false => RunFiles::new(&with_extension),
        }
    }
}

/// The class names of a classifier trained by `ecm-lcd train`: the `classes` of the run record
/// beside `weights_path` (any of the run's files), when there are exactly `classes` of them.
/// `None` for weights that no training run wrote (e.g. the imported ImageNet classifier).
pub fn class_names_of(weights_path: &Path, classes: usize) -> Option<Vec<String>> {
    let json = RunFiles::of_checkpoint(weights_path).json;
    let text = std::fs::read_to_string(json).ok()?;
    let value: serde_json::Value = serde_json::from_str(&text).ok()?;
    let names: Vec<String> =
        value.get("classes")?.as_array()?.iter().map(|v| v.as_str().map(str::to_string)).collect::<Option<_>>()?;
    (names.len() == classes).then_some(names)
}

/// The input size the training run that wrote `weights_path` (any of its files) trained at, from
/// its run record or report (`distill`, `train-place`); `None` for weights no training run wrote.
pub fn input_size_of(weights_path: &Path) -> Option<usize> {
    let text = std::fs::read_to_string(RunFiles::of_checkpoint(weights_path).json).ok()?;
    let value: serde_json::Value = serde_json::from_str(&text).ok()?;
    // `train` records it under `hyper`, `distill` and `train-place` reports under `config`.
    let size = value.get("hyper").or_else(|| value.get("config"))?.get("size")?;
    size.as_u64().map(|size| size as usize)
}

/// A classification training run.
#[derive(Clone, Debug)]
pub struct TrainConfig {
    pub data: PathBuf,
    pub arch: Arch,
    pub init: Option<PathBuf>,
    /// Expected number of classes (`None`: as many as the data has).
    pub classes: Option<usize>,
    pub val_fraction: f64,
    pub hyper: Hyper,
    pub out: PathBuf,
    pub resume: Option<PathBuf>,
    pub progress: bool,
    /// Stop after this many epochs of this invocation (the schedule still spans `hyper.opt.epochs`).
    pub stop_after: Option<usize>,
    /// Stop after the first epoch whose validation accuracy reaches this (the schedule still spans
    /// `hyper.opt.epochs`, so `resume` continues it).
    pub target_accuracy: Option<f64>,
}

/// Runs (or resumes) a classification training; returns the record also written as JSON.
pub fn train(config: &TrainConfig) -> Result<RunRecord> {
    let mut hyper = config.hyper.clone();
    let files = RunFiles::new(&config.out);
    files.check()?;
    // The resumed run's record, training form and best weights.
    let resumed: Option<(RunRecord, Weights, PathBuf)> = match &config.resume {
        Some(checkpoint) => {
            let from = RunFiles::of_checkpoint(checkpoint);
            let text = std::fs::read_to_string(&from.json)
                .with_context(|| format!("cannot read the run record {}", from.json.display()))?;
            let record: RunRecord =
                serde_json::from_str(&text).with_context(|| format!("{} is not a run record", from.json.display()))?;
            ensure!(record.arch == config.arch, "{} trained {}, not {}", from.json.display(), record.arch, config.arch);
            ensure!(
                record.epochs_done < record.hyper.opt.epochs,
                "{} finished its {} epochs: nothing to resume (train anew, without --resume, to train longer)",
                from.json.display(),
                record.epochs_done
            );
            if record.hyper != config.hyper {
                log::warn!(
                    "resuming {}: the run goes on with its own settings (size, epochs, learning rate, batch...); \
                     those given here differ and are not used",
                    from.json.display()
                );
            }
            hyper = record.hyper.clone();
            let training = from.training_of(&record)?;
            Some((record, Weights::load(&training)?, from.best))
        }
        None => None,
    };
    check_input_size(hyper.size)?;
    ensure!(hyper.opt.batch >= 2, "batch size {} is below 2 (BatchNorm needs two images)", hyper.opt.batch);
    hyper.opt.check()?;
    let folder = ImageFolder::open(&config.data, hyper.opt.seed, config.val_fraction)?;
    if let Some(k) = config.classes {
        ensure!(
            k == folder.classes.len(),
            "--classes {k} but {} has {} classes",
            config.data.display(),
            folder.classes.len()
        );
    }
    if let Some((record, _, _)) = &resumed {
        ensure!(
            record.classes == folder.classes,
            "the classes of {} differ from those of the resumed run",
            config.data.display()
        );
        // Another split would train on the run's validation images.
        ensure!(
            (record.split.as_str(), record.train_images, record.val_images)
                == (folder.split.as_str(), folder.train.len(), folder.val.len()),
            "the split now ({}: {} training, {} validation images) differs from the resumed run's ({}: {}, {}); \
             give the run's --val-fraction and data",
            folder.split,
            folder.train.len(),
            folder.val.len(),
            record.split,
            record.train_images,
            record.val_images
        );
    }
    let classes = folder.classes.len();
    ensure!(!folder.val.is_empty(), "no validation images (use --val-fraction > 0 or TestImages.txt)");
    let steps_per_epoch = hyper.opt.steps_per_epoch(folder.train.len());
    ensure!(steps_per_epoch > 0, "{} training images are too few for a batch", folder.train.len());
    let total_steps = steps_per_epoch * hyper.opt.epochs;
    let warmup = hyper.opt.warmup_steps(steps_per_epoch);

    let init_tensors: HashMap<String, Tensor> = match (&resumed, &config.init) {
        (Some((_, w, _)), _) => w
            .tensors
            .iter()
            .filter(|(n, _)| !n.starts_with("optimizer."))
            .map(|(n, t)| (n.clone(), t.clone()))
            .collect(),
        (None, Some(path)) => {
            let w = crate::model::weights::resolve::load_file(path)?.weights.for_arch(config.arch)?;
            let mut t = training_form(&w.tensors)?;
            if w.classes != Some(classes) {
                // A new head starts at zero: every class equally likely (loss ln K) and no
                // gradient into the body until the head has learnt something, so the first
                // steps cannot push random-head errors into the pretrained layers.
                let features = config.arch.spec().head_channels;
                t.retain(|n, _| !n.starts_with("classifier."));
                t.insert("classifier.weight".into(), Tensor::zeros((classes, features), DType::F32, &Device::Cpu)?);
                t.insert("classifier.bias".into(), Tensor::zeros(classes, DType::F32, &Device::Cpu)?);
            }
            t
        }
        (None, None) => HashMap::new(),
    };
    let model = Trainable::new(config.arch, Some(classes), &init_tensors, hyper.opt.seed)?;
    let mut params = trainable_params(&model.varmap);
    for p in params.iter_mut().filter(|p| !p.name.starts_with("classifier.")) {
        p.lr_scale = hyper.body_lr_scale;
    }
    let mut optimizer = hyper.opt.optimizer(params)?;
    let mut record = match resumed {
        Some((record, w, best)) => {
            optimizer.restore(&w.tensors, record.steps_done)?;
            // Resumed into another -o, once every check has passed: the best epoch so far is the
            // resumed run's, whose weights must be there too, or a run whose later epochs do not
            // beat it would name a file it never wrote.
            if record.best_epoch > 0 && !crate::io::output::same_file(&best, &files.best) {
                let bytes = std::fs::read(&best)
                    .with_context(|| format!("reading the resumed run's best weights {}", best.display()))?;
                crate::io::output::write_replacing(&files.best, &bytes)?;
            }
            record
        }
        None => RunRecord {
            command: "train".into(),
            data: config.data.clone(),
            arch: config.arch,
            classes: folder.classes.clone(),
            split: folder.split.clone(),
            train_images: folder.train.len(),
            val_images: folder.val.len(),
            init: config.init.as_ref().map(|p| p.display().to_string()),
            hyper: hyper.clone(),
            steps_per_epoch,
            epochs_done: 0,
            steps_done: 0,
            best_val_accuracy: -1.0,
            best_epoch: 0,
            history: Vec::new(),
            training_sha256: None,
        },
    };
    ensure!(
        record.steps_per_epoch == steps_per_epoch,
        "the resumed run had {} steps per epoch, the data now gives {steps_per_epoch}",
        record.steps_per_epoch
    );

    let train_set: Arc<dyn ImageSet> = Arc::new(FileSet(folder.train.clone()));
    let val_set: Arc<dyn ImageSet> = Arc::new(FileSet(folder.val.clone()));
    let calibration = if hyper.freeze_batch_norm {
        Vec::new()
    } else {
        calibration_batches(train_set.clone(), hyper.size, hyper.opt.batch, PRECISE_BN_IMAGES, hyper.opt.seed)?
    };
    let last_epoch =
        config.stop_after.map(|n| (record.epochs_done + n).min(hyper.opt.epochs)).unwrap_or(hyper.opt.epochs);
    let mode = if hyper.freeze_batch_norm { Mode::FineTune } else { Mode::Train };
    for epoch in record.epochs_done..last_epoch {
        let started = Instant::now();
        let bar =
            progress_bar(config.progress, steps_per_epoch as u64, &format!("epoch {}/{}", epoch + 1, hyper.opt.epochs));
        let loader = hyper.opt.epoch_loader(train_set.clone(), hyper.size, epoch);
        let (mut loss_sum, mut correct, mut seen, mut lr) = (0.0, 0usize, 0usize, 0.0);
        for batch in loader.batches.iter() {
            let batch = batch?;
            lr = learning_rate(record.steps_done, total_steps, warmup, hyper.opt.lr);
            let labels = Tensor::new(batch.labels.as_slice(), &Device::Cpu)?;
            let logits = model.network.logits(&batch.tensor(hyper.size)?, mode)?;
            let loss = smoothed_cross_entropy(&logits, &labels, hyper.label_smoothing)?;
            let grads = loss.backward()?;
            optimizer.step(&grads, lr)?;
            record.steps_done += 1;
            let predicted = logits.argmax(D::Minus1)?.to_vec1::<u32>()?;
            correct += predicted.iter().zip(&batch.labels).filter(|(p, l)| p == l).count();
            let loss = loss.to_scalar::<f32>()? as f64;
            ensure!(loss.is_finite(), "the loss diverged at step {} (learning rate {lr})", record.steps_done);
            loss_sum += loss * batch.len() as f64;
            seen += batch.len();
            bar.set_message(format!(
                "loss {:.3} acc {:.1}% {:.1} img/s lr {lr:.2e}",
                loss_sum / seen as f64,
                100.0 * correct as f64 / seen as f64,
                seen as f64 / started.elapsed().as_secs_f64()
            ));
            bar.inc(1);
        }
        drop(loader);
        if !hyper.freeze_batch_norm {
            model.precise_batch_norm(&calibration)?;
        }
        let weights =
            model.inference_weights(&format!("ecm-lcd train on {} (epoch {})", config.data.display(), epoch + 1))?;
        let val_accuracy = accuracy(&weights.network(true)?, val_set.clone(), hyper.size, hyper.opt.batch)?;
        bar.finish_with_message(format!(
            "loss {:.3} train acc {:.1}% val acc {:.1}%",
            loss_sum / seen.max(1) as f64,
            100.0 * correct as f64 / seen.max(1) as f64,
            100.0 * val_accuracy
        ));
        let seconds = started.elapsed().as_secs_f64();
        record.history.push(EpochResult {
            epoch: epoch + 1,
            train_loss: loss_sum / seen.max(1) as f64,
            train_accuracy: correct as f64 / seen.max(1) as f64,
            val_accuracy,
            learning_rate: lr,
            images_per_second: seen as f64 / seconds,
            seconds,
        });
        record.epochs_done = epoch + 1;
        let mut training = model.tensors();
        training.extend(optimizer.state_tensors()?);
        let training = Weights {
            arch: config.arch,
            classes: Some(classes),
            source: "ecm-lcd training form".into(),
            tensors: training,
        };
        // Nothing of an epoch that left the finite numbers is saved: the files of the last good
        // epoch stay, and the run says so (BatchNorm keeps the loss bounded while its statistics
        // overflow, so the loss alone does not tell).
        for form in [&weights, &training] {
            form.check_finite().with_context(|| {
                format!(
                    "training diverged in epoch {}; the files of the epoch before are kept (try a lower --lr, or a \
                     larger --batch or --size)",
                    epoch + 1
                )
            })?;
        }
        weights.save(&files.last)?;
        if val_accuracy > record.best_val_accuracy {
            record.best_val_accuracy = val_accuracy;
            record.best_epoch = epoch + 1;
            weights.save(&files.best)?;
        }
        // The training form is written under a name of its own, the record naming its hash next,
        // then the form renamed into place: a kill at any point leaves a record and a form that
        // belong together (`RunFiles::training_of`).
        let bytes = training.to_bytes()?;
        crate::io::output::write_replacing(&files.training_next(), &bytes)?;
        record.training_sha256 = Some(sha256_hex(&bytes));
        write_json(&files.json, &record)?;
        std::fs::rename(files.training_next(), &files.training)
            .with_context(|| format!("renaming {} into place", files.training_next().display()))?;
        if config.target_accuracy.is_some_and(|target| val_accuracy >= target) {
            break;
        }
    }
    Ok(record)
}

/// The JSON report written beside the weights `out` (its extension replaced by `.json`), once both
/// can be written ([`crate::io::output::ensure_writable_outputs`]; `-o x.json` would be replaced by
/// its own report).
pub fn report_beside(out: &Path) -> Result<PathBuf> {
    let mut json = weights_stem(out).into_os_string();
    json.push(".json");
    let json = PathBuf::from(json);
    crate::io::output::ensure_writable_outputs(&[("-o", out), ("the report", &json)])?;
    Ok(json)
}

/// `out` less a `.safetensors` extension, the name a run's other files are made from: any other dot
/// is part of the name (`-o lr0.001` and `-o lr0.003` are two runs, with `lr0.001.json` and
/// `lr0.003.json`).
fn weights_stem(out: &Path) -> PathBuf {
    match out.to_str().and_then(|text| text.strip_suffix(".safetensors")) {
        Some(stem) => PathBuf::from(stem),
        None => out.to_path_buf(),
    }
}

/// Writes `value` as pretty JSON to `path`.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    crate::io::output::write_replacing(path, (text + "\n").as_bytes())
}

/// A progress bar (hidden when `show` is false, e.g. in tests).
pub fn progress_bar(show: bool, len: u64, prefix: &str) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_prefix(prefix.to_string());
    bar
}

/// The compute device: only the CPU is built in.
pub fn check_device(name: &str) -> Result<()> {
    match name {
        "cpu" => Ok(()),
        "cuda" | "metal" => bail!(
            "device '{name}' is not built in: this ecm-lcd is built without candle's {name} feature (use --device cpu)"
        ),
        other => bail!("unknown device '{other}' (expected cpu)"),
    }
}

#[cfg(test)]
mod tests;
