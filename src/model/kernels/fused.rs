//! Fused CPU inference kernels on channels-last (NHWC) feature maps, as candle custom ops (what
//! the inference plan of [`Mode::Inference`] runs once BatchNorm is folded:
//! [`crate::model::plan`]; [`Mode::Reference`] runs stock candle ops and the tests check that the
//! two agree within 1e-4):
//!
//! - [`FusedBottleneck`]: a whole inverted-residual bottleneck in one op, `[B, H, W, C]` ->
//!   `[B, OH, OW, C']`: 1x1 expansion + ReLU6, 3x3 depthwise + ReLU6, optional ECA, the linear
//!   1x1 projection and the residual. The first block (no expansion) also runs with the stem
//!   fused in ([`FusedBottleneck::with_stem`]), taking the NCHW image: the stem's output rows
//!   are computed where the block would copy them, and the network's largest map is never stored.
//! - [`DenseConv`]: a full convolution (the stem) from the NCHW image to a channels-last map, or a
//!   1x1 convolution (the head) from channels-last to channels-last.
//!
//! Why channels-last: a pixel's channels are contiguous, so a 1x1 convolution is a matrix product
//! whose rows are pixels, tiled in registers by [`super::simd::pointwise`], and the depthwise
//! convolution runs sixteen channels per vector at any stride. In the bottleneck each task walks
//! its output rows in order, expanding input rows into a ring of three padded rows just before
//! the depthwise convolution reads them, so the expanded activation (the largest tensor of
//! MobileNetV2, 6x the block's input) never leaves the cache. Large maps split output rows among
//! the tasks (the row at a band's edge is expanded by both neighbours); maps of fewer than
//! `MIN_BAND_ROWS` (4) output rows per thread split whole weight panels of hidden channels
//! instead, where a band's edge would be a large share. With ECA the depthwise output is stored,
//! its channel sums taken as it is written. A band of rows is stored in a buffer of the thread
//! that made it and projected by that thread's next task, which scales the projection's weight
//! rows by the gate for itself (`W (g ⊙ x) = (W diag(g)) x`); the channel parts of a small map
//! share one buffer, which the gate scales, and whose projection splits pixels (or, for 7x7
//! maps, output channels) among the threads. Without ECA, on maps at least
//! `DIRECT_PROJECTION_WIDTH` (28) wide, each depthwise row goes through the projection as soon as
//! it is made and the depthwise output is never stored.
//!
//! Hidden channels are padded to a multiple of 16 with zero weights, whose outputs are zero.
//!
//! [`Mode::Inference`]: crate::model::layers::Mode::Inference
//! [`Mode::Reference`]: crate::model::layers::Mode::Reference

use std::cell::Cell;
use std::ops::Range;
use std::sync::Arc;

use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::depthwise::{same_padding, Activation};
// Buffers kept per thread across frames: taken out while in use and put back after, so that a
// pass this thread runs while waiting inside another (rayon's work stealing) finds the cell
// empty and allocates rather than sharing.
thread_local! {
    /// ECA-gated projection weights of the bottleneck being run on this thread.
    static SCALED_PROJECTION: Cell<PackedWeights> = Cell::new(PackedWeights::default());
    /// The depthwise output of the band of a large map that this thread made last.
    static BAND_OUT: Cell<Vec<f32>> = const { Cell::new(Vec::new()) };
    /// The depthwise output of the small map being run on this thread.
    static DEPTHWISE_OUT: Cell<Vec<f32>> = const { Cell::new(Vec::new()) };
}

use super::simd::{
    depthwise_row, pointwise, DepthwiseRow, PackedWeights, Pointwise, LANES, SHORT_CALL_ROWS, TILE_ROWS,
};

fn to_vec(t: &Tensor) -> Result<Vec<f32>> {
    t.flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()
}

fn input<'a>(storage: &'a CpuStorage, layout: &Layout, op: &str) -> Result<&'a [f32]> {
    super::contiguous_f32(storage, layout, op, "the input")
}

/// ECA's gate from per-channel sums over `count` values: mean, 1-D convolution across channels
/// (zero padding, `taps.len()` odd), sigmoid — as [`crate::model::layers::Eca::gate`].
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
                    if (0..channels).contains(&i) {
                        t as f64 * means[i as usize]
                    } else {
                        0.0
                    }
                })
                .sum();
            (1.0 / (1.0 + (-z).exp())) as f32
        })
        .collect()
}

/// A pointer that rayon's tasks may share: each task writes a part no other task touches.
#[derive(Clone, Copy)]
struct SharedMut(*mut f32);
// SAFETY: used only where the tasks write disjoint elements (said at each use).
unsafe impl Send for SharedMut {}
unsafe impl Sync for SharedMut {}

impl SharedMut {
    fn get(self) -> *mut f32 {
        self.0
    }
}

/// An output of `len` floats that `fill` writes through the pointer, every element: the ops'
/// outputs are not zeroed first (3.5 MB of memset a frame, most of it the 112x112 maps).
///
/// # Safety
/// `fill` writes all `len` floats at the pointer it is given.
unsafe fn written_output(len: usize, fill: impl FnOnce(*mut f32)) -> Vec<f32> {
    let mut out = Vec::with_capacity(len);
    fill(out.as_mut_ptr());
    // SAFETY: `fill` wrote every element (the caller's contract).
    unsafe { out.set_len(len) };
    out
}

/// `units` split into `parts` contiguous ranges whose sizes differ by at most one.
fn split(units: usize, parts: usize) -> Vec<Range<usize>> {
    let parts = parts.clamp(1, units.max(1));
    (0..parts).map(|i| units * i / parts..units * (i + 1) / parts).collect()
}

