//! Six-level descriptor codes: how the keyframe database keeps a unit descriptor in under a
//! kilobyte (`detector.storage`), and the scan that searches them without decoding.
//!
//! A descriptor `s` (`dim` values, mean `m`) is split into `m` and its deviations `r = s - m`,
//! root-mean-square `rms`. Each deviation `x` becomes a digit `d = floor((clamp(x, -c, c) + c) / w)`
//! in `0..6`, with `c = 2.5 rms` and `w = 2c / 6`: uniform levels over +-2.5 RMS around the row's
//! mean, one scale per row, no training data. Without the mean, a descriptor of non-negative values
//! (`l2`, `power` and `spatial` pool ReLU6 outputs) would leave the three negative levels unused.
//! Three digits pack into a byte, `d0 + 6 d1 + 36 d2` (216 of 256 values), so a row takes
//! `ceil(dim / 3)` bytes plus three `f32`s: 972 bytes for the default 2880-value descriptor. The
//! levels' centres `l = 2d - 5` give the direction of `r` (`descriptor_study`'s `l2q6` measured
//! such codes on the development sets before they were built).
//!
//! Search is asymmetric: the query `q` (mean `q_m`) stays a float vector. Its inner product with
//! `s` is `m sum(q) + (q - q_m).r`, as the deviations sum to zero, and the second term is estimated
//! as `|r|^2 ((q - q_m).l) / (r.l)`: the estimator RaBitQ uses (Gao and Long, SIGMOD 2024).
//! Projecting on the reconstruction alone shrinks every inner product by the code's fidelity
//! `r^.l^` (0.98 or so at six levels), which would move every score and the threshold with it;
//! divided by it, scores stay those of the `f32` rows on average, and a query equal to the stored
//! vector is at distance 0 exactly. With `k = |r|^2 / (r.l)`, the estimate is
//! `k (q.l) + q_m (dim m - k sum(l))` and the distance `|q|^2 + |s|^2 - 2 estimate`, so each row keeps
//! `|s|^2`, `k` and `dim m - k sum(l)`.
//!
//! So that the scan is integer arithmetic, the query is rounded once to `i16` (a step of
//! `max|q| / 32767`, far below a level's width) and split into three planes (every byte's first,
//! second and third value); `q.l` is then `step (2 sum q'd - 5 sum q')` with `sum q'd` from 16-bit
//! multiply-adds on the digits, which are unpacked by multiplying by reciprocals (AVX2, or AVX-512
//! with VNNI where the CPU has it: the same integers). The rounding moves distances by under 1e-4
//! (a test), against level steps of about 1e-2.
//!
//! A row is its codes then its factors, one contiguous span in a buffer of huge pages
//! ([`super::huge_pages`]): an index query reads a few thousand rows scattered over it, and each
//! row then costs one run of cache lines and no page walk.

use super::huge_pages::HugePageBytes;

/// Levels per value.
pub const LEVELS: u32 = 6;
/// Values per code byte.
const PER_BYTE: usize = 3;
/// Half-range of the levels, in RMS of the row.
const CLIP_RMS: f32 = 2.5;

/// Code bytes of a `dim`-value row.
pub fn code_len(dim: usize) -> usize {
    dim.div_ceil(PER_BYTE)
}

/// Bytes a coded row takes: its codes and its three factors.
pub fn row_bytes(dim: usize) -> usize {
    code_len(dim) + std::mem::size_of::<Factors>()
}

/// What a row keeps beside its codes (module doc).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Factors {
    /// `|s|^2`.
    pub norm2: f32,
    /// `k = |r|^2 / (r.l)`, which turns `q.l` into the deviations' part of the estimate (0 when
    /// every value is the mean).
    pub dot_scale: f32,
    /// `dim m - k sum(l)`: the query's mean times it completes the estimate.
    pub mean_term: f32,
}

/// The levels' centre of digit `d`: odd, in `-5..=5`.
#[inline(always)]
fn level(d: u32) -> i32 {
    2 * d as i32 - (LEVELS as i32 - 1)
}

