//! Aligning a walk of queries with a route stored beforehand: where every query is known before any
//! is matched (`eval --database --queries`), each query's place is read from the whole walk, the
//! queries after it as well as those before, not from a window of it (a hidden Markov model, after
//! Hansen and Browning, "Visual place recognition using HMM sequence matching", IROS 2014).
//!
//! Interpretation, written down once:
//! - **States.** A database keyframe and a direction along the database: forwards, or backwards (a
//!   corridor walked the other way).
//! - **Moves.** From one query to the next the walk holds or moves `1..=K` keyframes in its
//!   direction, all equally likely, `K` twice the walk's speed measured from its single-image matches
//!   ([`walk_speed`]) and at least 2: queries and keyframes need not be sampled
//!   alike. With probability [`JUMP`] it goes to any state instead (it left the route and came back
//!   elsewhere, or turned round).
//! - **Observations.** A query's single-image scores against every keyframe, each less that
//!   keyframe's baseline ([`keyframe_baselines`]), standardised over the database (minus their mean,
//!   over their standard deviation), weigh keyframe `p` by `exp(SHARPNESS * z_p)`: the scale of the
//!   scores differs from camera to camera and from query to query, their order and spread within one
//!   query is what tells. The baseline is how well a keyframe scores against every query, whatever
//!   the place: at low resolution and across light some keyframes (a dark or plain view) score high
//!   against all of them, and a walk that holds on such a hub collects its scores all along. The
//!   queries' nearest keyframes that measure the walk's speed are taken with the baselines removed too.
//! - **Answer.** Each query's keyframes ranked by their posterior probability (forward-backward, both
//!   directions summed). A match's score must say both that the place is certain and that the
//!   images agree, so it is the smaller of two values in `[0, 1]`: the probability that the query is
//!   within one largest move (`K` keyframes, the walk's own resolution) of the keyframe, and the
//!   query's own single-image score against it. The probability alone is relative to the stored
//!   route: a walk somewhere never stored is still sure of its best copy, and its low scores are what
//!   keep it under `detector.min_score` (its own, not its neighbours': a walk may leave the route); a
//!   route that repeats itself (two identical corridors) leaves the probability split between its
//!   copies, under any usual threshold.

use crate::descriptor::distance;

/// The weight of one standard deviation of a query's scores in its observation (`exp(SHARPNESS *
/// z)`): soft, so that one query's wrong best keyframe is outvoted by its neighbours in the walk.
pub const SHARPNESS: f32 = 0.5;

/// The probability, per query, that the walk goes anywhere rather than along the route.
pub const JUMP: f32 = 1e-3;

/// The largest walk, in queries times keyframes, that is aligned: four `f32` per pair are kept, the
/// caller's scores included (256 MiB at the bound).
pub const MAX_CELLS: usize = 1 << 24;

/// The share of queries, at least, whose successor must be nearer to them than half of the
/// queries spread over the set ([`SPREAD_COMPARISONS`]) for the queries to be taken as a walk: about
/// all of them in a walk, under half in a set in no order.
pub const WALK_EVIDENCE: f64 = 0.75;

/// How many queries, spread evenly over the set, each query's successor is compared with. More than
/// one, because a walk that covers its route twice or more passes its own places again: the query
/// half the set away may be the same place.
pub const SPREAD_COMPARISONS: usize = 8;

/// The fewest queries taken for a walk.
pub const MIN_WALK: usize = 4;

/// The farthest apart, in queries, that two queries' single-image matches are compared to measure
/// the walk's speed.
pub const SPEED_SPAN: usize = 10;

