//! Matching of ORB's 256-bit descriptors: mutual nearest neighbours by Hamming distance with a ratio
//! test, in one pass over the distance matrix.
//!
//! The result is exactly that of kornia's `match_descriptors(query, matched, None, true, Some(ratio))`
//! (the same ties, the same ratio rule; a test holds the two together). Kornia walks the matrix twice,
//! once per direction, and calls a distance function per pair; here each pair's distance is four
//! inlined population counts, computed once and used for both the row's best two and the column's
//! best, so a check of two keyframes with 1000 features each costs a fraction of the time. Where
//! the CPU has AVX-512's 64-bit population count, eight columns are done at once ([`avx512`]).

use rayon::prelude::*;

/// Query rows per parallel task: each task keeps its own column minima over all of `matched`.
const ROWS_PER_TASK: usize = 64;

/// A 256-bit descriptor as four words.
type Words = [u64; 4];

fn words(descriptor: &[u8; 32]) -> Words {
    std::array::from_fn(|k| u64::from_le_bytes(descriptor[8 * k..8 * k + 8].try_into().expect("8 bytes")))
}

#[inline(always)]
fn distance(a: &Words, b: &Words) -> u32 {
    (a[0] ^ b[0]).count_ones() + (a[1] ^ b[1]).count_ones() + (a[2] ^ b[2]).count_ones() + (a[3] ^ b[3]).count_ones()
}

/// The best match of one query row; `u32::MAX` stands for "none" (a second-best of a single
/// column).
#[derive(Clone, Copy, Debug, PartialEq)]
struct RowBest {
    index: usize,
    distance: u32,
    second: u32,
}

/// What one task finds over its query rows: each row's best match, and each matched column's
/// (distance, row) minimum over those rows, the first row winning a tie.
type TaskResult = (Vec<RowBest>, Vec<(u32, usize)>);

/// Pairs `(query index, matched index)` that are each other's nearest neighbour and pass the ratio
/// test (best distance / second-best distance below `ratio`; off at 1 or more), in query order.
pub fn mutual_matches(query: &[[u8; 32]], matched: &[[u8; 32]], ratio: f32) -> Vec<(usize, usize)> {
    let query: Vec<Words> = query.iter().map(words).collect();
    let matched: Vec<Words> = matched.iter().map(words).collect();
    #[cfg(target_arch = "x86_64")]
    if avx512::available() {
        let blocks = avx512::blocks(&matched);
        // SAFETY: the CPU has AVX-512F and VPOPCNTDQ (checked above).
        return mutual(&query, matched.len(), ratio, |rows, first| unsafe {
            avx512::task(rows, first, &blocks, matched.len())
        });
    }
    mutual(&query, matched.len(), ratio, |rows, first| task(rows, first, &matched))
}

/// The mutual and ratio tests over the rows' best matches, which `task` finds for a slice of query
/// rows (and the index of its first) against all `columns` matched descriptors.
fn mutual(
    query: &[Words],
    columns: usize,
    ratio: f32,
    task: impl Fn(&[Words], usize) -> TaskResult + Sync,
) -> Vec<(usize, usize)> {
    if query.is_empty() || columns == 0 {
        return Vec::new();
    }
    let tasks: Vec<TaskResult> =
        query.par_chunks(ROWS_PER_TASK).enumerate().map(|(i, rows)| task(rows, i * ROWS_PER_TASK)).collect();
    // Tasks are in row order, so a strict comparison keeps the first row of a tie.
    let mut column_best = vec![(u32::MAX, 0usize); columns];
    for (_, task_columns) in &tasks {
        for (best, &candidate) in column_best.iter_mut().zip(task_columns) {
            if candidate.0 < best.0 {
                *best = candidate;
            }
        }
    }
    tasks
        .iter()
        .flat_map(|(rows, _)| rows)
        .enumerate()
        .filter(|(i, best)| column_best[best.index].1 == *i)
        .filter(|(_, best)| {
            ratio >= 1.0 || {
                let denominator = if best.second == 0 { f32::EPSILON } else { best.second as f32 };
                (best.distance as f32 / denominator) < ratio
            }
        })
        .map(|(i, best)| (i, best.index))
        .collect()
}