/// `p` over all its rows and columns on rayon's threads: by blocks of rows where there are many
/// rows, else by columns (the 7x7 maps and the head).
///
/// # Safety
/// As [`pointwise`] for the whole call.
unsafe fn pointwise_parallel(p: &Pointwise) {
    let threads = rayon::current_num_threads().max(1);
    let tile = TILE_ROWS;
    let row_tiles = p.rows.div_ceil(tile);
    let panel = p.weights.panel;
    let panels = p.columns.end.div_ceil(panel) - p.columns.start / panel;
    if threads == 1 || (row_tiles < 2 * threads && panels < 2 * threads) {
        // SAFETY: as the caller's.
        return unsafe { pointwise(p) };
    }
    // Few rows: the weights are the larger operand, and split by panels each thread reads only
    // its share of them.
    if (p.rows > SHORT_CALL_ROWS && row_tiles >= 4 * threads) || panels < 2 * threads {
        split(row_tiles, threads).into_par_iter().for_each(|tiles| {
            let rows = tiles.start * tile..(tiles.end * tile).min(p.rows);
            let part = Pointwise {
                rows: rows.len(),
                a: p.a.wrapping_add(rows.start * p.lda),
                out: p.out.wrapping_add(rows.start * p.ldo),
                residual: if p.residual.is_null() { p.residual } else { p.residual.wrapping_add(rows.start * p.ldr) },
                columns: p.columns.clone(),
                ..*p
            };
            // SAFETY: each part writes its own rows.
            unsafe { pointwise(&part) }
        });
    } else {
        // By 16-column vectors, not whole panels: 320 columns are 5 panels of 64, which two
        // threads would share 3:2; a part may end inside a panel (its last tiles are narrower).
        let first = p.columns.start / LANES;
        let vectors = p.columns.end.div_ceil(LANES) - first;
        split(vectors, threads).into_par_iter().for_each(|part| {
            let columns = (first + part.start) * LANES..((first + part.end) * LANES).min(p.columns.end);
            // SAFETY: each part writes its own columns.
            unsafe { pointwise(&Pointwise { columns, ..*p }) }
        });
    }
}

/// The folded weights of one inverted-residual bottleneck with 3x3 depthwise convolution.
#[derive(Clone, Debug)]
pub struct FusedBottleneck {
    input: usize,
    hidden: usize,
    /// `hidden` rounded up to a multiple of 16: floats per pixel of the expanded rows.
    pitch: usize,
    output: usize,
    stride: usize,
    /// `[input, pitch]`, absent when the block has no expansion.
    expand: Option<PackedWeights>,
    /// Tap-major `[9, pitch]` and `[pitch]`.
    depthwise_weight: Vec<f32>,
    depthwise_bias: Vec<f32>,
    eca_taps: Option<Vec<f32>>,
    /// `[pitch, output]`.
    project: PackedWeights,
    residual: bool,
    /// The stem whose output this block takes, computed here row by row ([`Self::with_stem`]).
    stem: Option<Arc<DenseConv>>,
}

/// Output rows per thread from which a bottleneck's tasks split rows, not hidden channels: a band
/// of 4 rows at stride 1 expands 5 or 6 input rows, yet its stored rows stay in the core that
/// made them (14x14 maps at 2 threads: ECMobileNet 2.82-2.94 -> 2.74-2.85 ms in 4 interleaved
/// pairs, where 8 rows kept them to channel parts; splitting 7x7 maps' 4 and 3 rows cost 0.3 ms).
const MIN_BAND_ROWS: usize = 4;

/// Output width from which a bottleneck projects its depthwise rows one by one
/// ([`FusedBottleneck::forward_image`]).
const DIRECT_PROJECTION_WIDTH: usize = 28;

/// Where a bottleneck task's depthwise rows go.
#[derive(Clone, Copy)]
enum Sink<'a> {
    /// Into the whole depthwise output, `[oh, ow, pitch]`.
    Store(*mut f32),
    /// Each straight through the projection with `weights` (plus `residual`, or null) into `out`
    /// (`[oh, ow, output]`).
    Project { weights: &'a PackedWeights, out: *mut f32, residual: *const f32 },
}

// SAFETY: tasks given a sink write disjoint rows of its outputs (said at each use).
unsafe impl Send for Sink<'_> {}
unsafe impl Sync for Sink<'_> {}

/// What a bottleneck pass reads: a channels-last map, or (a block fused with the stem) the
/// zero-padded image and where the stem's taps are in it.
#[derive(Clone, Copy)]
enum Input<'a> {
    Map(&'a [f32]),
    Image(&'a PaddedImage<'a>),
}

