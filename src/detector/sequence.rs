//! Sequence matching: a revisit is a run of matches, not one (after SeqSLAM, Milford and Wyeth 2012).
//!
//! Interpretation, written down once:
//! - **Online, looking back.** The score of query `t` against keyframe `p` is the mean of the
//!   single-image scores of queries `t, t-1, ..., t-L+1` against keyframes `p, p∓1, ..., p∓(L-1)`: the
//!   diagonal that ends at the current query. No later query is waited for, so the answer has no
//!   delay; what it needs is the last `L - 1` query descriptors, kept here.
//! - **Filled where the queries are known beforehand.** Matched against a database made
//!   beforehand, every query is described before any is matched, so the first `L - 1` queries of a
//!   walk, which have fewer than `L - 1` before them, take the window of the first `L` queries
//!   ([`queries_ahead`]): every query of a walk of `L` or more is scored on `L` steps, the first
//!   ones too, whose scores would otherwise be means of fewer steps, on a higher scale than the
//!   rest. Later queries keep the window that ends at them (a window centred on each query was
//!   measured and lost: docs/accuracy.md).
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
//! - **When it is on.** Where `detector.sequence.length` is set above 1. Its default 0 means single
//!   images where keyframes come one by one and a revisit may be a single keyframe (a tracker's
//!   stream, a replay), and where queries are matched against a database made beforehand (`eval
//!   --database --queries`) the whole walk's alignment ([`super::walk`]), which sees later queries
//!   too, where the queries look like a walk.

use std::collections::VecDeque;

use crate::types::Stamp;

/// Keyframes nearest to the current query that the sequence score re-ranks.
pub const CANDIDATES: usize = 10;

/// The descriptors of the last `length - 1` queries, oldest first, each with what the recency rules
/// judged it by: its stamp and the history's length when it was matched.
#[derive(Clone, Debug, Default)]
pub struct RecentQueries {
    length: usize,
    queries: VecDeque<Vec<f32>>,
    judged_by: VecDeque<(Stamp, usize)>,
}

impl RecentQueries {
    /// Room for a sequence of `length` queries (the current one and `length - 1` kept).
    pub fn new(length: usize) -> Self {
        RecentQueries { length, queries: VecDeque::new(), judged_by: VecDeque::new() }
    }

    pub fn set_length(&mut self, length: usize) {
        self.length = length;
        self.trim();
    }

    pub fn clear(&mut self) {
        self.queries.clear();
        self.judged_by.clear();
    }

    /// Remembers a query that has been matched at `stamp` against a history of `history_len`
    /// keyframes (kept only while the sequence policy is on).
    pub fn push(&mut self, descriptor: &[f32], stamp: Stamp, history_len: usize) {
        if self.length > 1 {
            self.queries.push_back(descriptor.to_vec());
            self.judged_by.push_back((stamp, history_len));
            self.trim();
        }
    }

    /// The history lost its `dropped` oldest keyframes (a memory budget): the lengths the kept
    /// queries were matched against shrink with it, so positions still line up.
    pub fn history_dropped(&mut self, dropped: usize) {
        self.judged_by.iter_mut().for_each(|(_, len)| *len = len.saturating_sub(dropped));
    }

    /// The stamp and history length of the kept query `age` steps before the current one (1: the
    /// newest kept).
    pub fn judged_by(&self, age: usize) -> Option<(Stamp, usize)> {
        self.judged_by.len().checked_sub(age).map(|i| self.judged_by[i])
    }

    fn trim(&mut self) {
        while self.queries.len() > self.length.saturating_sub(1) {
            self.queries.pop_front();
            self.judged_by.pop_front();
        }
    }

    /// The kept queries, newest first (the query `k + 1` steps before the current one is item `k`).
    pub fn newest_first(&self) -> impl Iterator<Item = &[f32]> {
        self.queries.iter().rev().map(Vec::as_slice)
    }

    /// How many kept queries the window of the current query takes when `ahead` later queries join
    /// it: the window is `length` queries in all.
    pub fn behind(&self, ahead: usize) -> usize {
        self.queries.len().min(self.length.saturating_sub(1 + ahead))
    }

    /// The sequence score of the current query against keyframe `position` of a history of `len`
    /// keyframes (module doc), over a window of the current query, [`RecentQueries::behind`] kept
    /// ones and `ahead` later ones. `pair_score(offset, p)` is the single-image score against
    /// keyframe `p` of the query `offset` steps from the current one (0: the current one, -1: the one
    /// before it, i.e. item 0 of [`RecentQueries::newest_first`], 1: the one after it), and
    /// `eligible(offset, p)` whether the recency rules let `p` match that query: an earlier query is
    /// judged as it was when it came, so that it is never compared with itself or with keyframes
    /// too recent for it.
    pub fn sequence_score(
        &self,
        ahead: usize,
        position: usize,
        len: usize,
        pair_score: impl Fn(isize, usize) -> f32,
        eligible: impl Fn(isize, usize) -> bool,
    ) -> f32 {
        let first = pair_score(0, position);
        let step_score = |offset: isize, centre: isize| -> Option<f32> {
            (centre - 1..=centre + 1)
                .filter(|&p| p >= 0 && (p as usize) < len && eligible(offset, p as usize))
                .map(|p| pair_score(offset, p as usize))
                .reduce(f32::max)
        };
        let offsets: Vec<isize> = (1..=self.behind(ahead) as isize).map(|age| -age).chain(1..=ahead as isize).collect();
        [-1isize, 1]
            .into_iter()
            .map(|direction| {
                let (mut sum, mut steps) = (first, 1usize);
                for &offset in &offsets {
                    if let Some(score) = step_score(offset, position as isize - direction * offset) {
                        sum += score;
                        steps += 1;
                    }
                }
                sum / steps as f32
            })
            .fold(f32::NEG_INFINITY, f32::max)
    }
}

