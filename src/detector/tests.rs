//! Unit tests of the keyframe database and every detector policy rule.

use super::*;
use crate::descriptor::{distance, DescriptorMode};

fn secs(s: f64) -> Stamp {
    Stamp::from_secs_f64(s)
}

/// A deterministic pseudo-random generator (xorshift) so the tests need no extra crate.
fn pseudo_random(seed: u64, n: usize) -> Vec<f32> {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect()
}

#[test]
fn top_k_equals_a_naive_sort() {
    let dim = 37;
    let mut db = KeyframeDb::new(dim);
    let stored: Vec<Vec<f32>> = (0..200).map(|i| pseudo_random(i + 1, dim)).collect();
    for (i, d) in stored.iter().enumerate() {
        assert_eq!(db.insert(1000 + i as u64, secs(i as f64), d).unwrap(), i);
    }
    for q in 0..10 {
        let query = pseudo_random(500 + q, dim);
        let eligible = |p: usize| !p.is_multiple_of(3);
        for k in [1, 5, 17, 300] {
            let got = db.nearest(&query, k, eligible).unwrap();
            let mut naive: Vec<(usize, f32)> =
                (0..stored.len()).filter(|&p| eligible(p)).map(|p| (p, distance(&query, &stored[p]))).collect();
            naive.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
            naive.truncate(k);
            let got_positions: Vec<usize> = got.iter().map(|n| n.position).collect();
            let naive_positions: Vec<usize> = naive.iter().map(|n| n.0).collect();
            assert_eq!(got_positions, naive_positions, "query {q}, k {k}");
            for (n, (_, d)) in got.iter().zip(&naive) {
                assert!((n.squared_distance.sqrt() - d).abs() < 1e-4);
            }
        }
    }
    assert_eq!(db.len(), 200);
    assert_eq!(db.id(3), 1003);
    assert_eq!(db.stamp(3), secs(3.0));
    assert_eq!(db.descriptor(3), &stored[3][..]);
}

#[test]
fn ties_keep_insertion_order_and_k_zero_is_empty() {
    let mut db = KeyframeDb::new(2);
    for i in 0..4 {
        db.insert(i, secs(0.0), &[1.0, 0.0]).unwrap();
    }
    let got: Vec<usize> = db.nearest(&[0.0, 0.0], 3, |_| true).unwrap().iter().map(|n| n.position).collect();
    assert_eq!(got, vec![0, 1, 2]);
    assert!(db.nearest(&[0.0, 0.0], 0, |_| true).unwrap().is_empty());
}

#[test]
fn bad_descriptors_are_refused_with_reasons() {
    let mut db = KeyframeDb::new(3);
    let err = db.insert(7, secs(0.0), &[1.0, 2.0]).unwrap_err().to_string();
    assert!(err.contains("keyframe 7") && err.contains("2 values"), "{err}");
    let err = db.insert(8, secs(0.0), &[1.0, f32::NAN, 0.0]).unwrap_err().to_string();
    assert!(err.contains("value 1") && err.contains("NaN"), "{err}");
    assert!(db.is_empty());
    assert!(db.nearest(&[0.0; 4], 1, |_| true).is_err());
    let mut det = Detector::new(Descriptor::new(DescriptorMode::L2, 3), params_all_off());
    assert!(det.process(1, secs(0.0), &[0.0; 2]).is_err());
    assert!(det.best_match(secs(0.0), &[f32::INFINITY, 0.0, 0.0]).is_err());
}

/// L2 mode on 2-d unit vectors: the angle decides the distance.
fn unit(angle_deg: f32) -> [f32; 2] {
    let a = angle_deg.to_radians();
    [a.cos(), a.sin()]
}

fn l2_detector(params: DetectorParams) -> Detector {
    Detector::new(Descriptor::new(DescriptorMode::L2, 2), params)
}

/// Every rule off, every match accepted.
fn params_all_off() -> DetectorParams {
    DetectorParams {
        threshold: Threshold::MaxDistance(10.0),
        min_history: 0,
        exclude_recent_count: 0,
        exclude_recent_secs: 0.0,
        top_k: 1,
        consistency_queries: 1,
        consistency_delayed: true,
        consistency_window: 0,
        max_keyframes: 0,
        sequence_length: 1,
        centre_on_history: false,
        storage: Storage::Auto,
    }
}

fn match_ids(candidates: &[LoopCandidate]) -> Vec<u64> {
    candidates.iter().map(|c| c.match_id).collect()
}

