//! Register-blocked micro-kernels of the channels-last (NHWC) inference path in [`super::fused`]:
//!
//! - [`pointwise`]: a block of rows of `out = bias + a · W (+ residual)`, optional ReLU6 — a 1x1
//!   convolution on channels-last pixels (each pixel's channels are one row of `a`), the stem's
//!   columns, or the head. An `MR x NR` tile of output (pixels x 16-channel vectors) is kept in
//!   registers for the whole sum over `k`: each step loads `NR` weight vectors, broadcasts `MR`
//!   inputs and issues `MR * NR` fused multiply-adds, as in ONNX Runtime's MLAS and XNNPACK.
//! - [`depthwise_row`]: one output row of a 3x3 depthwise convolution + bias + ReLU6 on
//!   channels-last rows, adding each channel's outputs to a running sum (ECA's pooling).
//!
//! Both are written once, generic over [`Lanes`] (sixteen `f32` lanes), and built three times:
//! with AVX-512 intrinsics where the CPU has AVX-512F, with AVX2 and FMA intrinsics (two 8-lane
//! registers per vector) where it has those, and as plain arrays that any CPU runs; [`Build`]
//! picks the fastest at run time (`ECM_LCD_KERNELS` names one). The tests check every build
//! the CPU runs against naive loops. Rayon closures do not inherit `#[target_feature]`, so the
//! dispatch is per call of these kernels (a row or a block of rows), never inside them.

use std::ops::Range;

use super::depthwise::Activation;

/// Lanes per vector.
pub const LANES: usize = 16;

/// Sixteen `f32` lanes and the operations the kernels use.
pub(crate) trait Lanes: Copy {
    /// The widest [`pointwise`] tile, in vectors, whose accumulators still fit the register file
    /// beside its weight vectors and broadcast input (at [`TILE_ROWS`] pixels).
    const TILE_VECTORS: usize;
    /// Whether one-vector tiles sum even and odd steps apart (twice the accumulators, for the
    /// multiply-adds' latency), which needs the registers for it.
    const SPLIT_SUM: bool;
    /// # Safety
    /// `p` points at 16 readable floats.
    unsafe fn load(p: *const f32) -> Self;
    /// The first `n` (1..=16) floats at `p`, the other lanes zero.
    /// # Safety
    /// `p` points at `n` readable floats.
    unsafe fn load_first(p: *const f32, n: usize) -> Self;
    /// # Safety
    /// `p` points at 16 writable floats.
    unsafe fn store(self, p: *mut f32);
    /// Stores the first `n` (1..=16) lanes.
    /// # Safety
    /// `p` points at `n` writable floats.
    unsafe fn store_first(self, p: *mut f32, n: usize);
    fn splat(v: f32) -> Self;
    /// `self * b + c`.
    fn mul_add(self, b: Self, c: Self) -> Self;
    fn add(self, b: Self) -> Self;
    fn relu(self) -> Self;
    fn relu6(self) -> Self;
    fn to_array(self) -> [f32; LANES];
    /// Adds the lanes to `sums` (16 values) in double precision.
    fn add_to_f64(self, sums: &mut [f64]) {
        for (s, v) in sums.iter_mut().zip(self.to_array()) {
            *s += v as f64;
        }
    }
}

/// The portable build: an array the compiler vectorises as it can. One-vector tiles: a vector
/// is four registers of NEON or SSE.
#[derive(Clone, Copy)]
pub(crate) struct Portable([f32; LANES]);