/// Why `queries` (descriptors in their order) do not look like a walk, or `None` when they do: for
/// at least [`WALK_EVIDENCE`] of them the next query is nearer than at least half of the queries
/// [`SPREAD_COMPARISONS`] evenly spread offsets away (each offset once, never the query itself or
/// its successor). Fewer than [`MIN_WALK`] queries are not taken for one: too few to tell, and too
/// few for an alignment to be sure of any place (a single query would score at most the share of the
/// keyframes near its best).
pub fn why_not_a_walk(queries: &[Vec<f32>]) -> Option<String> {
    let n = queries.len();
    if n < MIN_WALK {
        return Some(format!("{n} queries are too few to tell whether they are a walk"));
    }
    let mut offsets: Vec<usize> = (1..=SPREAD_COMPARISONS).map(|j| j * n / (SPREAD_COMPARISONS + 1)).collect();
    offsets.dedup();
    offsets.retain(|&offset| offset > 1);
    let nearer = (0..n - 1)
        .filter(|&t| {
            let next = distance(&queries[t], &queries[t + 1]);
            let farther =
                offsets.iter().filter(|&&offset| next < distance(&queries[t], &queries[(t + offset) % n])).count();
            2 * farther >= offsets.len()
        })
        .count();
    let share = nearer as f64 / (n - 1) as f64;
    (share < WALK_EVIDENCE).then(|| {
        format!("the queries do not look like a walk (for {:.0}% of them the next one is nearer than half of the queries spread over the set)", 100.0 * share)
    })
}

/// How fast a walk of queries moves along the database, in database keyframes per query, from the
/// database position of each query's single-image nearest keyframe (`nearest`, in query order): the
/// Theil-Sen slope of position against query (the median of the slopes between every two queries
/// at most [`SPEED_SPAN`] apart, or over wider spans for a walk slower than the keyframes), either
/// way. Robust to the wrong single-image matches, up to about a
/// quarter of them, that the alignment is there to correct. About 1 where both are sampled alike,
/// whatever part of the route the queries cover; `None` for fewer than 2 queries.
fn walk_speed(nearest: &[usize]) -> Option<f64> {
    let mut span = SPEED_SPAN;
    loop {
        // Each query is compared with SPEED_SPAN others spread over the span, so a wide span costs
        // no more than the first.
        let offsets: Vec<usize> = (1..=SPEED_SPAN).map(|k| k * span / SPEED_SPAN).collect();
        let mut slopes: Vec<f64> = (0..nearest.len())
            .flat_map(|i| {
                offsets
                    .iter()
                    .map(move |&offset| i + offset)
                    .take_while(|&j| j < nearest.len())
                    .map(move |j| (nearest[j] as f64 - nearest[i] as f64) / (j - i) as f64)
            })
            .collect();
        if slopes.is_empty() {
            return None;
        }
        slopes.sort_by(f64::total_cmp);
        let speed = slopes[slopes.len() / 2].abs();
        // A walk slower than the database's sampling (every camera frame against keyframes) moves
        // less than a keyframe between most queries this close, and the median slope is 0: wider
        // spans, until they cover a few keyframes or the whole walk.
        if speed * span as f64 >= SLOW_SPAN_KEYFRAMES || span + 1 >= nearest.len() {
            return Some(speed);
        }
        span *= 2;
    }
}

/// How many keyframes, at least, the spans of queries that measure a walk's speed cover
/// ([`walk_speed`]).
const SLOW_SPAN_KEYFRAMES: f64 = 3.0;

/// The largest move between two queries, in keyframes, for a walk of `speed` keyframes per query.
fn largest_move(speed: f64) -> usize {
    ((2.0 * speed).ceil() as usize).max(2)
}

/// Each keyframe's baseline in single-image `scores` (one row per query, one column per keyframe;
/// module doc: observations), `seen_by` the most queries that can truly see one keyframe. Two
/// estimates, each biased its own way, and the one both support: the smaller of the two where they
/// agree in sign, else none.
/// - Over every query: counts the queries that see the keyframe, so a short walk along part of the
///   route makes each keyframe it passes look like a hub.
/// - Over all but each keyframe's `seen_by` highest scores: leaves those out, but then speaks only
///   for the queries farthest from the keyframe (in a walk that leaves the route, the ones from
///   elsewhere).
fn keyframe_baselines(scores: &[Vec<f32>], seen_by: usize) -> Vec<f32> {
    let every = shrunk_means(scores, 0);
    let far = shrunk_means(scores, seen_by);
    every
        .iter()
        .zip(&far)
        .map(|(&a, &b)| {
            if a * b > 0.0 {
                if a.abs() < b.abs() {
                    a
                } else {
                    b
                }
            } else {
                0.0
            }
        })
        .collect()
}

