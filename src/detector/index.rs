//! Nearest-neighbour search for [`super::KeyframeDb`]: a SIMD brute-force scan (exact) and an
//! inverted-file index (IVF, approximate) that the database builds by itself once it is large.
//!
//! - Exact scan: [`crate::descriptor::squared_distance`] (eight independent partial sums) inlined into a
//!   loop compiled twice, baseline and AVX2, picked at run time; the additions are the same in both, so
//!   the distances are bit-identical to the plain function.
//! - IVF: k-means centroids (a few Lloyd iterations on a sample) split the stored descriptors into
//!   `nlist` lists (spherical for unit descriptors: see [`IvfIndex::train`]); a query ranks the
//!   centroids (for coded rows: a shortlist by the centroids' codes, then exactly) and scans only the
//!   `nprobe` nearest lists, computing exact
//!   distances on the stored rows (`f32`, or six-level codes: [`super::codes`]), so a returned distance
//!   is always the one the exact scan gives and only the *set* of neighbours can differ from it. Chosen over a graph index (HNSW) because
//!   it is small (4 bytes per keyframe besides the descriptors, against 100+ for an HNSW graph), inserts
//!   incrementally at a fixed cost, tolerates dropping the oldest keyframes (the memory budget) with a
//!   linear pass, and its build time is bounded and predictable (seconds at 1M keyframes).
//! - Automatic choice ([`IndexPolicy`]): the index is trained when the database reaches
//!   `max(min_len, scan_values / dim)` keyframes (brute force then scans about 10 MB per query) and
//!   retrained from scratch each time the database has grown `retrain_growth` times since the last
//!   training (the lists would otherwise grow unevenly). Below the threshold the search is the exact scan.
//!   The first training is done at once; a retraining goes on a slice per insert ([`IvfTraining`]) while
//!   the previous index keeps serving, so no keyframe waits for it.
//! - Newly inserted keyframes are assigned to lists in batches ([`ASSIGN_BATCH`], one matrix product); the
//!   not-yet-assigned tail is scanned exactly on every query, so no keyframe is ever invisible.
//! - Filters (recent-keyframe exclusion) are applied while scanning; when the probed lists yield fewer
//!   than `k` eligible keyframes, the query falls back to the exact scan, so a query never returns
//!   fewer results than the exact search would. On a rayon worker the probed lists are scanned in parallel.

use rayon::prelude::*;

use super::rows::{PreparedQuery, RowFormat, Rows};
use super::Neighbour;
use crate::descriptor::squared_distance;

/// Keyframes assigned to the index's lists at once (the rest of the tail is scanned exactly).
pub const ASSIGN_BATCH: usize = 1024;

/// When the database builds and rebuilds its approximate index.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IndexPolicy {
    /// Never index fewer keyframes than this (`usize::MAX` disables the index: always exact).
    pub min_len: usize,
    /// Index once `len * dim` reaches this many values (the size of one exact scan).
    pub scan_values: usize,
    /// Retrain when the database has grown this many times since the last training.
    pub retrain_growth: usize,
    /// Fraction of the lists a query scans (at least 8): the speed/recall trade-off.
    pub probe_fraction: f64,
    /// Multiply-adds of a retraining done per insert ([`IvfTraining`]).
    pub retrain_slice_macs: usize,
}

impl Default for IndexPolicy {
    fn default() -> Self {
        // 2.5M values = 10 MB of f32: 20k keyframes at 128-d, 5k at 1280-d (the `min_len` floor),
        // where an exact scan costs about a millisecond and a half (128-d) to a few (1280-d).
        // A 64th of the lists (at least 8) kept recall@10 >= 0.99 on clustered data from 10k to 1M
        // keyframes at 128-d and 1280-d (0.996 at 1M: `ecm-lcd-bench speed --only search` measures it).
        // A retraining slice of 2^27 multiply-adds takes 2-3 ms of matrix products on two cores (a whole
        // retraining at 80k 1280-d keyframes, in one go: 3.5 s).
        IndexPolicy {
            min_len: 5000,
            scan_values: 2_621_440,
            retrain_growth: 4,
            probe_fraction: 1.0 / 64.0,
            retrain_slice_macs: 1 << 27,
        }
    }
}

impl IndexPolicy {
    /// Always exact.
    pub const EXACT: IndexPolicy = IndexPolicy {
        min_len: usize::MAX,
        scan_values: usize::MAX,
        retrain_growth: 8,
        probe_fraction: 1.0,
        retrain_slice_macs: usize::MAX,
    };