impl Lanes for Portable {
    const TILE_VECTORS: usize = 1;
    const SPLIT_SUM: bool = false;
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        Portable(unsafe { std::ptr::read_unaligned(p as *const [f32; LANES]) })
    }
    #[inline(always)]
    unsafe fn load_first(p: *const f32, n: usize) -> Self {
        let mut v = [0f32; LANES];
        v[..n].copy_from_slice(unsafe { std::slice::from_raw_parts(p, n) });
        Portable(v)
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        unsafe { std::ptr::write_unaligned(p as *mut [f32; LANES], self.0) }
    }
    #[inline(always)]
    unsafe fn store_first(self, p: *mut f32, n: usize) {
        unsafe { std::slice::from_raw_parts_mut(p, n) }.copy_from_slice(&self.0[..n]);
    }
    #[inline(always)]
    fn splat(v: f32) -> Self {
        Portable([v; LANES])
    }
    /// Fused only where the target has a fused multiply-add instruction: elsewhere `f32::mul_add`
    /// is a library call that emulates it (200x slower: 550 ms a forward pass).
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        if cfg!(any(target_arch = "aarch64", target_feature = "fma")) {
            Portable(std::array::from_fn(|i| self.0[i].mul_add(b.0[i], c.0[i])))
        } else {
            Portable(std::array::from_fn(|i| self.0[i] * b.0[i] + c.0[i]))
        }
    }
    #[inline(always)]
    fn add(self, b: Self) -> Self {
        Portable(std::array::from_fn(|i| self.0[i] + b.0[i]))
    }
    #[inline(always)]
    fn relu(self) -> Self {
        Portable(self.0.map(|v| v.max(0.0)))
    }
    #[inline(always)]
    fn relu6(self) -> Self {
        Portable(self.0.map(|v| v.clamp(0.0, 6.0)))
    }
    fn to_array(self) -> [f32; LANES] {
        self.0
    }
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use std::arch::x86_64::*;

    use super::{Lanes, LANES};

    /// One AVX-512 register. Only built into functions compiled with `avx512f`. 32 registers:
    /// tiles of 6 x 4 vectors (24 accumulators).
    #[derive(Clone, Copy)]
    pub(crate) struct Avx512(__m512);

    #[inline(always)]
    fn first(n: usize) -> __mmask16 {
        ((1u32 << n) - 1) as __mmask16
    }

    impl Lanes for Avx512 {
        const TILE_VECTORS: usize = 4;
        const SPLIT_SUM: bool = true;
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            Avx512(unsafe { _mm512_loadu_ps(p) })
        }
        #[inline(always)]
        unsafe fn load_first(p: *const f32, n: usize) -> Self {
            Avx512(unsafe { _mm512_maskz_loadu_ps(first(n), p) })
        }
        #[inline(always)]
        unsafe fn store(self, p: *mut f32) {
            unsafe { _mm512_storeu_ps(p, self.0) }
        }
        #[inline(always)]
        unsafe fn store_first(self, p: *mut f32, n: usize) {
            unsafe { _mm512_mask_storeu_ps(p, first(n), self.0) }
        }
        #[inline(always)]
        fn splat(v: f32) -> Self {
            Avx512(unsafe { _mm512_set1_ps(v) })
        }
        #[inline(always)]
        fn mul_add(self, b: Self, c: Self) -> Self {
            Avx512(unsafe { _mm512_fmadd_ps(self.0, b.0, c.0) })
        }
        #[inline(always)]
        fn add(self, b: Self) -> Self {
            Avx512(unsafe { _mm512_add_ps(self.0, b.0) })
        }
        #[inline(always)]
        fn relu(self) -> Self {
            Avx512(unsafe { _mm512_max_ps(self.0, _mm512_setzero_ps()) })
        }
        #[inline(always)]
        fn relu6(self) -> Self {
            Avx512(unsafe { _mm512_min_ps(_mm512_max_ps(self.0, _mm512_setzero_ps()), _mm512_set1_ps(6.0)) })
        }
        fn to_array(self) -> [f32; LANES] {
            let mut out = [0f32; LANES];
            unsafe { _mm512_storeu_ps(out.as_mut_ptr(), self.0) };
            out
        }
        #[inline(always)]
        fn add_to_f64(self, sums: &mut [f64]) {
            assert!(sums.len() >= LANES);
            unsafe {
                let low = _mm512_cvtps_pd(_mm512_castps512_ps256(self.0));
                let high = _mm512_cvtps_pd(_mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd(self.0), 1)));
                let p = sums.as_mut_ptr();
                _mm512_storeu_pd(p, _mm512_add_pd(_mm512_loadu_pd(p), low));
                _mm512_storeu_pd(p.add(8), _mm512_add_pd(_mm512_loadu_pd(p.add(8)), high));
            }
        }
    }

    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn pointwise(p: &super::Pointwise) {
        unsafe { super::pointwise_with::<Avx512>(p) }
    }

    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn depthwise_row(p: &super::DepthwiseRow, sums: &mut [f64]) {
        unsafe { super::depthwise_row_with::<Avx512>(p, sums) }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{Lanes, LANES};

    /// Two AVX2 registers. Only built into functions compiled with `avx2,fma`. 16 registers:
    /// tiles of 6 x 1 vectors (12 accumulators, 2 weight registers, 1 broadcast), as in MLAS's
    /// AVX2 kernel.
    #[derive(Clone, Copy)]
    pub(crate) struct Avx2([__m256; 2]);

    /// The lanes of a half below `n` (which may be negative or above 8), as a load/store mask.
    #[inline(always)]
    fn below(n: i32) -> __m256i {
        unsafe { _mm256_cmpgt_epi32(_mm256_set1_epi32(n), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7)) }
    }

    impl Lanes for Avx2 {
        const TILE_VECTORS: usize = 1;
        const SPLIT_SUM: bool = false;
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            Avx2(unsafe { [_mm256_loadu_ps(p), _mm256_loadu_ps(p.add(8))] })
        }
        #[inline(always)]
        unsafe fn load_first(p: *const f32, n: usize) -> Self {
            let n = n as i32;
            Avx2(unsafe { [_mm256_maskload_ps(p, below(n)), _mm256_maskload_ps(p.add(8), below(n - 8))] })
        }
        #[inline(always)]
        unsafe fn store(self, p: *mut f32) {
            unsafe {
                _mm256_storeu_ps(p, self.0[0]);
                _mm256_storeu_ps(p.add(8), self.0[1]);
            }
        }
        #[inline(always)]
        unsafe fn store_first(self, p: *mut f32, n: usize) {
            let n = n as i32;
            unsafe {
                _mm256_maskstore_ps(p, below(n), self.0[0]);
                _mm256_maskstore_ps(p.add(8), below(n - 8), self.0[1]);
            }
        }
        #[inline(always)]
        fn splat(v: f32) -> Self {
            let v = unsafe { _mm256_set1_ps(v) };
            Avx2([v, v])
        }
        #[inline(always)]
        fn mul_add(self, b: Self, c: Self) -> Self {
            Avx2(unsafe { [_mm256_fmadd_ps(self.0[0], b.0[0], c.0[0]), _mm256_fmadd_ps(self.0[1], b.0[1], c.0[1])] })
        }
        #[inline(always)]
        fn add(self, b: Self) -> Self {
            Avx2(unsafe { [_mm256_add_ps(self.0[0], b.0[0]), _mm256_add_ps(self.0[1], b.0[1])] })
        }
        #[inline(always)]
        fn relu(self) -> Self {
            let max = |v| unsafe { _mm256_max_ps(v, _mm256_setzero_ps()) };
            Avx2([max(self.0[0]), max(self.0[1])])
        }
        #[inline(always)]
        fn relu6(self) -> Self {
            let clamp = |v| unsafe { _mm256_min_ps(_mm256_max_ps(v, _mm256_setzero_ps()), _mm256_set1_ps(6.0)) };
            Avx2([clamp(self.0[0]), clamp(self.0[1])])
        }
        fn to_array(self) -> [f32; LANES] {
            let mut out = [0f32; LANES];
            unsafe { self.store(out.as_mut_ptr()) };
            out
        }
        #[inline(always)]
        fn add_to_f64(self, sums: &mut [f64]) {
            assert!(sums.len() >= LANES);
            unsafe {
                let p = sums.as_mut_ptr();
                for (h, half) in self.0.into_iter().enumerate() {
                    let low = _mm256_cvtps_pd(_mm256_castps256_ps128(half));
                    let high = _mm256_cvtps_pd(_mm256_extractf128_ps(half, 1));
                    let q = p.add(8 * h);
                    _mm256_storeu_pd(q, _mm256_add_pd(_mm256_loadu_pd(q), low));
                    _mm256_storeu_pd(q.add(4), _mm256_add_pd(_mm256_loadu_pd(q.add(4)), high));
                }
            }
        }
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn pointwise(p: &super::Pointwise) {
        unsafe { super::pointwise_with::<Avx2>(p) }
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn depthwise_row(p: &super::DepthwiseRow, sums: &mut [f64]) {
        unsafe { super::depthwise_row_with::<Avx2>(p, sums) }
    }
}

