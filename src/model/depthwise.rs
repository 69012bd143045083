//! Fast CPU kernels as candle custom ops, so the model stays a candle model:
//!
//! - [`depthwise_conv`]: depthwise 2-D convolution with TensorFlow "SAME" padding (possibly
//!   asymmetric: for stride 2 the extra pixel goes bottom/right), fused bias and optional ReLU6.
//!   candle's grouped convolution runs one tiny convolution per channel, which made depthwise
//!   layers ~80% of MobileNetV2's time; this kernel walks each channel plane directly.
//! - [`bias_activation_`]: adds a per-channel bias and applies the activation in place (fused
//!   epilogue for the 1x1 convolutions, which are plain matrix multiplies).
//!
//! Both are inference-only (no backward); training uses stock candle ops, and the tests check
//! that the two agree. The per-plane kernel is also what [`super::fused`]'s whole-bottleneck op
//! runs on each expanded channel.

use candle_core::{CpuStorage, CustomOp3, InplaceOp2, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// TensorFlow "SAME" padding for one spatial axis: output size and padding before/after.
pub fn same_padding(input: usize, kernel: usize, stride: usize) -> (usize, usize, usize) {
    let out = input.div_ceil(stride);
    let total = ((out - 1) * stride + kernel).saturating_sub(input);
    (out, total / 2, total - total / 2)
}

/// Fused activation after a convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    Identity,
    Relu6,
}

impl Activation {
    #[inline(always)]
    fn apply(self, row: &mut [f32]) {
        if self == Activation::Relu6 {
            for v in row {
                *v = v.clamp(0.0, 6.0);
            }
        }
    }

    /// The same activation with stock candle ops (reference and training path).
    pub fn forward(self, x: &Tensor) -> Result<Tensor> {
        match self {
            Activation::Identity => Ok(x.clone()),
            Activation::Relu6 => x.clamp(0f32, 6f32),
        }
    }
}

struct DepthwiseConv {
    stride: usize,
    activation: Activation,
}

fn contiguous<'a>(storage: &'a CpuStorage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    let (start, end) = layout
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg(format!("depthwise conv: {what} must be contiguous")))?;
    Ok(&storage.as_slice::<f32>()?[start..end])
}

impl CustomOp3 for DepthwiseConv {
    fn name(&self) -> &'static str {
        "depthwise-conv2d-same"
    }

    fn cpu_fwd(
        &self,
        s_in: &CpuStorage,
        l_in: &Layout,
        s_w: &CpuStorage,
        l_w: &Layout,
        s_b: &CpuStorage,
        l_b: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, height, width) = l_in.shape().dims4()?;
        let (wc, one, kh, kw) = l_w.shape().dims4()?;
        if wc != channels || one != 1 || l_b.shape().elem_count() != channels {
            candle_core::bail!(
                "depthwise conv: input {:?}, weight {:?}, bias {:?} do not agree",
                l_in.shape(),
                l_w.shape(),
                l_b.shape()
            );
        }
        let input = contiguous(s_in, l_in, "input")?;
        let weight = contiguous(s_w, l_w, "weight")?;
        let bias = contiguous(s_b, l_b, "bias")?;
        let s = self.stride;
        let (oh, pad_top, _) = same_padding(height, kh, s);
        let (ow, pad_left, _) = same_padding(width, kw, s);
        let mut out = vec![0f32; batch * channels * oh * ow];
        let geometry = PlaneGeometry { height, width, kh, kw, stride: s, ow, pad_top, pad_left };
        let activation = self.activation;
        out.par_chunks_mut(oh * ow).enumerate().for_each(|(plane, out_plane)| {
            let c = plane % channels;
            let src = &input[plane * height * width..(plane + 1) * height * width];
            let w = &weight[c * kh * kw..(c + 1) * kh * kw];
            convolve_plane(&geometry, src, w, bias[c], activation, out_plane);
        });
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, channels, oh, ow])))
    }
}

/// Sizes of one channel plane's convolution.
pub(crate) struct PlaneGeometry {
    pub height: usize,
    pub width: usize,
    pub kh: usize,
    pub kw: usize,
    pub stride: usize,
    pub ow: usize,
    pub pad_top: usize,
    pub pad_left: usize,
}

