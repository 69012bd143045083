//! A differentiable depthwise convolution for training: a candle custom op whose backward is two
//! more custom ops, so training no longer runs candle's grouped convolution (one tiny im2col +
//! matmul per channel, forward and backward).
//!
//! - [`depthwise_conv_train`]: `x` `[B, C, H, W]`, `weight` `[C, 1, kh, kw]`, TensorFlow "SAME"
//!   padding ([`same_padding`]: for stride 2 the extra pixel goes bottom/right), any stride, no bias
//!   and no activation (in training BatchNorm and the activation follow as stock ops).
//! - Its gradient with respect to the input is the transposed depthwise convolution of the output
//!   gradient (each output gradient scattered back through the kernel taps); with respect to the
//!   weight it is, per channel and tap, the correlation of the input with the output gradient,
//!   summed over the batch.
//!
//! All three walk the same list of row spans ([`Geometry::spans`]): one output row
//! segment, the input row segment it reads (every `stride`-th pixel), and the kernel tap. Work
//! is split over batch x channel planes with rayon. Tests check the gradients by finite
//! differences and against the gradients of candle's grouped convolution.

use candle_core::{CpuStorage, CustomOp2, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::depthwise::same_padding;

/// Sizes of one channel plane's "SAME" convolution.
#[derive(Clone, Copy, Debug)]
struct Geometry {
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

impl Geometry {
    fn new(height: usize, width: usize, kh: usize, kw: usize, stride: usize) -> Self {
        let (oh, pad_top, _) = same_padding(height, kh, stride);
        let (ow, pad_left, _) = same_padding(width, kw, stride);
        Geometry { height, width, kh, kw, stride, oh, ow, pad_top, pad_left }
    }

    /// Every run of outputs `out..out + len` (plane offsets) that reads input pixels `input,
    /// input + stride, ...` through kernel tap `tap` (`ky * kw + kx`); taps that fall into the
    /// padding are skipped. The list is the same for every plane, so each op makes it once.
    fn spans(&self) -> Vec<Span> {
        let s = self.stride;
        let mut spans = Vec::new();
        for oy in 0..self.oh {
            for ky in 0..self.kh {
                let iy = (oy * s + ky) as isize - self.pad_top as isize;
                if iy < 0 || iy >= self.height as isize {
                    continue;
                }
                for kx in 0..self.kw {
                    // Output columns whose input column ox*s + kx - pad_left lies inside the row.
                    let first = self.pad_left.saturating_sub(kx).div_ceil(s);
                    let last = (self.width + self.pad_left).saturating_sub(kx).div_ceil(s).min(self.ow);
                    if first >= last {
                        continue;
                    }
                    let len = last - first;
                    let input = iy as usize * self.width + first * s + kx - self.pad_left;
                    spans.push(Span {
                        out: oy * self.ow + first..oy * self.ow + last,
                        input: input..input + (len - 1) * s + 1,
                        tap: ky * self.kw + kx,
                    });
                }
            }
        }
        spans
    }
}

/// One run of a plane's outputs, the input pixels it reads (every `stride`-th of `input`) and
/// the kernel tap between them.
struct Span {
    out: std::ops::Range<usize>,
    input: std::ops::Range<usize>,
    tap: usize,
}

fn contiguous<'a>(storage: &'a CpuStorage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    super::contiguous_f32(storage, layout, "depthwise conv (training)", what)
}

/// The forward op: `(x, weight) -> y`.
struct DepthwiseForward {
    stride: usize,
}

impl CustomOp2 for DepthwiseForward {
    fn name(&self) -> &'static str {
        "depthwise-conv2d-same-train"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout, s_w: &CpuStorage, l_w: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, height, width) = l_x.shape().dims4()?;
        let (wc, one, kh, kw) = l_w.shape().dims4()?;
        if wc != channels || one != 1 {
            candle_core::bail!("depthwise conv: input {:?} and weight {:?} do not agree", l_x.shape(), l_w.shape());
        }
        let (x, w) = (contiguous(s_x, l_x, "input")?, contiguous(s_w, l_w, "weight")?);
        let g = Geometry::new(height, width, kh, kw, self.stride);
        let s = g.stride;
        let mut out = vec![0f32; batch * channels * g.oh * g.ow];
        let spans = g.spans();
        out.par_chunks_mut((g.oh * g.ow).max(1)).enumerate().for_each(|(plane, out_plane)| {
            let c = plane % channels;
            let src = &x[plane * height * width..(plane + 1) * height * width];
            let taps = &w[c * kh * kw..(c + 1) * kh * kw];
            for span in &spans {
                let wv = taps[span.tap];
                for (y, &x) in out_plane[span.out.clone()].iter_mut().zip(src[span.input.clone()].iter().step_by(s)) {
                    *y += wv * x;
                }
            }
        });
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, channels, g.oh, g.ow])))
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (_, _, height, width) = x.dims4()?;
        let grad = grad.contiguous()?;
        let grad_x = grad.apply_op2_no_bwd(weight, &InputGradient { stride: self.stride, height, width })?;
        let grad_w =
            x.apply_op2_no_bwd(&grad, &WeightGradient { stride: self.stride, kh: weight.dim(2)?, kw: weight.dim(3)? })?;
        Ok((Some(grad_x), Some(grad_w)))
    }
}

