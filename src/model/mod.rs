//! The networks: MobileNetV2 (reference and import target) and ECMobileNet (the paper's variant),
//! their building blocks ([`layers`]), the inference plan built from them ([`plan`]) and weights
//! import/load/save ([`weights`]); the CPU kernels they run on are apart, in [`kernels`].
//!
//! Both networks are the same skeleton described by data ([`NetworkSpec`]: one row per bottleneck
//! stage, as in the papers' tables): a 3x3 stride-2 stem, inverted-residual bottlenecks, a 1x1
//! convolution to 1280 channels, global average pooling and an optional classifier.
//! Tensors in and out are NCHW, input RGB scaled to [-1, 1]; the reference and training paths stay
//! NCHW, while the inference plan runs channels-last inside [`kernels::fused`].

pub mod ecmobilenet;
pub mod embedder;
pub mod kernels;
pub mod layers;
pub mod mobilenetv2;
pub mod plan;
pub mod weights;
pub mod xfeat;

use anyhow::{bail, Context};
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use serde::Serialize;
use std::fmt;
use std::str::FromStr;
use std::sync::Arc;

use kernels::depthwise::Activation;
use layers::{BlockShape, ConvKind, ConvUnit, InvertedResidual, Mode};
use plan::{InferencePlan, Step};

/// Which network.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Arch {
    MobileNetV2,
    EcMobileNet,
}

impl Arch {
    pub fn spec(self) -> &'static NetworkSpec {
        match self {
            Arch::MobileNetV2 => &mobilenetv2::MOBILENET_V2,
            Arch::EcMobileNet => &ecmobilenet::EC_MOBILENET,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Arch::MobileNetV2 => "mobilenetv2",
            Arch::EcMobileNet => "ecmobilenet",
        }
    }
}

impl fmt::Display for Arch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Arch {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        match s.to_ascii_lowercase().replace(['-', '_'], "").as_str() {
            "mobilenetv2" | "mnv2" => Ok(Arch::MobileNetV2),
            "ecmobilenet" | "ecm" => Ok(Arch::EcMobileNet),
            _ => bail!("unknown architecture '{s}' (expected ecmobilenet or mobilenetv2)"),
        }
    }
}

/// One row of a bottleneck table: expansion factor t, output channels c, repeats n, stride s
/// (the stride of the first block of the stage; the others have stride 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BottleneckRow {
    pub t: usize,
    pub c: usize,
    pub n: usize,
    pub s: usize,
}

/// A table row (t, c, n, s).
pub const fn row(t: usize, c: usize, n: usize, s: usize) -> BottleneckRow {
    BottleneckRow { t, c, n, s }
}

/// A whole network as data.
#[derive(Clone, Debug)]
pub struct NetworkSpec {
    pub arch: Arch,
    pub stem_channels: usize,
    pub rows: &'static [BottleneckRow],
    pub head_channels: usize,
    /// ECA kernel size for a bottleneck with this many hidden channels; `None`: no ECA.
    pub eca_kernel: Option<fn(usize) -> usize>,
}

impl NetworkSpec {
    /// The bottlenecks, one per block, in order.
    pub fn blocks(&self) -> Vec<BlockShape> {
        let mut input = self.stem_channels;
        let mut blocks = Vec::new();
        for row in self.rows {
            for i in 0..row.n {
                let hidden = input * row.t;
                blocks.push(BlockShape {
                    input,
                    hidden,
                    output: row.c,
                    stride: if i == 0 { row.s } else { 1 },
                    eca_kernel: self.eca_kernel.map(|k| k(hidden)),
                });
                input = row.c;
            }
        }
        blocks
    }

    /// Trainable parameters (convolution weights, BatchNorm scale and shift, ECA kernels, the
    /// classifier's weight and bias), as PyTorch counts them, and multiply-accumulates per image.
    pub fn cost(&self, classes: Option<usize>, input_size: usize) -> ModelCost {
        let stages = self.stage_costs(classes, input_size);
        ModelCost {
            arch: self.arch,
            params: stages.iter().map(|s| s.params).sum(),
            macs: stages.iter().map(|s| s.macs).sum(),
        }
    }