/// Convolves one channel plane, choosing the widest SIMD the CPU has at run time: the same
/// code compiled for AVX2+FMA, or for the baseline.
pub(crate) fn convolve_plane(g: &PlaneGeometry, src: &[f32], w: &[f32], bias: f32, act: Activation, out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { convolve_plane_avx2(g, src, w, bias, act, out) };
        }
    }
    convolve_plane_generic(g, src, w, bias, act, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn convolve_plane_avx2(g: &PlaneGeometry, src: &[f32], w: &[f32], bias: f32, act: Activation, out: &mut [f32]) {
    convolve_plane_generic(g, src, w, bias, act, out)
}

#[inline(always)]
fn convolve_plane_generic(g: &PlaneGeometry, src: &[f32], w: &[f32], bias: f32, act: Activation, out: &mut [f32]) {
    if g.kh == 3 && g.kw == 3 {
        return convolve_plane_3x3(g, src, w, bias, act, out);
    }
    let s = g.stride;
    for (oy, out_row) in out.chunks_exact_mut(g.ow).enumerate() {
        out_row.fill(bias);
        for ky in 0..g.kh {
            let iy = (oy * s + ky) as isize - g.pad_top as isize;
            if iy < 0 || iy >= g.height as isize {
                continue;
            }
            let in_row = &src[iy as usize * g.width..(iy as usize + 1) * g.width];
            for kx in 0..g.kw {
                let wv = w[ky * g.kw + kx];
                // Output columns whose input column ox*s + kx - pad_left lies inside the row.
                let first = g.pad_left.saturating_sub(kx).div_ceil(s);
                let last = (g.width + g.pad_left).saturating_sub(kx).div_ceil(s).min(g.ow);
                if first >= last {
                    continue;
                }
                let offset = first * s + kx - g.pad_left;
                for (i, o) in out_row[first..last].iter_mut().enumerate() {
                    *o += wv * in_row[offset + i * s];
                }
            }
        }
        act.apply(out_row);
    }
}

/// The 3x3 case (all of MobileNetV2): each output is computed in one pass from three input rows,
/// rows outside the image read as a zero row; interior columns run without bounds tests.
#[inline(always)]
fn convolve_plane_3x3(g: &PlaneGeometry, src: &[f32], w: &[f32], bias: f32, act: Activation, out: &mut [f32]) {
    let (s, width) = (g.stride, g.width);
    let zero = vec![0f32; width];
    let row = |iy: isize| -> &[f32] {
        if iy < 0 || iy >= g.height as isize {
            &zero
        } else {
            &src[iy as usize * width..(iy as usize + 1) * width]
        }
    };
    let tap = |r: &[f32], ix: isize| -> f32 {
        if ix < 0 || ix >= width as isize {
            0.0
        } else {
            r[ix as usize]
        }
    };
    // Interior output columns: ox*s - pad_left >= 0 and ox*s - pad_left + 2 < width.
    let lo = g.pad_left.div_ceil(s).min(g.ow);
    let hi = if width + g.pad_left >= 3 { ((width + g.pad_left - 3) / s + 1).clamp(lo, g.ow) } else { lo };
    let mut split = Vec::new();
    for (oy, out_row) in out.chunks_exact_mut(g.ow).enumerate() {
        let top = (oy * s) as isize - g.pad_top as isize;
        let (r0, r1, r2) = (row(top), row(top + 1), row(top + 2));
        let edge = |ox: usize| {
            let ix = (ox * s) as isize - g.pad_left as isize;
            let mut acc = bias;
            for (k, r) in [r0, r1, r2].into_iter().enumerate() {
                acc += w[3 * k] * tap(r, ix) + w[3 * k + 1] * tap(r, ix + 1) + w[3 * k + 2] * tap(r, ix + 2);
            }
            acc
        };
        for ox in (0..lo).chain(hi..g.ow) {
            out_row[ox] = edge(ox);
        }
        if hi > lo {
            let start = lo * s - g.pad_left;
            let span = (hi - lo - 1) * s + 3;
            let (a, b, c) = (&r0[start..start + span], &r1[start..start + span], &r2[start..start + span]);
            let dst = &mut out_row[lo..hi];
            if s == 1 {
                tap_sum(dst, bias, w, [a, &a[1..], &a[2..], b, &b[1..], &b[2..], c, &c[1..], &c[2..]]);
            } else if s == 2 {
                // Even and odd columns split once, so that every tap is a unit-stride load
                // (vectorisable) instead of a gather.
                let n = hi - lo;
                split.resize(3 * (2 * n + 1), 0.0);
                let (even, odd) = split.split_at_mut(3 * (n + 1));
                for (k, r) in [a, b, c].into_iter().enumerate() {
                    for i in 0..n {
                        even[k * (n + 1) + i] = r[2 * i];
                        odd[k * n + i] = r[2 * i + 1];
                    }
                    even[k * (n + 1) + n] = r[2 * n];
                }
                let (ea, eb, ec) = (&even[..n + 1], &even[n + 1..2 * n + 2], &even[2 * n + 2..]);
                let (oa, ob, oc) = (&odd[..n], &odd[n..2 * n], &odd[2 * n..3 * n]);
                tap_sum(dst, bias, w, [ea, oa, &ea[1..], eb, ob, &eb[1..], ec, oc, &ec[1..]]);
            } else {
                for (i, o) in dst.iter_mut().enumerate() {
                    let j = i * s;
                    *o = bias
                        + w[0] * a[j] + w[1] * a[j + 1] + w[2] * a[j + 2]
                        + w[3] * b[j] + w[4] * b[j + 1] + w[5] * b[j + 2]
                        + w[6] * c[j] + w[7] * c[j + 1] + w[8] * c[j + 2];
                }
            }
        }
        act.apply(out_row);
    }
}

/// `dst[i] = bias + Σ_k w[k] · taps[k][i]` over a row segment. Every tap is cut to `dst`'s length
/// first, so the loop runs without bounds checks and vectorises (one FMA per tap and lane).
#[inline(always)]
fn tap_sum(dst: &mut [f32], bias: f32, w: &[f32], taps: [&[f32]; 9]) {
    let n = dst.len();
    let w: &[f32; 9] = w.try_into().expect("3x3 taps");
    let [t0, t1, t2, t3, t4, t5, t6, t7, t8] = taps;
    let (t0, t1, t2, t3, t4, t5, t6, t7, t8) =
        (&t0[..n], &t1[..n], &t2[..n], &t3[..n], &t4[..n], &t5[..n], &t6[..n], &t7[..n], &t8[..n]);
    for i in 0..n {
        let mut acc = t0[i].mul_add(w[0], bias);
        acc = t1[i].mul_add(w[1], acc);
        acc = t2[i].mul_add(w[2], acc);
        acc = t3[i].mul_add(w[3], acc);
        acc = t4[i].mul_add(w[4], acc);
        acc = t5[i].mul_add(w[5], acc);
        acc = t6[i].mul_add(w[6], acc);
        acc = t7[i].mul_add(w[7], acc);
        dst[i] = t8[i].mul_add(w[8], acc);
    }
}

/// Depthwise convolution (`weight` `[C, 1, kh, kw]`, `bias` `[C]`) of `x` `[B, C, H, W]` with
/// "SAME" padding, fused bias and activation, by the direct kernel.
pub fn depthwise_conv(x: &Tensor, weight: &Tensor, bias: &Tensor, stride: usize, activation: Activation) -> Result<Tensor> {
    x.contiguous()?.apply_op3_no_bwd(&weight.contiguous()?, &bias.contiguous()?, &DepthwiseConv { stride, activation })
}

/// The same convolution with stock candle ops (explicit asymmetric zero padding, then a
/// grouped convolution). Differentiable; the reference for tests and the training path.
pub fn depthwise_conv_reference(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>, stride: usize) -> Result<Tensor> {
    let (_, channels, height, width) = x.dims4()?;
    let (_, _, kh, kw) = weight.dims4()?;
    let x = pad_same(x, height, width, kh, kw, stride)?;
    let y = x.conv2d(weight, 0, stride, 1, channels)?;
    match bias {
        Some(b) => y.broadcast_add(&b.reshape((1, channels, 1, 1))?),
        None => Ok(y),
    }
}

/// Zero-pads `x` `[B, C, H, W]` for a "SAME" convolution with the given kernel and stride.
pub fn pad_same(x: &Tensor, height: usize, width: usize, kh: usize, kw: usize, stride: usize) -> Result<Tensor> {
    let (_, top, bottom) = same_padding(height, kh, stride);
    let (_, left, right) = same_padding(width, kw, stride);
    if top + bottom + left + right == 0 {
        return Ok(x.clone());
    }
    x.pad_with_zeros(2, top, bottom)?.pad_with_zeros(3, left, right)
}

struct BiasActivation(Activation);

impl InplaceOp2 for BiasActivation {
    fn name(&self) -> &'static str {
        "bias-activation"
    }

    fn cpu_fwd(&self, s_x: &mut CpuStorage, l_x: &Layout, s_b: &CpuStorage, l_b: &Layout) -> Result<()> {
        let dims = l_x.shape().dims();
        if dims.len() < 2 {
            candle_core::bail!("bias-activation: input must be [B, C, ...], got {:?}", l_x.shape());
        }
        let channels = dims[1];
        let plane: usize = dims[2..].iter().product();
        let (start, end) = l_x
            .contiguous_offsets()
            .ok_or_else(|| candle_core::Error::Msg("bias-activation: input must be contiguous".into()))?;
        let bias = contiguous(s_b, l_b, "bias")?;
        if bias.len() != channels {
            candle_core::bail!("bias-activation: {} biases for {channels} channels", bias.len());
        }
        let CpuStorage::F32(x) = s_x else { candle_core::bail!("bias-activation: f32 only") };
        let act = self.0;
        x[start..end].par_chunks_mut(plane.max(1)).enumerate().for_each(|(i, row)| {
            let b = bias[i % channels];
            for v in row.iter_mut() {
                *v += b;
            }
            act.apply(row);
        });
        Ok(())
    }
}

