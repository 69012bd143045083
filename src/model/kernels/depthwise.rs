//! Fast CPU kernels as candle custom ops, so the model stays a candle model:
//!
//! - [`depthwise_conv`]: depthwise 2-D convolution with TensorFlow "SAME" padding (possibly
//!   asymmetric: for stride 2 the extra pixel goes bottom/right), fused bias and optional ReLU6.
//!   candle's grouped convolution runs one tiny convolution per channel, which made depthwise
//!   layers ~80% of MobileNetV2's time; this kernel walks each channel plane directly.
//! - [`bias_activation_`]: adds a per-channel bias and applies the activation in place (fused
//!   epilogue for the 1x1 convolutions, which are plain matrix multiplies).
//!
//! Both are inference-only (no backward); training uses the differentiable op of
//! [`super::depthwise_grad`], and the tests check all of them against stock candle ops. The per-plane kernel is also what [`super::fused`]'s whole-bottleneck op
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
    /// `max(0, x)` (XFeat).
    Relu,
    /// `min(max(0, x), 6)` (MobileNetV2).
    Relu6,
}

impl Activation {
    #[inline(always)]
    fn apply(self, row: &mut [f32]) {
        for v in row {
            *v = self.of(*v);
        }
    }

    /// The activation of one value.
    #[inline(always)]
    pub(crate) fn of(self, v: f32) -> f32 {
        match self {
            Activation::Identity => v,
            Activation::Relu => v.max(0.0),
            Activation::Relu6 => v.clamp(0.0, 6.0),
        }
    }

    /// The same activation with stock candle ops (reference and training path).
    pub fn forward(self, x: &Tensor) -> Result<Tensor> {
        match self {
            Activation::Identity => Ok(x.clone()),
            Activation::Relu => x.relu(),
            Activation::Relu6 => x.clamp(0f32, 6f32),
        }
    }
}

struct DepthwiseConv {
    stride: usize,
    activation: Activation,
}

fn contiguous<'a>(storage: &'a CpuStorage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    super::contiguous_f32(storage, layout, "depthwise conv", what)
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
/// code compiled for AVX-512, for AVX2+FMA, or for the baseline.
pub(crate) fn convolve_plane(g: &PlaneGeometry, src: &[f32], w: &[f32], bias: f32, act: Activation, out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { convolve_plane_avx512(g, src, w, bias, act, out) };
        }
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

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn convolve_plane_avx512(
    g: &PlaneGeometry,
    src: &[f32],
    w: &[f32],
    bias: f32,
    act: Activation,
    out: &mut [f32],
) {
    convolve_plane_generic(g, src, w, bias, act, out)
}

