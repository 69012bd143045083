//! Fused CPU inference kernels as candle custom ops (the fast path of [`Mode::Inference`]
//! once BatchNorm is folded; [`Mode::Reference`] runs stock candle ops and the tests check that
//! the two agree within 1e-4):
//!
//! - [`FusedBottleneck`]: a whole inverted-residual bottleneck in one op: 1x1 expansion + ReLU6,
//!   3x3 depthwise + ReLU6, optional ECA, the linear 1x1 projection and the residual. The expanded
//!   activation is the largest tensor of MobileNetV2 (6x the block's input); here it is computed a
//!   few channels at a time into a buffer that stays in cache and is consumed by the depthwise
//!   convolution at once, so it never travels to memory. ECA's channel means are summed while the
//!   depthwise output is written, and its gate scales the projection's weight columns
//!   (`W (g ⊙ x) = (W diag(g)) x`) instead of the activation.
//! - [`DenseConv`]: a full convolution (the stem) as padded-plane columns plus one matrix multiply, and a 1x1
//!   convolution (the head) as a plain matrix multiply on the NCHW planes.
//!
//! The matrix multiplies are calls to `gemm`, the crate behind candle's own CPU matmul, built
//! with its `x86-v4` feature so that it picks AVX-512 kernels at run time where the CPU has them
//! (1.4-1.7x the AVX2 kernels on this project's 1x1 shapes), with the
//! bias (and residual) preloaded into the destination so that no extra pass adds them.
//!
//! [`Mode::Inference`]: super::layers::Mode::Inference
//! [`Mode::Reference`]: super::layers::Mode::Reference

use std::cell::RefCell;

use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::depthwise::{convolve_plane, same_padding, Activation, PlaneGeometry};

/// Floats of the expanded-activation buffer each task works in: sized to stay in L2.
const EXPANDED_BUFFER_FLOATS: usize = 64 * 1024;

thread_local! {
    /// Reused across frames: one expanded-activation buffer per worker thread.
    static EXPANDED: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// Row-major `dst[m×n] = (dst if accumulate) + lhs[m×k] · rhs[k×n]` on the calling thread.
fn matmul(m: usize, n: usize, k: usize, dst: &mut [f32], accumulate: bool, lhs: &[f32], rhs: &[f32]) {
    assert!(dst.len() >= m * n && lhs.len() >= m * k && rhs.len() >= k * n, "matmul operand sizes");
    // SAFETY: the slices hold the row-major matrices whose sizes were checked above; dst does
    // not alias the inputs (distinct borrows).
    unsafe {
        gemm::gemm(
            m, n, k,
            dst.as_mut_ptr(), 1, n as isize, accumulate,
            lhs.as_ptr(), 1, k as isize,
            rhs.as_ptr(), 1, n as isize,
            1.0, 1.0, false, false, false, gemm::Parallelism::None,
        );
    }
}

/// Columns per thread from which [`matmul_parallel`] splits by columns rather than rows.
const COLUMN_SPLIT_MIN: usize = 256;

/// [`matmul`] (accumulating) split across rayon's threads. With many columns (pixels), each thread
/// takes a block of columns (a multiple of 16) and all rows: the blocks are even whatever the row
/// count (24 rows split by rows in multiples of 8 gave one thread twice the other's work), and each
/// thread reads only its part of `rhs`. With few columns (the 7x7 layers: 49), each thread takes a
/// block of rows (a multiple of 8) and reads all of `rhs`.
fn matmul_parallel(m: usize, n: usize, k: usize, dst: &mut [f32], lhs: &[f32], rhs: &[f32]) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(dst.len() >= m * n && lhs.len() >= m * k && rhs.len() >= k * n, "matmul operand sizes");
    let threads = rayon::current_num_threads().max(1);
    if threads > 1 && n >= COLUMN_SPLIT_MIN * threads {
        let block = n.div_ceil(threads).next_multiple_of(16);
        // Passed as an address: the threads write disjoint column blocks of one buffer.
        let dst_address = dst.as_mut_ptr() as usize;
        (0..n.div_ceil(block)).into_par_iter().for_each(|b| {
            let (first, cols) = (b * block, block.min(n - b * block));
            // SAFETY: sizes checked above; block `b` reads and writes only columns
            // [first, first + cols) of every row of dst, which no other block touches.
            unsafe {
                gemm::gemm(
                    m, cols, k,
                    (dst_address as *mut f32).add(first), 1, n as isize, true,
                    lhs.as_ptr(), 1, k as isize,
                    rhs.as_ptr().add(first), 1, n as isize,
                    1.0, 1.0, false, false, false, gemm::Parallelism::None,
                );
            }
        });
        return;
    }
    let rows = m.div_ceil(threads).next_multiple_of(8).min(m).max(1);
    dst[..m * n].par_chunks_mut(rows * n).zip(lhs[..m * k].par_chunks(rows * k)).for_each(|(dst, lhs)| {
        matmul(dst.len() / n, n, k, dst, true, lhs, rhs);
    });
}