#[test]
fn min_history_holds_queries_back() {
    let mut det = l2_detector(DetectorParams { min_history: 3, ..params_all_off() });
    assert!(det.process(0, secs(0.0), &unit(0.0)).unwrap().is_empty());
    assert!(det.process(1, secs(1.0), &unit(0.0)).unwrap().is_empty());
    assert!(det.process(2, secs(2.0), &unit(0.0)).unwrap().is_empty());
    assert!(det.best_match(secs(3.0), &unit(0.0)).unwrap().is_some());
    assert_eq!(det.process(3, secs(3.0), &unit(0.0)).unwrap().len(), 1);
    // With no minimum, the second keyframe can already match the first.
    let mut det = l2_detector(params_all_off());
    assert!(det.process(0, secs(0.0), &unit(0.0)).unwrap().is_empty());
    assert_eq!(match_ids(&det.process(1, secs(1.0), &unit(0.0)).unwrap()), vec![0]);
}

#[test]
fn recent_keyframes_are_excluded_by_count() {
    let mut det = l2_detector(DetectorParams { exclude_recent_count: 2, ..params_all_off() });
    // Keyframes at 0, 10, 20 degrees; a query at 21 degrees may not match 20 nor 10, only 0.
    for (id, angle) in [(0, 0.0), (1, 10.0), (2, 20.0)] {
        det.insert(id, secs(id as f64), &unit(angle)).unwrap();
    }
    let c = det.process(3, secs(3.0), &unit(21.0)).unwrap();
    assert_eq!(match_ids(&c), vec![0]);
    // Exclusion of everything leaves nothing.
    let mut det = l2_detector(DetectorParams { exclude_recent_count: 5, ..params_all_off() });
    for id in 0..5 {
        det.insert(id, secs(id as f64), &unit(0.0)).unwrap();
    }
    assert!(det.process(5, secs(5.0), &unit(0.0)).unwrap().is_empty());
    assert!(det.best_match(secs(6.0), &unit(0.0)).unwrap().is_some());
}

#[test]
fn recent_keyframes_are_excluded_by_time() {
    let mut det = l2_detector(DetectorParams { exclude_recent_secs: 10.0, ..params_all_off() });
    det.insert(0, secs(100.0), &unit(0.0)).unwrap();
    det.insert(1, secs(105.0), &unit(1.0)).unwrap();
    // At 110.5 s the keyframe at 100 s is 10.5 s old (eligible), the one at 105 s is too recent.
    let c = det.process(2, secs(110.5), &unit(1.0)).unwrap();
    assert_eq!(match_ids(&c), vec![0]);
    // Exactly the exclusion age is eligible.
    assert_eq!(det.best_match(secs(115.0), &unit(1.0)).unwrap().unwrap().id, 1);
    assert_eq!(det.best_match(secs(114.9), &unit(1.0)).unwrap().unwrap().id, 0);
    // Keyframes stamped after the query are never eligible under a time rule.
    assert!(det.best_match(secs(50.0), &unit(0.0)).unwrap().is_none());
}

#[test]
fn top_k_ranks_are_ordered_by_distance() {
    let mut det = l2_detector(DetectorParams { top_k: 3, ..params_all_off() });
    for (id, angle) in [(0, 40.0), (1, 10.0), (2, 90.0), (3, 20.0), (4, 5.0)] {
        det.insert(id, secs(id as f64), &unit(angle)).unwrap();
    }
    let c = det.process(9, secs(9.0), &unit(0.0)).unwrap();
    assert_eq!(match_ids(&c), vec![4, 1, 3]);
    assert_eq!(c.iter().map(|c| c.rank).collect::<Vec<_>>(), vec![0, 1, 2]);
    for cand in &c {
        assert_eq!(cand.query_id, 9);
        assert_eq!(cand.query_stamp, secs(9.0));
        assert_eq!(cand.match_stamp, secs(cand.match_id as f64));
        assert!((cand.score - det.descriptor().score(cand.distance)).abs() < 1e-7);
    }
    // 5 degrees apart on the unit circle: d = 2 sin(2.5°).
    assert!((c[0].distance - 2.0 * 2.5f32.to_radians().sin()).abs() < 1e-5);
    // The query was inserted after being answered.
    assert_eq!(det.db().len(), 6);
    assert_eq!(det.db().id(5), 9);
}