/// An image zero-padded for the stem ([`DenseConv::with_padded`]).
struct PaddedImage<'a> {
    data: &'a [f32],
    /// Padded width.
    width: usize,
    /// Offset of each tap (channel, ky, kx) from the top left of its patch.
    taps: Vec<usize>,
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
        let pitch = hidden.next_multiple_of(LANES);
        // Padded hidden channels: zero expansion weights and bias, so zero after ReLU6.
        let expand = expand
            .map(|(w, b)| {
                let (mut w, mut b) = (to_vec(w)?, to_vec(b)?);
                w.resize(pitch * input, 0.0);
                b.resize(pitch, 0.0);
                Ok::<_, candle_core::Error>(PackedWeights::from_output_major(&w, &b, pitch, input))
            })
            .transpose()?;
        let (dw, dw_bias) = (to_vec(depthwise.0)?, to_vec(depthwise.1)?);
        let mut depthwise_weight = vec![0f32; 9 * pitch];
        for (c, taps) in dw.chunks_exact(9).enumerate() {
            for (t, &v) in taps.iter().enumerate() {
                depthwise_weight[t * pitch + c] = v;
            }
        }
        let mut depthwise_bias = dw_bias;
        depthwise_bias.resize(pitch, 0.0);
        // Projection rows of padded channels are zero.
        let mut project_weight = vec![0f32; output * pitch];
        for (dst, src) in project_weight.chunks_exact_mut(pitch).zip(to_vec(project.0)?.chunks_exact(hidden)) {
            dst[..hidden].copy_from_slice(src);
        }
        Ok(FusedBottleneck {
            input,
            hidden,
            pitch,
            output,
            stride,
            expand,
            depthwise_weight,
            depthwise_bias,
            eca_taps: eca.map(to_vec).transpose()?,
            project: PackedWeights::from_output_major(&project_weight, &to_vec(project.1)?, output, pitch),
            residual: stride == 1 && input == output,
            stem: None,
        })
    }

    /// This block taking the NCHW image instead of its input map: each task computes the stem's
    /// output rows just before the depthwise convolution reads them, where a block without
    /// expansion would copy them from the stem's map. The stem's map (32 x 112 x 112, 1.6 MB at
    /// 224², the largest of the network) is then never written nor read back.
    pub fn with_stem(&self, stem: Arc<DenseConv>) -> Result<Self> {
        if self.expand.is_some() || stem.is_pointwise() || stem.out_channels != self.input || self.residual {
            candle_core::bail!("fused bottleneck: only a first block without expansion or residual takes the stem");
        }
        Ok(FusedBottleneck { stem: Some(stem), ..self.clone() })
    }

    /// Input row `y` of `x` (`[h, w, input]`) expanded (or copied, without expansion, or computed
    /// by the stem) into the padded `row` (`w + 2` pixels of `pitch`; pixels `1..=w`), channels
    /// `channels` only.
    fn fill_row(&self, x: Input, w: usize, y: usize, row: &mut [f32], channels: Range<usize>) {
        let pixels = &mut row[self.pitch..(w + 1) * self.pitch];
        let x = match (x, &self.stem) {
            (Input::Map(x), None) => x,
            (Input::Image(image), Some(stem)) => {
                let channels = channels.start..channels.end.min(self.input);
                // SAFETY: `pixels` holds the row's `w` pixels of `pitch` >= `input` floats.
                return unsafe { stem.output_row(image, w, y, channels, pixels.as_mut_ptr(), self.pitch) };
            }
            _ => unreachable!("fused bottleneck: the input matches the block (checked by cpu_fwd)"),
        };
        let source = &x[y * w * self.input..(y + 1) * w * self.input];
        match &self.expand {
            Some(weights) => {
                let p = Pointwise {
                    rows: w,
                    a: source.as_ptr(),
                    lda: self.input,
                    steps: None,
                    weights,
                    columns: channels,
                    out: pixels.as_mut_ptr(),
                    ldo: self.pitch,
                    residual: std::ptr::null(),
                    ldr: 0,
                    activation: Activation::Relu6,
                };
                // SAFETY: `source` holds the row's `w` pixels of `input`, `pixels` `w` of `pitch`.
                unsafe { pointwise(&p) }
            }
            None => {
                let channels = channels.start..channels.end.min(self.input);
                for (dst, src) in pixels.chunks_exact_mut(self.pitch).zip(source.chunks_exact(self.input)) {
                    dst[channels.clone()].copy_from_slice(&src[channels.clone()]);
                }
            }
        }
    }

    /// One image: `x` `[h, w, input]` -> `out` `[oh, ow, output]`.
    ///
    /// # Safety
    /// `out` points at `oh * ow * output` writable floats, all of which are written.
    unsafe fn forward_image(&self, x: Input, h: usize, w: usize, out: *mut f32) {
        let s = self.stride;
        let (oh, ow) = (same_padding(h, 3, s).0, same_padding(w, 3, s).0);
        let pitch = self.pitch;
        let threads = rayon::current_num_threads().max(1);
        let residual = match x {
            Input::Map(x) if self.residual => x.as_ptr(),
            _ => std::ptr::null(),
        };
        // Large maps split output rows (each task expands its rows, the one or two rows at a
        // band's edge twice); small maps split whole expansion panels.
        if !(oh >= MIN_BAND_ROWS * threads || threads == 1) {
            let panel = self.expand.as_ref().map_or(LANES, |e| e.panel);
            let channels = split(pitch.div_ceil(panel), threads)
                .into_iter()
                .map(|panels| panels.start * panel..(panels.end * panel).min(pitch))
                .collect();
            // SAFETY: as the caller's.
            return unsafe { self.forward_channel_parts(x, h, w, channels, residual, out) };
        }
        let bands = split(oh, threads);
        // Without ECA (MobileNetV2), on wide maps, each depthwise row goes through the projection
        // as soon as it is made, so the depthwise output is never stored (MobileNetV2 at 2
        // threads: 3.8-4.0 -> 3.5-3.6 ms). ECA's gate needs every row first. Making the rows
        // twice for it, a pass for the sums and one to project, where they are cheap (the first
        // block's, from the stem) cost ECMobileNet 0.3 ms more than it saved. Narrow maps keep
        // one projection of a band, which reads the weights once rather than once a row.
        if ow >= DIRECT_PROJECTION_WIDTH && self.eca_taps.is_none() {
            let sink = Sink::Project { weights: &self.project, out, residual };
            bands.par_iter().for_each(|rows| {
                let mut sums = vec![0f64; pitch];
                // SAFETY: the bands' rows of the outputs are disjoint.
                unsafe { self.expand_and_depthwise(x, h, w, rows.clone(), 0..pitch, sink, &mut sums) };
            });
            return;
        }
        // Each band's depthwise output goes to a buffer of the thread that makes it, and (after
        // the gate, which needs every band's sums) that thread's task, as rayon hands them out,
        // projects it: the stored rows stay in the core's own L2. One buffer for the whole map,
        // each task writing its band, had the cores taking lines from each other's caches
        // whenever a block's band boundary fell elsewhere than the last block's: ECMobileNet at 2
        // threads 3.00-3.38 -> 2.78-2.80 ms in 4 interleaved pairs.
        let stored: Vec<(Vec<f64>, Vec<f32>)> = bands
            .par_iter()
            .map(|rows| {
                let mut buffer = BAND_OUT.take();
                // Every element is written before it is read: a reused buffer is not cleared.
                let len = rows.len() * ow * pitch;
                if buffer.len() < len {
                    buffer.resize(len, 0.0);
                }
                let mut sums = vec![0f64; pitch];
                // The sink addresses the whole map; the buffer holds this band's rows.
                let sink = Sink::Store(buffer.as_mut_ptr().wrapping_sub(rows.start * ow * pitch));
                // SAFETY: this task writes rows `rows` of the sink, which its buffer holds.
                unsafe { self.expand_and_depthwise(x, h, w, rows.clone(), 0..pitch, sink, &mut sums) };
                (sums, buffer)
            })
            .collect();
        let sums: Vec<f64> = (0..self.hidden).map(|c| stored.iter().map(|(s, _)| s[c]).sum()).collect();
        let gate = self.eca_taps.as_ref().map(|taps| eca_gate(&sums, oh * ow, taps));
        let (out, residual) = (SharedMut(out), SharedMut(residual.cast_mut()));
        stored.into_par_iter().zip(&bands).for_each(|((_, buffer), rows)| {
            let first = rows.start * ow;
            let residual = residual.get().cast_const();
            self.with_gated_projection(gate.as_deref(), |weights| {
                let p = Pointwise {
                    rows: rows.len() * ow,
                    a: buffer.as_ptr(),
                    lda: pitch,
                    steps: None,
                    weights,
                    columns: 0..self.output,
                    out: out.get().wrapping_add(first * self.output),
                    ldo: self.output,
                    residual: if residual.is_null() { residual } else { residual.wrapping_add(first * self.input) },
                    ldr: self.input,
                    activation: Activation::Identity,
                };
                // SAFETY: the buffer holds the band's pixels of `pitch`; `out` and the residual
                // (same shape) hold the whole map, whose band rows are this task's alone.
                unsafe { pointwise(&p) }
            });
            BAND_OUT.set(buffer);
        });
    }

    /// `f` of the projection's weights, each row scaled by its channel's ECA `gate`
    /// (`W (g ⊙ x) = (W diag(g)) x`) into a buffer of this thread's (the weights as they are
    /// without a gate). Each task scales the weights it uses itself: scaled once and read by
    /// both cores, they crossed between the cores' caches every frame, and a 14x14 block
    /// spent more time on that than on scaling them twice.
    fn with_gated_projection<R>(&self, gate: Option<&[f32]>, f: impl FnOnce(&PackedWeights) -> R) -> R {
        let Some(gate) = gate else { return f(&self.project) };
        let mut scaled = SCALED_PROJECTION.take();
        self.project.scaled_rows_into(gate, &mut scaled);
        let result = f(&scaled);
        SCALED_PROJECTION.set(scaled);
        result
    }

    /// [`Self::forward_image`] of a small map, each task expanding and convolving every row for
    /// its `channels`, into one depthwise output shared by the tasks; the projection then splits
    /// pixels (or, for 7x7 maps, output channels) among the threads.
    ///
    /// # Safety
    /// As [`Self::forward_image`]; `residual` is null or the input map.
    unsafe fn forward_channel_parts(
        &self,
        x: Input,
        h: usize,
        w: usize,
        channels: Vec<Range<usize>>,
        residual: *const f32,
        out: *mut f32,
    ) {
        let (oh, ow) = (same_padding(h, 3, self.stride).0, same_padding(w, 3, self.stride).0);
        let pitch = self.pitch;
        let size = oh * ow * pitch;
        let mut buffer = DEPTHWISE_OUT.take();
        // Every element is written before it is read: a reused buffer is not cleared.
        if buffer.len() < size {
            buffer.resize(size, 0.0);
        }
        let depthwise_out = &mut buffer[..size];
        let sink = Sink::Store(depthwise_out.as_mut_ptr());
        let task_sums: Vec<Vec<f64>> = channels
            .par_iter()
            .map(|channels| {
                let mut sums = vec![0f64; pitch];
                // SAFETY: the tasks' channels of the depthwise output are disjoint.
                unsafe { self.expand_and_depthwise(x, h, w, 0..oh, channels.clone(), sink, &mut sums) };
                sums
            })
            .collect();
        let sums: Vec<f64> = (0..self.hidden).map(|c| task_sums.iter().map(|s| s[c]).sum()).collect();
        let project = |depthwise_out: &[f32], weights: &PackedWeights| {
            let p = Pointwise {
                rows: oh * ow,
                a: depthwise_out.as_ptr(),
                lda: pitch,
                steps: None,
                weights,
                columns: 0..self.output,
                out,
                ldo: self.output,
                residual,
                ldr: self.input,
                activation: Activation::Identity,
            };
            // SAFETY: `depthwise_out` holds oh*ow pixels of `pitch`, `out` and the residual
            // (same shape) oh*ow pixels of `output` channels.
            unsafe { pointwise_parallel(&p) }
        };
        // Small maps have few pixels: the gate scales the depthwise output, not the weights.
        if let Some(taps) = &self.eca_taps {
            let gate = eca_gate(&sums, oh * ow, taps);
            let threads = rayon::current_num_threads().max(1);
            depthwise_out.par_chunks_mut(pitch * (oh * ow).div_ceil(threads)).for_each(|part| {
                for pixel in part.chunks_exact_mut(pitch) {
                    pixel.iter_mut().zip(&gate).for_each(|(v, g)| *v *= g);
                }
            });
        }
        project(depthwise_out, &self.project);
        DEPTHWISE_OUT.set(buffer);
    }

    /// Output rows `rows`, channels `channels` of the depthwise convolution of the expanded
    /// input, to `sink`, adding each channel's outputs to `sums`. Input rows are expanded into a
    /// ring of three padded rows just before they are read.
    ///
    /// # Safety
    /// The sink's buffers hold the whole map (`oh * ow` pixels of `pitch` floats to store, of
    /// `output` to project, of `input` for the residual); no other thread writes this part.
    #[allow(clippy::too_many_arguments)]
    unsafe fn expand_and_depthwise(
        &self,
        x: Input,
        h: usize,
        w: usize,
        rows: Range<usize>,
        channels: Range<usize>,
        sink: Sink,
        sums: &mut [f64],
    ) {
        let s = self.stride;
        let (_, pad_top, _) = same_padding(h, 3, s);
        let (ow, pad_left, _) = same_padding(w, 3, s);
        let pitch = self.pitch;
        let row_floats = (w + 2) * pitch;
        let mut ring = vec![0f32; 4 * row_floats];
        let mut scratch = match sink {
            Sink::Store(_) => Vec::new(),
            _ => vec![0f32; ow * pitch],
        };
        let mut next = (rows.start * s).saturating_sub(pad_top);
        for oy in rows {
            let top = (oy * s) as isize - pad_top as isize;
            while (next as isize) <= (top + 2).min(h as isize - 1) {
                let row = &mut ring[next % 3 * row_floats..(next % 3 + 1) * row_floats];
                self.fill_row(x, w, next, row, channels.clone());
                next += 1;
            }
            let input_rows = [0, 1, 2].map(|ky| {
                let y = top + ky;
                let slot = if (0..h as isize).contains(&y) { y as usize % 3 } else { 3 };
                ring[slot * row_floats..].as_ptr()
            });
            let p = DepthwiseRow {
                rows: input_rows,
                pitch,
                stride: s,
                first_pixel: 1 - pad_left,
                width: ow,
                weights: &self.depthwise_weight,
                bias: &self.depthwise_bias,
                channels: channels.clone(),
                out: match sink {
                    Sink::Store(depthwise) => depthwise.wrapping_add(oy * ow * pitch),
                    _ => scratch.as_mut_ptr(),
                },
            };
            // SAFETY: the rows were filled above (or are the zero row) for these channels; the
            // caller's contract for the sink, or this task's scratch row.
            unsafe { depthwise_row(&p, &mut sums[channels.clone()]) };
            if let Sink::Project { weights, out, residual } = sink {
                let p = Pointwise {
                    rows: ow,
                    a: scratch.as_ptr(),
                    lda: pitch,
                    steps: None,
                    weights,
                    columns: 0..self.output,
                    out: out.wrapping_add(oy * ow * self.output),
                    ldo: self.output,
                    residual: if residual.is_null() { residual } else { residual.wrapping_add(oy * ow * self.input) },
                    ldr: self.input,
                    activation: Activation::Identity,
                };
                // SAFETY: the scratch row holds `ow` pixels of `pitch`; output row `oy` (and the
                // residual's) is this task's alone (the caller's contract).
                unsafe { pointwise(&p) };
            }
        }
    }
}