    /// [`NetworkSpec::cost`] stage by stage: `stem`, `blocks.{i}`, `head` and `classifier`.
    pub fn stage_costs(&self, classes: Option<usize>, input_size: usize) -> Vec<StageCost> {
        let mut stages = Vec::new();
        let mut size = input_size.div_ceil(2);
        // (params, macs) of a convolution followed by BatchNorm (gamma and beta).
        let conv = |inp: usize, out: usize, k: usize, groups: usize, spatial: usize| {
            let weights = out * (inp / groups) * k * k;
            (weights + 2 * out, weights * spatial * spatial)
        };
        let stage = |name: String, parts: &[(usize, usize)]| StageCost {
            name,
            params: parts.iter().map(|p| p.0).sum(),
            macs: parts.iter().map(|p| p.1).sum(),
        };
        stages.push(stage("stem".into(), &[conv(3, self.stem_channels, 3, 1, size)]));
        for (i, b) in self.blocks().into_iter().enumerate() {
            let mut parts = Vec::new();
            if b.has_expansion() {
                parts.push(conv(b.input, b.hidden, 1, 1, size));
            }
            size = size.div_ceil(b.stride);
            parts.push(conv(b.hidden, b.hidden, 3, b.hidden, size));
            if let Some(k) = b.eca_kernel {
                parts.push((k, k * b.hidden + b.hidden * size * size)); // 1-D conv + channel scaling
            }
            parts.push(conv(b.hidden, b.output, 1, 1, size));
            stages.push(stage(format!("blocks.{i}"), &parts));
        }
        let last = self.blocks().last().map(|b| b.output).unwrap_or(self.stem_channels);
        stages.push(stage("head".into(), &[conv(last, self.head_channels, 1, 1, size)]));
        if let Some(k) = classes {
            stages.push(stage("classifier".into(), &[(self.head_channels * k + k, self.head_channels * k)]));
        }
        stages
    }
}

/// Parameters and multiply-accumulates of one stage of a network.
#[derive(Clone, Debug, Serialize, PartialEq, Eq)]
pub struct StageCost {
    pub name: String,
    pub params: usize,
    pub macs: usize,
}

/// Size and arithmetic of a network.
#[derive(Clone, Copy, Debug, Serialize, PartialEq, Eq)]
pub struct ModelCost {
    pub arch: Arch,
    pub params: usize,
    pub macs: usize,
}

/// A loaded network.
#[derive(Clone, Debug)]
pub struct Network {
    pub spec: NetworkSpec,
    stem: ConvUnit,
    pub blocks: Vec<InvertedResidual>,
    head: ConvUnit,
    classifier: Option<candle_nn::Linear>,
    /// What [`Mode::Inference`] runs, where the weights are folded constants ([`plan`]).
    plan: Option<Arc<InferencePlan>>,
}

/// Where a descriptor reads the network: the output of bottleneck `i` (0-based, as in the weights'
/// `blocks.{i}`; a linear bottleneck, so values may be negative) or the head (the 1280-channel
/// ReLU6 map before global pooling).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Tap {
    Block(usize),
    Head,
}

impl Tap {
    /// Position in the pass: block `i` is `i`, the head comes after `blocks` blocks.
    fn depth(self, blocks: usize) -> usize {
        match self {
            Tap::Block(i) => i,
            Tap::Head => blocks,
        }
    }
}

impl fmt::Display for Tap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Tap::Block(i) => write!(f, "blocks.{i}"),
            Tap::Head => f.write_str("head"),
        }
    }
}

impl FromStr for Tap {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        if s == "head" {
            return Ok(Tap::Head);
        }
        let index = s.strip_prefix("blocks.").and_then(|i| i.parse().ok());
        index.map(Tap::Block).with_context(|| format!("unknown tap '{s}' (expected head or blocks.N)"))
    }
}

/// One stage of a pass: what [`Network::profile`] times.
#[derive(Clone, Copy, Debug)]
enum Stage<'a> {
    /// A step of the inference plan (channels-last maps between steps).
    Planned(&'a Step),
    /// A layer on NCHW maps.
    Stem,
    Block(usize),
    Head,
}