/// Encodes `v` into `codes` (`code_len(v.len())` bytes); returns the row's factors.
pub fn encode(v: &[f32], codes: &mut [u8]) -> Factors {
    debug_assert_eq!(codes.len(), code_len(v.len()));
    let dim = v.len().max(1) as f64;
    let mean = (v.iter().map(|&x| x as f64).sum::<f64>() / dim) as f32;
    let rms = (v.iter().map(|&x| (x - mean) * (x - mean)).sum::<f32>() / dim as f32).sqrt();
    let clip = CLIP_RMS * rms;
    let step = 2.0 * clip / LEVELS as f32;
    let digit = |x: f32| -> u32 {
        if step > 0.0 {
            (((x.clamp(-clip, clip) + clip) / step) as u32).min(LEVELS - 1)
        } else {
            LEVELS - 1
        }
    };
    let (mut norm2, mut deviation2, mut dot, mut level_sum) = (0f64, 0f64, 0f64, 0i64);
    for (byte, values) in codes.iter_mut().zip(v.chunks(PER_BYTE)) {
        let mut packed = 0u32;
        for (k, &x) in values.iter().enumerate() {
            let r = (x - mean) as f64;
            let d = digit(x - mean);
            norm2 += x as f64 * x as f64;
            deviation2 += r * r;
            dot += r * level(d) as f64;
            level_sum += level(d) as i64;
            packed += d * LEVELS.pow(k as u32);
        }
        *byte = packed as u8;
    }
    // A level has the sign of its deviation, so `r.l > 0` unless every value is the mean.
    let dot_scale = if dot > 0.0 { deviation2 / dot } else { 0.0 };
    let mean_term = dim * mean as f64 - dot_scale * level_sum as f64;
    Factors { norm2: norm2 as f32, dot_scale: dot_scale as f32, mean_term: mean_term as f32 }
}

/// The digits of a code byte.
#[inline(always)]
fn digits(byte: u8) -> [u32; PER_BYTE] {
    let b = byte as u32;
    [b % LEVELS, b / LEVELS % LEVELS, b / (LEVELS * LEVELS)]
}

/// The reconstruction of a coded row (`out`: its `dim` values): the row's mean plus the levels'
/// direction at the deviations' length.
pub fn decode_into(codes: &[u8], factors: Factors, out: &mut [f32]) {
    let dim = out.len();
    let levels = || codes.iter().flat_map(|&b| digits(b)).take(dim).map(|d| level(d) as i64);
    let (sum_squares, level_sum) = levels().fold((0i64, 0i64), |(q, s), l| (q + l * l, s + l));
    // Back from the factors: `dim m = mean_term + k sum(l)`, `|r|^2 = |s|^2 - dim m^2`.
    let mean = (factors.mean_term as f64 + factors.dot_scale as f64 * level_sum as f64) / dim.max(1) as f64;
    let deviation2 = (factors.norm2 as f64 - dim as f64 * mean * mean).max(0.0);
    let scale = (deviation2 / sum_squares.max(1) as f64).sqrt();
    for (values, &byte) in out.chunks_mut(PER_BYTE).zip(codes) {
        for (x, d) in values.iter_mut().zip(digits(byte)) {
            *x = (mean + scale * level(d) as f64) as f32;
        }
    }
}

/// A query prepared for scanning coded rows (module doc).
#[derive(Clone, Debug)]
pub struct CodedQuery {
    /// Three planes of `code_len` values each: the rounded query's first, second and third value of
    /// every byte's triple (zero past `dim`).
    planes: Vec<i16>,
    /// The rounding step: the query's value is `step * plane value`.
    step: f32,
    /// Sum of the rounded values.
    sum: i64,
    /// The query's mean value.
    mean: f32,
    norm2: f32,
}

impl CodedQuery {
    pub fn new(query: &[f32]) -> Self {
        let len = code_len(query.len());
        let largest = query.iter().fold(0f32, |m, x| m.max(x.abs()));
        let step = if largest > 0.0 { largest / i16::MAX as f32 } else { 1.0 };
        let mut planes = vec![0i16; PER_BYTE * len];
        let mut sum = 0i64;
        for (i, &x) in query.iter().enumerate() {
            let q = (x / step).round() as i16;
            planes[(i % PER_BYTE) * len + i / PER_BYTE] = q;
            sum += q as i64;
        }
        let mean = (query.iter().map(|&x| x as f64).sum::<f64>() / query.len().max(1) as f64) as f32;
        CodedQuery { planes, step, sum, mean, norm2: query.iter().map(|x| x * x).sum() }
    }

