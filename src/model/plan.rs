//! The inference plan: what a forward pass in [`Mode::Inference`] runs, built once when a network
//! is loaded with folded constant weights.
//!
//! Each stage of the network becomes one fused channels-last kernel ([`kernels::fused`]): the stem's
//! dense convolution (fused into the first bottleneck where that block can take it), one op per
//! bottleneck, and the head's 1x1 convolution, whose map is turned back to NCHW. The layers
//! ([`super::layers`]) keep only the network's definition and the reference and training paths;
//! where a weight is trainable or BatchNorm is not folded there is no plan, and inference runs the
//! layers.
//!
//! [`Mode::Inference`]: super::layers::Mode::Inference
//! [`kernels::fused`]: super::kernels::fused

use std::sync::Arc;

use candle_core::{Result, Tensor};

use super::kernels::fused::{channels_first, DenseConv, FusedBottleneck};
use super::layers::{ConvUnit, InvertedResidual};

/// One op of the plan.
#[derive(Clone, Debug)]
pub enum Step {
    /// The stem alone: the NCHW image to a channels-last map.
    Stem(Arc<DenseConv>),
    /// The stem and block 0 in one op: the NCHW image to block 0's channels-last map.
    StemAndFirstBlock(Arc<FusedBottleneck>),
    /// Bottleneck `i`, channels-last in and out.
    Block(usize, Arc<FusedBottleneck>),
    /// The head: channels-last in, NCHW out.
    Head(Arc<DenseConv>),
}

impl Step {
    /// Runs the op on `x`.
    pub fn run(&self, x: &Tensor) -> Result<Tensor> {
        let x = x.contiguous()?;
        match self {
            Step::Stem(op) => x.apply_op1_no_bwd(op.as_ref()),
            Step::StemAndFirstBlock(op) | Step::Block(_, op) => x.apply_op1_no_bwd(op.as_ref()),
            Step::Head(op) => channels_first(&x.apply_op1_no_bwd(op.as_ref())?),
        }
    }

    /// Whether the step's output is channels-last (every step's but the head's).
    pub fn gives_channels_last(&self) -> bool {
        !matches!(self, Step::Head(_))
    }
}

/// The steps of a network's inference pass, in order (module doc).
#[derive(Clone, Debug)]
pub struct InferencePlan {
    steps: Vec<Step>,
}

impl InferencePlan {
    /// The plan of these layers; `None` where one of them has no fused kernel (trainable weights,
    /// BatchNorm not folded).
    pub fn build(stem: &ConvUnit, blocks: &[InvertedResidual], head: &ConvUnit) -> Result<Option<Self>> {
        let (Some(stem), Some(head)) = (stem.dense_kernel()?, head.dense_kernel()?) else {
            return Ok(None);
        };
        let mut fused = Vec::with_capacity(blocks.len());
        for block in blocks {
            match block.fused_kernel()? {
                Some(kernel) => fused.push(Arc::new(kernel)),
                None => return Ok(None),
            }
        }
        let stem = Arc::new(stem);
        // The first block takes the stem where it can (no expansion, no residual: both networks).
        let with_stem = fused.first().and_then(|first| first.with_stem(stem.clone()).ok());
        let mut steps = Vec::with_capacity(blocks.len() + 2);
        let first_block = match with_stem {
            Some(op) => {
                steps.push(Step::StemAndFirstBlock(Arc::new(op)));
                1
            }
            None => {
                steps.push(Step::Stem(stem));
                0
            }
        };
        steps.extend(fused.into_iter().enumerate().skip(first_block).map(|(i, op)| Step::Block(i, op)));
        steps.push(Step::Head(Arc::new(head)));
        Ok(Some(InferencePlan { steps }))
    }

    pub fn steps(&self) -> &[Step] {
        &self.steps
    }
}