/// Adds `bias` `[C]` to the contiguous `x` `[B, C, ...]` and applies `activation`, in place.
/// `x` must be a fresh tensor that nothing else shares (e.g. a matmul output).
pub fn bias_activation_(x: &Tensor, bias: &Tensor, activation: Activation) -> Result<()> {
    x.inplace_op2(bias, &BiasActivation(activation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn same_padding_matches_tensorflow() {
        assert_eq!(same_padding(224, 3, 2), (112, 0, 1));
        assert_eq!(same_padding(112, 3, 1), (112, 1, 1));
        assert_eq!(same_padding(7, 3, 2), (4, 1, 1));
        assert_eq!(same_padding(7, 1, 1), (7, 0, 0));
        assert_eq!(same_padding(15, 5, 2), (8, 2, 2));
    }

    #[test]
    fn depthwise_kernel_equals_stock_grouped_conv() -> Result<()> {
        let dev = Device::Cpu;
        // Even and odd sizes, kernels 3 and 5, strides 1 and 2, batch 2.
        for &(h, w, k, stride) in &[(14, 14, 3, 1), (14, 14, 3, 2), (15, 9, 3, 2), (11, 12, 5, 1), (8, 7, 5, 2), (2, 3, 3, 2), (29, 31, 3, 2), (30, 28, 3, 2)] {
            let channels = 7;
            let x = Tensor::randn(0f32, 1.0, (2, channels, h, w), &dev)?;
            let weight = Tensor::randn(0f32, 1.0, (channels, 1, k, k), &dev)?;
            let bias = Tensor::randn(0f32, 1.0, channels, &dev)?;
            let fast = depthwise_conv(&x, &weight, &bias, stride, Activation::Identity)?;
            let reference = depthwise_conv_reference(&x, &weight, Some(&bias), stride)?;
            assert_eq!(fast.dims(), reference.dims());
            let diff = (fast - &reference)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(diff < 1e-4, "h={h} w={w} k={k} s={stride}: max diff {diff}");
            let fast_relu6 = depthwise_conv(&x, &weight, &bias, stride, Activation::Relu6)?;
            let diff = (fast_relu6 - reference.clamp(0f32, 6f32)?)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(diff < 1e-4, "relu6 h={h} w={w} k={k} s={stride}: max diff {diff}");
        }
        Ok(())
    }

    #[test]
    fn bias_activation_in_place_matches_stock_ops() -> Result<()> {
        let dev = Device::Cpu;
        let x = (Tensor::randn(0f32, 4.0, (2, 5, 3, 4), &dev)? * 1.0)?;
        let bias = Tensor::randn(0f32, 1.0, 5, &dev)?;
        let expected = x.broadcast_add(&bias.reshape((1, 5, 1, 1))?)?.clamp(0f32, 6f32)?;
        let y = x.copy()?;
        bias_activation_(&y, &bias, Activation::Relu6)?;
        let diff = (y - expected)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert!(diff < 1e-6);
        Ok(())
    }
}