impl Network {
    /// Builds `spec` from `vb` (names in [`weights`]). `classes`: load a classifier of that many
    /// outputs. `batch_norm`: keep BatchNorm layers (training form) instead of folding them.
    pub fn load(spec: &NetworkSpec, vb: VarBuilder, classes: Option<usize>, batch_norm: bool) -> Result<Self> {
        let stem = ConvUnit::load(
            vb.pp("stem"),
            (spec.stem_channels, 3, 3, 3),
            ConvKind::Full { stride: 2 },
            Activation::Relu6,
            batch_norm,
        )?;
        let blocks = spec
            .blocks()
            .into_iter()
            .enumerate()
            .map(|(i, shape)| InvertedResidual::load(vb.pp(format!("blocks.{i}")), shape, batch_norm))
            .collect::<Result<Vec<_>>>()?;
        let last = blocks.last().map(|b| b.shape.output).unwrap_or(spec.stem_channels);
        let head = ConvUnit::load(
            vb.pp("head"),
            (spec.head_channels, last, 1, 1),
            ConvKind::Pointwise,
            Activation::Relu6,
            batch_norm,
        )?;
        let classifier = classes.map(|k| candle_nn::linear(spec.head_channels, k, vb.pp("classifier"))).transpose()?;
        let plan = InferencePlan::build(&stem, &blocks, &head)?.map(Arc::new);
        Ok(Network { spec: spec.clone(), stem, blocks, head, classifier, plan })
    }

    pub fn arch(&self) -> Arch {
        self.spec.arch
    }

    pub fn classes(&self) -> Option<usize> {
        self.classifier.as_ref().map(|c| c.weight().dim(0)).transpose().ok().flatten()
    }

    /// The last feature map, `[B, head_channels, S/32, S/32]`, for input `x` `[B, 3, S, S]`.
    pub fn features(&self, x: &Tensor, mode: Mode) -> Result<Tensor> {
        let mut maps = self.tapped_features(x, mode, &[Tap::Head])?;
        Ok(maps.pop().expect("one map per tap"))
    }

    /// The maps at `taps`, each `[B, C, H, W]` (NCHW), in the order of `taps`. The pass stops after
    /// the deepest tap, so a descriptor on mid-level features does not pay for the later blocks.
    pub fn tapped_features(&self, x: &Tensor, mode: Mode, taps: &[Tap]) -> Result<Vec<Tensor>> {
        for tap in taps {
            if let Tap::Block(i) = tap {
                if *i >= self.blocks.len() {
                    candle_core::bail!("tap {tap} is past the last of {} blocks", self.blocks.len());
                }
            }
        }
        let Some(deepest) = taps.iter().map(|t| t.depth(self.blocks.len())).max() else {
            return Ok(Vec::new());
        };
        crate::runtime::with_hot_workers(|| {
            let mut y = x.clone();
            let mut maps: Vec<Option<Tensor>> = vec![None; taps.len()];
            for stage in self.stages(mode) {
                y = self.stage(stage, &y, mode)?;
                let Some(depth) = self.stage_depth(stage) else { continue };
                for (slot, tap) in maps.iter_mut().zip(taps) {
                    if tap.depth(self.blocks.len()) == depth {
                        let channels_last = matches!(stage, Stage::Planned(step) if step.gives_channels_last());
                        *slot = Some(if channels_last { kernels::fused::channels_first(&y)? } else { y.clone() });
                    }
                }
                if depth == deepest {
                    break;
                }
            }
            Ok(maps.into_iter().map(|m| m.expect("every tap is at or before the deepest")).collect())
        })
    }