    /// The estimated squared distance from the query to a coded row (module doc).
    #[inline(always)]
    pub fn squared_distance(&self, codes: &[u8], factors: Factors) -> f32 {
        let weighted = digit_dot(&self.planes, codes) as i64;
        let q_dot_levels = self.step * (2 * weighted - (LEVELS as i64 - 1) * self.sum) as f32;
        let estimate = factors.dot_scale * q_dot_levels + self.mean * factors.mean_term;
        (self.norm2 + factors.norm2 - 2.0 * estimate).max(0.0)
    }
}

/// `sum over bytes j and k < 3 of planes[k][j] * digit k of codes[j]`, with the widest SIMD the CPU has.
#[inline(always)]
fn digit_dot(planes: &[i16], codes: &[u8]) -> i32 {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512bw") && std::arch::is_x86_feature_detected!("avx512vnni") {
            // SAFETY: the CPU supports AVX-512 BW and VNNI (checked just above).
            return unsafe { digit_dot_avx512(planes, codes) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            return unsafe { digit_dot_avx2(planes, codes, 0) };
        }
    }
    digit_dot_portable(planes, codes, 0)
}

/// [`digit_dot`] over the bytes from `start`.
fn digit_dot_portable(planes: &[i16], codes: &[u8], start: usize) -> i32 {
    let len = planes.len() / PER_BYTE;
    let (a, rest) = planes.split_at(len);
    let (b, c) = rest.split_at(len);
    let mut acc = 0i32;
    for j in start..len.min(codes.len()) {
        let [d0, d1, d2] = digits(codes[j]);
        acc += a[j] as i32 * d0 as i32 + b[j] as i32 * d1 as i32 + c[j] as i32 * d2 as i32;
    }
    acc
}

/// [`digit_dot`] over the bytes from `start`, 16 bytes at a time: digits by multiplying by
/// reciprocals (`b / 36` is `(b * 1821) >> 16` and `r / 6` is `(r * 10923) >> 16` for every byte
/// value), then 16-bit multiply-adds (`|q| <= 32767` times a digit `<= 5`, summed over at most
/// 2^16 bytes a lane, fits an `i32`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn digit_dot_avx2(planes: &[i16], codes: &[u8], start: usize) -> i32 {
    use std::arch::x86_64::*;
    let len = planes.len() / PER_BYTE;
    let end = start + (len.min(codes.len()).saturating_sub(start)) / 16 * 16;
    let (by36, by6) = (_mm256_set1_epi16(1821), _mm256_set1_epi16(10923));
    let (thirty_six, six) = (_mm256_set1_epi16(36), _mm256_set1_epi16(6));
    let mut acc = _mm256_setzero_si256();
    for j in (start..end).step_by(16) {
        // SAFETY: j + 16 <= len <= codes.len(), and each plane holds `len` values from `k * len`.
        let (bytes, qa, qb, qc) = unsafe {
            (
                _mm256_cvtepu8_epi16(_mm_loadu_si128(codes.as_ptr().add(j).cast())),
                _mm256_loadu_si256(planes.as_ptr().add(j).cast()),
                _mm256_loadu_si256(planes.as_ptr().add(len + j).cast()),
                _mm256_loadu_si256(planes.as_ptr().add(2 * len + j).cast()),
            )
        };
        let d2 = _mm256_mulhi_epu16(bytes, by36);
        let rest = _mm256_sub_epi16(bytes, _mm256_mullo_epi16(d2, thirty_six));
        let d1 = _mm256_mulhi_epu16(rest, by6);
        let d0 = _mm256_sub_epi16(rest, _mm256_mullo_epi16(d1, six));
        acc = _mm256_add_epi32(acc, _mm256_madd_epi16(d0, qa));
        acc = _mm256_add_epi32(acc, _mm256_madd_epi16(d1, qb));
        acc = _mm256_add_epi32(acc, _mm256_madd_epi16(d2, qc));
    }
    let mut lanes = [0i32; 8];
    // SAFETY: `lanes` holds 8 i32s.
    unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast(), acc) };
    lanes.iter().sum::<i32>() + digit_dot_portable(planes, codes, end)
}