    /// The database length from which descriptors of length `dim` are indexed.
    pub fn threshold(&self, dim: usize) -> usize {
        if self.min_len == usize::MAX || dim == 0 {
            return usize::MAX;
        }
        self.min_len.max(self.scan_values.div_ceil(dim)).max(1)
    }
}

/// The `k` smallest `(squared distance, position)` pairs seen so far, smallest first; ties go to the
/// earlier position, so the order does not depend on the order of the scan.
pub(crate) struct TopK {
    k: usize,
    best: Vec<Neighbour>,
}

impl TopK {
    pub fn new(k: usize) -> Self {
        TopK { k, best: Vec::with_capacity(k + 1) }
    }

    #[inline]
    pub fn offer(&mut self, position: usize, squared_distance: f32) {
        let before = |n: &Neighbour| (n.squared_distance, n.position) < (squared_distance, position);
        if self.best.len() == self.k && self.best.last().is_some_and(before) {
            return;
        }
        let at = self.best.partition_point(before);
        self.best.insert(at, Neighbour { position, squared_distance });
        self.best.truncate(self.k);
    }

    pub fn len(&self) -> usize {
        self.best.len()
    }

    /// The top k of both.
    pub fn merge(mut self, other: TopK) -> TopK {
        for n in other.best {
            self.offer(n.position, n.squared_distance);
        }
        self
    }

    pub fn into_vec(self) -> Vec<Neighbour> {
        self.best
    }
}

/// Calls `visit(i, d2)` for each `(i, row)` that `rows` yields.
#[inline(always)]
fn scan_portable<'a>(
    query: &[f32],
    rows: impl Iterator<Item = (usize, &'a [f32])>,
    visit: &mut impl FnMut(usize, f32),
) {
    for (i, row) in rows {
        visit(i, squared_distance(query, row));
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn scan_avx2<'a>(query: &[f32], rows: impl Iterator<Item = (usize, &'a [f32])>, visit: &mut impl FnMut(usize, f32)) {
    scan_portable(query, rows, visit)
}

/// Squared distances from `query` to each `(i, row)`, with the widest SIMD the CPU has.
pub(crate) fn scan<'a>(
    query: &[f32],
    rows: impl Iterator<Item = (usize, &'a [f32])>,
    mut visit: impl FnMut(usize, f32),
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return unsafe { scan_avx2(query, rows, &mut visit) };
    }
    scan_portable(query, rows, &mut visit)
}

/// Rows ahead of the scan whose memory is requested early (see [`IvfIndex::nearest`]).
const PREFETCH_AHEAD: usize = 8;

/// Rows assigned per matrix product (bounds the `rows x nlist` product to a few MB per thousand lists).
const ASSIGN_CHUNK: usize = 2048;

/// Centroids prepared for assigning rows to them: transposed for the matrix product, with their
/// half squared norms. Made once per set of centroids (an index's, or a Lloyd pass's), not per call:
/// at 1024 x 1280 the transposed copy is 5 MB.
#[derive(Clone, Debug)]
struct CentroidMatrix {
    transposed: candle_core::Tensor,
    half_norms: Vec<f32>,
}

impl CentroidMatrix {
    fn new(centroids: &[f32], dim: usize) -> anyhow::Result<Self> {
        use candle_core::{Device, Tensor};
        let half_norms: Vec<f32> =
            centroids.chunks_exact(dim).map(|c| 0.5 * c.iter().map(|x| x * x).sum::<f32>()).collect();
        let transposed = Tensor::from_slice(centroids, (half_norms.len(), dim), &Device::Cpu)?.t()?.contiguous()?;
        Ok(CentroidMatrix { transposed, half_norms })
    }

    /// The nearest centroid of each row of `rows` (`dim` values each). Computed as the largest
    /// `x.c - |c|^2 / 2` with one matrix product per chunk (candle's gemm: SIMD and multi-threaded), which
    /// is an order of magnitude faster than a distance scan per row and ranks centroids the same way up
    /// to rounding (only the list a keyframe lands in depends on it, never a reported distance).
    fn nearest(&self, dim: usize, rows: &[f32]) -> anyhow::Result<Vec<usize>> {
        let nlist = self.half_norms.len();
        let mut out = Vec::with_capacity(rows.len() / dim);
        for chunk in rows.chunks(ASSIGN_CHUNK * dim) {
            let x = candle_core::Tensor::from_slice(chunk, (chunk.len() / dim, dim), &candle_core::Device::Cpu)?;
            let dots = x.matmul(&self.transposed)?.flatten_all()?.to_vec1::<f32>()?;
            out.extend(dots.chunks_exact(nlist).map(|row| {
                let mut best = (f32::NEG_INFINITY, 0);
                for (c, (&d, &h)) in row.iter().zip(&self.half_norms).enumerate() {
                    if d - h > best.0 {
                        best = (d - h, c);
                    }
                }
                best.1
            }));
        }
        Ok(out)
    }
}