/// Each keyframe's mean score over the queries but its `dropped` highest, less the mean of all
/// keyframes' such means, shrunk by the share of the spread of those means that is the keyframes' own
/// rather than the noise of averaging so few scores (empirical Bayes, `tau² / (tau² + sigma² / n)`:
/// `tau²` the spread of the means less that noise, `sigma²` the mean variance within a keyframe, `n`
/// the scores averaged). Few scores tell little about a keyframe, and the baselines are then near 0;
/// with many, a hub's shows. All 0 where fewer than two scores a keyframe are left.
fn shrunk_means(scores: &[Vec<f32>], dropped: usize) -> Vec<f32> {
    let keyframes = scores.first().map_or(0, Vec::len);
    let kept = scores.len().saturating_sub(dropped);
    if kept < 2 || keyframes < 2 {
        return vec![0.0; keyframes];
    }
    let mut column = Vec::with_capacity(scores.len());
    let (mut means, mut variance) = (Vec::with_capacity(keyframes), 0.0);
    for p in 0..keyframes {
        column.clear();
        column.extend(scores.iter().map(|row| row[p] as f64));
        if dropped > 0 {
            // The `kept` lowest first, in no order: no full sort is needed for a mean.
            column.select_nth_unstable_by(kept - 1, f64::total_cmp);
        }
        let lowest = &column[..kept];
        let mean = lowest.iter().sum::<f64>() / kept as f64;
        variance += lowest.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / (kept - 1) as f64;
        means.push(mean);
    }
    let noise = variance / keyframes as f64 / kept as f64;
    let overall = means.iter().sum::<f64>() / keyframes as f64;
    let spread = means.iter().map(|m| (m - overall).powi(2)).sum::<f64>() / (keyframes - 1) as f64;
    let own = (spread - noise).max(0.0);
    let shrink = if own + noise > 0.0 { own / (own + noise) } else { 0.0 };
    means.iter().map(|m| (shrink * (m - overall)) as f32).collect()
}

/// The whole alignment of a walk from its single-image `scores` (as [`align`] takes them): the
/// keyframes' baselines, with the queries that can see one keyframe counted from the speed of the
/// plain single-image matches; the walk's speed from the matches with the baselines removed; then
/// [`align`]. Returns each query's matches and that speed.
pub fn align_walk(scores: &[Vec<f32>], depth: usize) -> (Vec<Vec<(usize, f32)>>, f64) {
    let keyframes = scores.first().map_or(0, Vec::len);
    let plain = walk_speed(&nearest_keyframes(scores, &vec![0.0; keyframes])).unwrap_or(1.0);
    let baselines = keyframe_baselines(scores, 2 * largest_move(plain) + 1);
    let speed = walk_speed(&nearest_keyframes(scores, &baselines)).unwrap_or(1.0);
    (align(scores, &baselines, speed, depth), speed)
}

/// Each query's nearest keyframe by its single-image `scores` less the keyframes' `baselines` (the
/// first of equal ones), for [`walk_speed`].
fn nearest_keyframes(scores: &[Vec<f32>], baselines: &[f32]) -> Vec<usize> {
    scores
        .iter()
        .map(|row| {
            let relative = |p: usize| row[p] - baselines[p];
            (0..row.len()).fold(0, |best, p| if relative(p) > relative(best) { p } else { best })
        })
        .collect()
}

/// Aligns the walk whose single-image `scores` (one row per query, in walk order, one column per
/// keyframe in database order) are given, with the keyframes' `baselines` ([`keyframe_baselines`]),
/// moving `speed` keyframes per query. Returns for each query up to `depth` keyframe positions, most
/// probable first (ties: the earlier position), each with its match's score (module doc: answer).
fn align(scores: &[Vec<f32>], baselines: &[f32], speed: f64, depth: usize) -> Vec<Vec<(usize, f32)>> {
    most_probable(scores, baselines, speed, depth)
        .into_iter()
        .zip(scores)
        .map(|(places, row)| places.into_iter().map(|(p, probability)| (p, probability.min(row[p]))).collect())
        .collect()
}