/// A build of the kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Build {
    Avx512,
    Avx2,
    Portable,
}

impl Build {
    /// The builds this CPU runs, fastest first.
    pub fn available() -> Vec<Build> {
        let mut builds = Vec::new();
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                builds.push(Build::Avx512);
            }
            if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                builds.push(Build::Avx2);
            }
        }
        builds.push(Build::Portable);
        builds
    }

    /// The build that runs: the fastest available, or the one `ECM_LCD_KERNELS` names
    /// (`avx512`, `avx2`, `portable`) where it is available (checked once).
    pub fn chosen() -> Build {
        static CHOSEN: std::sync::OnceLock<Build> = std::sync::OnceLock::new();
        *CHOSEN.get_or_init(|| {
            let available = Build::available();
            let wanted = std::env::var("ECM_LCD_KERNELS").ok();
            match wanted.as_deref().and_then(|name| available.iter().find(|b| b.name() == name)) {
                Some(&build) => build,
                None => {
                    if let Some(name) = wanted {
                        log::warn!(
                            "ECM_LCD_KERNELS={name}: not a build this CPU runs ({available:?}); using {:?}",
                            available[0]
                        );
                    }
                    available[0]
                }
            }
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            Build::Avx512 => "avx512",
            Build::Avx2 => "avx2",
            Build::Portable => "portable",
        }
    }
}

/// A `k x n` weight matrix packed in column panels of 16-64 columns (`[k, panel]` each, the
/// last padded with zeros), and the bias padded alike: a tile reads its weights as one
/// contiguous stream (row-major rows of up to 5 KB made every step of the sum touch new
/// cache lines in another page, out of the prefetchers' reach), and every vector load is in
/// bounds.
#[derive(Clone, Debug, Default)]
pub struct PackedWeights {
    pub k: usize,
    pub n: usize,
    /// Columns per panel: 16 times [`panel_vectors`].
    pub panel: usize,
    pub data: Vec<f32>,
    pub bias: Vec<f32>,
}

/// Vectors per panel for `vectors` output vectors in all: all of them up to four, else four or
/// three, whichever gives an even number of whole panels, else four. (The even count was for
/// two threads sharing whole panels; they now share 16-column vectors, and the choice stays as
/// it was measured.) A tile is then up to 6 pixels by 4 vectors ([`TILE_ROWS`]): 24
/// accumulators, the weight vectors and the broadcast inputs fit AVX-512's 32 registers.
pub fn panel_vectors(vectors: usize) -> usize {
    match vectors {
        0 => 1,
        v if v <= 4 => v,
        v if v % 8 == 0 => 4,
        v if v % 6 == 0 => 3,
        _ => 4,
    }
}

