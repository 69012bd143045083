//! ECMobileNet (Zhou et al., "A Lightweight Neural Network for Loop Closure Detection in Indoor
//! Visual SLAM"): MobileNetV2 with Efficient Channel Attention in every bottleneck and some
//! bottlenecks removed.
//!
//! Interpretation of the paper, written down once:
//! - **Table 1.** Bottlenecks (t, c, n, s) = (1,16,1,1), (6,24,2,2), (6,32,2,2), (6,64,3,2),
//!   (6,96,2,1), (6,160,2,2), (6,320,1,1), after a 3x3 stride-2 stem of 32 channels, followed by a
//!   1x1 convolution to 1280, global average pooling and an optional 1x1 classifier to k classes.
//!   The table's stride column is misaligned against its own input-size column; the input sizes
//!   (112, 56, 28, 14, 14, 7, 7 at 224²) are taken as authoritative, which gives the strides above
//!   (the same as MobileNetV2's).
//! - **Removed bottlenecks.** Against MobileNetV2 the stages of 32, 64, 96 and 160 channels each
//!   lose one block. Those are stride-1 residual blocks with equal input and output, so which
//!   one goes does not change any shape; we keep the first n of each stage and drop the last,
//!   which is also what [`from_mobilenet_v2`] copies.
//! - **ECA placement** (Fig. 7): after the depthwise convolution (BN, ReLU6) and before the linear
//!   1x1 projection: global average pooling, a 1-D convolution across channels without bias, a
//!   sigmoid, and a channel-wise scale. Residual connection when stride is 1 and in = out.
//! - **ECA kernel size** k = |log2(C)/γ + b/γ| rounded to odd, with γ = 2, b = 1 and C the
//!   bottleneck's hidden (expanded) channel count. "Rounded to odd" follows ECA-Net's code:
//!   truncate to an integer, and add one if it is even ([`eca_kernel_size`]).

use std::collections::HashMap;

use anyhow::{ensure, Context, Result};
use candle_core::Tensor;

use super::{row, Arch, NetworkSpec};

/// Table 1 of the paper: 13 bottlenecks, each with ECA.
pub const EC_MOBILENET: NetworkSpec = NetworkSpec {
    arch: Arch::EcMobileNet,
    stem_channels: 32,
    rows: &[
        row(1, 16, 1, 1),
        row(6, 24, 2, 2),
        row(6, 32, 2, 2),
        row(6, 64, 3, 2),
        row(6, 96, 2, 1),
        row(6, 160, 2, 2),
        row(6, 320, 1, 1),
    ],
    head_channels: 1280,
    eca_kernel: Some(eca_kernel_size),
};

const GAMMA: f64 = 2.0;
const B: f64 = 1.0;

/// ECA's adaptive kernel size for `channels` channels: |log2(C)/γ + b/γ|, made odd.
pub fn eca_kernel_size(channels: usize) -> usize {
    let t = ((channels as f64).log2() / GAMMA + B / GAMMA).abs() as usize;
    if t % 2 == 1 {
        t
    } else {
        t + 1
    }
}