/// A small deterministic generator (xorshift64*) for sampling; no statistical quality needed.
#[derive(Clone, Debug)]
struct Sampler(u64);

impl Sampler {
    fn next(&mut self, below: usize) -> usize {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545F4914F6CDD1D) >> 11) as usize % below.max(1)
    }

    /// Roughly normal (a sum of four uniforms, centred): enough for synthetic data.
    fn gauss(&mut self) -> f32 {
        (0..4).map(|_| self.next(1 << 20) as f32 / (1 << 20) as f32).sum::<f32>() - 2.0
    }
}

/// Synthetic descriptor-like vectors for tests and benchmarks: unit vectors scattered around `clusters`
/// random centres (places seen again and again), unlike uniform noise, in which every point is nearly
/// equidistant from every other and no index (nor a real detector) could do well.
#[derive(Clone)]
pub struct ClusteredVectors {
    dim: usize,
    centres: Vec<f32>,
    rng: Sampler,
}

impl ClusteredVectors {
    /// Relative spread of a cluster (noise per value against the centres' spread).
    const SPREAD: f32 = 0.25;

    pub fn new(dim: usize, clusters: usize, seed: u64) -> Self {
        let mut rng = Sampler(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
        let centres = (0..clusters.max(1) * dim).map(|_| rng.gauss()).collect();
        ClusteredVectors { dim, centres, rng }
    }

    /// The same centres, another sequence of points (queries near the stored vectors).
    pub fn reseed(mut self, seed: u64) -> Self {
        self.rng = Sampler(seed.wrapping_mul(0xD1B5_4A32_D192_ED03) | 1);
        self
    }

    /// The next vector into `out` (`dim` values).
    pub fn next_into(&mut self, out: &mut [f32]) {
        let clusters = self.centres.len() / self.dim.max(1);
        let centre = &self.centres[self.rng.next(clusters) * self.dim..][..self.dim];
        for (o, &c) in out.iter_mut().zip(centre) {
            *o = c + Self::SPREAD * self.rng.gauss();
        }
        let norm = out.iter().map(|x| x * x).sum::<f32>().sqrt().max(f32::MIN_POSITIVE);
        out.iter_mut().for_each(|x| *x /= norm);
    }

    /// The next `count` vectors, one after the other.
    pub fn take(&mut self, count: usize) -> Vec<f32> {
        let mut out = vec![0f32; count * self.dim];
        out.chunks_exact_mut(self.dim.max(1)).for_each(|v| self.next_into(v));
        out
    }
}

/// Inverted lists over the database's descriptor buffer. Entries are *slots*: row numbers in that
/// buffer, counted from its start (including keyframes dropped but not yet drained).
#[derive(Clone, Debug)]
pub(crate) struct IvfIndex {
    dim: usize,
    centroids: Vec<f32>,
    /// For coded rows, the centroids coded too, so that ranking them reads a twelfth of the bytes.
    coded_centroids: Option<Rows>,
    matrix: CentroidMatrix,
    lists: Vec<Vec<u32>>,
    /// Slots `[0, assigned)` are in the lists; later ones are scanned exactly.
    assigned: usize,
    /// Live keyframes when the index was trained.
    trained_len: usize,
    nprobe: usize,
}

/// k-means iterations (Lloyd) when training; more change the lists little on descriptor-like data.
const KMEANS_ITERATIONS: usize = 6;
/// Lists probed at least.
const MIN_PROBE: usize = 8;
/// Bound on the bytes of centroids every query ranks: 1024 `f32` centroids up to 1280-d. With coded
/// rows a query ranks the centroids' codes (a twelfth of the bytes), so long coded descriptors get up
/// to [`MAX_LISTS`] lists too. Fewer, larger lists make a query scan a larger share of the keyframes
/// for the same recall; retraining in slices ([`IvfTraining`]) keeps the larger training affordable.
const MAX_RANKED_BYTES: usize = 1024 * 1280 * 4;
/// Lists at most.
const MAX_LISTS: usize = 1024;
/// Training sample per list.
const SAMPLE_PER_LIST: usize = 64;

/// An index being trained a slice at a time, so that a retraining never holds up one keyframe for
/// seconds (k-means and assigning every keyframe cost `n * nlist * dim` multiply-adds: 3.5 s at 80k
/// 1280-d keyframes in one go). [`IvfTraining::step`] does at most a given number of multiply-adds,
/// in order: [`KMEANS_ITERATIONS`] Lloyd passes over a fixed sample, then the assignment of every row,
/// catching up with rows inserted meanwhile. The database keeps searching with its previous index
/// until the new one is complete. The work is counted, not timed, so the result is deterministic and
/// the same as a training done in one go ([`IvfIndex::train`]).
#[derive(Clone, Debug)]
pub(crate) struct IvfTraining {
    dim: usize,
    nlist: usize,
    /// The rows' format, which the index's coded centroids follow.
    format: RowFormat,
    /// Rows copied at the start, in the rows' format (a coded sample takes a twelfth of the
    /// memory): later inserts and drops do not change them.
    sample: Rows,
    centroids: Vec<f32>,
    sampler: Sampler,
    /// `centroids` prepared for this Lloyd pass (made by its first step).
    matrix: Option<CentroidMatrix>,
    iteration: usize,
    /// Next sample row of the current Lloyd pass, and that pass's sums so far.
    cursor: usize,
    sums: Vec<f64>,
    counts: Vec<usize>,
    norm_sums: Vec<f64>,
    /// Where assignment starts (the first live slot at the start), until the index exists.
    first_slot: usize,
    trained_len: usize,
    probe_fraction: f64,
    /// Set once the Lloyd passes are done: the index whose lists are being filled.
    index: Option<IvfIndex>,
}

impl IvfTraining {
    /// Starts a training on the live rows `rows[first_live..]` (`dim` values each): only the sample is
    /// taken now.
    pub fn start(rows: &Rows, first_live: usize, probe_fraction: f64) -> Self {
        let (dim, total) = (rows.dim(), rows.slots());
        let live = total - first_live;
        let format = rows.format();
        // 2 sqrt(n) lists, at most MAX_LISTS and as many as MAX_RANKED_BYTES allows.
        let ranked_row_bytes = if format == RowFormat::F32 { 4 * dim } else { format.row_bytes(dim) };
        let max_lists = (MAX_RANKED_BYTES / ranked_row_bytes.max(1)).clamp(1, MAX_LISTS);
        let nlist = ((2.0 * (live as f64).sqrt()).round() as usize).clamp(1, max_lists);
        // A fixed sample: evenly spread over the history, then jittered, so training is reproducible.
        let mut sampler = Sampler(0x9E37_79B9_7F4A_7C15 ^ live as u64);
        let sample_len = (nlist * SAMPLE_PER_LIST).min(live).max(1);
        let stride = live / sample_len;
        let mut sample = Rows::with_capacity(format, dim, sample_len);
        for i in 0..sample_len {
            let slot = first_live + (i * stride + sampler.next(stride)).min(live - 1);
            sample.extend(&rows.values(slot, slot + 1));
        }
        // Initial centroids: sample rows spread over the sample.
        let centroids: Vec<f32> = (0..nlist)
            .flat_map(|c| {
                let row = c * sample_len / nlist;
                sample.values(row, row + 1).into_owned()
            })
            .collect();
        IvfTraining {
            dim,
            nlist,
            format,
            sample,
            centroids,
            sampler,
            matrix: None,
            iteration: 0,
            cursor: 0,
            sums: vec![0f64; nlist * dim],
            counts: vec![0usize; nlist],
            norm_sums: vec![0f64; nlist],
            first_slot: first_live,
            trained_len: live,
            probe_fraction,
            index: None,
        }
    }