/// How many of the queries after query `index` of `count` join its window of `length` when all of
/// them are known beforehand (module doc: the database/query mode): none where `length - 1` earlier
/// queries fill it, else as many as it lacks.
pub fn queries_ahead(length: usize, index: usize, count: usize) -> usize {
    let start = index.saturating_sub(length.saturating_sub(1)).min(count.saturating_sub(length));
    (start + length).min(count).saturating_sub(index + 1)
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
            recent.push(&unit(angle), Stamp::from_nanos(0), 0);
        }
        assert_eq!(recent.queries.len(), 2, "length 3 keeps the two before the current");
        let current = unit(0.5);
        let queries: Vec<&[f32]> = std::iter::once(&current[..]).chain(recent.newest_first()).collect();
        let pair = |offset: isize, p: usize| d.score(distance(queries[offset.unsigned_abs()], &history[p]));
        // The current query equals keyframe 5; the earlier ones were 0.3 (k=2) and 0.4 (k=1): forwards
        // (p-1 = 4, p-2 = 3) they match exactly, so the sequence score is 1.
        let score = recent.sequence_score(0, 5, history.len(), pair, |_, _| true);
        assert!((score - 1.0).abs() < 1e-6, "{score}");
        // Against keyframe 8, forwards the steps take the best of 6..=8 for 0.4 and of 5..=7 for 0.3;
        // backwards of 8..=9 and of 9 alone (10 and 11 are past the history).
        let single = |a: f32, b: f32| d.score(distance(&unit(a), &unit(b)));
        let expected_forwards = (single(0.5, 0.8) + single(0.4, 0.6) + single(0.3, 0.5)) / 3.0;
        let expected_backwards = (single(0.5, 0.8) + single(0.4, 0.8) + single(0.3, 0.9)) / 3.0;
        let score = recent.sequence_score(0, 8, history.len(), pair, |_, _| true);
        assert!((score - expected_forwards.max(expected_backwards)).abs() < 1e-6, "{score}");
        // Excluded keyframes are not steps: with only keyframe 5 eligible, the step of 0.4 (centre 4 or
        // 6) still reaches 5, the step of 0.3 (centre 3 or 7) reaches nothing and is left out.
        let score = recent.sequence_score(0, 5, history.len(), pair, |_, p| p == 5);
        assert!((score - (1.0 + single(0.4, 0.5)) / 2.0).abs() < 1e-6, "{score}");
        // Length 1 keeps nothing.
        let mut off = RecentQueries::new(1);
        off.push(&unit(0.0), Stamp::from_nanos(0), 0);
        assert!(off.queries.is_empty());
    }

    #[test]
    fn later_queries_join_the_window_where_they_are_known_and_the_window_keeps_its_length() {
        let d = Descriptor::new(DescriptorMode::L2, 2);
        let history: Vec<Vec<f32>> = (0..10).map(|i| unit(i as f32 * 0.1)).collect();
        let mut recent = RecentQueries::new(3);
        recent.push(&unit(0.4), Stamp::from_nanos(0), 0);
        // Query 0.5 with the one before it (0.4) and one after it (0.6): a walk along the history.
        let (current, later) = (unit(0.5), unit(0.6));
        let pair = |offset: isize, p: usize| {
            let q = match offset {
                0 => &current,
                -1 => &recent.queries[0],
                1 => &later,
                _ => panic!("offset {offset} is outside a window of 3"),
            };
            d.score(distance(q, &history[p]))
        };
        assert_eq!(recent.behind(1), 1);
        let score = recent.sequence_score(1, 5, history.len(), pair, |_, _| true);
        assert!((score - 1.0).abs() < 1e-6, "{score}");
        // Against keyframe 7 the later query's step takes the best of 7..=9 forwards (0.6 vs 0.7) and
        // of 5..=7 backwards (0.6 exactly), the earlier one's the best of 5..=7 forwards (0.4 vs 0.5)
        // and of 7..=9 backwards.
        let single = |a: f32, b: f32| d.score(distance(&unit(a), &unit(b)));
        let forwards = (single(0.5, 0.7) + single(0.6, 0.7) + single(0.4, 0.5)) / 3.0;
        let backwards = (single(0.5, 0.7) + 1.0 + single(0.4, 0.7)) / 3.0;
        let score = recent.sequence_score(1, 7, history.len(), pair, |_, _| true);
        assert!((score - forwards.max(backwards)).abs() < 1e-6, "{score}");
        // Two later queries fill the window of 3: no kept query is used.
        assert_eq!(recent.behind(2), 0);
    }

    #[test]
    fn a_known_walk_fills_the_windows_of_its_first_queries() {
        // Length 10 over 30 queries: the first ten share the window 0..10, then each window ends at
        // its query.
        assert_eq!(queries_ahead(10, 0, 30), 9);
        assert_eq!(queries_ahead(10, 4, 30), 5);
        assert_eq!(queries_ahead(10, 8, 30), 1);
        assert_eq!(queries_ahead(10, 9, 30), 0);
        assert_eq!(queries_ahead(10, 29, 30), 0);
        // Fewer queries than the length: all of them.
        assert_eq!(queries_ahead(10, 0, 4), 3);
        assert_eq!(queries_ahead(10, 3, 4), 0);
        // Single images: none.
        assert_eq!(queries_ahead(1, 0, 30), 0);
        assert_eq!(queries_ahead(0, 0, 30), 0);
        for index in 0..30 {
            let ahead = queries_ahead(10, index, 30);
            let behind = (10 - 1 - ahead).min(index);
            assert_eq!(behind + 1 + ahead, 10, "query {index}");
        }
    }
}