fn to_vec(t: &Tensor) -> Result<Vec<f32>> {
    t.flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()
}

fn input<'a>(storage: &'a CpuStorage, layout: &Layout, op: &str) -> Result<&'a [f32]> {
    super::contiguous_f32(storage, layout, op, "the input")
}

/// ECA's gate from per-channel sums over `count` values: mean, 1-D convolution across channels
/// (zero padding, `taps.len()` odd), sigmoid — as [`super::layers::Eca::gate`].
fn eca_gate(sums: &[f64], count: usize, taps: &[f32]) -> Vec<f32> {
    let channels = sums.len() as isize;
    let pad = (taps.len() as isize - 1) / 2;
    let means: Vec<f64> = sums.iter().map(|s| s / count as f64).collect();
    (0..channels)
        .map(|c| {
            let z: f64 = taps
                .iter()
                .enumerate()
                .map(|(j, &t)| {
                    let i = c + j as isize - pad;
                    if (0..channels).contains(&i) { t as f64 * means[i as usize] } else { 0.0 }
                })
                .sum();
            (1.0 / (1.0 + (-z).exp())) as f32
        })
        .collect()
}

/// Sum of a plane: eight f32 lanes (vectorised; each adds at most plane/8 values of ReLU6
/// outputs), combined in f64.
fn plane_sum(plane: &[f32]) -> f64 {
    let mut lanes = [0f32; 8];
    let mut chunks = plane.chunks_exact(8);
    for chunk in &mut chunks {
        for (l, v) in lanes.iter_mut().zip(chunk) {
            *l += v;
        }
    }
    lanes.iter().chain(chunks.remainder()).map(|&v| v as f64).sum()
}

/// The folded weights of one inverted-residual bottleneck with 3x3 depthwise convolution.
#[derive(Debug)]
pub struct FusedBottleneck {
    input: usize,
    hidden: usize,
    output: usize,
    stride: usize,
    /// `[hidden, input]` weight and `[hidden]` bias, absent when the block has no expansion.
    expand: Option<(Vec<f32>, Vec<f32>)>,
    depthwise_weight: Vec<f32>,
    depthwise_bias: Vec<f32>,
    eca_taps: Option<Vec<f32>>,
    project_weight: Vec<f32>,
    project_bias: Vec<f32>,
    residual: bool,
}