impl CustomOp1 for FusedBottleneck {
    fn name(&self) -> &'static str {
        "fused-inverted-residual-nhwc"
    }

    /// `[B, H, W, input]` -> `[B, OH, OW, output]`; fused with the stem, `[B, 3, H, W]` (the NCHW
    /// image) -> `[B, OH, OW, output]`.
    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = input(storage, layout, "fused bottleneck")?;
        let (batch, a, b, c) = layout.shape().dims4()?;
        let (channels, image_size, (h, w)) = match &self.stem {
            Some(stem) => (a, (b, c), stem.output_size(b, c)),
            None => (c, (a, b), (a, b)),
        };
        let expected = self.stem.as_ref().map_or(self.input, |stem| stem.in_channels);
        if channels != expected {
            candle_core::bail!("fused bottleneck: {channels} input channels, expected {expected}");
        }
        let (oh, ow) = (h.div_ceil(self.stride), w.div_ceil(self.stride));
        let per_image = self.output * oh * ow;
        // SAFETY: each image's pass writes all of its `per_image` floats.
        let out = unsafe {
            written_output(batch * per_image, |out| {
                // `[3, H, W]` images or `[h, w, input]` maps: `a * b * c` floats each.
                for (i, image) in x.chunks_exact((a * b * c).max(1)).take(batch).enumerate() {
                    let out = out.add(i * per_image);
                    match &self.stem {
                        Some(stem) => stem.with_padded(image, image_size.0, image_size.1, |padded| {
                            self.forward_image(Input::Image(padded), h, w, out)
                        }),
                        None => self.forward_image(Input::Map(image), h, w, out),
                    }
                }
            })
        };
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, oh, ow, self.output])))
    }
}

