//! Precision-recall metrics of a loop detector from its top-1 candidate per query.
//!
//! Interpretation: the queries are the results handed in, each once (the caller reports every
//! query, with `best: None` where the detector found nothing). A query is a positive if its truth
//! has any match; truth for indexes that are not queries is ignored.
//! Sweeping a threshold over the top-1 scores (descending), a query whose top-1 score is at or
//! above the threshold is reported; a reported query is a true positive if its match is one of its
//! true matches, otherwise a false positive (a wrong match of a positive query or any match of a
//! negative one). Precision = TP / reported, recall = TP / positives. Queries whose truth is
//! unknown are left out entirely, as are those whose top-1 match is a frame whose truth is unknown
//! (no pose: whether the match is right cannot be told). Equal scores form one threshold.
//!
//! Average precision is the step-wise area `sum (R_k - R_{k-1}) P_k` over the thresholds (no
//! interpolation, as scikit-learn's `average_precision_score`). Recall at 100% precision is the
//! largest recall of a threshold with no false positive (0 if the best-scored report is wrong).
//! Recall@1 is the fraction of positives whose top-1 match is true, whatever its score.

use super::truth::LoopTruth;
use anyhow::{bail, Result};
use serde::Serialize;
use std::collections::BTreeSet;

/// The detector's best candidate for one query.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QueryResult {
    /// Replay index of the query (or query index in database/query mode).
    pub query: usize,
    /// Index of the best match and its score (higher = more similar); `None` if the detector
    /// had no candidate at all.
    pub best: Option<(usize, f32)>,
}

/// One point of the precision-recall curve.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PrPoint {
    pub threshold: f32,
    pub precision: f64,
    pub recall: f64,
}

/// The metrics; recall-based values are `None` when there are no positive queries.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Metrics {
    /// Queries evaluated (truth known).
    pub queries: usize,
    /// Queries with at least one true match.
    pub positives: usize,
    /// Queries that reported a match, whatever its score: right ones and wrong ones.
    pub true_reports: usize,
    pub false_reports: usize,
    /// Queries left out because their truth is unknown.
    pub unknown: usize,
    /// Queries left out because their top-1 match's truth is unknown (a frame without a pose).
    pub unknown_matches: usize,
    pub recall_at_1: Option<f64>,
    pub recall_at_100_precision: Option<f64>,
    pub average_precision: Option<f64>,
    /// From the highest threshold down.
    #[serde(skip)]
    pub curve: Vec<PrPoint>,
}

impl Metrics {
    /// Precision and recall of the reports at or above `threshold` (a detector's setting): the curve's
    /// point of the lowest threshold not below it, `None` when nothing scores that high.
    pub fn at_threshold(&self, threshold: f32) -> Option<&PrPoint> {
        self.curve.iter().take_while(|p| p.threshold >= threshold).last()
    }

    /// The score of the best-scored wrong report: a threshold above it keeps precision at 100%.
    /// `None` when every report is right.
    pub fn highest_false_score(&self) -> Option<f32> {
        self.curve.iter().find(|p| p.precision < 1.0).map(|p| p.threshold)
    }
}