#[test]
fn thresholds_on_distance_and_score_agree() {
    // Stored at 0 and 60 degrees; query at 10 degrees: distances 2 sin 5° ≈ 0.174 and 2 sin 25° ≈ 0.845.
    let build = |threshold| {
        let mut det = l2_detector(DetectorParams { threshold, top_k: 2, ..params_all_off() });
        det.insert(0, secs(0.0), &unit(0.0)).unwrap();
        det.insert(1, secs(1.0), &unit(60.0)).unwrap();
        det
    };
    let near = 2.0 * 5f32.to_radians().sin();
    let far = 2.0 * 25f32.to_radians().sin();
    let mid = (near + far) / 2.0;
    let mut det = build(Threshold::MaxDistance(mid));
    assert_eq!(match_ids(&det.process(2, secs(2.0), &unit(10.0)).unwrap()), vec![0]);
    let mid_score = det.descriptor().score(mid);
    let mut det = build(Threshold::MinScore(mid_score));
    assert!((det.max_distance() - mid).abs() < 1e-5);
    assert_eq!(match_ids(&det.process(2, secs(2.0), &unit(10.0)).unwrap()), vec![0]);
    let mut det = build(Threshold::MaxDistance(far + 0.01));
    assert_eq!(match_ids(&det.process(2, secs(2.0), &unit(10.0)).unwrap()), vec![0, 1]);
    let mut det = build(Threshold::MinScore(1.0));
    assert!(det.process(2, secs(2.0), &unit(10.0)).unwrap().is_empty());
    // best_match ignores the threshold.
    let det = build(Threshold::MinScore(1.0));
    let m = det.best_match(secs(2.0), &unit(10.0)).unwrap().unwrap();
    assert_eq!(m.id, 0);
    assert!((m.distance - near).abs() < 1e-5);
    assert!((m.score - (1.0 + 10f32.to_radians().cos()) / 2.0).abs() < 1e-5);
}

/// A place sequence: positions 0..10 are places at 0, 10, ..., 90 degrees; later queries revisit them.
fn consistency_detector(queries: usize, window: usize) -> Detector {
    let mut det = l2_detector(DetectorParams {
        threshold: Threshold::MaxDistance(0.05),
        consistency_queries: queries,
        consistency_window: window,
        ..params_all_off()
    });
    for i in 0..10 {
        det.insert(i, secs(i as f64), &unit(10.0 * i as f32)).unwrap();
    }
    det
}

#[test]
fn consistency_off_reports_every_passing_match() {
    let mut det = consistency_detector(1, 0);
    assert_eq!(match_ids(&det.process(100, secs(100.0), &unit(50.0)).unwrap()), vec![5]);
    assert!(det.process(101, secs(101.0), &unit(55.0)).unwrap().is_empty());
    assert_eq!(match_ids(&det.process(102, secs(102.0), &unit(20.0)).unwrap()), vec![2]);
}

/// (query id, match id) of each candidate, in order.
fn query_and_match(candidates: &[LoopCandidate]) -> Vec<(u64, u64)> {
    candidates.iter().map(|c| (c.query_id, c.match_id)).collect()
}

#[test]
fn consistency_of_three_needs_three_agreeing_queries() {
    let mut det = consistency_detector(3, 1);
    // Revisit places 3, 4, 5 with a window of 1: at the third query |5 - 3| = 2 > 1, so it is not yet
    // consistent; the fourth (place 5 again, after 4 and 5) is, and completes the run 4, 5, 5 of the
    // three queries before it: the two held back are reported with it, under their own ids.
    assert!(det.process(100, secs(100.0), &unit(30.0)).unwrap().is_empty());
    assert!(det.process(101, secs(101.0), &unit(40.0)).unwrap().is_empty());
    assert!(det.process(102, secs(102.0), &unit(50.0)).unwrap().is_empty());
    let reported = det.process(103, secs(103.0), &unit(50.0)).unwrap();
    assert_eq!(query_and_match(&reported), vec![(101, 4), (102, 5), (103, 5)]);
    assert_eq!(reported[0].query_stamp, secs(101.0));
    assert!(reported.iter().all(|c| c.rank == 0));
    // Each once: the next query reports its own match only.
    assert_eq!(query_and_match(&det.process(104, secs(104.0), &unit(60.0)).unwrap()), vec![(104, 6)]);

    // A window of 2 accepts 3, 4, 5 at the third query.
    let mut det = consistency_detector(3, 2);
    assert!(det.process(100, secs(100.0), &unit(30.0)).unwrap().is_empty());
    assert!(det.process(101, secs(101.0), &unit(40.0)).unwrap().is_empty());
    let reported = det.process(102, secs(102.0), &unit(50.0)).unwrap();
    assert_eq!(query_and_match(&reported), vec![(100, 3), (101, 4), (102, 5)]);

    // A query without a passing match breaks the chain; two more agreeing queries are needed, and
    // the match before the break is not reported.
    let mut det = consistency_detector(3, 2);
    det.process(100, secs(100.0), &unit(30.0)).unwrap();
    det.process(101, secs(101.0), &unit(35.0)).unwrap(); // between places: nothing passes
    assert!(det.process(102, secs(102.0), &unit(40.0)).unwrap().is_empty());
    assert!(det.process(103, secs(103.0), &unit(40.0)).unwrap().is_empty());
    let reported = det.process(104, secs(104.0), &unit(40.0)).unwrap();
    assert_eq!(query_and_match(&reported), vec![(102, 4), (103, 4), (104, 4)]);

    // Far-apart matches do not agree.
    let mut det = consistency_detector(3, 2);
    det.process(100, secs(100.0), &unit(10.0)).unwrap();
    det.process(101, secs(101.0), &unit(80.0)).unwrap();
    assert!(det.process(102, secs(102.0), &unit(80.0)).unwrap().is_empty());

    // Lowering the requirement at run time trims the history and takes effect at once: the last
    // query and this one agree.
    det.set_params(DetectorParams { consistency_queries: 2, ..det.params().clone() });
    assert_eq!(query_and_match(&det.process(103, secs(103.0), &unit(80.0)).unwrap()), vec![(102, 8), (103, 8)]);
}