impl FusedBottleneck {
    /// From folded tensors: `expand` (`[hidden, input, 1, 1]`, `[hidden]`), `depthwise`
    /// (`[hidden, 1, 3, 3]`, `[hidden]`), ECA taps `[1, 1, k]`, `project` (`[output, hidden, 1, 1]`,
    /// `[output]`).
    pub fn new(
        stride: usize,
        expand: Option<(&Tensor, &Tensor)>,
        depthwise: (&Tensor, &Tensor),
        eca: Option<&Tensor>,
        project: (&Tensor, &Tensor),
    ) -> Result<Self> {
        let (hidden, _, kh, kw) = depthwise.0.dims4()?;
        if (kh, kw) != (3, 3) {
            candle_core::bail!("fused bottleneck: 3x3 depthwise kernels only, got {kh}x{kw}");
        }
        let (output, project_in, _, _) = project.0.dims4()?;
        let input = match expand {
            Some((w, _)) => w.dim(1)?,
            None => hidden,
        };
        if project_in != hidden {
            candle_core::bail!("fused bottleneck: projection takes {project_in} channels, depthwise gives {hidden}");
        }
        Ok(FusedBottleneck {
            input,
            hidden,
            output,
            stride,
            expand: expand.map(|(w, b)| Ok::<_, candle_core::Error>((to_vec(w)?, to_vec(b)?))).transpose()?,
            depthwise_weight: to_vec(depthwise.0)?,
            depthwise_bias: to_vec(depthwise.1)?,
            eca_taps: eca.map(to_vec).transpose()?,
            project_weight: to_vec(project.0)?,
            project_bias: to_vec(project.1)?,
            residual: stride == 1 && input == output,
        })
    }

    /// Hidden channels per task: the expanded planes fit [`EXPANDED_BUFFER_FLOATS`], and there are
    /// at least two tasks per thread.
    fn group_size(&self, plane: usize) -> usize {
        let by_cache = (EXPANDED_BUFFER_FLOATS / plane.max(1)).max(8);
        let by_threads = self.hidden.div_ceil(2 * rayon::current_num_threads().max(1));
        by_cache.min(by_threads).max(1)
    }

    /// One image: `x` `[input, h, w]` -> `out` `[output, oh, ow]`.
    fn forward_image(&self, x: &[f32], h: usize, w: usize, out: &mut [f32]) {
        let (oh, pad_top, _) = same_padding(h, 3, self.stride);
        let (ow, pad_left, _) = same_padding(w, 3, self.stride);
        let (plane_in, plane_out) = (h * w, oh * ow);
        let geometry = PlaneGeometry { height: h, width: w, kh: 3, kw: 3, stride: self.stride, ow, pad_top, pad_left };
        let group = self.group_size(plane_in);

        // Expansion + depthwise, a group of hidden channels per task.
        let mut depthwise_out = vec![0f32; self.hidden * plane_out];
        let mut sums = vec![0f64; self.hidden];
        depthwise_out.par_chunks_mut(group * plane_out).zip(sums.par_chunks_mut(group)).enumerate().for_each(
            |(g, (dst, sums))| {
                let (first, count) = (g * group, sums.len());
                let mut depthwise_group = |source: &[f32]| {
                    for (i, (plane, sum)) in dst.chunks_exact_mut(plane_out).zip(sums.iter_mut()).enumerate() {
                        let c = first + i;
                        let weights = &self.depthwise_weight[c * 9..(c + 1) * 9];
                        let src = &source[i * plane_in..(i + 1) * plane_in];
                        convolve_plane(&geometry, src, weights, self.depthwise_bias[c], Activation::Relu6, plane);
                        *sum = plane_sum(plane);
                    }
                };
                match &self.expand {
                    None => depthwise_group(&x[first * plane_in..(first + count) * plane_in]),
                    Some((weight, bias)) => EXPANDED.with_borrow_mut(|expanded| {
                        expanded.resize(count * plane_in, 0.0);
                        for (row, &b) in expanded.chunks_exact_mut(plane_in).zip(&bias[first..first + count]) {
                            row.fill(b);
                        }
                        let weight = &weight[first * self.input..(first + count) * self.input];
                        matmul(count, plane_in, self.input, expanded, true, weight, x);
                        for v in expanded.iter_mut() {
                            *v = v.clamp(0.0, 6.0);
                        }
                        depthwise_group(expanded);
                    }),
                }
            },
        );

        let scaled;
        let weight = match &self.eca_taps {
            Some(taps) => {
                let gate = eca_gate(&sums, plane_out, taps);
                scaled = self
                    .project_weight
                    .chunks_exact(self.hidden)
                    .flat_map(|row| row.iter().zip(&gate).map(|(w, g)| w * g))
                    .collect::<Vec<f32>>();
                &scaled
            }
            None => &self.project_weight,
        };
        for (o, row) in out.chunks_exact_mut(plane_out).enumerate() {
            match self.residual {
                true => {
                    for (v, &r) in row.iter_mut().zip(&x[o * plane_in..(o + 1) * plane_in]) {
                        *v = self.project_bias[o] + r;
                    }
                }
                false => row.fill(self.project_bias[o]),
            }
        }
        // Projection (+ bias + residual preloaded), ECA folded into the weight columns.
        matmul_parallel(self.output, plane_out, self.hidden, out, weight, &depthwise_out);
    }
}