    /// Does at most about `max_macs` multiply-adds of the training (at least one row's worth); the
    /// index once it is complete, with every row of `rows` assigned.
    pub fn step(&mut self, rows: &Rows, max_macs: usize) -> anyhow::Result<Option<IvfIndex>> {
        let (dim, nlist) = (self.dim, self.nlist);
        let step_rows = (max_macs / (nlist * dim).max(1)).max(1);
        if let Some(index) = &mut self.index {
            let end = index.assigned.saturating_add(step_rows).min(rows.slots());
            index.assign_pending(rows, end)?;
            return Ok((end == rows.slots()).then(|| self.index.take().expect("the index being filled")));
        }
        let sample_len = self.sample.slots();
        // At most a chunk at a time: a coded sample is decoded for the pass.
        let end = self.cursor.saturating_add(step_rows.min(ASSIGN_CHUNK)).min(sample_len);
        let chunk = self.sample.values(self.cursor, end);
        let matrix = match &mut self.matrix {
            Some(matrix) => matrix,
            none => none.insert(CentroidMatrix::new(&self.centroids, dim)?),
        };
        for (offset, c) in matrix.nearest(dim, &chunk)?.into_iter().enumerate() {
            let row = &chunk[offset * dim..(offset + 1) * dim];
            self.counts[c] += 1;
            self.norm_sums[c] += row.iter().map(|&x| (x as f64) * (x as f64)).sum::<f64>().sqrt();
            self.sums[c * dim..(c + 1) * dim].iter_mut().zip(row).for_each(|(s, &x)| *s += x as f64);
        }
        self.cursor = end;
        if end == sample_len {
            self.finish_pass()?;
        }
        Ok(None)
    }