/// A detector rebuilt from its history and its consistency state (through JSON, as a store keeps it)
/// goes on as the original: held-back matches are released by the next agreeing query, also where a
/// memory budget drops keyframes. Without the state, they are lost.
#[test]
fn consistency_resumes_from_its_state_on_a_reloaded_history() {
    let mut det = consistency_detector(3, 1);
    for (id, degrees) in [(100, 30.0), (101, 40.0), (102, 50.0)] {
        assert!(det.process(id, secs(id as f64), &unit(degrees)).unwrap().is_empty());
    }
    let json = serde_json::to_string(&det.consistency_state().expect("consistency is on")).unwrap();
    let state: ConsistencyState = serde_json::from_str(&json).unwrap();
    assert_eq!(state.queries.iter().map(|q| q.id).collect::<Vec<_>>(), vec![100, 101, 102]);
    assert_eq!(state.queries[2].matches, vec![(5, 0.0, 1.0, true)]);
    let next = |det: &mut Detector| det.process(103, secs(103.0), &unit(50.0)).unwrap();
    let resumed = |state: Option<ConsistencyState>, max_keyframes: usize| {
        let mut fresh = l2_detector(DetectorParams { max_keyframes, ..det.params().clone() });
        fresh.replace_history(det.db().clone()).unwrap();
        fresh.resume(&[], state);
        next(&mut fresh)
    };
    let expected = next(&mut det.clone());
    assert_eq!(query_and_match(&expected), vec![(101, 4), (102, 5), (103, 5)]);
    assert_eq!(resumed(Some(state.clone()), 0), expected);
    // Without it the restart starts a new run of queries: nothing yet.
    assert!(resumed(None, 0).is_empty());
    // A budget of 10 keeps places 4.. once query 103 is stored: query 100's match (place 3) is
    // forgotten, by the restarted detector as by the running one.
    let mut budgeted = det.clone();
    budgeted.set_params(DetectorParams { max_keyframes: 10, ..det.params().clone() });
    let expected = next(&mut budgeted);
    assert_eq!(query_and_match(&expected), vec![(101, 4), (102, 5), (103, 5)]);
    assert_eq!(resumed(Some(state), 10), expected);
    // Off, there is no state to keep.
    det.set_params(DetectorParams { consistency_queries: 1, ..det.params().clone() });
    assert_eq!(det.consistency_state(), None);
}

#[test]
fn without_delay_held_back_matches_are_dropped_as_dbow2_does() {
    let mut det = consistency_detector(3, 1);
    det.set_params(DetectorParams { consistency_delayed: false, ..det.params().clone() });
    for (id, degrees) in [(100, 30.0), (101, 40.0), (102, 50.0)] {
        assert!(det.process(id, secs(id as f64), &unit(degrees)).unwrap().is_empty());
    }
    assert_eq!(query_and_match(&det.process(103, secs(103.0), &unit(50.0)).unwrap()), vec![(103, 5)]);
}