/// `(grad_y, weight) -> grad_x`: the transposed depthwise convolution.
struct InputGradient {
    stride: usize,
    height: usize,
    width: usize,
}

impl CustomOp2 for InputGradient {
    fn name(&self) -> &'static str {
        "depthwise-conv2d-same-input-grad"
    }

    fn cpu_fwd(&self, s_g: &CpuStorage, l_g: &Layout, s_w: &CpuStorage, l_w: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, oh, ow) = l_g.shape().dims4()?;
        let (_, _, kh, kw) = l_w.shape().dims4()?;
        let g = Geometry::new(self.height, self.width, kh, kw, self.stride);
        if (g.oh, g.ow) != (oh, ow) || l_w.shape().dim(0)? != channels {
            candle_core::bail!(
                "depthwise conv gradient: {:?} is not the output of {}x{} through {:?}",
                l_g.shape(),
                self.height,
                self.width,
                l_w.shape()
            );
        }
        let (grad, w) = (contiguous(s_g, l_g, "gradient")?, contiguous(s_w, l_w, "weight")?);
        let (s, plane_in) = (g.stride, self.height * self.width);
        let mut out = vec![0f32; batch * channels * plane_in];
        let spans = g.spans();
        out.par_chunks_mut(plane_in.max(1)).enumerate().for_each(|(plane, gx)| {
            let c = plane % channels;
            let gy = &grad[plane * oh * ow..(plane + 1) * oh * ow];
            let taps = &w[c * kh * kw..(c + 1) * kh * kw];
            for span in &spans {
                let wv = taps[span.tap];
                for (gx, &gy) in gx[span.input.clone()].iter_mut().step_by(s).zip(&gy[span.out.clone()]) {
                    *gx += wv * gy;
                }
            }
        });
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, channels, self.height, self.width])))
    }
}

/// `(x, grad_y) -> grad_weight`: per channel and tap, the correlation of input and output
/// gradient, summed over the batch.
struct WeightGradient {
    stride: usize,
    kh: usize,
    kw: usize,
}

impl CustomOp2 for WeightGradient {
    fn name(&self) -> &'static str {
        "depthwise-conv2d-same-weight-grad"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout, s_g: &CpuStorage, l_g: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, height, width) = l_x.shape().dims4()?;
        let (kh, kw) = (self.kh, self.kw);
        let g = Geometry::new(height, width, kh, kw, self.stride);
        if l_g.shape().dims() != [batch, channels, g.oh, g.ow] {
            candle_core::bail!("depthwise conv gradient: {:?} is not the output of {:?}", l_g.shape(), l_x.shape());
        }
        let (x, grad) = (contiguous(s_x, l_x, "input")?, contiguous(s_g, l_g, "gradient")?);
        let (s, taps) = (g.stride, kh * kw);
        let (plane_in, plane_out) = (height * width, g.oh * g.ow);
        // Per plane partial sums (accumulated in f64: a plane can have thousands of terms), then
        // a sum over the batch.
        let mut partial = vec![0f64; batch * channels * taps];
        let spans = g.spans();
        partial.par_chunks_mut(taps).enumerate().for_each(|(plane, acc)| {
            let src = &x[plane * plane_in..(plane + 1) * plane_in];
            let gy = &grad[plane * plane_out..(plane + 1) * plane_out];
            for span in &spans {
                let sum: f32 = gy[span.out.clone()]
                    .iter()
                    .zip(src[span.input.clone()].iter().step_by(s))
                    .map(|(g, x)| g * x)
                    .sum();
                acc[span.tap] += sum as f64;
            }
        });
        let mut out = vec![0f32; channels * taps];
        for (c, dst) in out.chunks_mut(taps).enumerate() {
            for b in 0..batch {
                let src = &partial[(b * channels + c) * taps..(b * channels + c + 1) * taps];
                for (d, v) in dst.iter_mut().zip(src) {
                    *d += *v as f32;
                }
            }
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[channels, 1, kh, kw])))
    }
}

