//! The building blocks both networks share: a convolution unit (conv + BatchNorm or folded bias +
//! activation), Efficient Channel Attention, and the inverted-residual bottleneck. They hold the
//! definition and run the reference and training paths; the fused inference kernels are built from
//! them once, by [`super::plan`].
//!
//! Tensor names inside a unit: `weight` (OIHW), then either `bias` (BatchNorm folded, inference
//! form) or `bn.weight`, `bn.bias`, `bn.running_mean`, `bn.running_var` (training form).

use candle_core::{Module, ModuleT, Result, Tensor};
use candle_nn::{BatchNorm, BatchNormConfig, VarBuilder};

use super::kernels::depthwise::{self, Activation};
use super::kernels::fused::{DenseConv, FusedBottleneck};
use super::kernels::{batch_norm_train, depthwise_grad, train_ops};

/// How a forward pass runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Inference with the fast custom kernels: the network's [`super::plan`] where the weights are
    /// folded constants, else the layers with the NCHW depthwise kernel.
    Inference,
    /// Inference with stock candle ops only: the reference the fast path is checked against.
    Reference,
    /// Training: BatchNorm with batch statistics; differentiable ops, the depthwise convolution
    /// by [`super::depthwise_grad`] (tested equal to the stock grouped convolution).
    Train,
    /// Fine-tuning (distillation): as [`Mode::Train`] but BatchNorm uses its frozen running statistics.
    FineTune,
}

impl Mode {
    /// Whether gradients flow (the differentiable fast kernels are used).
    pub fn is_training(self) -> bool {
        matches!(self, Mode::Train | Mode::FineTune)
    }
}

/// What kind of convolution a unit is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConvKind {
    /// A full convolution (the stem), "SAME" padding.
    Full { stride: usize },
    /// One filter per channel, "SAME" padding.
    Depthwise { stride: usize },
    /// 1x1, a matrix multiply over channels.
    Pointwise,
}

/// TensorFlow's MobileNetV2 BatchNorm epsilon.
pub const BN_EPS: f64 = 1e-3;
/// Weight of a batch's statistics in the running statistics (candle's convention; TensorFlow's 0.99 decay).
pub const BN_MOMENTUM: f64 = 0.01;

/// Convolution followed by BatchNorm (or its folded bias) and an activation.
#[derive(Clone, Debug)]
pub struct ConvUnit {
    weight: Tensor,
    bias: Option<Tensor>,
    bn: Option<BatchNorm>,
    kind: ConvKind,
    activation: Activation,
}

/// Fast kernels copy the weights, so they are built only for constant (non-trainable) tensors.
fn frozen(weight: &Tensor) -> bool {
    !weight.is_variable()
}

impl ConvUnit {
    /// A folded unit (bias, no BatchNorm).
    fn with_bias(weight: Tensor, bias: Tensor, kind: ConvKind, activation: Activation) -> Self {
        ConvUnit { weight, bias: Some(bias), bn: None, kind, activation }
    }

    /// The fused kernel of a folded full or 1x1 convolution with constant weights (what the
    /// inference plan runs); `None` for other units.
    pub fn dense_kernel(&self) -> Result<Option<DenseConv>> {
        let (Some(bias), None, true) = (&self.bias, &self.bn, frozen(&self.weight)) else { return Ok(None) };
        match self.kind {
            ConvKind::Full { stride } => DenseConv::new(&self.weight, bias, stride, self.activation).map(Some),
            ConvKind::Pointwise => DenseConv::new(&self.weight, bias, 1, self.activation).map(Some),
            ConvKind::Depthwise { .. } => Ok(None),
        }
    }

    /// Loads `weight` `[out, in, kh, kw]` and the BatchNorm or bias under `vb`.
    /// `batch_norm`: keep BatchNorm as a layer (training); otherwise fold it into a bias.
    pub fn load(
        vb: VarBuilder,
        shape: (usize, usize, usize, usize),
        kind: ConvKind,
        activation: Activation,
        batch_norm: bool,
    ) -> Result<Self> {
        let out = shape.0;
        let weight = vb.get_with_hints(shape, "weight", candle_nn::init::DEFAULT_KAIMING_NORMAL)?;
        let has_bn = vb.contains_tensor("bn.running_mean");
        if batch_norm || (has_bn && !vb.contains_tensor("bias")) {
            let config = BatchNormConfig { eps: BN_EPS, remove_mean: true, affine: true, momentum: BN_MOMENTUM };
            let bn = candle_nn::batch_norm(out, config, vb.pp("bn"))?;
            let unit = ConvUnit { weight, bias: None, bn: Some(bn), kind, activation };
            return if batch_norm { Ok(unit) } else { unit.folded() };
        }
        let bias = vb.get(out, "bias")?;
        Ok(ConvUnit::with_bias(weight, bias, kind, activation))
    }