#[test]
fn a_match_no_later_query_agrees_with_is_never_reported() {
    let mut det = consistency_detector(2, 1);
    assert!(det.process(100, secs(100.0), &unit(20.0)).unwrap().is_empty());
    assert!(det.process(101, secs(101.0), &unit(70.0)).unwrap().is_empty());
    assert!(det.process(102, secs(102.0), &unit(35.0)).unwrap().is_empty()); // nothing passes
    let reported = det.process(103, secs(103.0), &unit(40.0)).unwrap();
    assert!(reported.is_empty(), "{reported:?}");
    assert_eq!(query_and_match(&det.process(104, secs(104.0), &unit(40.0)).unwrap()), vec![(103, 4), (104, 4)]);
}

#[test]
fn dropping_the_oldest_keeps_positions_ids_and_search_exact() {
    let dim = 5;
    let mut db = KeyframeDb::new(dim);
    let all: Vec<Vec<f32>> = (0..300).map(|i| pseudo_random(i + 7, dim)).collect();
    // Insert and drop in a pattern that crosses the batched reclamation many times.
    let mut first_kept = 0usize;
    for (i, d) in all.iter().enumerate() {
        db.insert(i as u64, secs(i as f64), d).unwrap();
        if i % 3 == 2 {
            db.drop_oldest(2);
            first_kept += 2;
        }
        assert_eq!(db.len(), i + 1 - first_kept);
        assert_eq!(db.id(0), first_kept as u64);
        assert_eq!(db.stamp(db.len() - 1), secs(i as f64));
        assert_eq!(db.descriptor(0), &all[first_kept][..]);
    }
    let query = pseudo_random(999, dim);
    let got: Vec<u64> = db.nearest(&query, 4, |_| true).unwrap().iter().map(|n| db.id(n.position)).collect();
    let mut naive: Vec<(u64, f32)> = (first_kept..all.len()).map(|p| (p as u64, distance(&query, &all[p]))).collect();
    naive.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    assert_eq!(got, naive.iter().take(4).map(|n| n.0).collect::<Vec<_>>());
    db.drop_oldest(10_000);
    assert!(db.is_empty());
}

#[test]
fn memory_budget_keeps_the_newest_keyframes_and_search_forgets_the_rest() {
    let mut det = l2_detector(DetectorParams { max_keyframes: 3, ..params_all_off() });
    for i in 0..10u64 {
        det.insert(i, secs(i as f64), &unit(10.0 * i as f32)).unwrap();
        assert_eq!(det.db().len(), (i as usize + 1).min(3));
    }
    assert_eq!((det.db().id(0), det.db().id(2)), (7, 9));
    // Keyframe 0's place is only matched to the nearest kept keyframe, 7.
    let got = det.process(10, secs(10.0), &unit(0.0)).unwrap();
    assert_eq!(got.iter().map(|c| c.match_id).collect::<Vec<_>>(), [7]);
    assert_eq!((det.db().len(), det.db().id(2)), (3, 10));
    // Lowering the budget at run time drops at once; 0 lifts it.
    det.set_params(DetectorParams { max_keyframes: 1, ..det.params().clone() });
    assert_eq!((det.db().len(), det.db().id(0)), (1, 10));
    det.set_params(DetectorParams { max_keyframes: 0, ..det.params().clone() });
    for i in 11..20 {
        det.insert(i, secs(i as f64), &unit(0.0)).unwrap();
    }
    assert_eq!(det.db().len(), 10);
    // A loaded history is trimmed too.
    let mut history = KeyframeDb::new(2);
    for i in 0..6 {
        history.insert(100 + i, secs(i as f64), &unit(i as f32)).unwrap();
    }
    det.set_params(DetectorParams { max_keyframes: 4, ..det.params().clone() });
    det.replace_history(history).unwrap();
    assert_eq!((det.db().len(), det.db().id(0)), (4, 102));
    assert!(det.replace_history(KeyframeDb::new(3)).is_err());
}

#[test]
fn a_loaded_history_is_indexed_before_the_first_keyframe() {
    // As a store load leaves it: the index deferred to the next insert.
    let dim = 8;
    let values = crate::detector::index::ClusteredVectors::new(dim, 10, 1).take(600);
    let stamps = (0..600).map(|i| secs(i as f64)).collect();
    let mut history = KeyframeDb::from_history(dim, (0..600).collect(), stamps, values.into()).unwrap();
    history.defer_index(true).unwrap();
    history.set_index_policy(IndexPolicy { min_len: 500, scan_values: 0, ..IndexPolicy::default() }).unwrap();
    history.index_at_next_insert();
    assert!(history.index_info().is_none());
    let mut det = Detector::new(Descriptor::new(DescriptorMode::L2, dim), params_all_off());
    det.replace_history(history).unwrap();
    assert_eq!(det.db().index_info().map(|i| i.trained_len), Some(600));
}