impl CustomOp1 for FusedBottleneck {
    fn name(&self) -> &'static str {
        "fused-inverted-residual"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, h, w) = layout.shape().dims4()?;
        if channels != self.input {
            candle_core::bail!("fused bottleneck: {channels} input channels, expected {}", self.input);
        }
        let x = input(storage, layout, "fused bottleneck")?;
        let (oh, ow) = (h.div_ceil(self.stride), w.div_ceil(self.stride));
        let mut out = vec![0f32; batch * self.output * oh * ow];
        for (image, out) in x.chunks_exact(channels * h * w).zip(out.chunks_exact_mut(self.output * oh * ow)) {
            self.forward_image(image, h, w, out);
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, self.output, oh, ow])))
    }
}

/// A dense convolution with "SAME" padding, fused bias and activation: im2col + one matrix
/// multiply (a 1x1 convolution at stride 1 needs no im2col: the NCHW planes are the matrix).
#[derive(Debug)]
pub struct DenseConv {
    out_channels: usize,
    in_channels: usize,
    kernel: (usize, usize),
    stride: usize,
    /// `[out, in * kh * kw]`, the OIHW weight flattened.
    weight: Vec<f32>,
    bias: Vec<f32>,
    activation: Activation,
}

impl DenseConv {
    pub fn new(weight: &Tensor, bias: &Tensor, stride: usize, activation: Activation) -> Result<Self> {
        let (out_channels, in_channels, kh, kw) = weight.dims4()?;
        Ok(DenseConv {
            out_channels,
            in_channels,
            kernel: (kh, kw),
            stride,
            weight: to_vec(weight)?,
            bias: to_vec(bias)?,
            activation,
        })
    }

    /// One image through a 3x3 kernel (the stem), without per-pixel im2col: each input channel is
    /// padded once ([`PlaneGeometry::padded_3x3`]), after which every tap's column row is one
    /// contiguous run of the padded plane at the padded pitch. The product is computed at that
    /// pitch and the extra columns dropped when the rows are copied out (with the activation).
    fn forward_3x3(&self, x: &[f32], h: usize, w: usize, out: &mut [f32]) {
        let s = self.stride;
        let (oh, pad_top, _) = same_padding(h, 3, s);
        let (ow, pad_left, _) = same_padding(w, 3, s);
        let geometry = PlaneGeometry { height: h, width: w, kh: 3, kw: 3, stride: s, ow, pad_top, pad_left };
        let layout = geometry.padded_3x3(oh);
        let flat = layout.flat_len;
        let mut cols = vec![0f32; self.in_channels * 9 * flat];
        cols.par_chunks_mut(9 * flat).zip(x.par_chunks(h * w)).for_each(|(rows, plane)| {
            let mut padded = vec![0f32; layout.size];
            geometry.fill_padded_3x3(&layout, plane, &mut padded);
            for (row, offset) in rows.chunks_exact_mut(flat).zip(layout.offsets) {
                row.copy_from_slice(&padded[offset..offset + flat]);
            }
        });
        let mut at_pitch = vec![0f32; self.out_channels * flat];
        for (row, &b) in at_pitch.chunks_exact_mut(flat).zip(&self.bias) {
            row.fill(b);
        }
        matmul_parallel(self.out_channels, flat, self.in_channels * 9, &mut at_pitch, &self.weight, &cols);
        let relu6 = self.activation == Activation::Relu6;
        out.par_chunks_mut(oh * ow).zip(at_pitch.par_chunks(flat)).for_each(|(plane, source)| {
            for (row, source_row) in plane.chunks_exact_mut(ow).zip(source.chunks(layout.pitch)) {
                row.copy_from_slice(&source_row[..ow]);
                if relu6 {
                    row.iter_mut().for_each(|v| *v = v.clamp(0.0, 6.0));
                }
            }
        });
    }