impl PackedWeights {
    /// From the `[n, k]` (output-major, as a flattened OIHW weight) matrix `w` and bias `b`.
    pub fn from_output_major(w: &[f32], b: &[f32], n: usize, k: usize) -> Self {
        assert_eq!((w.len(), b.len()), (n * k, n), "packed weights: sizes");
        let panel = panel_vectors(n.div_ceil(LANES)) * LANES;
        let padded = n.next_multiple_of(panel);
        let mut data = vec![0f32; k * padded];
        for (c, row) in w.chunks_exact(k).enumerate() {
            for (i, &v) in row.iter().enumerate() {
                data[Self::offset(k, panel, i, c)] = v;
            }
        }
        let mut bias = vec![0f32; padded];
        bias[..n].copy_from_slice(b);
        PackedWeights { k, n, panel, data, bias }
    }

    fn offset(k: usize, panel: usize, i: usize, c: usize) -> usize {
        c / panel * k * panel + i * panel + c % panel
    }

    /// These weights with row `i` (input channel `i`) multiplied by `scale[i]` (rows past
    /// `scale` as they are), written over `out` (whose buffers are reused): ECA's gate, once a
    /// frame, on the way into the projection.
    pub fn scaled_rows_into(&self, scale: &[f32], out: &mut PackedWeights) {
        out.k = self.k;
        out.n = self.n;
        out.panel = self.panel;
        out.bias.clone_from(&self.bias);
        out.data.resize(self.data.len(), 0.0);
        let panel_floats = (self.k * self.panel).max(1);
        for (dst, src) in out.data.chunks_mut(panel_floats).zip(self.data.chunks(panel_floats)) {
            for (i, (dst, src)) in dst.chunks_exact_mut(self.panel).zip(src.chunks_exact(self.panel)).enumerate() {
                let g = scale.get(i).copied().unwrap_or(1.0);
                dst.iter_mut().zip(src).for_each(|(d, s)| *d = s * g);
            }
        }
    }
}

/// One call of [`pointwise`]: rows `0..rows` and output columns `columns` of
/// `out[r, c] = activation(bias[c] + sum_i a[r, i] weight[i, c] (+ residual[r, c]))`.
pub(crate) struct Pointwise<'a> {
    pub rows: usize,
    /// Row `r` of the left operand starts at `a + r * lda`; step `i` of its sum reads the float
    /// at `steps[i]` from there (`None`: at `i`, a plain row of `weights.k` floats). The stem
    /// reads its 3x3 patches straight from the padded image this way, without im2col.
    pub a: *const f32,
    pub lda: usize,
    pub steps: Option<&'a [usize]>,
    pub weights: &'a PackedWeights,
    /// Output columns; the start is a multiple of 16.
    pub columns: Range<usize>,
    pub out: *mut f32,
    pub ldo: usize,
    /// Null, or a matrix added before the activation, with row pitch `ldr`.
    pub residual: *const f32,
    pub ldr: usize,
    pub activation: Activation,
}

// SAFETY: the pointers are read, or written in parts that no two threads share (the callers' contract).
unsafe impl Send for Pointwise<'_> {}
unsafe impl Sync for Pointwise<'_> {}

/// Rows up to which a call goes panel by panel ([`pointwise_rows`]).
pub(crate) const SHORT_CALL_ROWS: usize = 64;

/// Computes one [`Pointwise`] block.
///
/// # Safety
/// The pointers address the rows and columns the call names (`a`: `rows` rows of `weights.k`
/// floats, or reaching the largest of `steps`; `out` and `residual`: `rows` rows covering `columns`), and no other thread writes
/// those `out` elements meanwhile.
pub(crate) unsafe fn pointwise(p: &Pointwise) {
    unsafe { pointwise_in(Build::chosen(), p) }
}

/// [`pointwise`] in `build`, which must be one of [`Build::available`].
///
/// # Safety
/// As [`pointwise`].
unsafe fn pointwise_in(build: Build, p: &Pointwise) {
    assert!(
        p.columns.start.is_multiple_of(LANES) && p.columns.end <= p.weights.n,
        "pointwise: columns {:?}",
        p.columns
    );
    match build {
        #[cfg(target_arch = "x86_64")]
        Build::Avx512 => unsafe { avx512::pointwise(p) },
        #[cfg(target_arch = "x86_64")]
        Build::Avx2 => unsafe { avx2::pointwise(p) },
        _ => unsafe { pointwise_with::<Portable>(p) },
    }
}

/// Pixels per tile. Every row of a tile has its own pointer, and six of them stay in general
/// registers beside the loop's own; taller tiles (8 x 3, 12 x 2, 24 x 1 vectors, tried first to
/// keep 24 accumulators busy) ran out of registers, reloaded row pointers from the stack and
/// spilled accumulators: 25-40 GMAC/s against 60-80 for 6 x 4 on one core.
pub(crate) const TILE_ROWS: usize = 6;