#[test]
fn memory_budget_keeps_consistency_positions_in_step() {
    // Consistency over 2 queries with a window of 0: two revisits of place 3 agree only if the first
    // one's match position is renumbered when the oldest keyframe is dropped between them.
    let mut det = consistency_detector(2, 0);
    det.set_params(DetectorParams { max_keyframes: 10, ..det.params().clone() });
    assert!(det.process(100, secs(100.0), &unit(30.0)).unwrap().is_empty());
    assert_eq!((det.db().len(), det.db().id(0)), (10, 1));
    // Place 3 moved from position 3 to 2; the ties with keyframe 100 go to the earlier position. The
    // first revisit's match, held back, is reported with the second and still names place 3.
    let reported = det.process(101, secs(101.0), &unit(30.0)).unwrap();
    assert_eq!(query_and_match(&reported), vec![(100, 3), (101, 3)]);
}

/// A place's descriptor: a random unit vector per place index (8-d), so places are unrelated.
fn place(index: usize) -> Vec<f32> {
    let mut v: Vec<f32> = pseudo_random(7000 + index as u64, 8).iter().map(|x| x - 0.5).collect();
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    v.iter_mut().for_each(|x| *x /= norm);
    v
}

/// `a` moved a fraction `t` of the way towards `b`, renormalised.
fn blend(a: &[f32], b: &[f32], t: f32) -> Vec<f32> {
    let mut v: Vec<f32> = a.iter().zip(b).map(|(x, y)| (1.0 - t) * x + t * y).collect();
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    v.iter_mut().for_each(|x| *x /= norm);
    v
}

#[test]
fn sequence_matching_finds_a_loop_that_single_images_miss() {
    // Lap 1: places 0..20. Lap 2 revisits places 5..15 in order, each seen with a change of look
    // (blended halfway towards an unrelated "lighting" vector); query 10 of the lap (place 10) is
    // made to look more like place 3 than like place 10, an alias a single image cannot resolve.
    let run = |sequence_length: usize| -> Vec<Option<u64>> {
        let params = DetectorParams { sequence_length, exclude_recent_count: 3, ..params_all_off() };
        let mut det = Detector::new(Descriptor::new(DescriptorMode::L2, 8), params);
        for p in 0..20 {
            det.process(p as u64, secs(p as f64), &place(p)).unwrap();
        }
        let lighting = place(99);
        (5..15)
            .map(|p| {
                let seen = blend(&place(p), &lighting, 0.4);
                let seen = if p == 10 { blend(&seen, &place(3), 0.7) } else { seen };
                let (nearest, _) = det.process_ranked(100 + p as u64, secs(100.0 + p as f64), &seen, 1).unwrap();
                nearest.first().map(|m| m.id)
            })
            .collect()
    };
    let single = run(1);
    assert_eq!(single[5], Some(3), "the alias fools a single image");
    let sequence = run(4);
    // From the fourth query of the revisit on, the whole diagonal lies in it; the first three are
    // scored partly with queries from before the revisit (module doc of `sequence`).
    let expected: Vec<Option<u64>> = (8..15).map(|p| Some(p as u64)).collect();
    assert_eq!(sequence[3..], expected[..], "the run of matches puts query 10 at place 10");
}