/// [`digit_dot_avx2`] 32 bytes at a time, the multiply-adds accumulating in one instruction (VNNI):
/// the same integers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vnni,avx2")]
unsafe fn digit_dot_avx512(planes: &[i16], codes: &[u8]) -> i32 {
    use std::arch::x86_64::*;
    let len = planes.len() / PER_BYTE;
    let end = len.min(codes.len()) / 32 * 32;
    let (by36, by6) = (_mm512_set1_epi16(1821), _mm512_set1_epi16(10923));
    let (thirty_six, six) = (_mm512_set1_epi16(36), _mm512_set1_epi16(6));
    // Two accumulators, so that consecutive multiply-adds do not wait for each other.
    let (mut even, mut odd) = (_mm512_setzero_si512(), _mm512_setzero_si512());
    for j in (0..end).step_by(32) {
        // SAFETY: j + 32 <= len <= codes.len(), and each plane holds `len` values from `k * len`.
        let (bytes, qa, qb, qc) = unsafe {
            (
                _mm512_cvtepu8_epi16(_mm256_loadu_si256(codes.as_ptr().add(j).cast())),
                _mm512_loadu_si512(planes.as_ptr().add(j).cast()),
                _mm512_loadu_si512(planes.as_ptr().add(len + j).cast()),
                _mm512_loadu_si512(planes.as_ptr().add(2 * len + j).cast()),
            )
        };
        let d2 = _mm512_mulhi_epu16(bytes, by36);
        let rest = _mm512_sub_epi16(bytes, _mm512_mullo_epi16(d2, thirty_six));
        let d1 = _mm512_mulhi_epu16(rest, by6);
        let d0 = _mm512_sub_epi16(rest, _mm512_mullo_epi16(d1, six));
        even = _mm512_dpwssd_epi32(even, d0, qa);
        odd = _mm512_dpwssd_epi32(odd, d1, qb);
        even = _mm512_dpwssd_epi32(even, d2, qc);
    }
    // SAFETY: the CPU has AVX2 (implied by AVX-512), for the last bytes.
    _mm512_reduce_add_epi32(_mm512_add_epi32(even, odd)) + unsafe { digit_dot_avx2(planes, codes, end) }
}

/// Coded rows one after another, growing at the end and shrinking at the front (the coded
/// counterpart of [`super::rows::DescriptorRows`]). Each row is its codes followed by its factors
/// (little-endian `f32`s), so that a scan reads one contiguous span a row.
#[derive(Clone, Debug, Default)]
pub struct CodedRows {
    dim: usize,
    /// Huge pages: an index query jumps between rows all over it ([`super::huge_pages`]).
    bytes: HugePageBytes,
}

impl CodedRows {
    pub fn with_capacity(dim: usize, rows: usize) -> Self {
        CodedRows { dim, bytes: HugePageBytes::with_capacity(rows * row_bytes(dim)) }
    }

    pub fn rows(&self) -> usize {
        self.bytes.len() / row_bytes(self.dim)
    }

    /// Appends the code of each `dim`-value row of `values`.
    pub fn extend_from_values(&mut self, values: &[f32]) {
        let len = code_len(self.dim);
        for row in values.chunks_exact(self.dim.max(1)) {
            let (codes, factors) = self.bytes.extend_zeroed(row_bytes(self.dim)).split_at_mut(len);
            let Factors { norm2, dot_scale, mean_term } = encode(row, codes);
            factors[..4].copy_from_slice(&norm2.to_le_bytes());
            factors[4..8].copy_from_slice(&dot_scale.to_le_bytes());
            factors[8..].copy_from_slice(&mean_term.to_le_bytes());
        }
    }

    /// Moves `other`'s rows (of the same length) to the end of these.
    pub fn append(&mut self, other: CodedRows) {
        debug_assert_eq!(self.dim, other.dim);
        self.bytes.extend_from_slice(&other.bytes);
    }

    /// Removes the first `rows` rows.
    pub fn drain_front(&mut self, rows: usize) {
        self.bytes.drain_front(rows * row_bytes(self.dim));
    }

    /// The codes and factors of row `slot`.
    #[inline(always)]
    pub fn row(&self, slot: usize) -> (&[u8], Factors) {
        let (codes, factors) = self.row_span(slot).split_at(code_len(self.dim));
        let value = |at: usize| f32::from_le_bytes(factors[at..at + 4].try_into().expect("4 bytes"));
        (codes, Factors { norm2: value(0), dot_scale: value(4), mean_term: value(8) })
    }

    /// The bytes of row `slot`: what to prefetch.
    #[inline(always)]
    pub fn row_span(&self, slot: usize) -> &[u8] {
        let len = row_bytes(self.dim);
        &self.bytes[slot * len..(slot + 1) * len]
    }

    /// The reconstruction of row `slot` into `out` (`dim` values).
    pub fn decode_into(&self, slot: usize, out: &mut [f32]) {
        let (codes, factors) = self.row(slot);
        decode_into(codes, factors, out)
    }