/// A folded convolution with fused bias and activation, on channels-last output: a full
/// convolution (the stem) reads the NCHW image and multiplies each output row's columns by the
/// weights; a 1x1 convolution (the head) is one product on the channels-last pixels.
#[derive(Debug)]
pub struct DenseConv {
    in_channels: usize,
    out_channels: usize,
    kernel: (usize, usize),
    stride: usize,
    padding: Padding,
    /// `[in * kh * kw, out]`.
    weights: PackedWeights,
    activation: Activation,
}

/// Where a full convolution's zero padding goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Padding {
    /// TensorFlow's "SAME" (the TFLite networks): `ceil(size / stride)` outputs, the odd extra
    /// pixel of padding at the bottom and right.
    Same,
    /// PyTorch's `padding = kernel / 2` on every side (XFeat).
    HalfKernel,
}

impl Padding {
    /// Output size and padding before the first pixel, along a side of `input` pixels.
    fn geometry(self, input: usize, kernel: usize, stride: usize) -> (usize, usize) {
        match self {
            Padding::Same => {
                let (out, before, _) = same_padding(input, kernel, stride);
                (out, before)
            }
            Padding::HalfKernel => ((input + 2 * (kernel / 2) - kernel) / stride + 1, kernel / 2),
        }
    }
}

impl DenseConv {
    /// With TensorFlow's "SAME" padding.
    pub fn new(weight: &Tensor, bias: &Tensor, stride: usize, activation: Activation) -> Result<Self> {
        Self::with_padding(weight, bias, stride, Padding::Same, activation)
    }