/// A walk with no revisit: an earlier query of a sequence window is never compared with itself or
/// with keyframes too recent for it, which would score the walk as a loop with its own past.
#[test]
fn sequence_windows_judge_each_earlier_query_by_its_own_recency() {
    // Keyframe i shares a random component with its two neighbours on each side and none with
    // keyframes four or more away, as a camera's overlapping views do.
    let component = |i: usize| -> Vec<f32> { pseudo_random(9000 + i as u64, 64).iter().map(|x| x - 0.5).collect() };
    let view = |i: usize| -> Vec<f32> {
        let mut v = vec![0f32; 64];
        (i..i + 3).for_each(|c| v.iter_mut().zip(component(c)).for_each(|(x, y)| *x += y));
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.iter_mut().for_each(|x| *x /= norm);
        v
    };
    for budget in [0, 12] {
        let params = DetectorParams {
            sequence_length: 5,
            exclude_recent_count: 3,
            min_history: 2,
            max_keyframes: budget,
            ..params_all_off()
        };
        let mut det = Detector::new(Descriptor::new(DescriptorMode::L2, 64), params);
        let mut best = 0f32;
        for i in 0..40 {
            let (nearest, _) = det.process_ranked(i as u64, secs(i as f64), &view(i), 1).unwrap();
            best = nearest.first().map_or(best, |m| best.max(m.score));
        }
        // Unrelated views score about 0.5; a window that met its own queries scored 0.7 and more.
        assert!(best < 0.66, "budget {budget}: a walk without a revisit scored {best}");
    }
    // The threshold applies to the sequence score, given as a score or as the same distance.
    let descriptor = Descriptor::new(DescriptorMode::L2, 64);
    let reported = |threshold: Threshold| -> Vec<(u64, u64, f32)> {
        let params = DetectorParams { sequence_length: 5, exclude_recent_count: 3, threshold, ..params_all_off() };
        let mut det = Detector::new(descriptor, params);
        let walk = (0..30).chain(5..20).enumerate();
        let candidates = walk.flat_map(|(i, place)| det.process(i as u64, secs(i as f64), &view(place)).unwrap());
        candidates.map(|c| (c.query_id, c.match_id, c.score)).collect()
    };
    let by_score = reported(Threshold::MinScore(0.8));
    assert!(by_score.len() >= 8 && by_score.iter().all(|c| c.2 >= 0.8), "{by_score:?}");
    assert_eq!(reported(Threshold::MaxDistance(descriptor.distance_for_score(0.8))), by_score);
}

/// The centred comparison, written out plainly: subtract the mean, then the cosine.
fn centred_reference(a: &[f32], b: &[f32], mean: &[f64]) -> f64 {
    let a: Vec<f64> = a.iter().zip(mean).map(|(x, m)| *x as f64 - m).collect();
    let b: Vec<f64> = b.iter().zip(mean).map(|(x, m)| *x as f64 - m).collect();
    let dot: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
    dot / (a.iter().map(|x| x * x).sum::<f64>().sqrt() * b.iter().map(|x| x * x).sum::<f64>().sqrt())
}

#[test]
fn centring_compares_against_the_mean_of_the_searched_history() {
    let params = DetectorParams { centre_on_history: true, top_k: 3, max_keyframes: 6, ..params_all_off() };
    let mut det = Detector::new(Descriptor::new(DescriptorMode::L2, 8), params);
    let stored: Vec<Vec<f32>> = (0..9).map(|i| blend(&place(i), &place(50), 0.6)).collect();
    for (i, d) in stored.iter().enumerate() {
        det.insert(i as u64, secs(i as f64), d).unwrap();
    }
    // The budget keeps keyframes 3..9; the mean is over those six, shrunk by 6 / 7.
    let kept = &stored[3..];
    let mean: Vec<f64> = (0..8).map(|c| kept.iter().map(|d| d[c] as f64).sum::<f64>() / 7.0).collect();
    let query = blend(&place(4), &place(50), 0.5);
    let m = det.best_match(secs(100.0), &query).unwrap().unwrap();
    let cosines: Vec<f64> = kept.iter().map(|d| centred_reference(&query, d, &mean)).collect();
    let best = (0..kept.len()).max_by(|&a, &b| cosines[a].total_cmp(&cosines[b])).unwrap();
    assert_eq!(m.id, 3 + best as u64);
    assert!((m.score as f64 - (1.0 + cosines[best]) / 2.0).abs() < 1e-5, "{} vs {}", m.score, cosines[best]);
    assert!((m.distance as f64 - (2.0 - 2.0 * cosines[best]).sqrt()).abs() < 1e-4);
    // A loaded history gives the same mean as one built keyframe by keyframe.
    let mut loaded = Detector::new(Descriptor::new(DescriptorMode::L2, 8), det.params().clone());
    loaded.replace_history(det.db().clone()).unwrap();
    assert_eq!(loaded.best_match(secs(100.0), &query).unwrap().unwrap(), m);
    // The paper's descriptor is never centred.
    let mut paper = Detector::new(Descriptor::new(DescriptorMode::Paper, 80), det.params().clone());
    for (i, d) in stored.iter().enumerate() {
        paper.insert(i as u64, secs(i as f64), &d.iter().map(|x| x.abs()).cycle().take(8).collect::<Vec<_>>()).unwrap();
    }
    assert!(paper.centring().is_none());
}