#[inline(always)]
unsafe fn pointwise_with<L: Lanes>(p: &Pointwise) {
    match p.steps {
        Some(steps) => unsafe { pointwise_rows::<L, true>(p, steps) },
        None => unsafe { pointwise_rows::<L, false>(p, &[]) },
    }
}

/// Rows in tiles of [`TILE_ROWS`] by columns in tiles of one panel (or the part of it in
/// `columns`). Long calls (a whole map) go row tile by row tile, each across all panels: the
/// tile's inputs stay in L1 while the weights stream from L2. Short calls (up to
/// [`SHORT_CALL_ROWS`] rows: 7x7 maps, the head) go panel by panel, each down all rows: their
/// weights (up to 1.6 MB) are the larger operand, and are then read from memory once instead of
/// once per row tile (head 60 -> 70 GMAC/s, 960->160 expansion 65 -> 79). The last tile
/// of a plain call is exactly as tall as the rows left (maps 7 or 14 pixels wide would
/// otherwise compute up to 5 of every 12 rows for nothing); gathered calls (the stem, 112
/// pixels a row) repeat their last row instead, to keep the number of kernels down.
#[inline(always)]
unsafe fn pointwise_rows<L: Lanes, const GATHER: bool>(p: &Pointwise, steps: &[usize]) {
    assert!(!GATHER || steps.len() >= p.weights.k, "pointwise: {} steps for k = {}", steps.len(), p.weights.k);
    // A macro, not a closure: closures do not inherit the caller's `target_feature`.
    macro_rules! tile {
        ($r:expr, $c:expr) => {
            unsafe { pointwise_tile::<L, GATHER>(p, steps, $r, $c) }
        };
    }
    if p.rows <= SHORT_CALL_ROWS {
        let mut c = p.columns.start;
        while c < p.columns.end {
            let mut next = c;
            for r in (0..p.rows).step_by(TILE_ROWS) {
                next = tile!(r, c);
            }
            c = next;
        }
    } else {
        for r in (0..p.rows).step_by(TILE_ROWS) {
            let mut c = p.columns.start;
            while c < p.columns.end {
                c = tile!(r, c);
            }
        }
    }
}

/// The tile of `p` at row `r` and column `c`; returns the column after it.
#[inline(always)]
unsafe fn pointwise_tile<L: Lanes, const GATHER: bool>(p: &Pointwise, steps: &[usize], r: usize, c: usize) -> usize {
    let panel = p.weights.panel;
    let rows = TILE_ROWS.min(p.rows - r);
    let width = (p.columns.end - c).min(panel - c % panel).min(L::TILE_VECTORS * LANES);
    let tile = Tile { p, steps, row: r, rows, column: c, width };
    macro_rules! by_width {
        ($mr:literal) => {
            match width.div_ceil(LANES) {
                1 => unsafe { tile.run::<L, $mr, 1, GATHER>() },
                2 => unsafe { tile.run::<L, $mr, 2, GATHER>() },
                3 => unsafe { tile.run::<L, $mr, 3, GATHER>() },
                _ => unsafe { tile.run::<L, $mr, 4, GATHER>() },
            }
        };
    }
    match if GATHER { TILE_ROWS } else { rows } {
        1 => by_width!(1),
        2 => by_width!(2),
        3 => by_width!(3),
        4 => by_width!(4),
        5 => by_width!(5),
        _ => by_width!(6),
    }
    c + width
}

/// `$body` once for each value, with `$name` a constant of that value: literal indices where a
/// loop, even over constant bounds, might not be unrolled before registers are assigned.
macro_rules! unrolled {
    ($name:ident in [$($value:literal)*] $body:block) => {
        $({
            const $name: usize = $value;
            $body
        })*
    };
}

/// One `MR x NR`-vector tile of a [`Pointwise`] call at (`row`, `column`): `rows` (<= MR) rows
/// and `width` (<= 16 NR) columns are stored.
struct Tile<'a, 'b> {
    p: &'a Pointwise<'b>,
    /// `p.steps` where the call gathers (`GATHER`), else unused.
    steps: &'a [usize],
    row: usize,
    rows: usize,
    column: usize,
    width: usize,
}