    /// The columns of one image `x` `[in, h, w]`: row `(c, ky, kx)` holds the input pixel each
    /// output position sees through that tap (zero outside the image).
    fn im2col(&self, x: &[f32], h: usize, w: usize) -> Vec<f32> {
        let ((kh, kw), s) = (self.kernel, self.stride);
        let (oh, top, _) = same_padding(h, kh, s);
        let (ow, left, _) = same_padding(w, kw, s);
        let mut cols = vec![0f32; self.in_channels * kh * kw * oh * ow];
        cols.par_chunks_mut(oh * ow).enumerate().for_each(|(r, col)| {
            let (c, ky, kx) = (r / (kh * kw), r / kw % kh, r % kw);
            let plane = &x[c * h * w..(c + 1) * h * w];
            for (oy, out_row) in col.chunks_exact_mut(ow).enumerate() {
                let iy = (oy * s + ky) as isize - top as isize;
                if !(0..h as isize).contains(&iy) {
                    continue;
                }
                let in_row = &plane[iy as usize * w..(iy as usize + 1) * w];
                for (ox, v) in out_row.iter_mut().enumerate() {
                    let ix = (ox * s + kx) as isize - left as isize;
                    if (0..w as isize).contains(&ix) {
                        *v = in_row[ix as usize];
                    }
                }
            }
        });
        cols
    }
}