#[inline(always)]
fn convolve_plane_generic(g: &PlaneGeometry, src: &[f32], w: &[f32], bias: f32, act: Activation, out: &mut [f32]) {
    if g.kh == 3 && g.kw == 3 && (g.stride == 1 || g.stride == 2) {
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

/// A channel plane copied into a zero border ("SAME" padding made explicit), reused across
/// planes of one geometry so that only the interior is rewritten, and the flat output it gives.
#[derive(Default)]
struct PaddedPlane {
    key: Padded3x3,
    /// Stride 1: the padded plane, `rows x pitch`. Stride 2: its four phases (even/odd rows x
    /// even/odd columns), each `(oh + 1) x pitch`.
    data: Vec<f32>,
    /// The output at the padded pitch: `oh x pitch`, of which the first `ow` of each row are kept.
    flat_out: Vec<f32>,
}

thread_local! {
    static PADDED: std::cell::Cell<PaddedPlane> = std::cell::Cell::new(PaddedPlane::default());
}

/// Output rows narrower than this are computed as one pass over the whole plane.
const WHOLE_PLANE_BELOW_WIDTH: usize = 32;

/// The 3x3 case (all of MobileNetV2), strides 1 and 2.
///
/// The plane is copied into a zero border whose rows all have one pitch; then output pixel
/// `(oy, ox)` at flat position `oy * pitch + ox` reads tap `k` at a fixed flat offset, so the whole
/// plane is one bounds-check-free vectorised pass ([`tap_sum`], bias and activation fused) rather
/// than one short pass per row, which left the 7x7 and 14x14 planes mostly scalar. The columns past
/// `ow` in each flat row are computed and dropped when the rows are copied out; rows of at least
/// [`WHOLE_PLANE_BELOW_WIDTH`] are long enough to vectorise, and are written directly instead.
///
/// Stride 2 keeps the padded plane as its four phases (row parity x column parity): padded pixel
/// `(2y + a, 2x + b)` is phase `(a, b)`'s pixel `(y, x)`, so tap `(ky, kx)` of output `(oy, ox)` is
/// phase `(ky % 2, kx % 2)` at `(oy + ky / 2, ox + kx / 2)`, again a fixed offset. Other strides
/// take the general path.
#[inline(always)]
fn convolve_plane_3x3(g: &PlaneGeometry, src: &[f32], w: &[f32], bias: f32, act: Activation, out: &mut [f32]) {
    let ow = g.ow;
    let oh = out.len() / ow;
    let layout = g.padded_3x3(oh);
    // Taken out of the thread-local rather than used in a closure: a closure would be compiled
    // without this function's SIMD features, and `mul_add` would become a library call.
    let mut padded = PADDED.take();
    {
        if padded.key != layout || padded.data.len() != layout.size {
            padded.key = layout;
            padded.data.clear();
            padded.data.resize(layout.size, 0.0);
        }
        if ow < WHOLE_PLANE_BELOW_WIDTH {
            padded.flat_out.resize(layout.flat_len, 0.0);
        }
        let PaddedPlane { data, flat_out, .. } = &mut padded;
        g.fill_padded_3x3(&layout, src, data);
        let (pitch, offsets) = (layout.pitch, layout.offsets);
        if ow >= WHOLE_PLANE_BELOW_WIDTH {
            for (oy, out_row) in out.chunks_exact_mut(ow).enumerate() {
                tap_sum(out_row, bias, w, offsets.map(|o| &data[o + oy * pitch..]), act);
            }
        } else {
            tap_sum(flat_out, bias, w, offsets.map(|o| &data[o..]), act);
            for (out_row, flat_row) in out.chunks_exact_mut(ow).zip(flat_out.chunks(pitch)) {
                out_row.copy_from_slice(&flat_row[..ow]);
            }
        }
    }
    PADDED.set(padded);
}

/// Where a plane's "SAME"-padded copy for a 3x3 kernel keeps its pixels ([`convolve_plane_3x3`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Padded3x3 {
    /// Floats from one padded row (of a phase, at stride 2) to the next.
    pub pitch: usize,
    /// Floats of the whole padded copy.
    pub size: usize,
    /// Output `(oy, ox)` reads tap `ky * 3 + kx` at `offsets[tap] + oy * pitch + ox`.
    pub offsets: [usize; 9],
    /// Flat outputs at the pitch, `(oh - 1) * pitch + ow` (the last row needs no padding columns).
    pub flat_len: usize,
    /// The padded extent (rows, columns) before any phase split.
    extent: (usize, usize),
    /// Input geometry this is for (a reused buffer is valid while this stays the same).
    geometry: (usize, usize, usize, usize, usize),
}

impl PlaneGeometry {
    /// The padded layout for `oh` output rows (3x3 kernel, stride 1 or 2).
    pub(crate) fn padded_3x3(&self, oh: usize) -> Padded3x3 {
        let (s, ow) = (self.stride, self.ow);
        debug_assert!((self.kh, self.kw) == (3, 3) && (s == 1 || s == 2));
        // The padded extent the outputs need: exactly the input plus its "SAME" padding.
        let (rows, cols) = ((oh - 1) * s + 3, (ow - 1) * s + 3);
        let (pitch, size, offsets) = if s == 1 {
            (cols, rows * cols, std::array::from_fn(|k| k / 3 * cols + k % 3))
        } else {
            let pitch = ow + 1;
            let phase_size = (oh + 1) * pitch;
            // Phases in order: (even row, even col), (odd row, even col), (even row, odd col), (odd row, odd col).
            let offsets = std::array::from_fn(|k| {
                let (ky, kx) = (k / 3, k % 3);
                ((kx % 2) * 2 + ky % 2) * phase_size + (ky / 2) * pitch + kx / 2
            });
            (pitch, 4 * phase_size, offsets)
        };
        let geometry = (self.height, self.width, s, self.pad_top, self.pad_left);
        Padded3x3 { pitch, size, offsets, flat_len: (oh - 1) * pitch + ow, extent: (rows, cols), geometry }
    }

    /// Copies plane `src` into `data` (`layout.size` floats) at `layout`; the border is not written,
    /// so a buffer zeroed once serves every plane of one layout.
    #[inline(always)]
    pub(crate) fn fill_padded_3x3(&self, layout: &Padded3x3, src: &[f32], data: &mut [f32]) {
        let (width, pitch, (rows, cols)) = (self.width, layout.pitch, layout.extent);
        // Input rows/columns that land inside the padded extent.
        let (y_end, x_end) = (self.height.min(rows - self.pad_top), width.min(cols - self.pad_left));
        if self.stride == 1 {
            for y in 0..y_end {
                let at = (y + self.pad_top) * pitch + self.pad_left;
                data[at..at + x_end].copy_from_slice(&src[y * width..y * width + x_end]);
            }
        } else {
            let phase_size = layout.size / 4;
            // Padded column x: phase column x / 2 of the even (x even) or odd (x odd) phases.
            let first_even = self.pad_left % 2;
            for y in 0..y_end {
                let py = y + self.pad_top;
                let row = &src[y * width..y * width + x_end];
                let (even_phase, odd_phase) = data.split_at_mut(2 * phase_size);
                let at = (py % 2) * phase_size + py / 2 * pitch;
                let e = &mut even_phase[at..at + pitch][(first_even + self.pad_left) / 2..];
                let o = &mut odd_phase[at..at + pitch][(1 - first_even + self.pad_left) / 2..];
                split_columns(row, first_even, e, o);
            }
        }
    }
}

/// Deals `row`'s columns out to `even` and `odd` (the first column is even unless
/// `first_is_odd == 1`), as far as each has room.
#[inline(always)]
fn split_columns(row: &[f32], first_is_odd: usize, even: &mut [f32], odd: &mut [f32]) {
    // An odd first column goes to `odd` alone; the rest starts on an even column.
    let lead = first_is_odd.min(row.len()).min(odd.len());
    odd[..lead].copy_from_slice(&row[..lead]);
    let (row, odd) = (&row[lead..], &mut odd[lead..]);
    // (even, odd) pairs in one pass, which the compiler turns into vector shuffles.
    let pairs = row.chunks_exact(2);
    let n = pairs.len().min(even.len()).min(odd.len());
    for ((d_even, d_odd), pair) in even[..n].iter_mut().zip(&mut odd[..n]).zip(pairs) {
        (*d_even, *d_odd) = (pair[0], pair[1]);
    }
    // What the pairs left: an unpaired last column, or columns past the shorter side.
    for (d, &v) in even[n..].iter_mut().zip(row[(2 * n).min(row.len())..].iter().step_by(2)) {
        *d = v;
    }
    for (d, &v) in odd[n..].iter_mut().zip(row[(2 * n + 1).min(row.len())..].iter().step_by(2)) {
        *d = v;
    }
}

/// `dst[i] = act(bias + Σ_k w[k] · taps[k][i])` over a row. Every tap is cut to `dst`'s length
/// first, so the loop runs without bounds checks and vectorises (one FMA per tap and lane).
#[inline(always)]
fn tap_sum(dst: &mut [f32], bias: f32, w: &[f32], taps: [&[f32]; 9], act: Activation) {
    // One loop per activation, so that each vectorises without a branch.
    match act {
        Activation::Identity => tap_sum_with::<{ Activation::Identity as u8 }>(dst, bias, w, taps),
        Activation::Relu => tap_sum_with::<{ Activation::Relu as u8 }>(dst, bias, w, taps),
        Activation::Relu6 => tap_sum_with::<{ Activation::Relu6 as u8 }>(dst, bias, w, taps),
    }
}

#[inline(always)]
fn tap_sum_with<const ACT: u8>(dst: &mut [f32], bias: f32, w: &[f32], taps: [&[f32]; 9]) {
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
        acc = t8[i].mul_add(w[8], acc);
        dst[i] = if ACT == Activation::Relu6 as u8 {
            acc.clamp(0.0, 6.0)
        } else if ACT == Activation::Relu as u8 {
            acc.max(0.0)
        } else {
            acc
        };
    }
}