impl Tile<'_, '_> {
    /// The tile's sum. With one vector per step the sum runs in two interleaved halves (even and
    /// odd steps, added at the end): six accumulators alone would wait on the multiply-adds'
    /// latency (two units, four cycles: eight must be in flight).
    #[inline(always)]
    unsafe fn run<L: Lanes, const MR: usize, const NR: usize, const GATHER: bool>(&self) {
        let p = self.p;
        let (k, pitch) = (p.weights.k, p.weights.panel);
        let halves = if NR == 1 && L::SPLIT_SUM { 2 } else { 1 };
        let weights = unsafe { p.weights.data.as_ptr().add(PackedWeights::offset(k, pitch, 0, self.column)) };
        let bias = unsafe { p.weights.bias.as_ptr().add(self.column) };
        // Every accumulator is indexed by a literal constant ([`unrolled`]), so the compiler keeps
        // them all in registers; loops over the tile, even with constant bounds, were not always
        // unrolled in time, and the array then lived in memory with a store after every
        // multiply-add (2.5x slower).
        // Rows past the end (gathered calls only) repeat the last row: computed, never stored.
        let mut a = [p.a; MR];
        unrolled!(I in [0 1 2 3 4 5] {
            if I < MR {
                a[I] = unsafe { p.a.add((self.row + last_row_from(I, self.rows)) * p.lda) };
            }
        });
        let mut acc = [[[L::splat(0.0); NR]; MR]; 2];
        unrolled!(J in [0 1 2 3] {
            if J < NR {
                let b = unsafe { L::load(bias.add(J * LANES)) };
                unrolled!(I in [0 1 2 3 4 5] {
                    if I < MR {
                        acc[0][I][J] = b;
                    }
                });
            }
        });
        // One pass of `halves` steps: the weights advance by pointer and the inputs by one index,
        // so that the loop keeps only the row pointers, two counters and the weight pointer in
        // registers.
        let mut weights = weights;
        let mut step = 0;
        let whole = k - k % halves;
        macro_rules! pass {
            ($halves:expr) => {
                unrolled!(H in [0 1] {
                    if H < $halves {
                        let offset = if GATHER { unsafe { *self.steps.get_unchecked(step + H) } } else { step + H };
                        let mut w = [L::splat(0.0); NR];
                        unrolled!(J in [0 1 2 3] {
                            if J < NR {
                                w[J] = unsafe { L::load(weights.add(H * pitch + J * LANES)) };
                            }
                        });
                        unrolled!(I in [0 1 2 3 4 5] {
                            if I < MR {
                                let x = L::splat(unsafe { *a[I].add(offset) });
                                unrolled!(J in [0 1 2 3] {
                                    if J < NR {
                                        acc[H][I][J] = x.mul_add(w[J], acc[H][I][J]);
                                    }
                                });
                            }
                        });
                    }
                });
                weights = unsafe { weights.add($halves * pitch) };
                step += $halves;
            };
        }
        while step < whole {
            pass!(halves);
        }
        if step < k {
            // The odd last step of a two-half sum: the counters are not read again.
            #[allow(unused_assignments)]
            {
                pass!(1);
            }
        }
        // The accumulators leave by literal indices too: a loop over them here, not unrolled
        // for its size, kept the whole array in memory.
        unrolled!(I in [0 1 2 3 4 5] {
            if I < MR && I < self.rows {
                unrolled!(J in [0 1 2 3] {
                    if J < NR {
                        let v = if halves == 2 { acc[0][I][J].add(acc[1][I][J]) } else { acc[0][I][J] };
                        unsafe { self.store(v, I, J) };
                    }
                });
            }
        });
    }
}
impl Tile<'_, '_> {
    /// Stores vector `j` of tile row `i` (adding the residual, applying the activation).
    #[inline(always)]
    unsafe fn store<L: Lanes>(&self, v: L, i: usize, j: usize) {
        let p = self.p;
        let r = self.row + i;
        let column = self.column + j * LANES;
        let n = (self.width - j * LANES).min(LANES);
        let mut v = v;
        if !p.residual.is_null() {
            v = v.add(unsafe { L::load_first(p.residual.add(r * p.ldr + column), n) });
        }
        match p.activation {
            Activation::Identity => {}
            Activation::Relu => v = v.relu(),
            Activation::Relu6 => v = v.relu6(),
        }
        let out = unsafe { p.out.add(r * p.ldo + column) };
        if n == LANES {
            unsafe { v.store(out) }
        } else {
            unsafe { v.store_first(out, n) }
        }
    }
}

/// One call of [`depthwise_row`]: output row `out[x, c]` for `x < width` and channels `channels`
/// of a 3x3 depthwise convolution + bias + ReLU6.
pub(crate) struct DepthwiseRow<'a> {
    /// The three input rows the output row sees (a zero row for padding), each laid out as
    /// `pixels x pitch` floats with a zero pixel on each side: input column `x` is pixel `x + 1`.
    pub rows: [*const f32; 3],
    /// Floats per pixel in `rows` and `out`.
    pub pitch: usize,
    pub stride: usize,
    /// Padded-row pixel of output column 0's left tap: 1 - the "SAME" padding on the left.
    pub first_pixel: usize,
    pub width: usize,
    /// Tap-major weights `[9, pitch]` and the bias `[pitch]`.
    pub weights: &'a [f32],
    pub bias: &'a [f32],
    /// Channels to compute: multiples of 16.
    pub channels: Range<usize>,
    pub out: *mut f32,
}