impl CustomOp1 for DenseConv {
    fn name(&self) -> &'static str {
        "dense-conv2d-same"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let (batch, channels, h, w) = layout.shape().dims4()?;
        if channels != self.in_channels {
            candle_core::bail!("dense conv: {channels} input channels, expected {}", self.in_channels);
        }
        let x = input(storage, layout, "dense conv")?;
        let ((kh, kw), s) = (self.kernel, self.stride);
        let (oh, ow) = (same_padding(h, kh, s).0, same_padding(w, kw, s).0);
        let (plane_out, taps) = (oh * ow, channels * kh * kw);
        let mut out = vec![0f32; batch * self.out_channels * plane_out];
        for (image, out) in x.chunks_exact(channels * h * w).zip(out.chunks_exact_mut(self.out_channels * plane_out)) {
            if kh == 3 && kw == 3 && (s == 1 || s == 2) {
                self.forward_3x3(image, h, w, out);
                continue;
            }
            let cols;
            let rhs = if (kh, kw, s) == (1, 1, 1) {
                image
            } else {
                cols = self.im2col(image, h, w);
                &cols
            };
            for (row, &b) in out.chunks_exact_mut(plane_out).zip(&self.bias) {
                row.fill(b);
            }
            matmul_parallel(self.out_channels, plane_out, taps, out, &self.weight, rhs);
            if self.activation == Activation::Relu6 {
                out.par_chunks_mut(plane_out).for_each(|row| row.iter_mut().for_each(|v| *v = v.clamp(0.0, 6.0)));
            }
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, self.out_channels, oh, ow])))
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use candle_core::{DType, Device};
    use candle_nn::VarBuilder;

    use super::*;
    use crate::model::layers::{BlockShape, ConvKind, ConvUnit, InvertedResidual, Mode};

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    fn random(shape: &[usize], std: f32) -> Tensor {
        Tensor::randn(0f32, std, shape, &Device::Cpu).unwrap()
    }

    #[test]
    fn fused_bottleneck_equals_stock_ops() -> Result<()> {
        // With and without expansion, ECA and residual; strides 1 and 2; odd and even sizes; batch 2;
        // on three threads, the last two with enough pixels that the projection is split by columns
        // and rows wide enough for the row-by-row depthwise pass.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let cases = [
            (BlockShape { input: 8, hidden: 48, output: 8, stride: 1, eca_kernel: Some(3) }, 9, 11),
            (BlockShape { input: 8, hidden: 48, output: 16, stride: 2, eca_kernel: Some(5) }, 14, 14),
            (BlockShape { input: 16, hidden: 16, output: 8, stride: 1, eca_kernel: None }, 12, 7),
            (BlockShape { input: 12, hidden: 72, output: 12, stride: 1, eca_kernel: None }, 5, 5),
            (BlockShape { input: 12, hidden: 72, output: 24, stride: 2, eca_kernel: Some(3) }, 7, 9),
            (BlockShape { input: 8, hidden: 24, output: 8, stride: 1, eca_kernel: Some(3) }, 23, 41),
            (BlockShape { input: 8, hidden: 24, output: 12, stride: 2, eca_kernel: None }, 61, 66),
        ];
        for (shape, h, w) in cases {
            let mut tensors = HashMap::new();
            if shape.has_expansion() {
                tensors.insert("expand.weight".to_string(), random(&[shape.hidden, shape.input, 1, 1], 0.5));
                tensors.insert("expand.bias".to_string(), random(&[shape.hidden], 1.0));
            }
            tensors.insert("depthwise.weight".to_string(), random(&[shape.hidden, 1, 3, 3], 0.5));
            tensors.insert("depthwise.bias".to_string(), random(&[shape.hidden], 1.0));
            if let Some(k) = shape.eca_kernel {
                tensors.insert("eca.weight".to_string(), random(&[1, 1, k], 1.0));
            }
            tensors.insert("project.weight".to_string(), random(&[shape.output, shape.hidden, 1, 1], 0.3));
            tensors.insert("project.bias".to_string(), random(&[shape.output], 1.0));
            let block = InvertedResidual::load(VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu), shape, false)?;
            let x = random(&[2, shape.input, h, w], 2.0);
            let fast = pool.install(|| block.forward_t(&x, Mode::Inference))?;
            let reference = block.forward_t(&x, Mode::Reference)?;
            assert_eq!(fast.dims(), reference.dims(), "{shape:?}");
            let diff = max_diff(&fast, &reference);
            assert!(diff < 1e-4, "{shape:?} {h}x{w}: max diff {diff}");
        }
        Ok(())
    }

    #[test]
    fn dense_conv_equals_stock_ops() -> Result<()> {
        // The stem (3x3, stride 2, odd and even sizes) and 1x1 units, batch 2; on three threads,
        // the larger ones with enough pixels that the product is split by columns.
        let cases = [
            (3, 2, 16, 16, Activation::Relu6),
            (3, 2, 9, 12, Activation::Relu6),
            (3, 1, 7, 6, Activation::Identity),
            (1, 1, 5, 4, Activation::Relu6),
            (3, 2, 70, 57, Activation::Relu6),
            (1, 1, 31, 40, Activation::Identity),
        ];
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        for (kernel, stride, h, w, activation) in cases {
            let kind = if kernel == 1 { ConvKind::Pointwise } else { ConvKind::Full { stride } };
            let tensors = HashMap::from([
                ("weight".to_string(), random(&[6, 3, kernel, kernel], 1.0)),
                ("bias".to_string(), random(&[6], 1.0)),
            ]);
            let unit = ConvUnit::load(VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu), (6, 3, kernel, kernel), kind, activation, false)?;
            let x = random(&[2, 3, h, w], 2.0);
            let (fast, reference) = (pool.install(|| unit.forward_t(&x, Mode::Inference))?, unit.forward_t(&x, Mode::Reference)?);
            assert_eq!(fast.dims(), reference.dims());
            let diff = max_diff(&fast, &reference);
            assert!(diff < 1e-4, "{kernel}x{kernel} s{stride} {h}x{w}: max diff {diff}");
        }
        Ok(())
    }
}