/// Up to `depth` keyframe positions of each query, most probable first, each with the probability
/// that the query is within one largest move ([`largest_move`]) of it.
fn most_probable(scores: &[Vec<f32>], baselines: &[f32], speed: f64, depth: usize) -> Vec<Vec<(usize, f32)>> {
    let queries = scores.len();
    let keyframes = scores.first().map_or(0, Vec::len);
    if keyframes == 0 {
        return vec![Vec::new(); queries];
    }
    let mut scores = scores.to_vec();
    for row in &mut scores {
        row.iter_mut().zip(baselines).for_each(|(s, b)| *s -= b);
        observe(row);
    }
    let moves = Moves { keyframes, largest: largest_move(speed) };
    let states = 2 * keyframes;
    // Forward probabilities of every query, each normalised to sum 1.
    let mut forward = vec![0f32; queries * states];
    for t in 0..queries {
        let (before, rest) = forward.split_at_mut(t * states);
        let current = &mut rest[..states];
        if t == 0 {
            current.fill(1.0);
        } else {
            moves.ahead(&before[(t - 1) * states..], current);
        }
        for (state, value) in current.iter_mut().enumerate() {
            *value *= scores[t][state % keyframes];
        }
        normalise(current);
    }
    let mut answers = vec![Vec::new(); queries];
    let mut backward = vec![1f32; states];
    let mut weighted = vec![0f32; states];
    for t in (0..queries).rev() {
        if t + 1 < queries {
            for (state, value) in weighted.iter_mut().enumerate() {
                *value = scores[t + 1][state % keyframes] * backward[state];
            }
            moves.behind(&weighted, &mut backward);
            normalise(&mut backward);
        }
        let at = &forward[t * states..(t + 1) * states];
        let mut posterior: Vec<f32> =
            (0..keyframes).map(|p| at[p] * backward[p] + at[keyframes + p] * backward[keyframes + p]).collect();
        normalise(&mut posterior);
        answers[t] = ranked(&posterior, depth, moves.largest);
    }
    answers
}

/// Turns one query's scores into its observation weights (module doc).
fn observe(row: &mut [f32]) {
    let n = row.len() as f64;
    let mean = row.iter().map(|&s| s as f64).sum::<f64>() / n;
    let spread = (row.iter().map(|&s| (s as f64 - mean).powi(2)).sum::<f64>() / n).sqrt();
    let spread = if spread > 0.0 { spread } else { 1.0 };
    let best = row.iter().copied().fold(f32::NEG_INFINITY, f32::max) as f64;
    for s in row.iter_mut() {
        // Relative to the best, so the largest weight is 1 and none overflows.
        *s = (SHARPNESS as f64 * (*s as f64 - best) / spread).exp() as f32;
    }
}

fn normalise(values: &mut [f32]) {
    let sum: f64 = values.iter().map(|&v| v as f64).sum();
    if sum > 0.0 {
        values.iter_mut().for_each(|v| *v = (*v as f64 / sum) as f32);
    }
}

/// Up to `depth` positions by `posterior`, each with the probability within `reach` keyframes of it.
fn ranked(posterior: &[f32], depth: usize, reach: usize) -> Vec<(usize, f32)> {
    let mut order: Vec<usize> = (0..posterior.len()).collect();
    order.sort_by(|&a, &b| posterior[b].total_cmp(&posterior[a]).then(a.cmp(&b)));
    order.truncate(depth);
    let near = |p: usize| {
        posterior[p.saturating_sub(reach)..(p + reach + 1).min(posterior.len())].iter().sum::<f32>().min(1.0)
    };
    order.into_iter().map(|p| (p, near(p))).collect()
}

/// The walk's moves over states `[forwards at 0..n, backwards at 0..n]` (module doc).
struct Moves {
    keyframes: usize,
    largest: usize,
}

impl Moves {
    /// `next` from `previous` (summing to 1): the probability of each state one query later.
    fn ahead(&self, previous: &[f32], next: &mut [f32]) {
        let n = self.keyframes;
        let (forwards, backwards) = previous.split_at(n);
        let (next_forwards, next_backwards) = next.split_at_mut(n);
        // Forwards, state p is reached from p - largest ..= p; backwards from p ..= p + largest.
        self.window_sums(forwards, next_forwards, |p| (p.saturating_sub(self.largest), p + 1));
        self.window_sums(backwards, next_backwards, |p| (p, (p + self.largest + 1).min(n)));
        self.mix_in_jumps(previous.iter().map(|&v| v as f64).sum(), next);
    }