    pub fn with_padding(
        weight: &Tensor,
        bias: &Tensor,
        stride: usize,
        padding: Padding,
        activation: Activation,
    ) -> Result<Self> {
        let (out_channels, in_channels, kh, kw) = weight.dims4()?;
        Ok(DenseConv {
            in_channels,
            out_channels,
            kernel: (kh, kw),
            stride,
            padding,
            weights: PackedWeights::from_output_major(
                &to_vec(weight)?,
                &to_vec(bias)?,
                out_channels,
                in_channels * kh * kw,
            ),
            activation,
        })
    }

    /// Whether the op takes a channels-last map (1x1 at stride 1) rather than the NCHW image.
    pub fn is_pointwise(&self) -> bool {
        (self.kernel, self.stride) == ((1, 1), 1)
    }

    /// Output height and width for an `h x w` image (a full convolution).
    fn output_size(&self, h: usize, w: usize) -> (usize, usize) {
        (self.padding.geometry(h, self.kernel.0, self.stride).0, self.padding.geometry(w, self.kernel.1, self.stride).0)
    }

    /// `f` of the NCHW image `x` (`[in, h, w]`) zero-padded for this convolution, in a buffer
    /// kept per thread: the same shape as last time leaves the padding as it was, zero, and only
    /// the image is copied in.
    fn with_padded<R>(&self, x: &[f32], h: usize, w: usize, f: impl FnOnce(&PaddedImage) -> R) -> R {
        let ((kh, kw), s) = (self.kernel, self.stride);
        let (oh, top) = self.padding.geometry(h, kh, s);
        let (ow, left) = self.padding.geometry(w, kw, s);
        let (ph, pw) = ((oh - 1) * s + kh, (ow - 1) * s + kw);
        let shape = (self.in_channels, ph, pw, top, left, h, w);
        let size = self.in_channels * ph * pw;
        let run = |padded: &mut [f32]| {
            for (plane, source) in padded.chunks_exact_mut(ph * pw).zip(x.chunks_exact(h * w)) {
                for (row, source_row) in plane.chunks_exact_mut(pw).skip(top).zip(source.chunks_exact(w)) {
                    let n = w.min(pw - left);
                    row[left..left + n].copy_from_slice(&source_row[..n]);
                }
            }
            let taps = (0..self.in_channels * kh * kw)
                .map(|t| (t / (kh * kw)) * ph * pw + (t / kw % kh) * pw + t % kw)
                .collect();
            f(&PaddedImage { data: padded, width: pw, taps })
        };
        PADDED_IMAGE.with(|buffer| match buffer.try_borrow_mut() {
            Ok(mut reused) => {
                if reused.0 != shape {
                    *reused = (shape, vec![0f32; size]);
                }
                run(&mut reused.1)
            }
            // This thread is already inside a stem (it stole another pass's work while waiting).
            Err(_) => run(&mut vec![0f32; size]),
        })
    }

    /// Output row `oy` (`ow` pixels), channels `columns`, of the full convolution of `image`, to
    /// `out` with `ldo` floats per pixel: one product whose rows (output pixels) read their
    /// patches from the padded image through the offsets of the taps ([`Pointwise::steps`]).
    ///
    /// # Safety
    /// `out` points at `ow` pixels of `ldo` floats covering `columns`, which no other thread
    /// writes meanwhile; `oy` and `ow` are within the convolution's output.
    unsafe fn output_row(
        &self,
        image: &PaddedImage,
        ow: usize,
        oy: usize,
        columns: Range<usize>,
        out: *mut f32,
        ldo: usize,
    ) {
        let p = Pointwise {
            rows: ow,
            a: image.data[oy * self.stride * image.width..].as_ptr(),
            lda: self.stride,
            steps: Some(&image.taps),
            weights: &self.weights,
            columns,
            out,
            ldo,
            residual: std::ptr::null(),
            ldr: 0,
            activation: self.activation,
        };
        // SAFETY: every patch of the row lies in the padded image (its size covers the last
        // patch); the caller's contract for `out`.
        unsafe { pointwise(&p) }
    }

    /// The full convolution of one NCHW image `x` `[in, h, w]` into `out` `[oh, ow, out]`, the
    /// output rows split among the threads.
    ///
    /// # Safety
    /// `out` points at `oh * ow * out_channels` writable floats, all of which are written.
    unsafe fn forward_full(&self, x: &[f32], h: usize, w: usize, out: *mut f32) {
        let (oh, ow) = self.output_size(h, w);
        let row_out = ow * self.out_channels;
        let out = SharedMut(out);
        self.with_padded(x, h, w, |image| {
            split(oh, rayon::current_num_threads()).into_par_iter().for_each(|rows| {
                for oy in rows {
                    // SAFETY: output row `oy` is this task's alone.
                    unsafe {
                        self.output_row(
                            image,
                            ow,
                            oy,
                            0..self.out_channels,
                            out.get().wrapping_add(oy * row_out),
                            self.out_channels,
                        )
                    };
                }
            })
        })
    }
}

/// Channels, padded height and width, top and left padding, height and width of a padded image.
type PaddedShape = (usize, usize, usize, usize, usize, usize, usize);

thread_local! {
    /// The stem's zero-padded image, kept with the shape it was made for.
    static PADDED_IMAGE: std::cell::RefCell<(PaddedShape, Vec<f32>)> = Default::default();
}