    /// Bytes of memory the rows take.
    pub fn bytes(&self) -> usize {
        self.bytes.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detector::index::ClusteredVectors;

    #[test]
    fn digits_by_reciprocals_match_division_for_every_byte() {
        for b in 0..=255u32 {
            let d2 = (b * 1821) >> 16;
            let rest = b - 36 * d2;
            let d1 = (rest * 10923) >> 16;
            assert_eq!([rest - 6 * d1, d1, d2], [b % 6, b / 6 % 6, b / 36], "byte {b}");
        }
    }

    /// The plain reference: the levels' centres one value at a time over +-2.5 RMS around zero, as
    /// `descriptor_study`'s `l2q6`.
    fn reference_levels(v: &[f32]) -> Vec<f32> {
        let rms = (v.iter().map(|x| x * x).sum::<f32>() / v.len() as f32).sqrt();
        if rms == 0.0 {
            return vec![0.0; v.len()];
        }
        let (clip, step) = (2.5 * rms, 5.0 * rms / 6.0);
        v.iter().map(|x| ((x.clamp(-clip, clip - 1e-6) + clip) / step).floor() * step - clip + step / 2.0).collect()
    }

    fn mean(v: &[f32]) -> f64 {
        v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64
    }

    /// The row's deviations from its mean.
    fn deviations(v: &[f32]) -> Vec<f32> {
        let m = mean(v) as f32;
        v.iter().map(|x| x - m).collect()
    }

    fn dot(a: &[f32], b: &[f32]) -> f64 {
        a.iter().zip(b).map(|(&x, &y)| x as f64 * y as f64).sum()
    }

    #[test]
    fn a_row_takes_under_a_kilobyte_and_decodes_to_the_reference_levels() {
        assert_eq!(row_bytes(2880), 972);
        for dim in [1, 2, 3, 7, 128, 2880] {
            // Not unit length: the factors carry the length.
            let v: Vec<f32> = ClusteredVectors::new(dim, 3, dim as u64).take(1).iter().map(|x| 3.0 * x).collect();
            let mut codes = vec![0u8; code_len(dim)];
            let factors = encode(&v, &mut codes);
            assert!(codes.iter().all(|&b| b < 216));
            let mut decoded = vec![0f32; dim];
            decode_into(&codes, factors, &mut decoded);
            // The decoded vector is the mean plus the deviations' reference levels at their length.
            let r = deviations(&v);
            let want = reference_levels(&r);
            let (norm_want, norm_r, norm_v) = (dot(&want, &want).sqrt(), dot(&r, &r).sqrt(), dot(&v, &v).sqrt());
            for (i, (got, want)) in decoded.iter().zip(&want).enumerate() {
                let want = if norm_want > 0.0 { *want as f64 / norm_want * norm_r } else { 0.0 } + mean(&v);
                assert!((*got as f64 - want).abs() < 1e-5, "dim {dim} value {i}: {got} vs {want}");
            }
            assert!((factors.norm2 as f64 - norm_v * norm_v).abs() < 1e-4);
        }
        // A zero vector: no NaN, and every query is at its own length from it.
        let mut codes = vec![0u8; 2];
        let factors = encode(&[0.0; 5], &mut codes);
        let query = [0.5, -0.25, 0.0, 1.0, 0.0];
        let got = CodedQuery::new(&query).squared_distance(&codes, factors);
        assert!((got - 1.3125).abs() < 1e-5, "{got}");
    }

    #[test]
    fn the_scan_distance_is_the_estimate_from_the_f32_reconstruction() {
        for dim in [5, 16, 48, 49, 100, 2880] {
            let mut gen = ClusteredVectors::new(dim, 4, 3 + dim as u64);
            let stored = gen.take(20);
            let mut rows = CodedRows::with_capacity(dim, 20);
            rows.extend_from_values(&stored);
            for query in gen.take(5).chunks_exact(dim).chain(stored.chunks_exact(dim).take(3)) {
                let prepared = CodedQuery::new(query);
                let mut decoded = vec![0f32; dim];
                for (slot, s) in stored.chunks_exact(dim).enumerate() {
                    rows.decode_into(slot, &mut decoded);
                    // |q|^2 + |s|^2 - 2 (m sum(q) + (q - q_m).d |r|^2 / (r.d)), in f64, with `d` the
                    // decoded reconstruction's deviations from the stored mean `m`.
                    let (m, r) = (mean(s), deviations(s));
                    let d: Vec<f32> = decoded.iter().map(|x| (*x as f64 - m) as f32).collect();
                    let centred_query = deviations(query);
                    let estimate = m * mean(query) * dim as f64 + dot(&centred_query, &d) * dot(&r, &r) / dot(&r, &d);
                    let want = dot(query, query) + dot(s, s) - 2.0 * estimate;
                    let (codes, factors) = rows.row(slot);
                    let got = prepared.squared_distance(codes, factors);
                    assert!((got as f64 - want.max(0.0)).abs() < 1e-4, "dim {dim}, row {slot}: {got} vs {want}");
                    if query == s {
                        assert!(got < 1e-4, "a stored vector is at distance 0 from itself, not {got}");
                    }
                    // Every SIMD kernel and the plain unpacking agree exactly.
                    let plain = digit_dot_portable(&prepared.planes, codes, 0);
                    assert_eq!(digit_dot(&prepared.planes, codes), plain);
                    #[cfg(target_arch = "x86_64")]
                    if std::arch::is_x86_feature_detected!("avx2") {
                        // SAFETY: checked just above.
                        assert_eq!(unsafe { digit_dot_avx2(&prepared.planes, codes, 0) }, plain);
                    }
                }
            }
        }
    }

    #[test]
    fn estimated_scores_keep_the_f32_scale_where_the_plain_projection_shrinks_them() {
        // Neighbours in a cluster: the estimate's error averages out, the projection's bias does not.
        let dim = 2880;
        let mut gen = ClusteredVectors::new(dim, 2, 9);
        let stored = gen.take(50);
        let mut rows = CodedRows::with_capacity(dim, 50);
        rows.extend_from_values(&stored);
        let query = gen.take(1);
        let prepared = CodedQuery::new(&query);
        let (mut estimate_error, mut projection_error) = (0f64, 0f64);
        let mut decoded = vec![0f32; dim];
        for (slot, s) in stored.chunks_exact(dim).enumerate() {
            let exact = dot(&query, s);
            let (codes, factors) = rows.row(slot);
            let d2 = prepared.squared_distance(codes, factors) as f64;
            estimate_error += (1.0 + 1.0 - d2) / 2.0 - exact;
            rows.decode_into(slot, &mut decoded);
            projection_error += dot(&query, &decoded) - exact;
        }
        let (estimate_bias, projection_bias) = (estimate_error / 50.0, projection_error / 50.0);
        assert!(projection_bias < -0.005, "the projection shrinks inner products: {projection_bias}");
        assert!(estimate_bias.abs() < projection_bias.abs() / 5.0, "{estimate_bias} vs {projection_bias}");
    }

    #[test]
    fn a_non_negative_row_is_coded_around_its_mean() {
        // Pooled ReLU6 features (`l2`, `power`): every value non-negative. Levels around zero would
        // leave the three negative ones unused.
        let dim = 1280;
        let v: Vec<f32> = ClusteredVectors::new(dim, 2, 5).take(1).iter().map(|x| x.abs()).collect();
        let mut codes = vec![0u8; code_len(dim)];
        let factors = encode(&v, &mut codes);
        let mut decoded = vec![0f32; dim];
        decode_into(&codes, factors, &mut decoded);
        let cosine = |a: &[f32], b: &[f32]| dot(a, b) / (dot(a, a) * dot(b, b)).sqrt();
        let around_mean = cosine(&v, &decoded);
        let around_zero = cosine(&v, &reference_levels(&v));
        assert!(around_mean > 0.98, "{around_mean}");
        assert!(1.0 - around_mean < (1.0 - around_zero) / 2.0, "{around_mean} vs {around_zero}");
        let used: std::collections::BTreeSet<u32> = codes.iter().flat_map(|&b| digits(b)).collect();
        assert_eq!(used.len(), LEVELS as usize);
    }

    #[test]
    fn drained_rows_keep_the_rest() {
        let dim = 10;
        let values = ClusteredVectors::new(dim, 2, 1).take(6);
        let mut rows = CodedRows::with_capacity(dim, 6);
        rows.extend_from_values(&values);
        let last = rows.row(5).0.to_vec();
        rows.drain_front(4);
        assert_eq!(rows.rows(), 2);
        assert_eq!(rows.row(1).0, &last[..]);
        assert_eq!(rows.bytes(), 2 * row_bytes(dim));
    }
}
