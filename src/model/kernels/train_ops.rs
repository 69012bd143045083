//! Differentiable CPU ops for [`Mode::Train`](crate::model::layers::Mode::Train), each one candle custom
//! op with a hand-written backward, replacing compositions of stock ops whose backward passes
//! dominated a training step (measured: 580 ms per step of ECMobileNet at 32 px, batch 16, most
//! of it in the backward passes of `clamp`, broadcasts and their gradient accumulation).
//!
//! - [`relu6`]: stock `clamp(0, 6)` is a `maximum` and a `minimum` against broadcast scalars,
//!   whose backward is about thirty full-size tensor ops. Here: one pass each way. At the
//!   measure-zero ties `x = 0` and `x = 6` the gradient is halved, as candle's `maximum` /
//!   `minimum` do, so the op equals the stock one everywhere.
//! - [`pointwise_conv`]: a 1x1 convolution `[B, C, H, W] x [O, C, 1, 1]` as one matrix multiply
//!   per image (`gemm`); backward: `dx_b = Wᵀ dy_b`, `dW = Σ_b dy_b x_bᵀ`.
//! - [`im2col_same`]: the patches of a "SAME"-padded convolution as channels, so that the stem is
//!   `im2col` + [`pointwise_conv`]; backward: the scatter-add of the patches (col2im), skipped
//!   when the input needs no gradient (the image).
//! - [`channel_mean`] and [`channel_scale`]: ECA's pooling and its channel-wise gate without
//!   candle's broadcast ops (whose backward materialises and then reduces full-size tensors).
//!
//! [`crate::model::layers`] uses them only in the training modes; [`Mode::Reference`]
//! (crate::model::layers::Mode::Reference) keeps the stock ops, and the tests here check every op
//! against the stock composition (values and gradients).

use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::depthwise::same_padding;
use super::matmul::{matmul, View};

use super::contiguous_f32 as contiguous;

// ---------------------------------------------------------------------------------------------
// ReLU6

struct Relu6;

impl CustomOp1 for Relu6 {
    fn name(&self) -> &'static str {
        "relu6-train"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = contiguous(s, l, "relu6", "the input")?;
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(4096).zip(x.par_chunks(4096)).for_each(|(y, x)| {
            for (y, &x) in y.iter_mut().zip(x) {
                *y = x.clamp(0.0, 6.0);
            }
        });
        Ok((CpuStorage::F32(out), l.shape().clone()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(x.apply_op2_no_bwd(&grad.contiguous()?, &Relu6Grad)?))
    }
}

/// `(x, dy) -> dx`.
struct Relu6Grad;

impl CustomOp2 for Relu6Grad {
    fn name(&self) -> &'static str {
        "relu6-train-grad"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout, s_g: &CpuStorage, l_g: &Layout) -> Result<(CpuStorage, Shape)> {
        if l_x.shape() != l_g.shape() {
            candle_core::bail!("relu6 gradient {:?} for input {:?}", l_g.shape(), l_x.shape());
        }
        let (x, g) = (contiguous(s_x, l_x, "relu6", "the input")?, contiguous(s_g, l_g, "relu6", "the gradient")?);
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(4096).zip(x.par_chunks(4096).zip(g.par_chunks(4096))).for_each(|(dx, (x, g))| {
            for ((dx, &x), &g) in dx.iter_mut().zip(x).zip(g) {
                *dx = if x > 0.0 && x < 6.0 {
                    g
                } else if x == 0.0 || x == 6.0 {
                    0.5 * g
                } else {
                    0.0
                };
            }
        });
        Ok((CpuStorage::F32(out), l_x.shape().clone()))
    }
}

/// `min(max(x, 0), 6)`, differentiable (see the module doc for the ties).
pub fn relu6(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1(Relu6)
}

// ---------------------------------------------------------------------------------------------
// 1x1 convolution

/// `[B, C, H, W]` and `[O, C, 1, 1]` (or `[O, C]`) as (batch, channels, plane, outputs).
fn pointwise_dims(x: &Shape, w: &Shape) -> Result<(usize, usize, usize, usize)> {
    let (b, c, h, wd) = x.dims4()?;
    let wdims = w.dims();
    let ok = match wdims {
        [_, wc] => *wc == c,
        [_, wc, 1, 1] => *wc == c,
        _ => false,
    };
    if !ok {
        candle_core::bail!("pointwise conv: input {x:?} and weight {w:?} do not agree");
    }
    Ok((b, c, h * wd, wdims[0]))
}

