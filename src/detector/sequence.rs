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
//! - **When it is on.** `detector.sequence.length` 0, the default, means: [`ROUTE_LENGTH`] where
//!   queries are matched against a database made beforehand (`eval --database --queries`: a route
//!   travelled again, the queries a walk along it), single images where keyframes come one by one
//!   and a revisit may be a single keyframe (a tracker's stream, a replay). The diagonal takes one
//!   database keyframe per query, so the walk is only assumed where both are sampled alike and the
//!   queries look like one ([`why_not_a_walk`]): as many queries as keyframes, or single-image
//!   matches that move along the database at one keyframe per query ([`walk_speed`]: a walk along
//!   part of the route), either within [`MAX_SAMPLING_RATIO`]; and for [`WALK_EVIDENCE`] of the
//!   queries the next is nearer than the one half the set away.

use std::collections::VecDeque;

use crate::descriptor::distance;

/// Keyframes nearest to the current query that the sequence score re-ranks.
pub const CANDIDATES: usize = 10;

/// The sequence length of a route travelled again (module doc: when it is on); SeqSLAM's usual
/// length.
pub const ROUTE_LENGTH: usize = 10;

/// The largest ratio, either way, of the database's count to the queries', or of a walk's speed
/// (database keyframes per query, [`walk_speed`]) to 1, at which the queries are taken as a walk
/// sampled like the database.
pub const MAX_SAMPLING_RATIO: f64 = 1.5;

/// The share of queries, at least, whose successor must be nearer to them than the query half the
/// set away for the queries to be taken as a walk: about all of them in a walk, about half in a set
/// in no order.
pub const WALK_EVIDENCE: f64 = 0.75;

/// How fast a walk of queries moves along the database, in database keyframes per query, from the
/// database position of each query's single-image nearest keyframe (`nearest`, in query order): the
/// Theil-Sen slope of position against query (the median of the slopes between every two queries
/// at most [`ROUTE_LENGTH`] apart), either way. Robust to the wrong single-image matches, up to
/// about a quarter of them, that sequence matching is there to correct. About 1 where both are
/// sampled alike, whatever part of the route the queries cover; `None` for fewer than 2 queries.
pub fn walk_speed(nearest: &[usize]) -> Option<f64> {
    let mut slopes: Vec<f64> = (0..nearest.len())
        .flat_map(|i| {
            (i + 1..nearest.len().min(i + ROUTE_LENGTH + 1))
                .map(move |j| (nearest[j] as f64 - nearest[i] as f64) / (j - i) as f64)
        })
        .collect();
    if slopes.is_empty() {
        return None;
    }
    slopes.sort_by(f64::total_cmp);
    Some(slopes[slopes.len() / 2].abs())
}