    /// `before` from `after` (the next query's observation times its backward probabilities): the
    /// backward probability of each state one query earlier.
    fn behind(&self, after: &[f32], before: &mut [f32]) {
        let n = self.keyframes;
        let (forwards, backwards) = after.split_at(n);
        let (before_forwards, before_backwards) = before.split_at_mut(n);
        // Forwards, state p moves to p ..= p + largest; backwards to p - largest ..= p.
        self.window_sums(forwards, before_forwards, |p| (p, (p + self.largest + 1).min(n)));
        self.window_sums(backwards, before_backwards, |p| (p.saturating_sub(self.largest), p + 1));
        self.mix_in_jumps(after.iter().map(|&v| v as f64).sum(), before);
    }

    /// `to[p]` = the mean move probability times the sum of `from` over the window `range(p)`.
    fn window_sums(&self, from: &[f32], to: &mut [f32], range: impl Fn(usize) -> (usize, usize)) {
        let mut prefix = Vec::with_capacity(from.len() + 1);
        prefix.push(0f64);
        for &v in from {
            prefix.push(prefix[prefix.len() - 1] + v as f64);
        }
        let each = 1.0 / (self.largest + 1) as f64;
        for (p, value) in to.iter_mut().enumerate() {
            let (start, end) = range(p);
            *value = (each * (prefix[end] - prefix[start])) as f32;
        }
    }