    /// The inference form: BatchNorm folded into the convolution's weight and bias.
    pub fn folded(&self) -> Result<Self> {
        let Some(bn) = &self.bn else { return Ok(self.clone()) };
        let out = self.weight.dim(0)?;
        let (gamma, beta) = bn.weight_and_bias().map(|(w, b)| (w.clone(), b.clone())).unwrap_or((
            Tensor::ones(out, self.weight.dtype(), self.weight.device())?,
            Tensor::zeros(out, self.weight.dtype(), self.weight.device())?,
        ));
        let scale = (gamma / (bn.running_var().affine(1.0, BN_EPS)?.sqrt()?))?;
        let weight = self.weight.broadcast_mul(&scale.reshape((out, 1, 1, 1))?)?;
        let bias = (beta - bn.running_mean().mul(&scale)?)?;
        Ok(ConvUnit::with_bias(weight, bias, self.kind, self.activation))
    }

    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    pub fn bias(&self) -> Option<&Tensor> {
        self.bias.as_ref()
    }

    pub fn forward_t(&self, x: &Tensor, mode: Mode) -> Result<Tensor> {
        let fast = mode == Mode::Inference && self.bn.is_none();
        if fast {
            let bias = self.bias.as_ref().expect("a unit without BatchNorm has a bias");
            return match self.kind {
                ConvKind::Depthwise { stride } => {
                    depthwise::depthwise_conv(x, &self.weight, bias, stride, self.activation)
                }
                ConvKind::Pointwise => {
                    let y = pointwise(x, &self.weight)?;
                    depthwise::bias_activation_(&y, bias, self.activation)?;
                    Ok(y)
                }
                ConvKind::Full { stride } => {
                    let y = self.convolve(x, stride, 1)?;
                    depthwise::bias_activation_(&y, bias, self.activation)?;
                    Ok(y)
                }
            };
        }
        // Training runs ops with hand-written backward passes (tested equal to the stock ones).
        let y = match self.kind {
            ConvKind::Full { stride } if mode.is_training() => train_ops::conv_same(x, &self.weight, stride)?,
            ConvKind::Full { stride } => self.convolve(x, stride, 1)?,
            ConvKind::Depthwise { stride } if mode.is_training() => {
                depthwise_grad::depthwise_conv_train(x, &self.weight, stride)?
            }
            ConvKind::Depthwise { stride } => self.convolve(x, stride, x.dim(1)?)?,
            ConvKind::Pointwise if mode.is_training() => train_ops::pointwise_conv(x, &self.weight)?,
            ConvKind::Pointwise => x.conv2d(&self.weight, 0, 1, 1, 1)?,
        };
        let y = match (&self.bn, &self.bias) {
            (Some(bn), _) if mode == Mode::Train => batch_norm_train::batch_norm_train(bn, &y)?,
            (Some(bn), _) => bn.forward_t(&y, mode == Mode::Train)?,
            (None, Some(b)) => y.broadcast_add(&b.reshape((1, b.dim(0)?, 1, 1))?)?,
            (None, None) => y,
        };
        match self.activation {
            Activation::Relu6 if mode.is_training() => train_ops::relu6(&y),
            activation => activation.forward(&y),
        }
    }

    fn convolve(&self, x: &Tensor, stride: usize, groups: usize) -> Result<Tensor> {
        let (_, _, h, w) = x.dims4()?;
        let (_, _, kh, kw) = self.weight.dims4()?;
        depthwise::pad_same(x, h, w, kh, kw, stride)?.conv2d(&self.weight, 0, stride, 1, groups)
    }
}

/// A 1x1 convolution as a plain matrix multiply: `[O, I] x [B, I, H*W]`, no im2col copy.
fn pointwise(x: &Tensor, weight: &Tensor) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    let out = weight.dim(0)?;
    let weight = weight.reshape((out, c))?;
    let x = x.contiguous()?.reshape((b, c, h * w))?;
    let y = if b == 1 { weight.matmul(&x.squeeze(0)?)?.unsqueeze(0)? } else { weight.broadcast_left(b)?.matmul(&x)? };
    y.reshape((b, out, h, w))
}

/// Efficient Channel Attention (Wang et al., ECA-Net): global average pool, a 1-D convolution
/// across channels with `kernel` taps and no bias, a sigmoid, and a channel-wise scale.
#[derive(Clone, Debug)]
pub struct Eca {
    weight: Tensor, // [1, 1, kernel]
}

impl Eca {
    pub fn load(vb: VarBuilder, kernel: usize) -> Result<Self> {
        let weight = vb.get_with_hints((1, 1, kernel), "weight", candle_nn::init::DEFAULT_KAIMING_UNIFORM)?;
        Ok(Eca { weight })
    }

    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    pub fn kernel(&self) -> usize {
        self.weight.dims()[2]
    }

    /// The per-channel gate in (0, 1), shape `[B, C, 1, 1]`.
    pub fn gate(&self, x: &Tensor) -> Result<Tensor> {
        self.gate_t(x, Mode::Reference)
    }