struct PointwiseConv;

impl CustomOp2 for PointwiseConv {
    fn name(&self) -> &'static str {
        "pointwise-conv-train"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout, s_w: &CpuStorage, l_w: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, plane, outputs) = pointwise_dims(l_x.shape(), l_w.shape())?;
        let (x, w) = (
            contiguous(s_x, l_x, "pointwise conv", "the input")?,
            contiguous(s_w, l_w, "pointwise conv", "the weight")?,
        );
        let mut out = vec![0f32; batch * outputs * plane];
        out.par_chunks_mut((outputs * plane).max(1)).zip(x.par_chunks((channels * plane).max(1))).for_each(|(y, x)| {
            matmul(outputs, plane, channels, y, false, View::rows(w, channels), View::rows(x, plane));
        });
        let (_, _, h, wd) = l_x.shape().dims4()?;
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, outputs, h, wd])))
    }

    fn bwd(&self, x: &Tensor, w: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let grad_x = if x.track_op() {
            Some(grad.apply_op2_no_bwd(w, &PointwiseInputGrad { input: x.shape().clone() })?)
        } else {
            None
        };
        let grad_w = x.apply_op2_no_bwd(&grad, &PointwiseWeightGrad { weight: w.shape().clone() })?;
        Ok((grad_x, Some(grad_w)))
    }
}

/// `(dy, w) -> dx`, `dx_b = Wᵀ dy_b`.
struct PointwiseInputGrad {
    input: Shape,
}

impl CustomOp2 for PointwiseInputGrad {
    fn name(&self) -> &'static str {
        "pointwise-conv-train-input-grad"
    }

    fn cpu_fwd(&self, s_g: &CpuStorage, l_g: &Layout, s_w: &CpuStorage, l_w: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, plane, outputs) = pointwise_dims(&self.input, l_w.shape())?;
        if l_g.shape().elem_count() != batch * outputs * plane {
            candle_core::bail!("pointwise conv gradient {:?} for input {:?}", l_g.shape(), self.input);
        }
        let (g, w) = (
            contiguous(s_g, l_g, "pointwise conv", "the gradient")?,
            contiguous(s_w, l_w, "pointwise conv", "the weight")?,
        );
        let mut out = vec![0f32; batch * channels * plane];
        out.par_chunks_mut((channels * plane).max(1)).zip(g.par_chunks((outputs * plane).max(1))).for_each(
            |(dx, g)| {
                matmul(channels, plane, outputs, dx, false, View::transposed(w, channels), View::rows(g, plane));
            },
        );
        Ok((CpuStorage::F32(out), self.input.clone()))
    }
}

/// `(x, dy) -> dW`, `dW = Σ_b dy_b x_bᵀ`.
struct PointwiseWeightGrad {
    weight: Shape,
}

impl CustomOp2 for PointwiseWeightGrad {
    fn name(&self) -> &'static str {
        "pointwise-conv-train-weight-grad"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout, s_g: &CpuStorage, l_g: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, plane, outputs) = pointwise_dims(l_x.shape(), &self.weight)?;
        if l_g.shape().elem_count() != batch * outputs * plane {
            candle_core::bail!("pointwise conv gradient {:?} for input {:?}", l_g.shape(), l_x.shape());
        }
        let (x, g) = (
            contiguous(s_x, l_x, "pointwise conv", "the input")?,
            contiguous(s_g, l_g, "pointwise conv", "the gradient")?,
        );
        let mut out = vec![0f32; outputs * channels];
        // Rows of dW split across threads; each thread sums over the whole batch.
        let threads = rayon::current_num_threads().max(1);
        let rows = outputs.div_ceil(threads).max(1);
        out.par_chunks_mut((rows * channels).max(1)).enumerate().for_each(|(chunk, dw)| {
            let (first, count) = (chunk * rows, dw.len() / channels.max(1));
            for b in 0..batch {
                let g_b = &g[(b * outputs + first) * plane..(b * outputs + first + count) * plane];
                let x_b = &x[b * channels * plane..(b + 1) * channels * plane];
                matmul(count, channels, plane, dw, b > 0, View::rows(g_b, plane), View::transposed(x_b, plane));
            }
        });
        Ok((CpuStorage::F32(out), self.weight.clone()))
    }
}