/// Depthwise convolution (`weight` `[C, 1, kh, kw]`, `bias` `[C]`) of `x` `[B, C, H, W]` with
/// "SAME" padding, fused bias and activation, by the direct kernel.
pub fn depthwise_conv(
    x: &Tensor,
    weight: &Tensor,
    bias: &Tensor,
    stride: usize,
    activation: Activation,
) -> Result<Tensor> {
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
        // Even and odd sizes, kernels 3 and 5, strides 1 and 2, batch 2; rows narrower and wider
        // than WHOLE_PLANE_BELOW_WIDTH.
        for &(h, w, k, stride) in &[
            (14, 14, 3, 1),
            (14, 14, 3, 2),
            (15, 9, 3, 2),
            (11, 12, 5, 1),
            (8, 7, 5, 2),
            (2, 3, 3, 2),
            (29, 31, 3, 2),
            (30, 28, 3, 2),
            (5, 40, 3, 1),
            (6, 67, 3, 2),
        ] {
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

    /// Every SIMD build of the plane kernel this CPU can run gives what the baseline build gives
    /// (the stock comparison above only reaches the one the dispatcher picks).
    #[test]
    fn every_simd_build_of_the_plane_kernel_agrees_with_the_baseline() {
        for &(h, w, stride) in &[(7, 7, 1), (14, 14, 2), (9, 40, 1), (12, 70, 2), (15, 33, 2)] {
            let (oh, pad_top, _) = same_padding(h, 3, stride);
            let (ow, pad_left, _) = same_padding(w, 3, stride);
            let g = PlaneGeometry { height: h, width: w, kh: 3, kw: 3, stride, ow, pad_top, pad_left };
            let src: Vec<f32> = (0..h * w).map(|i| ((i * 37) % 23) as f32 * 0.3 - 3.0).collect();
            let weights: Vec<f32> = (0..9).map(|i| i as f32 * 0.25 - 1.0).collect();
            let run = |kernel: &dyn Fn(&mut [f32])| {
                let mut out = vec![0f32; oh * ow];
                kernel(&mut out);
                out
            };
            let baseline = run(&|out| convolve_plane_generic(&g, &src, &weights, 0.5, Activation::Relu6, out));
            #[cfg(target_arch = "x86_64")]
            {
                let mut builds: Vec<(&str, Vec<f32>)> = Vec::new();
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    // SAFETY: the CPU has the features.
                    builds.push((
                        "avx2",
                        run(&|out| unsafe { convolve_plane_avx2(&g, &src, &weights, 0.5, Activation::Relu6, out) }),
                    ));
                }
                if std::is_x86_feature_detected!("avx512f") {
                    // SAFETY: the CPU has the features.
                    builds.push((
                        "avx512",
                        run(&|out| unsafe { convolve_plane_avx512(&g, &src, &weights, 0.5, Activation::Relu6, out) }),
                    ));
                }
                for (name, out) in builds {
                    let diff = out.iter().zip(&baseline).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
                    assert!(diff < 1e-5, "{name} {h}x{w} stride {stride}: max diff {diff}");
                }
            }
        }
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