/// Computes one [`DepthwiseRow`] and adds each channel's outputs to `sums[c - channels.start]`.
///
/// # Safety
/// The rows hold `first_pixel + (width - 1) * stride + 3` pixels of `pitch` floats; `out` holds
/// `width` pixels; no other thread writes those channels of `out` meanwhile.
pub(crate) unsafe fn depthwise_row(p: &DepthwiseRow, sums: &mut [f64]) {
    unsafe { depthwise_row_in(Build::chosen(), p, sums) }
}

/// [`depthwise_row`] in `build`, which must be one of [`Build::available`].
///
/// # Safety
/// As [`depthwise_row`].
unsafe fn depthwise_row_in(build: Build, p: &DepthwiseRow, sums: &mut [f64]) {
    assert!(
        p.channels.start.is_multiple_of(LANES) && p.channels.end.is_multiple_of(LANES) && p.channels.end <= p.pitch
    );
    assert!(p.weights.len() >= 9 * p.pitch && p.bias.len() >= p.pitch && sums.len() >= p.channels.len());
    match build {
        #[cfg(target_arch = "x86_64")]
        Build::Avx512 => unsafe { avx512::depthwise_row(p, sums) },
        #[cfg(target_arch = "x86_64")]
        Build::Avx2 => unsafe { avx2::depthwise_row(p, sums) },
        _ => unsafe { depthwise_row_with::<Portable>(p, sums) },
    }
}

#[inline(always)]
unsafe fn depthwise_row_with<L: Lanes>(p: &DepthwiseRow, sums: &mut [f64]) {
    match p.stride {
        1 => unsafe { depthwise_row_strided::<L, 1>(p, sums) },
        2 => unsafe { depthwise_row_strided::<L, 2>(p, sums) },
        s => panic!("depthwise_row: stride {s}"),
    }
}

/// [`depthwise_row`] at stride `S`, one 16-channel vector at a time with its nine weights in
/// registers, by steps of four output pixels (then one step of the one to three left): each input
/// pixel a step reads is loaded once and feeds every output it touches (6 loads per row for 4
/// outputs at stride 1, 9 at stride 2, against 12), and the four sums run side by side instead
/// of one chain of nine multiply-adds per pixel (1.2-1.7x on the network's shapes).
#[inline(always)]
unsafe fn depthwise_row_strided<L: Lanes, const S: usize>(p: &DepthwiseRow, sums: &mut [f64]) {
    for c in p.channels.clone().step_by(LANES) {
        let w: [L; 9] = std::array::from_fn(|t| unsafe { L::load(p.weights.as_ptr().add(t * p.pitch + c)) });
        let bias = unsafe { L::load(p.bias.as_ptr().add(c)) };
        let mut sum = L::splat(0.0);
        let mut x = 0;
        while x + 4 <= p.width {
            sum = sum.add(unsafe { depthwise_step::<L, S, 4>(p, c, x, &w, bias) });
            x += 4;
        }
        sum = sum.add(match p.width - x {
            0 => L::splat(0.0),
            1 => unsafe { depthwise_step::<L, S, 1>(p, c, x, &w, bias) },
            2 => unsafe { depthwise_step::<L, S, 2>(p, c, x, &w, bias) },
            _ => unsafe { depthwise_step::<L, S, 3>(p, c, x, &w, bias) },
        });
        sum.add_to_f64(&mut sums[c - p.channels.start..c - p.channels.start + LANES]);
    }
}

/// Whether input pixel `i` of a step is one of the three taps of the output whose first tap is
/// pixel `first` (a function, so that the literal indices do not read as constant comparisons).
#[inline(always)]
const fn feeds(i: usize, first: usize) -> bool {
    i >= first && i - first < 3
}

/// Tile row `i`, or the last of `rows` rows past the end (those repeat the last row).
#[inline(always)]
const fn last_row_from(i: usize, rows: usize) -> usize {
    if i < rows {
        i
    } else {
        rows - 1
    }
}