/// A 1x1 convolution of `x` `[B, C, H, W]` by `weight` `[O, C, 1, 1]` (or `[O, C]`), no bias:
/// `[B, O, H, W]`, differentiable with respect to both.
pub fn pointwise_conv(x: &Tensor, weight: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op2(&weight.contiguous()?, PointwiseConv)
}

// ---------------------------------------------------------------------------------------------
// im2col

/// Output size and the padding before the first row / column of a "SAME" convolution.
#[derive(Clone, Copy, Debug)]
struct Patches {
    channels: usize,
    height: usize,
    width: usize,
    kh: usize,
    kw: usize,
    stride: usize,
    oh: usize,
    ow: usize,
    pad_top: usize,
    pad_left: usize,
}

impl Patches {
    fn new(channels: usize, height: usize, width: usize, kh: usize, kw: usize, stride: usize) -> Self {
        let (oh, pad_top, _) = same_padding(height, kh, stride);
        let (ow, pad_left, _) = same_padding(width, kw, stride);
        Patches { channels, height, width, kh, kw, stride, oh, ow, pad_top, pad_left }
    }

    /// Calls `f(row, out_index, in_index)` for every patch element inside the image, where
    /// `row = (c * kh + ky) * kw + kx` is the patch channel and the indices are plane offsets.
    #[inline(always)]
    fn for_each(&self, row: usize, mut f: impl FnMut(usize, usize)) {
        let (kx, ky) = (row % self.kw, (row / self.kw) % self.kh);
        for oy in 0..self.oh {
            let iy = (oy * self.stride + ky) as isize - self.pad_top as isize;
            if iy < 0 || iy >= self.height as isize {
                continue;
            }
            for ox in 0..self.ow {
                let ix = (ox * self.stride + kx) as isize - self.pad_left as isize;
                if ix >= 0 && ix < self.width as isize {
                    f(oy * self.ow + ox, iy as usize * self.width + ix as usize);
                }
            }
        }
    }

    fn rows(&self) -> usize {
        self.channels * self.kh * self.kw
    }
}

struct Im2Col {
    kh: usize,
    kw: usize,
    stride: usize,
}

impl CustomOp1 for Im2Col {
    fn name(&self) -> &'static str {
        "im2col-same-train"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, height, width) = l.shape().dims4()?;
        let x = contiguous(s, l, "im2col", "the input")?;
        let p = Patches::new(channels, height, width, self.kh, self.kw, self.stride);
        let (plane_in, plane_out) = (height * width, p.oh * p.ow);
        let mut out = vec![0f32; batch * p.rows() * plane_out];
        out.par_chunks_mut(plane_out.max(1)).enumerate().for_each(|(index, col)| {
            let (b, row) = (index / p.rows(), index % p.rows());
            let c = row / (p.kh * p.kw);
            let src = &x[(b * channels + c) * plane_in..(b * channels + c + 1) * plane_in];
            p.for_each(row, |o, i| col[o] = src[i]);
        });
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, p.rows(), p.oh, p.ow])))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        if !x.track_op() {
            return Ok(None);
        }
        let (_, channels, height, width) = x.dims4()?;
        let patches = Patches::new(channels, height, width, self.kh, self.kw, self.stride);
        Ok(Some(grad.contiguous()?.apply_op1_no_bwd(&Col2Im { patches })?))
    }
}

/// The adjoint of [`Im2Col`]: every patch element added back to the pixel it came from.
struct Col2Im {
    patches: Patches,
}