impl CustomOp1 for DenseConv {
    fn name(&self) -> &'static str {
        "dense-conv2d-same-nhwc"
    }

    /// 1x1: `[B, H, W, in]` -> `[B, H, W, out]`; otherwise `[B, in, H, W]` -> `[B, OH, OW, out]`.
    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = input(storage, layout, "dense conv")?;
        let (batch, a, b, c) = layout.shape().dims4()?;
        if self.is_pointwise() {
            let (h, w, channels) = (a, b, c);
            if channels != self.in_channels {
                candle_core::bail!("1x1 conv: {channels} input channels, expected {}", self.in_channels);
            }
            // SAFETY: the product writes every column of every pixel of the batch.
            let out = unsafe {
                written_output(batch * h * w * self.out_channels, |out| {
                    let p = Pointwise {
                        rows: batch * h * w,
                        a: x.as_ptr(),
                        lda: channels,
                        steps: None,
                        weights: &self.weights,
                        columns: 0..self.out_channels,
                        out,
                        ldo: self.out_channels,
                        residual: std::ptr::null(),
                        ldr: 0,
                        activation: self.activation,
                    };
                    // SAFETY: `x` and `out` hold all the pixels of the batch.
                    pointwise_parallel(&p)
                })
            };
            return Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, h, w, self.out_channels])));
        }
        let (channels, h, w) = (a, b, c);
        if channels != self.in_channels {
            candle_core::bail!("dense conv: {channels} input channels, expected {}", self.in_channels);
        }
        let (oh, ow) = self.output_size(h, w);
        let per_image = oh * ow * self.out_channels;
        // SAFETY: each image's convolution writes all of its `per_image` floats.
        let out = unsafe {
            written_output(batch * per_image, |out| {
                for (i, image) in x.chunks_exact(channels * h * w).enumerate() {
                    self.forward_full(image, h, w, out.add(i * per_image));
                }
            })
        };
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, oh, ow, self.out_channels])))
    }
}

/// `[B, H, W, C]` -> `[B, C, H, W]` for the inference path's last map (no gradient), sixteen
/// channels at a time: 42 us for the 7x7x1280 head map, where candle's strided copy of the
/// permuted tensor, element by element, took 107 us.
pub fn channels_first(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1_no_bwd(&ChannelsFirst)
}

struct ChannelsFirst;