/// ECMobileNet weights from MobileNetV2 weights (inference form, names as in
/// [`super::weights`]): the stem, the head, the classifier and the kept bottlenecks are copied;
/// removed bottlenecks are dropped. Every ECA starts with a zero kernel, whose gate is a constant
/// sigmoid(0) = 0.5; the projection weights are doubled to compensate, so each kept block computes
/// exactly what the MobileNetV2 block did (training then moves the ECA kernels away from zero).
pub fn from_mobilenet_v2(mnv2: &HashMap<String, Tensor>) -> Result<HashMap<String, Tensor>> {
    let source = &super::mobilenetv2::MOBILENET_V2;
    let target = &EC_MOBILENET;
    let mut out = HashMap::new();
    for (name, tensor) in mnv2 {
        if !name.starts_with("blocks.") {
            out.insert(name.clone(), tensor.clone());
        }
    }
    let target_blocks = target.blocks();
    let (mut src_index, mut dst_index) = (0usize, 0usize);
    for (src_row, dst_row) in source.rows.iter().zip(target.rows) {
        ensure!(
            (src_row.t, src_row.c, src_row.s) == (dst_row.t, dst_row.c, dst_row.s) && dst_row.n <= src_row.n,
            "ECMobileNet row {dst_row:?} cannot be taken from MobileNetV2 row {src_row:?}"
        );
        for i in 0..dst_row.n {
            let (src, dst) = (format!("blocks.{}.", src_index + i), format!("blocks.{}.", dst_index + i));
            let mut copied = 0;
            for (name, tensor) in mnv2.iter().filter(|(n, _)| n.starts_with(&src)) {
                let rest = &name[src.len()..];
                // The gate is 0.5 everywhere: doubling the linear projection's weights undoes it.
                let tensor = if rest == "project.weight" { (tensor * 2.0)? } else { tensor.clone() };
                out.insert(format!("{dst}{rest}"), tensor);
                copied += 1;
            }
            ensure!(copied > 0, "MobileNetV2 weights have no tensors for {src}*");
            let k = target_blocks[dst_index + i].eca_kernel.context("ECMobileNet block without ECA")?;
            let device = mnv2.values().next().map(|t| t.device().clone()).unwrap_or(candle_core::Device::Cpu);
            out.insert(format!("{dst}eca.weight"), Tensor::zeros((1, 1, k), candle_core::DType::F32, &device)?);
        }
        src_index += src_row.n;
        dst_index += dst_row.n;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{layers::Mode, Network};
    use candle_core::{DType, Device};
    use candle_nn::{VarBuilder, VarMap};

    #[test]
    fn table_one_strides_follow_the_input_sizes() {
        // Feature-map side after each stage at 224² input: 112, 56, 28, 14, 14, 7, 7.
        let mut size = 112;
        let mut sizes = vec![];
        for row in EC_MOBILENET.rows {
            size /= row.s;
            sizes.push(size);
        }
        assert_eq!(sizes, [112, 56, 28, 14, 14, 7, 7]);
        assert_eq!(EC_MOBILENET.blocks().len(), 13);
    }

    #[test]
    fn eca_kernel_sizes_follow_the_formula() {
        // Hidden channels of the 13 bottlenecks and the kernel |log2(C)/2 + 1/2| made odd.
        let expected = [
            (32, 3),  // log2 32 = 5 -> 3
            (96, 3),  // 6.58 -> 3.79 -> 3
            (144, 5), // 7.17 -> 4.08 -> 4 -> 5
            (144, 5),
            (192, 5), // 7.58 -> 4.29 -> 4 -> 5
            (192, 5),
            (384, 5), // 8.58 -> 4.79 -> 4 -> 5
            (384, 5),
            (384, 5),
            (576, 5), // 9.17 -> 5.08 -> 5
            (576, 5),
            (960, 5), // 9.91 -> 5.45 -> 5
            (960, 5),
        ];
        let blocks = EC_MOBILENET.blocks();
        let got: Vec<(usize, usize)> = blocks.iter().map(|b| (b.hidden, b.eca_kernel.unwrap())).collect();
        assert_eq!(got, expected);
        assert_eq!(eca_kernel_size(4096), 7); // 12/2 + 0.5 = 6.5 -> 6 -> 7
    }

    /// A kept block initialised from MobileNetV2 computes what the MobileNetV2 block did.
    #[test]
    fn eca_initialisation_preserves_a_kept_block() -> Result<()> {
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        // Random MobileNetV2 in training form, then folded to the inference form's names.
        let mnv2 = Network::load(&super::super::mobilenetv2::MOBILENET_V2, vb, None, true)?;
        let tensors = crate::model::weights::inference_tensors(&mnv2)?;
        let ecm_tensors = from_mobilenet_v2(&tensors)?;
        let mnv2 = Network::load(
            &super::super::mobilenetv2::MOBILENET_V2,
            VarBuilder::from_tensors(tensors, DType::F32, &dev),
            None,
            false,
        )?;
        let ecm = Network::load(&EC_MOBILENET, VarBuilder::from_tensors(ecm_tensors, DType::F32, &dev), None, false)?;
        // Block 3 of MobileNetV2 (first of the 32-channel stage) is ECMobileNet's block 3 too;
        // block 10 of MobileNetV2 (first 96) is ECMobileNet's block 8.
        for (m, e) in [(3, 3), (10, 8), (0, 0)] {
            let shape = mnv2.blocks[m].shape;
            let x = Tensor::randn(0f32, 1.0, (2, shape.input, 14, 14), &dev)?;
            for mode in [Mode::Inference, Mode::Reference] {
                let a = mnv2.blocks[m].forward_t(&x, mode)?;
                let b = ecm.blocks[e].forward_t(&x, mode)?;
                let diff = (a - b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
                assert!(diff < 1e-4, "block {m} vs {e} ({mode:?}): {diff}");
            }
            assert!(ecm.blocks[e].eca().is_some());
        }
        Ok(())
    }

    /// Training form: BatchNorm uses batch statistics and every weight, ECA included, gets a gradient.
    #[test]
    fn training_mode_runs_and_backpropagates() -> Result<()> {
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let net = Network::load(&EC_MOBILENET, vb, Some(3), true)?;
        let x = Tensor::randn(0f32, 1.0, (2, 3, 64, 64), &dev)?;
        let logits = net.logits(&x, Mode::Train)?;
        assert_eq!(logits.dims(), &[2, 3]);
        let grads = logits.sqr()?.sum_all()?.backward()?;
        let vars = varmap.data().lock().unwrap();
        for name in [
            "blocks.0.eca.weight",
            "blocks.5.depthwise.weight",
            "blocks.5.depthwise.bn.weight",
            "stem.weight",
            "classifier.weight",
        ] {
            let var = vars.get(name).unwrap_or_else(|| panic!("no variable {name}"));
            let g = grads.get(var.as_tensor()).unwrap_or_else(|| panic!("no gradient for {name}"));
            assert!(g.abs()?.sum_all()?.to_scalar::<f32>()? > 0.0, "zero gradient for {name}");
        }
        // Inference form of the same network gives the same logits as the stock path.
        let folded = crate::model::weights::inference_tensors(&net)?;
        let inference =
            Network::load(&EC_MOBILENET, VarBuilder::from_tensors(folded, DType::F32, &dev), Some(3), false)?;
        // Batch 2 runs ECA on the activations, batch 1 folds the (trained, non-constant) gate
        // into the projection weights: both must agree with the stock path.
        for x in [x.clone(), x.narrow(0, 0, 1)?] {
            let a = inference.logits(&x, Mode::Inference)?;
            let b = net.logits(&x, Mode::Reference)?;
            let diff = (a - b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(diff < 1e-3, "folded vs BatchNorm inference, batch {}: {diff}", x.dim(0)?);
        }
        Ok(())
    }
}