impl CustomOp1 for Col2Im {
    fn name(&self) -> &'static str {
        "col2im-same-train"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let p = self.patches;
        let (batch, rows, oh, ow) = l.shape().dims4()?;
        if (rows, oh, ow) != (p.rows(), p.oh, p.ow) {
            candle_core::bail!("col2im: {:?} are not the patches of {:?}", l.shape(), p);
        }
        let cols = contiguous(s, l, "col2im", "the gradient")?;
        let (plane_in, plane_out, taps) = (p.height * p.width, oh * ow, p.kh * p.kw);
        let mut out = vec![0f32; batch * p.channels * plane_in];
        out.par_chunks_mut(plane_in.max(1)).enumerate().for_each(|(index, dx)| {
            let (b, c) = (index / p.channels, index % p.channels);
            for tap in 0..taps {
                let row = c * taps + tap;
                let col = &cols[(b * rows + row) * plane_out..(b * rows + row + 1) * plane_out];
                p.for_each(row, |o, i| dx[i] += col[o]);
            }
        });
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, p.channels, p.height, p.width])))
    }
}

/// The `kh x kw` patches of `x` `[B, C, H, W]` under "SAME" padding and `stride`, as
/// `[B, C * kh * kw, OH, OW]` (patch channel `(c * kh + ky) * kw + kx`, the order of an OIHW
/// weight's flattened `I, H, W`), differentiable.
pub fn im2col_same(x: &Tensor, kh: usize, kw: usize, stride: usize) -> Result<Tensor> {
    if stride == 0 || kh == 0 || kw == 0 {
        candle_core::bail!("im2col: kernel {kh}x{kw}, stride {stride}");
    }
    x.contiguous()?.apply_op1(Im2Col { kh, kw, stride })
}

/// A full "SAME" convolution of `x` by `weight` `[O, C, kh, kw]` as [`im2col_same`] +
/// [`pointwise_conv`], no bias, differentiable.
pub fn conv_same(x: &Tensor, weight: &Tensor, stride: usize) -> Result<Tensor> {
    let (out, inp, kh, kw) = weight.dims4()?;
    if kh == 1 && kw == 1 && stride == 1 {
        return pointwise_conv(x, weight);
    }
    pointwise_conv(&im2col_same(x, kh, kw, stride)?, &weight.reshape((out, inp * kh * kw))?)
}

// ---------------------------------------------------------------------------------------------
// ECA's pooling and channel scale

/// `x [B, C, H, W] -> [B, C]`: the mean of each channel plane.
struct ChannelMean;

impl CustomOp1 for ChannelMean {
    fn name(&self) -> &'static str {
        "channel-mean-train"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, h, w) = l.shape().dims4()?;
        let x = contiguous(s, l, "channel mean", "the input")?;
        let plane = (h * w).max(1);
        let out: Vec<f32> =
            x.par_chunks(plane).map(|p| (p.iter().map(|&v| v as f64).sum::<f64>() / plane as f64) as f32).collect();
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, channels])))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let (_, _, h, w) = x.dims4()?;
        Ok(Some(grad.contiguous()?.apply_op1_no_bwd(&ChannelMeanGrad { height: h, width: w })?))
    }
}

/// `dy [B, C] -> dx [B, C, H, W]`, each plane filled with `dy / (H W)`.
struct ChannelMeanGrad {
    height: usize,
    width: usize,
}

impl CustomOp1 for ChannelMeanGrad {
    fn name(&self) -> &'static str {
        "channel-mean-train-grad"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels) = l.shape().dims2()?;
        let g = contiguous(s, l, "channel mean", "the gradient")?;
        let plane = self.height * self.width;
        let mut out = vec![0f32; batch * channels * plane];
        out.par_chunks_mut(plane.max(1)).zip(g.par_iter()).for_each(|(dx, &g)| dx.fill(g / plane as f32));
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, channels, self.height, self.width])))
    }
}

/// The mean of every channel plane of `x` `[B, C, H, W]`: `[B, C]`, differentiable.
pub fn channel_mean(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1(ChannelMean)
}

/// `(x [B, C, H, W], gate [B, C]) -> x * gate` per channel plane.
struct ChannelScale;

fn scale_dims(x: &Shape, gate: &Shape) -> Result<(usize, usize)> {
    let (b, c, h, w) = x.dims4()?;
    if gate.elem_count() != b * c || gate.dims().first() != Some(&b) {
        candle_core::bail!("channel scale: gate {gate:?} for input {x:?}");
    }
    Ok((b * c, h * w))
}