/// Depthwise convolution of `x` `[B, C, H, W]` by `weight` `[C, 1, kh, kw]` with "SAME" padding,
/// differentiable with respect to both (f32, CPU).
pub fn depthwise_conv_train(x: &Tensor, weight: &Tensor, stride: usize) -> Result<Tensor> {
    if stride == 0 {
        candle_core::bail!("depthwise conv: stride 0");
    }
    x.contiguous()?.apply_op2(&weight.contiguous()?, DepthwiseForward { stride })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::kernels::depthwise::depthwise_conv_reference;
    use candle_core::{Device, Var};

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    /// Sizes covering even/odd planes, strides 1 and 2, kernels 3 (the networks') and 5.
    const CASES: [(usize, usize, usize, usize); 6] =
        [(8, 8, 3, 1), (8, 8, 3, 2), (7, 9, 3, 2), (5, 6, 3, 1), (9, 7, 5, 2), (2, 3, 3, 2)];

    #[test]
    fn forward_and_gradients_equal_candles_grouped_convolution() -> Result<()> {
        let dev = Device::Cpu;
        for (h, w, k, stride) in CASES {
            let channels = 5;
            let x = Var::randn(0f32, 1.0, (3, channels, h, w), &dev)?;
            let weight = Var::randn(0f32, 1.0, (channels, 1, k, k), &dev)?;
            let fast = depthwise_conv_train(&x, &weight, stride)?;
            let stock = depthwise_conv_reference(&x, &weight, None, stride)?;
            assert_eq!(fast.dims(), stock.dims());
            assert!(max_abs_diff(&fast, &stock) < 1e-5, "forward h={h} w={w} k={k} s={stride}");
            // A loss with a non-uniform output gradient.
            let probe = Tensor::randn(0f32, 1.0, fast.shape(), &dev)?;
            let g_fast = (&fast * &probe)?.sum_all()?.backward()?;
            let g_stock = (&stock * &probe)?.sum_all()?.backward()?;
            for (name, v) in [("input", &x), ("weight", &weight)] {
                let (a, b) = (g_fast.get(v.as_tensor()).unwrap(), g_stock.get(v.as_tensor()).unwrap());
                assert_eq!(a.dims(), b.dims());
                let d = max_abs_diff(a, b);
                assert!(d < 1e-4, "{name} gradient h={h} w={w} k={k} s={stride}: max diff {d}");
            }
        }
        Ok(())
    }

    /// Central finite differences (in f64 arithmetic on f32 evaluations) of
    /// `L = sum(probe * conv(x, w))` at a few coordinates of `x` and `w`.
    #[test]
    fn gradients_match_finite_differences() -> Result<()> {
        let dev = Device::Cpu;
        for (h, w, k, stride) in CASES {
            let channels = 3;
            let x = Var::randn(0f32, 1.0, (2, channels, h, w), &dev)?;
            let weight = Var::randn(0f32, 1.0, (channels, 1, k, k), &dev)?;
            let probe = Tensor::randn(0f32, 1.0, depthwise_conv_train(&x, &weight, stride)?.shape(), &dev)?;
            let loss = |x: &Tensor, w: &Tensor| -> Result<f64> {
                Ok(depthwise_conv_train(x, w, stride)?.mul(&probe)?.sum_all()?.to_scalar::<f32>()? as f64)
            };
            let grads = depthwise_conv_train(&x, &weight, stride)?.mul(&probe)?.sum_all()?.backward()?;
            for (name, var) in [("input", &x), ("weight", &weight)] {
                let analytic = grads.get(var.as_tensor()).unwrap().flatten_all()?.to_vec1::<f32>()?;
                let values = var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
                let n = values.len();
                // Every coordinate of small tensors; a spread of them otherwise.
                for index in (0..n).step_by((n / 40).max(1)) {
                    let eps = 1e-2f32;
                    let mut plus = values.clone();
                    plus[index] += eps;
                    let mut minus = values.clone();
                    minus[index] -= eps;
                    let at = |v: Vec<f32>| Tensor::from_vec(v, var.shape(), &dev);
                    let (lp, lm) = if name == "input" {
                        (loss(&at(plus)?, &weight)?, loss(&at(minus)?, &weight)?)
                    } else {
                        (loss(&x, &at(plus)?)?, loss(&x, &at(minus)?)?)
                    };
                    let numeric = (lp - lm) / (2.0 * eps as f64);
                    let a = analytic[index] as f64;
                    // The loss is linear in each argument, so the only error is f32 rounding.
                    assert!(
                        (numeric - a).abs() <= 2e-3 * (1.0 + a.abs()),
                        "{name}[{index}] h={h} w={w} k={k} s={stride}: numeric {numeric} analytic {a}"
                    );
                }
            }
        }
        Ok(())
    }

    #[test]
    fn mismatched_shapes_are_errors() -> Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::zeros((1, 4, 6, 6), candle_core::DType::F32, &dev)?;
        let weight = Tensor::zeros((3, 1, 3, 3), candle_core::DType::F32, &dev)?;
        assert!(depthwise_conv_train(&x, &weight, 1).is_err());
        assert!(depthwise_conv_train(&x, &Tensor::zeros((4, 1, 3, 3), candle_core::DType::F32, &dev)?, 0).is_err());
        Ok(())
    }
}