    /// Blends the moves along the route with a jump to any state, `total` the mass it jumps from.
    fn mix_in_jumps(&self, total: f64, states: &mut [f32]) {
        let anywhere = (JUMP as f64 * total / states.len() as f64) as f32;
        states.iter_mut().for_each(|v| *v = (1.0 - JUMP) * *v + anywhere);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// [`align`] with the baselines the scores give for a walk of `speed`.
    fn aligned(scores: &[Vec<f32>], speed: f64, depth: usize) -> Vec<Vec<(usize, f32)>> {
        align(scores, &keyframe_baselines(scores, 2 * largest_move(speed) + 1), speed, depth)
    }

    fn probable(scores: &[Vec<f32>], speed: f64, depth: usize) -> Vec<Vec<(usize, f32)>> {
        most_probable(scores, &keyframe_baselines(scores, 2 * largest_move(speed) + 1), speed, depth)
    }

    /// Scores of a walk over `route` (the place seen at each keyframe) for queries at the places
    /// `walk`: 0.9 where the places agree, 0.5 elsewhere, with the places in `misleading` (query
    /// index, keyframe) scored 0.95 instead: single images that point elsewhere.
    fn scores(route: &[usize], walk: &[usize], misleading: &[(usize, usize)]) -> Vec<Vec<f32>> {
        walk.iter()
            .enumerate()
            .map(|(t, place)| {
                (0..route.len())
                    .map(|p| match () {
                        _ if misleading.contains(&(t, p)) => 0.95,
                        _ if route[p] == *place => 0.9,
                        _ => 0.5,
                    })
                    .collect()
            })
            .collect()
    }

    fn best(answers: &[Vec<(usize, f32)>]) -> Vec<usize> {
        answers.iter().map(|a| a[0].0).collect()
    }

    #[test]
    fn the_walk_outvotes_single_images_that_point_elsewhere() {
        let route: Vec<usize> = (0..40).collect();
        let walk: Vec<usize> = (10..30).collect();
        let misleading = [(3, 35), (4, 2), (11, 0), (12, 39)];
        let scores = scores(&route, &walk, &misleading);
        let single: Vec<usize> = scores
            .iter()
            .map(|row| (0..row.len()).max_by(|&a, &b| row[a].total_cmp(&row[b]).then(b.cmp(&a))).unwrap())
            .collect();
        assert_eq!(single.iter().zip(&walk).filter(|(s, w)| s != w).count(), 4);
        let probable = probable(&scores, 1.0, 3);
        assert_eq!(best(&probable), walk);
        for answer in &probable {
            assert_eq!(answer.len(), 3);
            assert!(answer[0].1 > 0.9 && answer[0].1 <= 1.0, "{answer:?}");
            assert!(answer[1].1 <= answer[0].1 + 1e-6);
        }
        // Sure of every place: the score is the query's own, 0.9 here.
        let answers = aligned(&scores, 1.0, 3);
        assert_eq!(best(&answers), walk);
        assert!(answers.iter().all(|a| (a[0].1 - 0.9).abs() < 1e-5), "{answers:?}");
    }

    #[test]
    fn a_keyframe_that_scores_high_against_every_query_does_not_hold_the_walk() {
        // Keyframe 5 scores 0.93 against every query, above the true places' 0.9: a hub.
        let route: Vec<usize> = (0..40).collect();
        let walk: Vec<usize> = (10..30).collect();
        let mut with_hub = scores(&route, &walk, &[]);
        with_hub.iter_mut().for_each(|row| row[5] = 0.93);
        let none = vec![0.0; route.len()];
        assert!(nearest_keyframes(&with_hub, &none).iter().all(|&p| p == 5));
        let held = align(&with_hub, &none, 1.0, 1);
        assert!(best(&held).iter().filter(|&&p| p == 5).count() >= 10, "the walk holds on the hub: {held:?}");
        let baselines = keyframe_baselines(&with_hub, 5);
        assert!(baselines[5] > 0.3, "{baselines:?}");
        assert!(baselines.iter().enumerate().all(|(p, b)| p == 5 || b.abs() < 0.05), "{baselines:?}");
        assert_eq!(nearest_keyframes(&with_hub, &baselines), walk);
        let (answers, speed) = align_walk(&with_hub, 1);
        assert_eq!((best(&answers), speed), (walk, 1.0));
        // Nothing to tell keyframes apart by: no baselines.
        assert_eq!(keyframe_baselines(&vec![vec![0.7; 12]; 5], 0), vec![0.0; 12]);
        assert_eq!(keyframe_baselines(&[vec![0.2, 0.9, 0.4]], 0), vec![0.0; 3], "one query tells nothing");
    }

    #[test]
    fn a_short_walk_along_part_of_the_route_is_not_taken_for_hubs() {
        // Five queries along the first half of ten keyframes, each also alike to its neighbours:
        // over every query, the keyframes passed score higher than the others, as hubs would.
        let walk: Vec<usize> = (0..5).collect();
        let scores: Vec<Vec<f32>> = walk
            .iter()
            .map(|&place| {
                (0..10).map(|p: usize| [0.9, 0.8, 0.7].get(p.abs_diff(place)).copied().unwrap_or(0.5)).collect()
            })
            .collect();
        assert!(shrunk_means(&scores, 0)[2] > 0.1, "every query: {:?}", shrunk_means(&scores, 0));
        assert_eq!(keyframe_baselines(&scores, 5), vec![0.0; 10], "none is left once the five highest are dropped");
        let (answers, _) = align_walk(&scores, 1);
        assert_eq!(best(&answers), walk);
    }

    #[test]
    fn a_walk_never_stored_is_sure_of_its_best_copy_but_scored_by_its_images() {
        // A look-alike route: the walk's best keyframes form a clean diagonal, at 0.6.
        let route: Vec<usize> = (0..40).collect();
        let walk: Vec<usize> = (10..30).collect();
        let look_alike: Vec<Vec<f32>> =
            scores(&route, &walk, &[]).into_iter().map(|row| row.into_iter().map(|s| s.min(0.6)).collect()).collect();
        assert!(probable(&look_alike, 1.0, 1).iter().all(|a| a[0].1 > 0.9));
        let answers = aligned(&look_alike, 1.0, 1);
        assert!(answers.iter().all(|a| (a[0].1 - 0.6).abs() < 1e-5), "{answers:?}");
    }

    #[test]
    fn walks_backwards_and_faster_than_the_route_are_followed() {
        let route: Vec<usize> = (0..40).collect();
        let backwards: Vec<usize> = (5..35).rev().collect();
        assert_eq!(best(&aligned(&scores(&route, &backwards, &[(7, 1)]), 1.0, 1)), backwards);
        // Every third keyframe: the speed sets the largest move.
        let fast: Vec<usize> = (0..40).step_by(3).collect();
        assert_eq!(largest_move(3.0), 6);
        assert_eq!(largest_move(0.4), 2);
        assert_eq!(best(&aligned(&scores(&route, &fast, &[(5, 30)]), 3.0, 1)), fast);
    }

    #[test]
    fn a_route_that_repeats_itself_leaves_the_walk_unsure() {
        // Two identical halves: places 0..20, then the same places again.
        let route: Vec<usize> = (0..40).map(|p| p % 20).collect();
        let walk: Vec<usize> = (3..15).collect();
        let answers = aligned(&scores(&route, &walk, &[]), 1.0, 2);
        for (answer, place) in answers.iter().zip(&walk) {
            // Both copies are found, each with about half of the probability.
            let mut found = [answer[0].0, answer[1].0];
            found.sort();
            assert_eq!(found, [*place, place + 20]);
            assert!((0.3..0.7).contains(&answer[0].1), "{answer:?}");
        }
    }

    /// Unit vectors at `angle` in a plane.
    fn unit(angle: f32) -> Vec<f32> {
        vec![angle.cos(), angle.sin()]
    }

    #[test]
    fn a_walk_is_told_from_photos_in_no_order_and_its_speed_measured() {
        // A walk: each query a small step from the last along a turning route.
        let walk: Vec<Vec<f32>> = (0..40).map(|i| unit(i as f32 * 0.05)).collect();
        assert_eq!(why_not_a_walk(&walk), None);
        assert_eq!(why_not_a_walk(&walk[..4]), None);
        assert!(why_not_a_walk(&walk[..3]).unwrap().contains("too few"));
        // The same queries in no order (a fixed permutation).
        let shuffled: Vec<Vec<f32>> = (0..40).map(|i| walk[(i * 17) % 40].clone()).collect();
        let why = why_not_a_walk(&shuffled).expect("photos in no order");
        assert!(why.contains("do not look like a walk"), "{why}");
        // A walk that covers its route twice, or three times, passes its own places again: the
        // query half (a third) of the set away is the same place, yet it is a walk.
        for laps in [2, 3] {
            let again: Vec<Vec<f32>> = (0..40 * laps).map(|i| walk[i % 40].clone()).collect();
            assert_eq!(why_not_a_walk(&again), None, "{laps} laps");
            let shuffled: Vec<Vec<f32>> = (0..40 * laps).map(|i| again[(i * 17) % (40 * laps)].clone()).collect();
            assert!(why_not_a_walk(&shuffled).is_some(), "{laps} laps in no order");
        }
        let along =
            |speed: f64, from: usize| -> Vec<usize> { (0..40).map(|i| from + (i as f64 * speed) as usize).collect() };
        assert_eq!(walk_speed(&along(1.0, 500)), Some(1.0));
        assert_eq!(walk_speed(&along(2.0, 0)), Some(2.0));
        assert_eq!(walk_speed(&along(0.5, 0)), Some(0.5));
        // Slower than the keyframes (every camera frame against keyframes): not 0.
        let slow: Vec<usize> = (0..200).map(|i| i / 10).collect();
        let measured = walk_speed(&slow).unwrap();
        assert!((0.08..=0.12).contains(&measured), "{measured}");
        let backwards: Vec<usize> = along(1.0, 0).into_iter().rev().collect();
        assert_eq!(walk_speed(&backwards), Some(1.0), "the route the other way");
        // Wrong single-image matches, one query in four, do not move the median.
        let mut noisy = along(1.0, 0);
        for (i, n) in noisy.iter_mut().enumerate().filter(|(i, _)| i % 4 == 1) {
            *n = (i * 37) % 400;
        }
        assert_eq!(walk_speed(&noisy), Some(1.0));
        assert_eq!(walk_speed(&[3]), None);
    }

    #[test]
    fn degenerate_walks() {
        assert_eq!(aligned(&[], 1.0, 3), Vec::<Vec<(usize, f32)>>::new());
        assert_eq!(aligned(&[Vec::new(), Vec::new()], 1.0, 3), vec![Vec::new(); 2]);
        // One query: its own scores decide; equal scores everywhere leave the walk unsure of every
        // keyframe (the edges, with fewer neighbours, a little less likely).
        let one = aligned(&[vec![0.5, 0.9, 0.5]], 1.0, 3);
        assert_eq!(one[0][0].0, 1);
        let flat = aligned(&vec![vec![0.7; 12]; 3], 1.0, 12);
        assert!(flat.iter().all(|a| a.iter().all(|&(_, p)| (0.15..0.6).contains(&p))), "{flat:?}");
    }
}