impl CustomOp2 for ChannelScale {
    fn name(&self) -> &'static str {
        "channel-scale-train"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout, s_g: &CpuStorage, l_g: &Layout) -> Result<(CpuStorage, Shape)> {
        let (_, plane) = scale_dims(l_x.shape(), l_g.shape())?;
        let (x, gate) =
            (contiguous(s_x, l_x, "channel scale", "the input")?, contiguous(s_g, l_g, "channel scale", "the gate")?);
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(plane.max(1)).zip(x.par_chunks(plane.max(1))).zip(gate.par_iter()).for_each(
            |((y, x), &g)| {
                for (y, &x) in y.iter_mut().zip(x) {
                    *y = x * g;
                }
            },
        );
        Ok((CpuStorage::F32(out), l_x.shape().clone()))
    }

    fn bwd(&self, x: &Tensor, gate: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let grad_x = grad.apply_op2_no_bwd(gate, &ChannelScale)?;
        let grad_gate = x.apply_op2_no_bwd(&grad, &ChannelScaleGateGrad)?.reshape(gate.shape())?;
        Ok((Some(grad_x), Some(grad_gate)))
    }
}

/// `(x, dy) -> dgate [B, C]`: `Σ_plane x dy`.
struct ChannelScaleGateGrad;

impl CustomOp2 for ChannelScaleGateGrad {
    fn name(&self) -> &'static str {
        "channel-scale-train-gate-grad"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout, s_d: &CpuStorage, l_d: &Layout) -> Result<(CpuStorage, Shape)> {
        if l_x.shape() != l_d.shape() {
            candle_core::bail!("channel scale gradient {:?} for input {:?}", l_d.shape(), l_x.shape());
        }
        let (b, c, h, w) = l_x.shape().dims4()?;
        let (x, d) = (
            contiguous(s_x, l_x, "channel scale", "the input")?,
            contiguous(s_d, l_d, "channel scale", "the gradient")?,
        );
        let plane = (h * w).max(1);
        let out: Vec<f32> = x
            .par_chunks(plane)
            .zip(d.par_chunks(plane))
            .map(|(x, d)| x.iter().zip(d).map(|(&x, &d)| x as f64 * d as f64).sum::<f64>() as f32)
            .collect();
        Ok((CpuStorage::F32(out), Shape::from_dims(&[b, c])))
    }
}