/// Output pixels `x..x + P` of channel vector `c` of [`depthwise_row`]; returns their sum.
#[inline(always)]
unsafe fn depthwise_step<L: Lanes, const S: usize, const P: usize>(
    p: &DepthwiseRow,
    c: usize,
    x: usize,
    w: &[L; 9],
    bias: L,
) -> L {
    let pitch = p.pitch;
    let mut acc = [bias; P];
    unrolled!(KY in [0 1 2] {
        let row = unsafe { p.rows[KY].add(c + (p.first_pixel + x * S) * pitch) };
        // Input pixel `I` of the step feeds output `O` through tap `I - O * S`.
        unrolled!(I in [0 1 2 3 4 5 6 7 8] {
            if I < (P - 1) * S + 3 {
                let v = unsafe { L::load(row.add(I * pitch)) };
                unrolled!(O in [0 1 2 3] {
                    if O < P && feeds(I, O * S) {
                        acc[O] = v.mul_add(w[KY * 3 + I - O * S], acc[O]);
                    }
                });
            }
        });
    });
    let mut sum = L::splat(0.0);
    unrolled!(O in [0 1 2 3] {
        if O < P {
            let v = acc[O].relu6();
            sum = sum.add(v);
            unsafe { v.store(p.out.add(c + (x + O) * pitch)) };
        }
    });
    sum
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` values in [-1, 1) from `seed`.
    fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = crate::synth::SplitMix64::new(seed);
        (0..n).map(|_| (rng.next_f64() * 2.0 - 1.0) as f32).collect()
    }

    /// Every build of `pointwise` against a naive product, over tile shapes, row and column tails,
    /// residual and activation.
    #[test]
    fn pointwise_equals_naive_product_in_every_build() {
        use Activation::{Identity, Relu, Relu6};
        for (rows, k, n, columns, residual, activation) in [
            (1, 3, 5, 0..5, false, Identity),
            (13, 27, 32, 0..32, false, Relu6),
            (37, 16, 96, 48..96, false, Relu),
            (25, 96, 24, 0..24, true, Identity),
            (49, 320, 1280, 640..1280, false, Relu6),
            (7, 64, 144, 0..144, true, Relu),
            (50, 40, 160, 16..112, true, Identity),
            (70, 17, 16, 0..16, true, Relu6),
            (100, 24, 144, 0..144, false, Relu),
        ] {
            let (lda, ldo) = (k + 3, n + 5);
            let a = random(rows * lda, 1);
            let w = random(n * k, 2);
            let b = random(n, 3);
            let res = random(rows * ldo, 4);
            let weights = PackedWeights::from_output_major(&w, &b, n, k);
            let mut expected = vec![0f32; rows * ldo];
            for r in 0..rows {
                for c in columns.clone() {
                    let mut v = b[c] + (0..k).map(|i| a[r * lda + i] * w[c * k + i]).sum::<f32>();
                    if residual {
                        v += res[r * ldo + c];
                    }
                    expected[r * ldo + c] = activation.of(v);
                }
            }
            let run = |build: Build| {
                let mut out = vec![0f32; rows * ldo];
                let p = Pointwise {
                    rows,
                    a: a.as_ptr(),
                    lda,
                    steps: None,
                    weights: &weights,
                    columns: columns.clone(),
                    out: out.as_mut_ptr(),
                    ldo,
                    residual: if residual { res.as_ptr() } else { std::ptr::null() },
                    ldr: ldo,
                    activation,
                };
                unsafe { pointwise_in(build, &p) };
                out
            };
            for build in Build::available() {
                let (name, out) = (build.name(), run(build));
                for (i, (&got, &want)) in out.iter().zip(&expected).enumerate() {
                    assert!((got - want).abs() < 1e-4, "{name} {rows}x{k}x{n} {columns:?} at {i}: {got} vs {want}");
                }
            }
        }
    }

    /// Every build of `depthwise_row` against naive loops, strides 1 and 2, both paddings.
    #[test]
    fn depthwise_row_equals_naive_loops_in_every_build() {
        for (stride, first_pixel, width, pitch, channels) in [
            (1, 0, 9, 32, 0..32),
            (2, 1, 5, 48, 16..48),
            (2, 0, 4, 16, 0..16),
            (1, 0, 1, 64, 32..64),
            (1, 1, 14, 16, 0..16),
            (2, 1, 11, 32, 0..32),
        ] {
            let pixels = first_pixel + (width - 1) * stride + 3;
            let rows: Vec<Vec<f32>> = (0..3).map(|i| random(pixels * pitch, 10 + i)).collect();
            let weights = random(9 * pitch, 20);
            let bias = random(pitch, 21);
            let mut expected = vec![0f32; width * pitch];
            let mut expected_sums = vec![0f64; channels.len()];
            for x in 0..width {
                for c in channels.clone() {
                    let mut v = bias[c];
                    for (ky, row) in rows.iter().enumerate() {
                        for kx in 0..3 {
                            v += row[(first_pixel + x * stride + kx) * pitch + c] * weights[(ky * 3 + kx) * pitch + c];
                        }
                    }
                    let v = v.clamp(0.0, 6.0);
                    expected[x * pitch + c] = v;
                    expected_sums[c - channels.start] += v as f64;
                }
            }
            let run = |build: Build| {
                let mut out = vec![0f32; width * pitch];
                let mut sums = vec![0f64; channels.len()];
                let p = DepthwiseRow {
                    rows: [rows[0].as_ptr(), rows[1].as_ptr(), rows[2].as_ptr()],
                    pitch,
                    stride,
                    first_pixel,
                    width,
                    weights: &weights,
                    bias: &bias,
                    channels: channels.clone(),
                    out: out.as_mut_ptr(),
                };
                unsafe { depthwise_row_in(build, &p, &mut sums) };
                (out, sums)
            };
            for build in Build::available() {
                let (name, (out, sums)) = (build.name(), run(build));
                for (i, (&got, &want)) in out.iter().zip(&expected).enumerate() {
                    assert!((got - want).abs() < 1e-5, "{name} stride {stride} at {i}: {got} vs {want}");
                }
                for (got, want) in sums.iter().zip(&expected_sums) {
                    assert!((got - want).abs() < 1e-4, "{name} sums: {got} vs {want}");
                }
            }
        }
    }
}