    /// Ends a Lloyd pass: moves each centroid to its members; after the last pass, the index to fill.
    fn finish_pass(&mut self) -> anyhow::Result<()> {
        let (dim, sample_len) = (self.dim, self.sample.slots());
        for c in 0..self.nlist {
            let centroid = &mut self.centroids[c * dim..(c + 1) * dim];
            if self.counts[c] == 0 {
                // An empty list takes a random sample row, so no centroid is wasted.
                let row = self.sampler.next(sample_len);
                centroid.copy_from_slice(&self.sample.values(row, row + 1));
            } else {
                // The members' mean direction at their mean length: for unit descriptors this is
                // spherical k-means. A plain mean is shorter than its members, and short centroids
                // attract ever more points, giving a few huge lists that every query probes.
                let sum = &self.sums[c * dim..(c + 1) * dim];
                let sum_norm = sum.iter().map(|s| s * s).sum::<f64>().sqrt().max(f64::MIN_POSITIVE);
                let scale = self.norm_sums[c] / self.counts[c] as f64 / sum_norm;
                centroid.iter_mut().zip(sum).for_each(|(x, &s)| *x = (s * scale) as f32);
            }
        }
        self.sums.iter_mut().for_each(|s| *s = 0.0);
        self.counts.iter_mut().for_each(|n| *n = 0);
        self.norm_sums.iter_mut().for_each(|s| *s = 0.0);
        self.cursor = 0;
        self.matrix = None;
        self.iteration += 1;
        if self.iteration == KMEANS_ITERATIONS {
            let nprobe = ((self.nlist as f64 * self.probe_fraction).round() as usize).max(MIN_PROBE).min(self.nlist);
            let coded_centroids = (self.format == RowFormat::Levels6).then(|| {
                let mut coded = Rows::with_capacity(self.format, dim, self.nlist);
                coded.extend(&self.centroids);
                coded
            });
            self.index = Some(IvfIndex {
                dim,
                coded_centroids,
                matrix: CentroidMatrix::new(&self.centroids, dim)?,
                centroids: std::mem::take(&mut self.centroids),
                lists: vec![Vec::new(); self.nlist],
                assigned: self.first_slot,
                trained_len: self.trained_len,
                nprobe,
            });
            // The sample is no longer needed; free it while the assignment goes on.
            self.sample = Rows::with_capacity(self.format, dim, 0);
        }
        Ok(())
    }

    /// The first `count` slots were removed from the buffer (see [`IvfIndex::drain`]).
    pub fn drain(&mut self, count: usize) {
        self.first_slot = self.first_slot.saturating_sub(count);
        if let Some(index) = &mut self.index {
            index.drain(count);
        }
    }
}

impl IvfIndex {
    /// Trains on the live rows (slots from `first_live`) and assigns every row, in one go.
    pub fn train(rows: &Rows, first_live: usize, probe_fraction: f64) -> anyhow::Result<Self> {
        let mut training = IvfTraining::start(rows, first_live, probe_fraction);
        loop {
            if let Some(index) = training.step(rows, usize::MAX)? {
                return Ok(index);
            }
        }
    }

    pub fn nlist(&self) -> usize {
        self.lists.len()
    }

    pub fn nprobe(&self) -> usize {
        self.nprobe
    }

    pub fn largest_list(&self) -> usize {
        self.lists.iter().map(Vec::len).max().unwrap_or(0)
    }

    pub fn trained_len(&self) -> usize {
        self.trained_len
    }

    /// Rows not yet in a list.
    pub fn pending(&self, rows: &Rows) -> usize {
        rows.slots() - self.assigned
    }

    /// Puts every slot before `end` not yet assigned into its list, a chunk at a time (coded rows
    /// are decoded a chunk at a time).
    pub fn assign_pending(&mut self, rows: &Rows, end: usize) -> anyhow::Result<()> {
        for start in (self.assigned..end).step_by(ASSIGN_CHUNK) {
            let stop = (start + ASSIGN_CHUNK).min(end);
            let lists = self.matrix.nearest(self.dim, &rows.values(start, stop))?;
            for (offset, c) in lists.into_iter().enumerate() {
                self.lists[c].push((start + offset) as u32);
            }
        }
        self.assigned = self.assigned.max(end);
        Ok(())
    }