/// Computes the metrics; fails if a query appears twice or a score is NaN.
pub fn evaluate(results: &[QueryResult], truth: &LoopTruth) -> Result<Metrics> {
    let mut seen = BTreeSet::new();
    let mut queries = 0;
    let mut positives = 0;
    let mut unknown = 0;
    let mut unknown_matches = 0;
    let mut top1_hits = 0;
    // (score, is true positive) of each reported query.
    let mut reported: Vec<(f32, bool)> = Vec::new();
    for result in results {
        if !seen.insert(result.query) {
            bail!("query {} has more than one result", result.query);
        }
        let Some(matches) = truth.matches(result.query) else {
            unknown += 1;
            continue;
        };
        if result.best.is_some_and(|(matched, _)| truth.is_unknown_match(matched)) {
            unknown_matches += 1;
            continue;
        }
        queries += 1;
        let positive = !matches.is_empty();
        positives += positive as usize;
        if let Some((matched, score)) = result.best {
            if score.is_nan() {
                bail!("query {}: score is NaN", result.query);
            }
            let correct = matches.contains(&matched);
            top1_hits += correct as usize;
            reported.push((score, correct));
        }
    }
    reported.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut curve = Vec::new();
    let (mut tp, mut fp) = (0usize, 0usize);
    let mut k = 0;
    while k < reported.len() {
        let threshold = reported[k].0;
        while k < reported.len() && reported[k].0 == threshold {
            if reported[k].1 {
                tp += 1;
            } else {
                fp += 1;
            }
            k += 1;
        }
        let recall = if positives > 0 { tp as f64 / positives as f64 } else { 0.0 };
        curve.push(PrPoint { threshold, precision: tp as f64 / (tp + fp) as f64, recall });
    }
    let (recall_at_1, recall_at_100_precision, average_precision) = if positives == 0 {
        (None, None, None)
    } else {
        let at_full_precision = curve.iter().take_while(|p| p.precision >= 1.0).map(|p| p.recall).fold(0.0, f64::max);
        let mut previous_recall = 0.0;
        let mut ap = 0.0;
        for point in &curve {
            ap += (point.recall - previous_recall) * point.precision;
            previous_recall = point.recall;
        }
        (Some(top1_hits as f64 / positives as f64), Some(at_full_precision), Some(ap))
    };
    let true_reports = reported.iter().filter(|(_, correct)| *correct).count();
    let false_reports = reported.len() - true_reports;
    Ok(Metrics {
        queries,
        positives,
        true_reports,
        false_reports,
        unknown,
        unknown_matches,
        recall_at_1,
        recall_at_100_precision,
        average_precision,
        curve,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn result(query: usize, best: Option<(usize, f32)>) -> QueryResult {
        QueryResult { query, best }
    }

    /// Truth: queries 10..=13 are positives (10 -> {1}, 11 -> {2, 3}, 12 -> {4}, 13 -> {5});
    /// 14 and 15 are negatives; 16 is unknown; frame 7 has no pose.
    fn truth() -> LoopTruth {
        let mut truth = LoopTruth::default();
        for (q, m) in [(10, 1), (11, 2), (11, 3), (12, 4), (13, 5)] {
            truth.insert(q, m);
        }
        truth.mark_unknown(16);
        truth.mark_unknown_match(7);
        truth
    }

    #[test]
    fn hand_computed_metrics() {
        let results = [
            result(10, Some((1, 0.9))),  // TP
            result(11, Some((3, 0.8))),  // TP
            result(14, Some((0, 0.7))),  // FP (negative query)
            result(12, Some((9, 0.6))),  // FP (wrong match)
            result(13, Some((5, 0.5))),  // TP
            result(15, None),            // negative, nothing reported
            result(16, Some((0, 0.95))), // unknown truth: ignored
            result(17, Some((7, 0.99))), // a match without a pose: ignored
        ];
        let m = evaluate(&results, &truth()).unwrap();
        assert_eq!((m.queries, m.positives, m.unknown, m.unknown_matches), (6, 4, 1, 1));
        // Curve: 0.9 -> P 1, R 1/4; 0.8 -> 1, 2/4; 0.7 -> 2/3, 2/4; 0.6 -> 2/4, 2/4; 0.5 -> 3/5, 3/4.
        let expected = [(0.9, 1.0, 0.25), (0.8, 1.0, 0.5), (0.7, 2.0 / 3.0, 0.5), (0.6, 0.5, 0.5), (0.5, 0.6, 0.75)];
        assert_eq!(m.curve.len(), expected.len());
        for (point, (t, p, r)) in m.curve.iter().zip(expected) {
            assert_eq!(point.threshold, t);
            assert!((point.precision - p).abs() < 1e-12 && (point.recall - r).abs() < 1e-12, "{point:?}");
        }
        // AP = 0.25*1 + 0.25*1 + 0 + 0 + 0.25*0.6 = 0.65.
        assert!((m.average_precision.unwrap() - 0.65).abs() < 1e-12);
        assert_eq!(m.recall_at_100_precision, Some(0.5));
        // Top-1 true for 10, 11, 13 of 4 positives.
        assert_eq!(m.recall_at_1, Some(0.75));
        // At a threshold of 0.75 the reports of 0.9 and 0.8 pass; 0.95 passes none.
        assert_eq!(m.at_threshold(0.75).map(|p| (p.precision, p.recall)), Some((1.0, 0.5)));
        assert_eq!(m.at_threshold(0.5).map(|p| p.threshold), Some(0.5));
        assert!(m.at_threshold(0.95).is_none());
        assert_eq!(m.highest_false_score(), Some(0.7));
        let all_right = evaluate(&results[..2], &truth()).unwrap();
        assert_eq!(all_right.highest_false_score(), None);
    }

    #[test]
    fn ties_form_one_threshold_and_a_wrong_best_gives_zero_recall_at_full_precision() {
        let results = [result(10, Some((1, 0.9))), result(14, Some((0, 0.9))), result(11, Some((2, 0.4)))];
        let m = evaluate(&results, &truth()).unwrap();
        // Positives are counted among the queries given: 10 and 11.
        assert_eq!((m.queries, m.positives), (3, 2));
        assert_eq!(m.curve.len(), 2);
        assert_eq!((m.curve[0].threshold, m.curve[0].precision, m.curve[0].recall), (0.9, 0.5, 0.5));
        assert_eq!((m.curve[1].threshold, m.curve[1].recall), (0.4, 1.0));
        assert_eq!(m.recall_at_100_precision, Some(0.0));
        // AP = 0.5*0.5 + 0.5*(2/3).
        assert!((m.average_precision.unwrap() - (0.25 + 1.0 / 3.0)).abs() < 1e-12);
        assert_eq!(m.recall_at_1, Some(1.0));
    }

    #[test]
    fn no_positives_gives_no_recall_and_bad_input_is_refused() {
        let m = evaluate(&[result(14, Some((0, 0.5))), result(15, None)], &truth()).unwrap();
        assert_eq!((m.queries, m.positives), (2, 0));
        assert_eq!((m.recall_at_1, m.average_precision, m.recall_at_100_precision), (None, None, None));
        let err = evaluate(&[result(10, None), result(10, None)], &truth()).unwrap_err();
        assert!(err.to_string().contains("query 10 has more than one result"));
        assert!(evaluate(&[result(10, Some((1, f32::NAN)))], &truth()).is_err());
    }
}
