//! Matching of ORB's 256-bit descriptors: mutual nearest neighbours by Hamming distance with a ratio
//! test, in one pass over the distance matrix.
//!
//! The result is exactly that of kornia's `match_descriptors(query, matched, None, true, Some(ratio))`
//! (the same ties, the same ratio rule; a test holds the two together). Kornia walks the matrix twice,
//! once per direction, and calls a distance function per pair; here each pair's distance is four
//! inlined population counts, computed once and used for both the row's best two and the column's
//! best, so a check of two keyframes with 1000 features each costs a fraction of the time.

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

/// The best match of one query row: (index, distance, second-best distance).
struct RowBest {
    index: usize,
    distance: u32,
    second: u32,
}

/// Pairs `(query index, matched index)` that are each other's nearest neighbour and pass the ratio
/// test (best distance / second-best distance below `ratio`; off at 1 or more), in query order.
pub fn mutual_matches(query: &[[u8; 32]], matched: &[[u8; 32]], ratio: f32) -> Vec<(usize, usize)> {
    if query.is_empty() || matched.is_empty() {
        return Vec::new();
    }
    let query: Vec<Words> = query.iter().map(words).collect();
    let matched: Vec<Words> = matched.iter().map(words).collect();
    // Per task: the best match of each of its rows, and each column's (distance, row) minimum
    // over its rows, the first row winning a tie.
    let tasks: Vec<(Vec<RowBest>, Vec<(u32, usize)>)> = query
        .par_chunks(ROWS_PER_TASK)
        .enumerate()
        .map(|(task, rows)| {
            let mut columns = vec![(u32::MAX, 0usize); matched.len()];
            let rows = rows
                .iter()
                .enumerate()
                .map(|(offset, a)| {
                    let row = task * ROWS_PER_TASK + offset;
                    let mut best = RowBest { index: 0, distance: u32::MAX, second: u32::MAX };
                    for (j, (b, column)) in matched.iter().zip(columns.iter_mut()).enumerate() {
                        let d = distance(a, b);
                        if d < best.distance {
                            best = RowBest { index: j, distance: d, second: best.distance };
                        } else if d < best.second {
                            best.second = d;
                        }
                        if d < column.0 {
                            *column = (d, row);
                        }
                    }
                    best
                })
                .collect();
            (rows, columns)
        })
        .collect();
    // Tasks are in row order, so a strict comparison keeps the first row of a tie.
    let mut column_best = vec![(u32::MAX, 0usize); matched.len()];
    for (_, columns) in &tasks {
        for (best, &candidate) in column_best.iter_mut().zip(columns) {
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