#[test]
fn storage_codes_the_large_unit_descriptors_and_keeps_the_paper_s_exact() {
    // The default: 3x3 cells of MobileNetV2's last bottleneck (320 channels).
    let regional = Descriptor::regional(320, 3, Default::default());
    assert_eq!(regional.dim(), 2880);
    assert_eq!(Storage::Auto.format_for(&regional), RowFormat::Levels6);
    assert_eq!(Storage::Auto.format_for(&Descriptor::new(DescriptorMode::L2, 256)), RowFormat::F32);
    assert_eq!(Storage::Auto.format_for(&Descriptor::new(DescriptorMode::Paper, 1280)), RowFormat::F32);
    assert_eq!(Storage::F32.format_for(&regional), RowFormat::F32);
    assert_eq!("levels6".parse::<Storage>(), Ok(Storage::Levels6));
    assert!("f16".parse::<Storage>().is_err());
    assert_eq!(RowFormat::Levels6.row_bytes(2880), 972);
}

#[test]
fn a_coded_detector_finds_the_revisits_an_exact_one_finds_with_nearly_its_scores() {
    let dim = 1280;
    let descriptor = Descriptor::new(DescriptorMode::L2, dim);
    let mut places = crate::detector::index::ClusteredVectors::new(dim, 30, 5);
    let data = places.take(300);
    let coded_params = params_all_off();
    let mut coded = Detector::new(descriptor, coded_params.clone());
    let mut exact = Detector::new(descriptor, DetectorParams { storage: Storage::F32, ..coded_params });
    assert_eq!((coded.db().format(), exact.db().format()), (RowFormat::Levels6, RowFormat::F32));
    assert_eq!((coded.row_bytes(), exact.row_bytes()), (439, 5120));
    // The points of a cluster are near ties (noise in every value), so which one is best may
    // change; what must hold is that the coded best is as good, by exact distance, as the exact
    // best, and that its reported score is the exact score of that keyframe.
    let (mut worse, mut change, mut bias) = (Vec::new(), Vec::new(), 0f32);
    for (i, v) in data.chunks_exact(dim).enumerate() {
        let stamp = secs(i as f64);
        let (c, e) = (coded.best_match(stamp, v).unwrap(), exact.best_match(stamp, v).unwrap());
        if let (Some(c), Some(e)) = (c, e) {
            let exact_score_of_coded_best = descriptor.score(exact.db().squared_distance_to(v, c.id as usize).sqrt());
            worse.push(e.score - exact_score_of_coded_best);
            change.push((c.score - exact_score_of_coded_best).abs());
            bias += c.score - exact_score_of_coded_best;
        }
        coded.insert(i as u64, stamp, v).unwrap();
        exact.insert(i as u64, stamp, v).unwrap();
    }
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
    let largest = |v: &[f32]| v.iter().fold(0f32, |m, &x| m.max(x));
    assert!(
        mean(&worse) < 0.002 && largest(&worse) < 0.015,
        "coded best matches score below the exact best: {worse:?}"
    );
    assert!(mean(&change) < 0.004 && largest(&change) < 0.015, "coded scores differ from exact ones: {change:?}");
    // No shrinking (the estimator's point): only the best-of-noisy-estimates' slight upward pull.
    assert!((bias / change.len() as f32).abs() < 0.003, "mean score change {}", bias / change.len() as f32);
    // A stored descriptor queried again is found at distance 0, as with f32 rows.
    let again = coded.best_match(secs(1000.0), &data[..dim]).unwrap().unwrap();
    assert_eq!(again.id, 0);
    assert!(again.distance < 1e-2, "{}", again.distance);
    // A history loaded as f32 rows is coded on the way in.
    let history = exact.db().clone();
    coded.replace_history(history).unwrap();
    assert_eq!((coded.db().format(), coded.db().len()), (RowFormat::Levels6, 300));
}

#[test]
fn a_budget_that_leaves_nothing_to_match_is_named() {
    let params = |max_keyframes, exclude_recent_count, min_history| DetectorParams {
        max_keyframes,
        exclude_recent_count,
        min_history,
        ..params_all_off()
    };
    assert_eq!(params(0, 5, 5).never_matches(), None);
    assert_eq!(params(6, 5, 6).never_matches(), None);
    assert!(params(5, 5, 0).never_matches().unwrap().contains("detector.exclude_recent.count (5)"));
    assert!(params(4, 0, 5).never_matches().unwrap().contains("detector.min_history (5)"));
    // And indeed nothing matches.
    let mut det = l2_detector(params(2, 2, 0));
    let reported: usize = (0..10).map(|i| det.process(i, secs(i as f64), &unit(0.0)).unwrap().len()).sum();
    assert_eq!(reported, 0);
}