    /// The first `count` slots were removed from the buffer: forget them and renumber the rest.
    pub fn drain(&mut self, count: usize) {
        let count32 = count as u32;
        for list in &mut self.lists {
            list.retain(|&slot| slot >= count32);
            list.iter_mut().for_each(|slot| *slot -= count32);
        }
        self.assigned = self.assigned.saturating_sub(count);
    }

    /// The approximate top `k` over live rows (slots from `first_live`) that `eligible` accepts
    /// (positions = slot - first_live), `prepared` being `query` prepared for `rows`. `None` when
    /// fewer than `k` eligible rows were found, so the caller falls back to the exact scan.
    pub fn nearest(
        &self,
        rows: &Rows,
        first_live: usize,
        query: &[f32],
        prepared: &PreparedQuery<'_>,
        k: usize,
        eligible: &(dyn Fn(usize) -> bool + Sync),
    ) -> Option<Vec<Neighbour>> {
        let dim = self.dim;
        let mut probe = TopK::new(self.nprobe);
        let centroid = |c: usize| (c, &self.centroids[c * dim..(c + 1) * dim]);
        match &self.coded_centroids {
            // The codes' estimate shortlists twice the lists, and the exact distances pick from those:
            // the lists the exact ranking alone would probe, at a fraction of its reads.
            Some(coded) => {
                let mut shortlist = TopK::new(2 * self.nprobe);
                coded.scan(prepared, (0..self.nlist()).map(|c| (c, c)), |c, d2| shortlist.offer(c, d2));
                let shortlisted = shortlist.into_vec().into_iter().map(|n| centroid(n.position));
                scan(query, shortlisted, |c, d2| probe.offer(c, d2));
            }
            None => scan(query, (0..self.nlist()).map(centroid), |c, d2| probe.offer(c, d2)),
        }
        // On a rayon worker (the pipeline runs there: `runtime::on_worker`), the probed lists are
        // scanned in parallel, each into a top-k of its own, merged after: the scan waits on memory
        // (rows are scattered), and two threads overlap twice the misses. From any other thread a
        // parallel region costs a cross-thread hand-off (about 0.25 ms here, more than a 128-d
        // query), so the lists are scanned in turn. TopK breaks ties by position, so the result does
        // not depend on the split.
        let scan_list = |list: Neighbour| {
            let list = &self.lists[list.position];
            let mut top = TopK::new(k);
            let slots = list.iter().enumerate().filter_map(|(j, &slot)| {
                // A list's rows are scattered over the buffer: fetch a few rows ahead so the memory
                // latency overlaps the arithmetic (the scan is latency-bound otherwise).
                if let Some(&ahead) = list.get(j + PREFETCH_AHEAD) {
                    rows.prefetch(ahead as usize);
                }
                let slot = slot as usize;
                (slot >= first_live && eligible(slot - first_live)).then_some((slot - first_live, slot))
            });
            rows.scan(prepared, slots, |p, d2| top.offer(p, d2));
            top
        };
        let lists = probe.into_vec();
        let mut top = if rayon::current_thread_index().is_some() {
            lists.into_par_iter().map(scan_list).reduce(|| TopK::new(k), TopK::merge)
        } else {
            lists.into_iter().map(scan_list).fold(TopK::new(k), TopK::merge)
        };
        let tail = (self.assigned.max(first_live)..rows.slots()).map(|s| s - first_live).filter(|&p| eligible(p));
        rows.scan(prepared, tail.map(|p| (p, p + first_live)), |p, d2| top.offer(p, d2));
        (top.len() == k).then(|| top.into_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detector::{KeyframeDb, RowFormat};
    use crate::types::Stamp;

    fn clustered(count: usize, dim: usize, clusters: usize, seed: u64) -> Vec<f32> {
        ClusteredVectors::new(dim, clusters, seed).take(count)
    }

    #[test]
    fn simd_scan_is_bit_identical_to_the_descriptor_distance() {
        for dim in [1, 7, 8, 13, 128, 1280] {
            let rows = clustered(5, dim, 2, dim as u64);
            let query = &rows[..dim];
            scan(query, rows.chunks_exact(dim).enumerate(), |i, d2| {
                assert_eq!(d2.to_bits(), crate::descriptor::squared_distance(query, &rows[i * dim..][..dim]).to_bits());
            });
        }
    }

    #[test]
    fn index_is_chosen_by_size_and_keeps_recall() -> anyhow::Result<()> {
        for format in [RowFormat::F32, RowFormat::Levels6] {
            index_keeps_recall(format)?;
        }
        Ok(())
    }

    fn index_keeps_recall(format: RowFormat) -> anyhow::Result<()> {
        let (dim, count) = (32, 6000);
        let policy = IndexPolicy { min_len: 2000, scan_values: 0, ..IndexPolicy::default() };
        assert_eq!(policy.threshold(dim), 2000);
        assert_eq!(IndexPolicy::EXACT.threshold(dim), usize::MAX);
        let data = clustered(count, dim, 60, 7);
        let mut db = KeyframeDb::with_format(format, dim, 0);
        db.set_index_policy(policy)?;
        let mut exact = KeyframeDb::with_format(format, dim, 0);
        exact.set_index_policy(IndexPolicy::EXACT)?;
        for (i, v) in data.chunks_exact(dim).enumerate() {
            db.insert(i as u64, Stamp::from_nanos(i as i64), v)?;
            exact.insert(i as u64, Stamp::from_nanos(i as i64), v)?;
            assert_eq!(db.index_info().is_some(), i + 1 >= 2000, "after {} keyframes", i + 1);
        }
        let info = db.index_info().unwrap();
        assert!(info.nlist > 1 && info.nprobe < info.nlist, "{info:?}");
        let queries = ClusteredVectors::new(dim, 60, 7).reseed(99).take(100);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build()?;
        let (k, mut hits) = (10, 0);
        for q in queries.chunks_exact(dim) {
            // Exclude the newest 500 as the detector does.
            let eligible = |p: usize| p < count - 500;
            let got = db.nearest(q, k, eligible)?;
            let want = exact.nearest(q, k, eligible)?;
            // On a pool's worker the probed lists are scanned in parallel: the same answer.
            assert_eq!(pool.install(|| db.nearest(q, k, eligible))?, got);
            assert_eq!(got.len(), k);
            assert!(got.iter().all(|n| eligible(n.position)));
            hits += got.iter().filter(|n| want.contains(n)).count();
        }
        let recall = hits as f64 / (100 * k) as f64;
        assert!(recall >= 0.99, "{format:?} recall@{k} {recall}");
        Ok(())
    }

    #[test]
    fn a_training_in_slices_equals_one_in_one_go() -> anyhow::Result<()> {
        let dim = 24;
        let rows = Rows::plain(dim, clustered(4000, dim, 40, 11).into());
        let whole = IvfIndex::train(&rows, 100, 1.0 / 64.0)?;
        let mut training = IvfTraining::start(&rows, 100, 1.0 / 64.0);
        let mut steps = 1;
        // A slice of 300 rows' worth of work.
        let sliced = loop {
            if let Some(index) = training.step(&rows, 300 * whole.nlist() * dim)? {
                break index;
            }
            steps += 1;
        };
        // 6 Lloyd passes over a 3900-row sample (13 slices each) and 3900 rows to assign (13).
        assert_eq!(whole.nlist(), 125);
        assert_eq!(steps, KMEANS_ITERATIONS * 13 + 13);
        assert_eq!(sliced.centroids, whole.centroids);
        assert_eq!(sliced.lists, whole.lists);
        assert_eq!(
            (sliced.assigned, sliced.trained_len, sliced.nprobe),
            (whole.assigned, whole.trained_len, whole.nprobe)
        );
        Ok(())
    }

    #[test]
    fn a_retraining_goes_on_over_inserts_while_the_old_index_serves() -> anyhow::Result<()> {
        let dim = 32;
        let data = clustered(9000, dim, 80, 13);
        // Retrained at 4000 (growth 2 from 2000), a slice of about 100 rows' worth of work per insert.
        let slice = 100 * 126 * dim;
        let policy = IndexPolicy {
            min_len: 2000,
            scan_values: 0,
            retrain_growth: 2,
            retrain_slice_macs: slice,
            ..IndexPolicy::default()
        };
        let mut db = KeyframeDb::new(dim);
        db.set_index_policy(policy)?;
        let mut exact = KeyframeDb::new(dim);
        exact.set_index_policy(IndexPolicy::EXACT)?;
        let mut swapped_at = None;
        for (i, v) in data.chunks_exact(dim).enumerate() {
            db.insert(i as u64, Stamp::from_nanos(i as i64), v)?;
            exact.insert(i as u64, Stamp::from_nanos(i as i64), v)?;
            let trained_len = db.index_info().map(|info| info.trained_len);
            match i + 1 {
                n if n < 2000 => assert_eq!(trained_len, None),
                n if n < 4000 => assert_eq!(trained_len, Some(2000), "after {n}"),
                n => {
                    if trained_len == Some(4000) && swapped_at.is_none() {
                        swapped_at = Some(n);
                    }
                    assert_eq!(trained_len, Some(if swapped_at.is_some() { 4000 } else { 2000 }), "after {n}");
                }
            }
            // Dropping the oldest keyframes during the retraining renumbers both indexes' slots.
            if i + 1 == 4100 {
                db.drop_oldest(1000);
                exact.drop_oldest(1000);
            }
            // While the old index serves, during the retraining and after it, every keyframe is found.
            if (i + 1) % 250 == 0 {
                let q = &data[(i - 3) * dim..(i - 2) * dim];
                let got = db.nearest(q, 5, |_| true)?;
                assert_eq!(db.id(got[0].position), i as u64 - 3, "after {}", i + 1);
                assert_eq!(got[0], exact.nearest(q, 5, |_| true)?[0]);
            }
        }
        // 126 lists, a 4000-row sample (6 passes of 40 slices), 3000 live rows to assign: about 270
        // inserts (each insert adds a row to assign).
        let swapped_at = swapped_at.expect("the retraining ended");
        assert!((4200..4400).contains(&swapped_at), "{swapped_at}");
        assert_eq!(db.index_info().unwrap().nlist, 126);
        // Every live keyframe is in the new index's lists or its unassigned tail: each finds itself.
        for p in (0..db.len()).step_by(37) {
            let q = &data[(p + 1000) * dim..(p + 1001) * dim];
            assert_eq!(db.nearest(q, 1, |_| true)?[0].position, p);
        }
        Ok(())
    }

    #[test]
    fn a_deferred_bulk_load_builds_the_index_once_at_the_end() -> anyhow::Result<()> {
        let dim = 8;
        let data = clustered(3000, dim, 20, 5);
        let mut db = KeyframeDb::new(dim);
        db.set_index_policy(IndexPolicy { min_len: 500, scan_values: 0, ..IndexPolicy::default() })?;
        db.defer_index(true)?;
        for (i, v) in data.chunks_exact(dim).enumerate() {
            db.insert(i as u64, Stamp::from_nanos(i as i64), v)?;
        }
        assert!(db.index_info().is_none(), "no index while deferred");
        let mut later = db.clone();
        db.defer_index(false)?;
        assert_eq!(db.index_info().unwrap().trained_len, 3000);
        // Ending the deferral for later: built by the next insert.
        later.index_at_next_insert();
        assert!(later.index_info().is_none());
        later.insert(3000, Stamp::from_nanos(3000), &data[..dim])?;
        assert_eq!(later.index_info().unwrap().trained_len, 3001);
        // Incremental afterwards: the next keyframe is found at once (scanned as the unassigned tail).
        db.insert(3000, Stamp::from_nanos(3000), &data[..dim])?;
        let got = db.nearest(&data[..dim], 2, |_| true)?;
        assert_eq!(got.iter().map(|n| n.position).collect::<Vec<_>>(), vec![0, 3000]);
        Ok(())
    }

    #[test]
    fn short_filtered_results_fall_back_to_exact_and_drops_renumber() -> anyhow::Result<()> {
        let dim = 16;
        let data = clustered(3000, dim, 30, 3);
        let mut db = KeyframeDb::new(dim);
        db.set_index_policy(IndexPolicy {
            min_len: 1000,
            scan_values: 0,
            retrain_growth: 2,
            ..IndexPolicy::default()
        })?;
        for (i, v) in data.chunks_exact(dim).enumerate() {
            db.insert(i as u64, Stamp::from_nanos(i as i64), v)?;
        }
        // Retrained at 2000 (growth 2 from 1000).
        assert_eq!(db.index_info().unwrap().trained_len, 2000);
        let mut exact = db.clone();
        exact.set_index_policy(IndexPolicy::EXACT)?;
        // Only three positions are eligible: the probed lists may miss them, the fallback may not.
        let eligible = |p: usize| p % 1000 == 17;
        let q = &data[5 * dim..6 * dim];
        assert_eq!(db.nearest(q, 3, eligible)?, exact.nearest(q, 3, eligible)?);
        // Drop the oldest 1200 (drained, since 1200 >= 1800 / 8): positions renumber, ids follow.
        db.drop_oldest(1200);
        exact.drop_oldest(1200);
        assert_eq!(db.len(), 1800);
        let q = &data[2500 * dim..2501 * dim];
        let got = db.nearest(q, 1, |_| true)?;
        assert_eq!(db.id(got[0].position), 2500);
        assert_eq!(got, exact.nearest(q, 1, |_| true)?);
        Ok(())
    }
}