    fn gate_t(&self, x: &Tensor, mode: Mode) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        let pooled = if mode.is_training() {
            train_ops::channel_mean(x)?
        } else {
            // One reduction over each contiguous channel plane.
            x.contiguous()?.reshape((b, c, h * w))?.mean(2)?
        };
        let k = self.kernel();
        let y = pooled.reshape((b, 1, c))?.conv1d(&self.weight, (k - 1) / 2, 1, 1, 1)?;
        candle_nn::ops::sigmoid(&y)?.reshape((b, c, 1, 1))
    }

    /// `x` scaled by its gate; the training modes use the ops of [`train_ops`].
    pub fn forward_t(&self, x: &Tensor, mode: Mode) -> Result<Tensor> {
        let gate = self.gate_t(x, mode)?;
        if mode.is_training() {
            train_ops::channel_scale(x, &gate)
        } else {
            x.broadcast_mul(&gate)
        }
    }
}

impl Module for Eca {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        x.broadcast_mul(&self.gate(x)?)
    }
}

/// Shape of one bottleneck once the table rows are expanded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BlockShape {
    pub input: usize,
    pub hidden: usize,
    pub output: usize,
    pub stride: usize,
    /// ECA kernel size, `None` for MobileNetV2's plain bottleneck.
    pub eca_kernel: Option<usize>,
}

impl BlockShape {
    pub fn has_expansion(&self) -> bool {
        self.hidden != self.input
    }
    pub fn has_residual(&self) -> bool {
        self.stride == 1 && self.input == self.output
    }
}

/// MobileNetV2's inverted residual bottleneck, optionally with ECA after the depthwise
/// convolution (BN, ReLU6) and before the linear 1x1 projection, as in the paper's Fig. 7.
#[derive(Clone, Debug)]
pub struct InvertedResidual {
    pub shape: BlockShape,
    expand: Option<ConvUnit>,
    depthwise: ConvUnit,
    eca: Option<Eca>,
    project: ConvUnit,
}

impl InvertedResidual {
    pub fn load(vb: VarBuilder, shape: BlockShape, batch_norm: bool) -> Result<Self> {
        let expand = if shape.has_expansion() {
            Some(ConvUnit::load(
                vb.pp("expand"),
                (shape.hidden, shape.input, 1, 1),
                ConvKind::Pointwise,
                Activation::Relu6,
                batch_norm,
            )?)
        } else {
            None
        };
        let depthwise = ConvUnit::load(
            vb.pp("depthwise"),
            (shape.hidden, 1, 3, 3),
            ConvKind::Depthwise { stride: shape.stride },
            Activation::Relu6,
            batch_norm,
        )?;
        let eca = shape.eca_kernel.map(|k| Eca::load(vb.pp("eca"), k)).transpose()?;
        let project = ConvUnit::load(
            vb.pp("project"),
            (shape.output, shape.hidden, 1, 1),
            ConvKind::Pointwise,
            Activation::Identity,
            batch_norm,
        )?;
        Ok(InvertedResidual { shape, expand, depthwise, eca, project })
    }

    /// The whole block as one fused kernel (what the inference plan runs), where every unit is
    /// folded and constant; `None` otherwise.
    pub fn fused_kernel(&self) -> Result<Option<FusedBottleneck>> {
        fn folded(unit: &ConvUnit) -> Option<(&Tensor, &Tensor)> {
            match (&unit.bias, &unit.bn) {
                (Some(bias), None) if frozen(&unit.weight) => Some((&unit.weight, bias)),
                _ => None,
            }
        }
        let expand = match &self.expand {
            Some(unit) => match folded(unit) {
                Some(folded) => Some(folded),
                None => return Ok(None),
            },
            None => None,
        };
        let (Some(depthwise), Some(project)) = (folded(&self.depthwise), folded(&self.project)) else {
            return Ok(None);
        };
        let eca = self.eca.as_ref().map(|e| &e.weight);
        FusedBottleneck::new(self.shape.stride, expand, depthwise, eca, project).map(Some)
    }

    /// The convolution units with their names: `expand` (if any), `depthwise`, `project`.
    pub fn units(&self) -> Vec<(&'static str, &ConvUnit)> {
        let mut units = Vec::with_capacity(3);
        if let Some(e) = &self.expand {
            units.push(("expand", e));
        }
        units.push(("depthwise", &self.depthwise));
        units.push(("project", &self.project));
        units
    }

    pub fn eca(&self) -> Option<&Eca> {
        self.eca.as_ref()
    }

    pub fn forward_t(&self, x: &Tensor, mode: Mode) -> Result<Tensor> {
        let mut y = match &self.expand {
            Some(expand) => expand.forward_t(x, mode)?,
            None => x.clone(),
        };
        y = self.depthwise.forward_t(&y, mode)?;
        y = match &self.eca {
            Some(eca) => self.project.forward_t(&eca.forward_t(&y, mode)?, mode)?,
            None => self.project.forward_t(&y, mode)?,
        };
        if self.shape.has_residual() {
            y = (y + x)?;
        }
        Ok(y)
    }
}
