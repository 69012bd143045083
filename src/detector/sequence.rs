//! Sequence matching: a revisit is a run of matches, not one (after SeqSLAM, Milford and Wyeth 2012).
//!
//! Interpretation, written down once:
//! - **Online, looking back.** The score of query `t` against keyframe `p` is the mean of the
//!   single-image scores of queries `t, t-1, ..., t-L+1` against keyframes `p, p∓1, ..., p∓(L-1)`: the
//!   diagonal that ends at the current query. No later query is waited for, so the answer has no
//!   delay; what it needs is the last `L - 1` query descriptors, kept here.
//! - **Both directions.** A second visit may go the other way along a corridor, so the diagonal is
//!   followed forwards (`p - k`) and backwards (`p + k`) and the better one counts.
//! - **Speed.** Keyframes of the two visits are not taken at the same places: each step of the
//!   diagonal takes the best of the keyframes one before, at, and one after its position.
//! - **Edges.** Diagonal steps that fall outside the history, on keyframes the recency rules exclude,
//!   or before the first query are left out and the mean is over the steps taken; at the start of a
//!   run the score is the single-image score.
//! - **Start of a revisit.** The first `L - 1` queries of a revisit are scored partly with queries
//!   from before it, which match nothing there; sequence matching pays off from the `L`-th on.
//! - **Candidates.** Only the nearest [`CANDIDATES`] keyframes of the current query are scored, so the
//!   index still bounds the work: `CANDIDATES * L * 3` distances per query.
//! - **When it is on.** `detector.sequence.length` 0, the default, means: [`ROUTE_LENGTH`] where
//!   queries are matched against a database made beforehand (`eval --database --queries`: a route
//!   travelled again, the queries a walk along it), single images where keyframes come one by one
//!   and a revisit may be a single keyframe (a tracker's stream, a replay). The diagonal takes one
//!   database keyframe per query, so the walk is only assumed where both are sampled alike and the
//!   queries look like one ([`why_not_a_walk`]): counts within [`MAX_COUNT_RATIO`] of each other,
//!   and for [`WALK_EVIDENCE`] of the queries the next is nearer than the one half the set away.

use std::collections::VecDeque;

use crate::descriptor::distance;

/// Keyframes nearest to the current query that the sequence score re-ranks.
pub const CANDIDATES: usize = 10;

/// The sequence length of a route travelled again (module doc: when it is on); SeqSLAM's usual
/// length.
pub const ROUTE_LENGTH: usize = 10;

/// The largest ratio of database to query count (either way) at which queries are taken as a walk
/// sampled like the database.
pub const MAX_COUNT_RATIO: f64 = 1.5;

/// The share of queries, at least, whose successor must be nearer to them than the query half the
/// set away for the queries to be taken as a walk: about all of them in a walk, about half in a set
/// in no order.
pub const WALK_EVIDENCE: f64 = 0.75;

/// Why `queries` (descriptors in their order) against a database of `database` keyframes are not a
/// walk sampled like it, or `None` when they are (module doc: when it is on).
pub fn why_not_a_walk(database: usize, queries: &[Vec<f32>]) -> Option<String> {
    let n = queries.len();
    let (fewer, more) = (database.min(n), database.max(n));
    if fewer == 0 || more as f64 > MAX_COUNT_RATIO * fewer as f64 {
        return Some(format!("{database} database images and {n} queries are not sampled alike"));
    }
    if n < 4 {
        return None;
    }
    let nearer = (0..n - 1)
        .filter(|&t| {
            let far = (t + n / 2) % n;
            distance(&queries[t], &queries[t + 1]) < distance(&queries[t], &queries[far])
        })
        .count();
    let share = nearer as f64 / (n - 1) as f64;
    (share < WALK_EVIDENCE).then(|| {
        format!("the queries do not look like a walk (for {:.0}% of them the next one is nearer than one half the set away)", 100.0 * share)
    })
}

/// The descriptors of the last `length - 1` queries, oldest first.
#[derive(Clone, Debug, Default)]
pub struct RecentQueries {
    length: usize,
    queries: VecDeque<Vec<f32>>,
}

impl RecentQueries {
    /// Room for a sequence of `length` queries (the current one and `length - 1` kept).
    pub fn new(length: usize) -> Self {
        RecentQueries { length, queries: VecDeque::new() }
    }

    pub fn set_length(&mut self, length: usize) {
        self.length = length;
        self.trim();
    }

    pub fn clear(&mut self) {
        self.queries.clear();
    }

    /// Remembers a query that has been matched (kept only while the sequence policy is on).
    pub fn push(&mut self, descriptor: &[f32]) {
        if self.length > 1 {
            self.queries.push_back(descriptor.to_vec());
            self.trim();
        }
    }

    fn trim(&mut self) {
        while self.queries.len() > self.length.saturating_sub(1) {
            self.queries.pop_front();
        }
    }

    /// The kept queries, newest first (the query `k + 1` steps before the current one is item `k`).
    pub fn newest_first(&self) -> impl Iterator<Item = &[f32]> {
        self.queries.iter().rev().map(Vec::as_slice)
    }