/// One task on any CPU: each pair's distance once, scanned in column order.
fn task(rows: &[Words], first_row: usize, matched: &[Words]) -> TaskResult {
    let mut columns = vec![(u32::MAX, 0usize); matched.len()];
    let rows = rows
        .iter()
        .enumerate()
        .map(|(offset, a)| {
            let mut best = RowBest { index: 0, distance: u32::MAX, second: u32::MAX };
            for (j, (b, column)) in matched.iter().zip(columns.iter_mut()).enumerate() {
                let d = distance(a, b);
                if d < best.distance {
                    best = RowBest { index: j, distance: d, second: best.distance };
                } else if d < best.second {
                    best.second = d;
                }
                if d < column.0 {
                    *column = (d, first_row + offset);
                }
            }
            best
        })
        .collect();
    (rows, columns)
}

/// The same task eight columns at a time: AVX-512's population count of 64-bit lanes gives eight
/// distances in four instructions, and each lane keeps its own best two and column minima, which
/// are merged as a scan in column order would have found them.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use std::arch::x86_64::*;

    use super::{RowBest, TaskResult, Words};

    /// Eight matched descriptors word by word: `block[k][lane]` is word `k` of descriptor
    /// `8 * block + lane` (zero past the last).
    pub(super) type Block = [[u64; 8]; 4];

    pub(super) fn available() -> bool {
        is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512vpopcntdq")
    }

    pub(super) fn blocks(matched: &[Words]) -> Vec<Block> {
        matched
            .chunks(8)
            .map(|chunk| std::array::from_fn(|k| std::array::from_fn(|lane| chunk.get(lane).map_or(0, |w| w[k]))))
            .collect()
    }

    fn lanes(v: __m512i) -> [u64; 8] {
        // SAFETY: both are 64 plain bytes.
        unsafe { std::mem::transmute(v) }
    }

    /// A distance, with the lanes' "none" (`u64::MAX`) as `u32::MAX`.
    fn narrow(d: u64) -> u32 {
        u32::try_from(d).unwrap_or(u32::MAX)
    }

    /// # Safety
    /// The CPU must have AVX-512F and VPOPCNTDQ ([`available`]); `blocks` hold `columns`
    /// descriptors.
    #[target_feature(enable = "avx512f,avx512vpopcntdq")]
    pub(super) unsafe fn task(rows: &[Words], first_row: usize, blocks: &[Block], columns: usize) -> TaskResult {
        let none = _mm512_set1_epi64(-1);
        let eight = _mm512_set1_epi64(8);
        // Lanes past the last descriptor keep "none", which no comparison lets through.
        let last_lanes: __mmask8 = match columns % 8 {
            0 => 0xff,
            n => (1u8 << n) - 1,
        };
        let mut column_distance = vec![u64::MAX; blocks.len() * 8];
        let mut column_row = vec![0u64; blocks.len() * 8];
        let mut best_rows = Vec::with_capacity(rows.len());
        for (offset, a) in rows.iter().enumerate() {
            let row = _mm512_set1_epi64((first_row + offset) as i64);
            let a = a.map(|w| _mm512_set1_epi64(w as i64));
            let (mut best, mut second, mut best_index) = (none, none, _mm512_setzero_si512());
            let mut index = _mm512_setr_epi64(0, 1, 2, 3, 4, 5, 6, 7);
            for (b, block) in blocks.iter().enumerate() {
                let mut d = _mm512_setzero_si512();
                for (word, column_words) in a.iter().zip(block) {
                    // SAFETY: eight u64 in reach.
                    let w = unsafe { _mm512_loadu_si512(column_words.as_ptr().cast()) };
                    d = _mm512_add_epi64(d, _mm512_popcnt_epi64(_mm512_xor_si512(*word, w)));
                }
                if b + 1 == blocks.len() {
                    d = _mm512_mask_blend_epi64(last_lanes, none, d);
                }
                // As the scan: nearer than the best moves the best to second, else it may be second.
                let nearer = _mm512_cmplt_epu64_mask(d, best);
                second = _mm512_mask_blend_epi64(nearer, _mm512_min_epu64(second, d), best);
                best = _mm512_mask_blend_epi64(nearer, best, d);
                best_index = _mm512_mask_blend_epi64(nearer, best_index, index);
                index = _mm512_add_epi64(index, eight);
                // SAFETY: the column arrays hold 8 values per block.
                unsafe {
                    let distance_at = column_distance.as_mut_ptr().add(8 * b);
                    let closer = _mm512_cmplt_epu64_mask(d, _mm512_loadu_si512(distance_at.cast()));
                    _mm512_mask_storeu_epi64(distance_at.cast(), closer, d);
                    _mm512_mask_storeu_epi64(column_row.as_mut_ptr().add(8 * b).cast(), closer, row);
                }
            }
            // Each lane scanned its columns in order; the nearest over the lanes (the first column
            // on a tie) is the row's best, and its second is the nearest of the rest.
            let (best, second, best_index) = (lanes(best), lanes(second), lanes(best_index));
            let lane = (0..8).min_by_key(|&l| (best[l], best_index[l])).expect("eight lanes");
            let second = (0..8).filter(|&l| l != lane).map(|l| best[l]).chain([second[lane]]).min().expect("lanes");
            best_rows.push(RowBest {
                index: best_index[lane] as usize,
                distance: narrow(best[lane]),
                second: narrow(second),
            });
        }
        let columns =
            column_distance.iter().zip(&column_row).take(columns).map(|(&d, &r)| (narrow(d), r as usize)).collect();
        (best_rows, columns)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use kornia_imgproc::features::match_descriptors;
    use rand::{Rng, SeedableRng};

    /// `count` descriptors, each a random base (one of `bases`) with `flips` random bits flipped, so
    /// that near neighbours, ties and ambiguous matches all occur.
    fn descriptors(rng: &mut rand::rngs::StdRng, bases: &[[u8; 32]], count: usize, flips: u32) -> Vec<[u8; 32]> {
        (0..count)
            .map(|_| {
                let mut d = bases[rng.random_range(0..bases.len())];
                for _ in 0..rng.random_range(0..=flips) {
                    let bit = rng.random_range(0..256);
                    d[bit / 8] ^= 1 << (bit % 8);
                }
                d
            })
            .collect()
    }

    #[test]
    fn matches_are_kornias_exactly() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for (bases, query_count, matched_count, flips) in
            [(40, 300, 280, 20), (5, 130, 150, 3), (1000, 70, 65, 0), (3, 1, 200, 1), (200, 200, 1, 10)]
        {
            let bases: Vec<[u8; 32]> = (0..bases).map(|_| rng.random()).collect();
            let query = descriptors(&mut rng, &bases, query_count, flips);
            let matched = descriptors(&mut rng, &bases, matched_count, flips);
            for ratio in [0.8, 0.9, 1.0] {
                let ours = mutual_matches(&query, &matched, ratio);
                let kornias = match_descriptors(&query, &matched, None, true, Some(ratio));
                assert_eq!(ours, kornias, "{query_count} x {matched_count}, {flips} flips, ratio {ratio}");
            }
        }
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn the_avx512_task_finds_what_the_scan_finds() {
        if !avx512::available() {
            eprintln!("no AVX-512 VPOPCNTDQ here: nothing to compare");
            return;
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        for (bases, query_count, matched_count, flips) in
            [(30, 70, 61, 12), (4, 64, 8, 2), (500, 9, 1, 0), (3, 40, 17, 1)]
        {
            let bases: Vec<[u8; 32]> = (0..bases).map(|_| rng.random()).collect();
            let query: Vec<Words> = descriptors(&mut rng, &bases, query_count, flips).iter().map(words).collect();
            let matched: Vec<Words> = descriptors(&mut rng, &bases, matched_count, flips).iter().map(words).collect();
            let blocks = avx512::blocks(&matched);
            for first_row in [0, 128] {
                // SAFETY: checked above.
                let vectorised = unsafe { avx512::task(&query, first_row, &blocks, matched.len()) };
                assert_eq!(vectorised, task(&query, first_row, &matched), "{query_count} x {matched_count}");
            }
        }
    }

    #[test]
    fn a_ratio_at_the_limit_is_refused_as_by_kornia() {
        let with_bits = |n: usize| -> [u8; 32] { std::array::from_fn(|k| if k < n { 1 } else { 0 }) };
        // Distances 4 and 5 from the query: a ratio of exactly 0.8.
        let matched = [with_bits(4), with_bits(5)];
        for ratio in [0.8, 0.81] {
            let ours = mutual_matches(&[[0; 32]], &matched, ratio);
            assert_eq!(ours, match_descriptors(&[[0; 32]], &matched, None, true, Some(ratio)), "ratio {ratio}");
            assert_eq!(ours.is_empty(), ratio == 0.8, "ratio {ratio}");
        }
    }

    #[test]
    fn nothing_matches_nothing() {
        assert!(mutual_matches(&[], &[[0; 32]], 0.8).is_empty());
        assert!(mutual_matches(&[[0; 32]], &[], 0.8).is_empty());
    }
}