/// `x` `[B, C, H, W]` times `gate` (`B x C` values, e.g. `[B, C, 1, 1]`) per channel plane,
/// differentiable with respect to both.
pub fn channel_scale(x: &Tensor, gate: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op2(&gate.contiguous()?, ChannelScale)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::kernels::depthwise::pad_same;
    use candle_core::{Device, Var};

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    /// Compares `ours(vars)` with `stock(vars)`: values, and gradients of `Σ probe · out` for each var.
    fn check_against_stock(
        what: &str,
        vars: &[&Var],
        ours: impl Fn(&[Tensor]) -> Result<Tensor>,
        stock: impl Fn(&[Tensor]) -> Result<Tensor>,
    ) -> Result<()> {
        let args: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
        let (a, b) = (ours(&args)?, stock(&args)?);
        assert_eq!(a.dims(), b.dims(), "{what}: shapes");
        let d = max_abs_diff(&a, &b);
        assert!(d < 1e-4, "{what}: forward max diff {d}");
        let probe = Tensor::randn(0f32, 1.0, a.shape(), &Device::Cpu)?;
        let (ga, gb) = ((&a * &probe)?.sum_all()?.backward()?, (&b * &probe)?.sum_all()?.backward()?);
        for (i, v) in vars.iter().enumerate() {
            let (x, y) = (ga.get(v.as_tensor()).expect("our gradient"), gb.get(v.as_tensor()).expect("stock gradient"));
            assert_eq!(x.dims(), y.dims(), "{what}: gradient {i} shapes");
            let scale = y.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?.max(1.0);
            let d = max_abs_diff(x, y);
            assert!(d < 1e-4 * scale, "{what}: gradient {i} max diff {d} (scale {scale})");
        }
        Ok(())
    }

    #[test]
    fn relu6_equals_stock_clamp_including_ties() -> Result<()> {
        let dev = Device::Cpu;
        let mut values = Tensor::randn(0f32, 5.0, 4 * 3 * 5 * 7, &dev)?.to_vec1::<f32>()?;
        // Exact ties, where candle halves the gradient.
        values[0] = 0.0;
        values[1] = 6.0;
        let x = Var::from_tensor(&Tensor::from_vec(values, (4, 3, 5, 7), &dev)?)?;
        check_against_stock("relu6", &[&x], |a| relu6(&a[0]), |a| a[0].clamp(0f32, 6f32))
    }

    #[test]
    fn pointwise_conv_equals_stock_conv2d() -> Result<()> {
        let dev = Device::Cpu;
        for (b, c, o, h, w) in [(3, 5, 7, 4, 6), (2, 16, 3, 1, 1), (1, 4, 9, 3, 3), (4, 24, 40, 8, 8)] {
            let x = Var::randn(0f32, 1.0, (b, c, h, w), &dev)?;
            let weight = Var::randn(0f32, 1.0, (o, c, 1, 1), &dev)?;
            check_against_stock(
                &format!("pointwise {b}x{c}x{h}x{w} -> {o}"),
                &[&x, &weight],
                |a| pointwise_conv(&a[0], &a[1]),
                |a| a[0].conv2d(&a[1], 0, 1, 1, 1),
            )?;
        }
        Ok(())
    }

    #[test]
    fn same_convolution_equals_padded_stock_conv2d() -> Result<()> {
        let dev = Device::Cpu;
        for (h, w, k, stride) in [(8, 8, 3, 2), (7, 9, 3, 2), (6, 5, 3, 1), (9, 7, 5, 2), (2, 3, 3, 2)] {
            let x = Var::randn(0f32, 1.0, (3, 3, h, w), &dev)?;
            let weight = Var::randn(0f32, 1.0, (8, 3, k, k), &dev)?;
            let stock = |a: &[Tensor]| pad_same(&a[0], h, w, k, k, stride)?.conv2d(&a[1], 0, stride, 1, 1);
            check_against_stock(
                &format!("conv {h}x{w} k{k} s{stride}"),
                &[&x, &weight],
                |a| conv_same(&a[0], &a[1], stride),
                stock,
            )?;
        }
        // The image needs no gradient: the patches' backward is skipped, the weight's is not.
        let x = Tensor::randn(0f32, 1.0, (2, 3, 8, 8), &dev)?;
        let weight = Var::randn(0f32, 1.0, (4, 3, 3, 3), &dev)?;
        let grads = conv_same(&x, &weight, 2)?.sum_all()?.backward()?;
        assert!(grads.get(&x).is_none());
        assert!(grads.get(weight.as_tensor()).is_some());
        Ok(())
    }

    #[test]
    fn channel_mean_and_scale_equal_stock_broadcasts() -> Result<()> {
        let dev = Device::Cpu;
        for (b, c, h, w) in [(3, 5, 4, 6), (2, 7, 1, 1)] {
            let x = Var::randn(0f32, 1.0, (b, c, h, w), &dev)?;
            let gate = Var::randn(0f32, 1.0, (b, c, 1, 1), &dev)?;
            check_against_stock("channel mean", &[&x], |a| channel_mean(&a[0]), |a| a[0].mean((2, 3)))?;
            check_against_stock(
                "channel scale",
                &[&x, &gate],
                |a| channel_scale(&a[0], &a[1]),
                |a| a[0].broadcast_mul(&a[1]),
            )?;
        }
        Ok(())
    }

    #[test]
    fn mismatched_shapes_are_errors() -> Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::zeros((2, 4, 3, 3), candle_core::DType::F32, &dev)?;
        assert!(pointwise_conv(&x, &Tensor::zeros((5, 3, 1, 1), candle_core::DType::F32, &dev)?).is_err());
        assert!(channel_scale(&x, &Tensor::zeros((2, 3, 1, 1), candle_core::DType::F32, &dev)?).is_err());
        assert!(im2col_same(&x, 3, 3, 0).is_err());
        Ok(())
    }
}