impl CustomOp1 for ChannelsFirst {
    fn name(&self) -> &'static str {
        "channels-first"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = input(storage, layout, "channels first")?;
        let (batch, h, w, c) = layout.shape().dims4()?;
        let pixels = h * w;
        let mut out = vec![0f32; x.len()];
        for (image, out) in x.chunks_exact(pixels * c).zip(out.chunks_exact_mut(pixels * c)) {
            // Sixteen channels (one cache line of each pixel) at a time, into sixteen output rows.
            for first in (0..c).step_by(LANES) {
                let channels = first..(first + LANES).min(c);
                for (p, pixel) in image.chunks_exact(c).enumerate() {
                    for (j, &v) in pixel[channels.clone()].iter().enumerate() {
                        out[(first + j) * pixels + p] = v;
                    }
                }
            }
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[batch, c, h, w])))
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use candle_core::{DType, Device};
    use candle_nn::VarBuilder;

    use super::*;
    use crate::model::layers::{BlockShape, ConvKind, ConvUnit, InvertedResidual, Mode};

    /// `[B, C, H, W]` -> contiguous `[B, H, W, C]`.
    fn to_channels_last(x: &Tensor) -> Result<Tensor> {
        x.permute((0, 2, 3, 1))?.contiguous()
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    fn random(shape: &[usize], std: f32) -> Tensor {
        Tensor::randn(0f32, std, shape, &Device::Cpu).unwrap()
    }

    /// A folded bottleneck of `shape` with random weights.
    fn random_block(shape: BlockShape) -> Result<InvertedResidual> {
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
        InvertedResidual::load(VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu), shape, false)
    }

    #[test]
    fn fused_bottleneck_equals_stock_ops() -> Result<()> {
        // With and without expansion, ECA and residual; strides 1 and 2; odd and even sizes; hidden
        // counts that are and are not multiples of 16; batch 2; on three threads: maps of fewer
        // than 12 output rows split the hidden channels among the tasks, the others split
        // output rows (tasks expanding the rows at their edges twice), at stride 2 with odd and
        // even sizes.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let cases = [
            (BlockShape { input: 8, hidden: 48, output: 8, stride: 1, eca_kernel: Some(3) }, 9, 11),
            (BlockShape { input: 8, hidden: 48, output: 16, stride: 2, eca_kernel: Some(5) }, 14, 14),
            (BlockShape { input: 16, hidden: 16, output: 8, stride: 1, eca_kernel: None }, 12, 7),
            (BlockShape { input: 12, hidden: 72, output: 12, stride: 1, eca_kernel: None }, 5, 5),
            (BlockShape { input: 12, hidden: 72, output: 24, stride: 2, eca_kernel: Some(3) }, 7, 9),
            (BlockShape { input: 8, hidden: 24, output: 8, stride: 1, eca_kernel: Some(3) }, 23, 41),
            (BlockShape { input: 8, hidden: 24, output: 12, stride: 2, eca_kernel: None }, 61, 66),
            (BlockShape { input: 16, hidden: 96, output: 16, stride: 1, eca_kernel: Some(3) }, 50, 30),
            (BlockShape { input: 8, hidden: 48, output: 16, stride: 2, eca_kernel: Some(3) }, 53, 47),
            // Without ECA on wide maps: each depthwise row projected as it is made, with and
            // without residual.
            (BlockShape { input: 16, hidden: 96, output: 16, stride: 1, eca_kernel: None }, 40, 30),
            // Copied (not expanded) rows narrower than the pitch.
            (BlockShape { input: 12, hidden: 12, output: 8, stride: 1, eca_kernel: Some(3) }, 30, 9),
        ];
        for (shape, h, w) in cases {
            let block = random_block(shape)?;
            let op = block.fused_kernel()?.expect("folded constant weights have a fused kernel");
            let x = random(&[2, shape.input, h, w], 2.0);
            let fast = pool.install(|| channels_first(&to_channels_last(&x)?.apply_op1_no_bwd(&op)?))?;
            let reference = block.forward_t(&x, Mode::Reference)?;
            assert_eq!(fast.dims(), reference.dims(), "{shape:?}");
            let diff = max_diff(&fast, &reference);
            assert!(diff < 1e-4, "{shape:?} {h}x{w}: max diff {diff}");
            // The layers' own inference path (NCHW depthwise kernel), where there is no plan.
            let layered = pool.install(|| block.forward_t(&x, Mode::Inference))?;
            let diff = max_diff(&layered, &reference);
            assert!(diff < 1e-4, "{shape:?} {h}x{w}: layers' inference max diff {diff}");
        }
        Ok(())
    }

    #[test]
    fn dense_conv_equals_stock_ops() -> Result<()> {
        // The stem (3x3, stride 2, odd and even sizes, 32 outputs as in the networks) and 1x1 units,
        // batch 2; on three threads: the products split by rows where there are many pixels, by
        // weight panels for a head-like 1x1 with few pixels and 384 outputs.
        let cases = [
            (3, 2, 16, 16, 6, Activation::Relu6),
            (3, 2, 9, 12, 6, Activation::Relu6),
            (3, 1, 7, 6, 6, Activation::Identity),
            (1, 1, 5, 4, 6, Activation::Relu6),
            (3, 2, 70, 57, 32, Activation::Relu6),
            (1, 1, 31, 40, 6, Activation::Identity),
            (1, 1, 3, 3, 384, Activation::Relu6),
        ];
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        for (kernel, stride, h, w, out, activation) in cases {
            let kind = if kernel == 1 { ConvKind::Pointwise } else { ConvKind::Full { stride } };
            let tensors = HashMap::from([
                ("weight".to_string(), random(&[out, 3, kernel, kernel], 1.0)),
                ("bias".to_string(), random(&[out], 1.0)),
            ]);
            let unit = ConvUnit::load(
                VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu),
                (out, 3, kernel, kernel),
                kind,
                activation,
                false,
            )?;
            let op = unit.dense_kernel()?.expect("a folded constant unit has a fused kernel");
            let x = random(&[2, 3, h, w], 2.0);
            // The op takes the NCHW image (full convolution) or a channels-last map (1x1).
            let input = if op.is_pointwise() { to_channels_last(&x)? } else { x.contiguous()? };
            let fast = pool.install(|| channels_first(&input.apply_op1_no_bwd(&op)?))?;
            let reference = unit.forward_t(&x, Mode::Reference)?;
            assert_eq!(fast.dims(), reference.dims());
            let diff = max_diff(&fast, &reference);
            assert!(diff < 1e-4, "{kernel}x{kernel} s{stride} {h}x{w} -> {out}: max diff {diff}");
            let layered = pool.install(|| unit.forward_t(&x, Mode::Inference))?;
            let diff = max_diff(&layered, &reference);
            assert!(diff < 1e-4, "{kernel}x{kernel} s{stride} {h}x{w} -> {out}: layer's inference max diff {diff}");
        }
        Ok(())
    }

    #[test]
    fn dense_conv_with_half_kernel_padding_and_relu_equals_stock_ops() -> Result<()> {
        // PyTorch's padding (XFeat): 3x3 at strides 1 and 2 on odd and even sizes, and 1x1.
        let cases = [(3, 1, 12, 16, 8), (3, 2, 12, 16, 24), (3, 2, 9, 13, 4), (3, 1, 7, 5, 64), (1, 1, 6, 10, 65)];
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        for (kernel, stride, h, w, out) in cases {
            let (weight, bias) = (random(&[out, 5, kernel, kernel], 1.0), random(&[out], 1.0));
            let op = DenseConv::with_padding(&weight, &bias, stride, Padding::HalfKernel, Activation::Relu)?;
            let x = random(&[1, 5, h, w], 2.0);
            let input = if op.is_pointwise() { to_channels_last(&x)? } else { x.contiguous()? };
            let fast = pool.install(|| channels_first(&input.apply_op1_no_bwd(&op)?))?;
            let reference =
                x.conv2d(&weight, kernel / 2, stride, 1, 1)?.broadcast_add(&bias.reshape((1, out, 1, 1))?)?.relu()?;
            assert_eq!(fast.dims(), reference.dims(), "{kernel}x{kernel} s{stride} {h}x{w}");
            let diff = max_diff(&fast, &reference);
            assert!(diff < 1e-4, "{kernel}x{kernel} s{stride} {h}x{w} -> {out}: max diff {diff}");
        }
        Ok(())
    }

    /// The stem fused into a first block without expansion (with and without ECA, odd and even
    /// sizes, batch 2, three threads: row bands whose edge rows the stem computes twice) equals the
    /// stock stem followed by the stock block; a block with expansion does not take the stem.
    #[test]
    fn stem_fused_into_first_block_equals_stock_ops() -> Result<()> {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let stem_tensors = HashMap::from([
            ("weight".to_string(), random(&[32, 3, 3, 3], 0.5)),
            ("bias".to_string(), random(&[32], 1.0)),
        ]);
        let stem = ConvUnit::load(
            VarBuilder::from_tensors(stem_tensors, DType::F32, &Device::Cpu),
            (32, 3, 3, 3),
            ConvKind::Full { stride: 2 },
            Activation::Relu6,
            false,
        )?;
        let stem_op = Arc::new(stem.dense_kernel()?.expect("a folded stem has a fused kernel"));
        for (eca_kernel, h, w) in [(Some(3), 61, 50), (None, 40, 33)] {
            let block = random_block(BlockShape { input: 32, hidden: 32, output: 16, stride: 1, eca_kernel })?;
            let fused = block.fused_kernel()?.expect("a folded block").with_stem(stem_op.clone())?;
            let x = random(&[2, 3, h, w], 2.0);
            let fast = pool.install(|| channels_first(&x.apply_op1_no_bwd(&fused)?))?;
            let reference = block.forward_t(&stem.forward_t(&x, Mode::Reference)?, Mode::Reference)?;
            assert_eq!(fast.dims(), reference.dims());
            let diff = max_diff(&fast, &reference);
            assert!(diff < 1e-4, "{h}x{w} eca {eca_kernel:?}: max diff {diff}");
        }
        let expanding = random_block(BlockShape { input: 32, hidden: 96, output: 16, stride: 2, eca_kernel: Some(3) })?;
        assert!(expanding.fused_kernel()?.expect("a folded block").with_stem(stem_op).is_err());
        Ok(())
    }
}