/// Why `queries` (descriptors in their order), against a database of `database` keyframes in which
/// their single-image nearest are at the positions `nearest`, are not a walk sampled like the
/// database, or `None` when they are (module doc: when it is on). Sampled alike means: as many
/// queries as keyframes, or a speed of one keyframe per query (a walk along part of the route),
/// each within [`MAX_SAMPLING_RATIO`]. The count alone serves where the single-image matches are
/// too often wrong for the speed to be measured.
pub fn why_not_a_walk(database: usize, nearest: &[usize], queries: &[Vec<f32>]) -> Option<String> {
    let n = queries.len();
    let alike = |ratio: f64| (1.0 / MAX_SAMPLING_RATIO..=MAX_SAMPLING_RATIO).contains(&ratio);
    let counts_alike = n > 0 && alike(database as f64 / n as f64);
    let speed = walk_speed(nearest);
    if !counts_alike && !speed.is_some_and(alike) {
        let speed =
            speed.map_or(String::new(), |s| format!(" (their single-image matches move {s:.2} images per query)"));
        return Some(format!("{database} database images and {n} queries are not sampled alike{speed}"));
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
    /// `eligible(p)` whether the recency rules let `p` match.
    pub fn sequence_score(
        &self,
        ahead: usize,
        position: usize,
        len: usize,
        pair_score: impl Fn(isize, usize) -> f32,
        eligible: impl Fn(usize) -> bool,
    ) -> f32 {
        let first = pair_score(0, position);
        let step_score = |offset: isize, centre: isize| -> Option<f32> {
            (centre - 1..=centre + 1)
                .filter(|&p| p >= 0 && (p as usize) < len && eligible(p as usize))
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
            recent.push(&unit(angle));
        }
        assert_eq!(recent.queries.len(), 2, "length 3 keeps the two before the current");
        let current = unit(0.5);
        let queries: Vec<&[f32]> = std::iter::once(&current[..]).chain(recent.newest_first()).collect();
        let pair = |offset: isize, p: usize| d.score(distance(queries[offset.unsigned_abs()], &history[p]));
        // The current query equals keyframe 5; the earlier ones were 0.3 (k=2) and 0.4 (k=1): forwards
        // (p-1 = 4, p-2 = 3) they match exactly, so the sequence score is 1.
        let score = recent.sequence_score(0, 5, history.len(), pair, |_| true);
        assert!((score - 1.0).abs() < 1e-6, "{score}");
        // Against keyframe 8, forwards the steps take the best of 6..=8 for 0.4 and of 5..=7 for 0.3;
        // backwards of 8..=9 and of 9 alone (10 and 11 are past the history).
        let single = |a: f32, b: f32| d.score(distance(&unit(a), &unit(b)));
        let expected_forwards = (single(0.5, 0.8) + single(0.4, 0.6) + single(0.3, 0.5)) / 3.0;
        let expected_backwards = (single(0.5, 0.8) + single(0.4, 0.8) + single(0.3, 0.9)) / 3.0;
        let score = recent.sequence_score(0, 8, history.len(), pair, |_| true);
        assert!((score - expected_forwards.max(expected_backwards)).abs() < 1e-6, "{score}");
        // Excluded keyframes are not steps: with only keyframe 5 eligible, the step of 0.4 (centre 4 or
        // 6) still reaches 5, the step of 0.3 (centre 3 or 7) reaches nothing and is left out.
        let score = recent.sequence_score(0, 5, history.len(), pair, |p| p == 5);
        assert!((score - (1.0 + single(0.4, 0.5)) / 2.0).abs() < 1e-6, "{score}");
        // Length 1 keeps nothing.
        let mut off = RecentQueries::new(1);
        off.push(&unit(0.0));
        assert!(off.queries.is_empty());
    }

    #[test]
    fn later_queries_join_the_window_where_they_are_known_and_the_window_keeps_its_length() {
        let d = Descriptor::new(DescriptorMode::L2, 2);
        let history: Vec<Vec<f32>> = (0..10).map(|i| unit(i as f32 * 0.1)).collect();
        let mut recent = RecentQueries::new(3);
        recent.push(&unit(0.4));
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
        let score = recent.sequence_score(1, 5, history.len(), pair, |_| true);
        assert!((score - 1.0).abs() < 1e-6, "{score}");
        // Against keyframe 7 the later query's step takes the best of 7..=9 forwards (0.6 vs 0.7) and
        // of 5..=7 backwards (0.6 exactly), the earlier one's the best of 5..=7 forwards (0.4 vs 0.5)
        // and of 7..=9 backwards.
        let single = |a: f32, b: f32| d.score(distance(&unit(a), &unit(b)));
        let forwards = (single(0.5, 0.7) + single(0.6, 0.7) + single(0.4, 0.5)) / 3.0;
        let backwards = (single(0.5, 0.7) + 1.0 + single(0.4, 0.7)) / 3.0;
        let score = recent.sequence_score(1, 7, history.len(), pair, |_| true);
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

    #[test]
    fn a_walk_is_assumed_only_where_both_sets_are_sampled_alike_and_the_queries_look_like_one() {
        // A walk: each query a small step from the last along a turning route.
        let walk: Vec<Vec<f32>> = (0..40).map(|i| unit(i as f32 * 0.05)).collect();
        let along =
            |speed: f64, from: usize| -> Vec<usize> { (0..40).map(|i| from + (i as f64 * speed) as usize).collect() };
        assert_eq!(walk_speed(&along(1.0, 0)), Some(1.0));
        assert_eq!(why_not_a_walk(40, &along(1.0, 0), &walk), None);
        assert_eq!(why_not_a_walk(1000, &along(1.0, 500), &walk), None, "a walk along a part of a longer route");
        let backwards: Vec<usize> = along(1.0, 0).into_iter().rev().collect();
        assert_eq!(why_not_a_walk(1000, &backwards, &walk), None, "the route the other way");
        assert_eq!(why_not_a_walk(1000, &along(1.5, 0), &walk), None, "within 1.5x either way");
        assert_eq!(why_not_a_walk(1000, &along(0.7, 0), &walk), None);
        let why = why_not_a_walk(80, &along(2.0, 0), &walk).expect("every second database keyframe queried");
        assert!(why.contains("not sampled alike (their single-image matches move 2.00 images per query)"), "{why}");
        assert!(why_not_a_walk(1000, &along(1.6, 0), &walk).is_some());
        assert!(why_not_a_walk(20, &along(0.5, 0), &walk).is_some(), "two queries per database keyframe");
        // As many queries as keyframes: a walk, whatever the single-image matches (too often wrong
        // for a speed) say; within 1.5x either way.
        let wrong: Vec<usize> = (0..40).map(|i| (i * 7) % 40).collect();
        assert_eq!(why_not_a_walk(40, &wrong, &walk), None);
        assert_eq!(why_not_a_walk(60, &wrong, &walk), None);
        assert_eq!(why_not_a_walk(27, &wrong, &walk), None);
        assert!(why_not_a_walk(61, &wrong, &walk).is_some());
        assert!(why_not_a_walk(26, &wrong, &walk).is_some());
        assert!(why_not_a_walk(0, &[], &walk).is_some());
        // Wrong single-image matches, one query in four, do not move the median.
        let mut noisy = along(1.0, 0);
        for (i, n) in noisy.iter_mut().enumerate().filter(|(i, _)| i % 4 == 1) {
            *n = (i * 37) % 400;
        }
        assert_eq!(walk_speed(&noisy), Some(1.0));
        // The same queries in no order (a fixed permutation).
        let shuffled: Vec<Vec<f32>> = (0..40).map(|i| walk[(i * 17) % 40].clone()).collect();
        let why = why_not_a_walk(40, &along(1.0, 0), &shuffled).expect("photos in no order");
        assert!(why.contains("do not look like a walk"), "{why}");
        assert_eq!(walk_speed(&[3]), None);
    }
}