    /// Stages of a pass in `mode`: the plan's steps in inference where there is a plan, else the
    /// stem, each block and the head.
    fn stages(&self, mode: Mode) -> Vec<Stage<'_>> {
        match self.plan.as_deref().filter(|_| mode == Mode::Inference) {
            Some(plan) => plan.steps().iter().map(Stage::Planned).collect(),
            None => std::iter::once(Stage::Stem)
                .chain((0..self.blocks.len()).map(Stage::Block))
                .chain(std::iter::once(Stage::Head))
                .collect(),
        }
    }

    /// Where a stage's output is in the pass (block `i`: `i`, the head: after the blocks; the stem
    /// alone: nowhere a tap reads).
    fn stage_depth(&self, stage: Stage) -> Option<usize> {
        match stage {
            Stage::Stem | Stage::Planned(Step::Stem(_)) => None,
            Stage::Planned(Step::StemAndFirstBlock(_)) => Some(0),
            Stage::Block(i) | Stage::Planned(&Step::Block(i, _)) => Some(i),
            Stage::Head | Stage::Planned(Step::Head(_)) => Some(self.blocks.len()),
        }
    }

    /// A stage's name: `stem`, `blocks.{i}`, `head`, or `stem+blocks.0` for the fused pair.
    fn stage_name(stage: Stage) -> String {
        match stage {
            Stage::Stem | Stage::Planned(Step::Stem(_)) => "stem".into(),
            Stage::Planned(Step::StemAndFirstBlock(_)) => "stem+blocks.0".into(),
            Stage::Block(i) | Stage::Planned(&Step::Block(i, _)) => format!("blocks.{i}"),
            Stage::Head | Stage::Planned(Step::Head(_)) => "head".into(),
        }
    }

    /// Runs `stage` on `x` in `mode`.
    fn stage(&self, stage: Stage, x: &Tensor, mode: Mode) -> Result<Tensor> {
        match stage {
            Stage::Planned(step) => step.run(x),
            Stage::Stem => self.stem.forward_t(x, mode),
            Stage::Block(i) => self.blocks[i].forward_t(x, mode),
            Stage::Head => self.head.forward_t(x, mode),
        }
    }

    /// Whether inference runs the plan (the weights are folded constants).
    pub fn is_planned(&self) -> bool {
        self.plan.is_some()
    }

    /// Mean time of each stage ([`Self::stage_name`]) over `runs` passes of `x` in `mode`,
    /// after one warm-up pass: the profile behind the benchmark's totals.
    pub fn profile(&self, x: &Tensor, mode: Mode, runs: usize) -> Result<Vec<(String, std::time::Duration)>> {
        // With the workers kept hot as in `features`, so that the stages add up to its time.
        crate::runtime::with_hot_workers(|| {
            let stages = self.stages(mode);
            let mut totals = vec![std::time::Duration::ZERO; stages.len()];
            for run in 0..=runs {
                let mut y = x.clone();
                for (&stage, total) in stages.iter().zip(&mut totals) {
                    let started = std::time::Instant::now();
                    y = self.stage(stage, &y, mode)?;
                    if run > 0 {
                        *total += started.elapsed();
                    }
                }
            }
            Ok(stages
                .into_iter()
                .zip(totals)
                .map(|(stage, t)| (Self::stage_name(stage), t / runs.max(1) as u32))
                .collect())
        })
    }

    /// Calls `f(name, weight, bias)` for every parameter tensor group in inference form
    /// (BatchNorm folded), with the names of [`weights`].
    pub fn visit_units(&self, f: &mut dyn FnMut(&str, &Tensor, Option<&Tensor>)) -> Result<()> {
        let unit = |f: &mut dyn FnMut(&str, &Tensor, Option<&Tensor>), name: &str, unit: &ConvUnit| -> Result<()> {
            let folded = unit.folded()?;
            f(name, folded.weight(), folded.bias());
            Ok(())
        };
        unit(f, "stem", &self.stem)?;
        for (i, block) in self.blocks.iter().enumerate() {
            for (part, u) in block.units() {
                unit(f, &format!("blocks.{i}.{part}"), u)?;
            }
            if let Some(eca) = block.eca() {
                f(&format!("blocks.{i}.eca"), eca.weight(), None);
            }
        }
        unit(f, "head", &self.head)?;
        if let Some(c) = &self.classifier {
            f("classifier", c.weight(), c.bias());
        }
        Ok(())
    }

    /// Class logits `[B, classes]`.
    pub fn logits(&self, x: &Tensor, mode: Mode) -> anyhow::Result<Tensor> {
        let classifier = self.classifier.as_ref().context("this network was loaded without a classifier")?;
        let pooled = self.features(x, mode)?.mean((2, 3))?;
        Ok(candle_core::Module::forward(classifier, &pooled)?)
    }
}

/// The largest network input side, the `input_size` parameter's bound (activations grow with its
/// square: a typo such as 65536 would ask for tens of gigabytes).
pub const MAX_INPUT_SIZE: usize = 1024;

/// `size` when it is a positive multiple of 32 up to [`MAX_INPUT_SIZE`].
pub fn check_input_size(size: usize) -> anyhow::Result<usize> {
    if size == 0 || !size.is_multiple_of(32) || size > MAX_INPUT_SIZE {
        bail!("input size {size} is not a multiple of 32 in [32, {MAX_INPUT_SIZE}]");
    }
    Ok(size)
}