    /// The sequence score of the current query against keyframe `position` of a history of `len`
    /// keyframes (module doc). `pair_score(age, p)` is the single-image score against keyframe `p`
    /// of the query `age` steps back (0: the current one, `k + 1`: item `k` of
    /// [`RecentQueries::newest_first`]), and `eligible(p)` whether the recency rules let `p` match.
    pub fn sequence_score(
        &self,
        position: usize,
        len: usize,
        pair_score: impl Fn(usize, usize) -> f32,
        eligible: impl Fn(usize) -> bool,
    ) -> f32 {
        let first = pair_score(0, position);
        let step_score = |age: usize, centre: isize| -> Option<f32> {
            (centre - 1..=centre + 1)
                .filter(|&p| p >= 0 && (p as usize) < len && eligible(p as usize))
                .map(|p| pair_score(age, p as usize))
                .reduce(f32::max)
        };
        [-1isize, 1]
            .into_iter()
            .map(|direction| {
                let (mut sum, mut steps) = (first, 1usize);
                for age in 1..=self.queries.len() {
                    let centre = position as isize + direction * age as isize;
                    if let Some(score) = step_score(age, centre) {
                        sum += score;
                        steps += 1;
                    }
                }
                sum / steps as f32
            })
            .fold(f32::NEG_INFINITY, f32::max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::descriptor::{distance, Descriptor, DescriptorMode};

    fn unit(angle: f32) -> Vec<f32> {
        vec![angle.cos(), angle.sin()]
    }

    #[test]
    fn the_diagonal_is_averaged_both_ways_and_only_recent_queries_are_kept() {
        let d = Descriptor::new(DescriptorMode::L2, 2);
        // History: keyframes at angles 0, 0.1, ..., 0.9.
        let history: Vec<Vec<f32>> = (0..10).map(|i| unit(i as f32 * 0.1)).collect();
        let mut recent = RecentQueries::new(3);
        for angle in [0.5, 0.3, 0.4] {
            recent.push(&unit(angle));
        }
        assert_eq!(recent.queries.len(), 2, "length 3 keeps the two before the current");
        let current = unit(0.5);
        let queries: Vec<&[f32]> = std::iter::once(&current[..]).chain(recent.newest_first()).collect();
        let pair = |age: usize, p: usize| d.score(distance(queries[age], &history[p]));
        // The current query equals keyframe 5; the earlier ones were 0.3 (k=2) and 0.4 (k=1): forwards
        // (p-1 = 4, p-2 = 3) they match exactly, so the sequence score is 1.
        let score = recent.sequence_score(5, history.len(), pair, |_| true);
        assert!((score - 1.0).abs() < 1e-6, "{score}");
        // Against keyframe 8, forwards the steps take the best of 6..=8 for 0.4 and of 5..=7 for 0.3;
        // backwards of 8..=9 and of 9 alone (10 and 11 are past the history).
        let single = |a: f32, b: f32| d.score(distance(&unit(a), &unit(b)));
        let expected_forwards = (single(0.5, 0.8) + single(0.4, 0.6) + single(0.3, 0.5)) / 3.0;
        let expected_backwards = (single(0.5, 0.8) + single(0.4, 0.8) + single(0.3, 0.9)) / 3.0;
        let score = recent.sequence_score(8, history.len(), pair, |_| true);
        assert!((score - expected_forwards.max(expected_backwards)).abs() < 1e-6, "{score}");
        // Excluded keyframes are not steps: with only keyframe 5 eligible, the step of 0.4 (centre 4 or
        // 6) still reaches 5, the step of 0.3 (centre 3 or 7) reaches nothing and is left out.
        let score = recent.sequence_score(5, history.len(), pair, |p| p == 5);
        assert!((score - (1.0 + single(0.4, 0.5)) / 2.0).abs() < 1e-6, "{score}");
        // Length 1 keeps nothing.
        let mut off = RecentQueries::new(1);
        off.push(&unit(0.0));
        assert!(off.queries.is_empty());
    }

    #[test]
    fn a_walk_is_assumed_only_where_both_sets_are_sampled_alike_and_the_queries_look_like_one() {
        // A walk: each query a small step from the last along a turning route.
        let walk: Vec<Vec<f32>> = (0..40).map(|i| unit(i as f32 * 0.05)).collect();
        assert_eq!(why_not_a_walk(40, &walk), None);
        assert_eq!(why_not_a_walk(60, &walk), None, "within 1.5x either way");
        assert_eq!(why_not_a_walk(27, &walk), None);
        let why = why_not_a_walk(80, &walk).expect("twice as many keyframes as queries");
        assert!(why.contains("not sampled alike"), "{why}");
        assert!(why_not_a_walk(26, &walk).is_some());
        assert!(why_not_a_walk(0, &walk).is_some());
        // The same queries in no order (a fixed permutation).
        let shuffled: Vec<Vec<f32>> = (0..40).map(|i| walk[(i * 17) % 40].clone()).collect();
        let why = why_not_a_walk(40, &shuffled).expect("photos in no order");
        assert!(why.contains("do not look like a walk"), "{why}");
    }
}
