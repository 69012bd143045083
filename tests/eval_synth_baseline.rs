//! Evaluation end to end on a synthetic sequence with a deliberately simple place recogniser
//! (tiny grey thumbnails, cosine similarity): revisits must look alike enough for it to score
//! well, and a recogniser that ignores the images must score badly under the same truth.

use ecm_lcd::eval::{evaluate, loop_truth_from_poses, PoseLoopCriteria, QueryResult};
use ecm_lcd::synth::{Scene, SynthConfig};
use ecm_lcd::types::Stamp;
use image::imageops::{grayscale, resize, FilterType};

fn thumbnail(image: &image::RgbImage) -> Vec<f32> {
    let small = resize(&grayscale(image), 16, 12, FilterType::Triangle);
    let values: Vec<f32> = small.as_raw().iter().map(|&v| v as f32).collect();
    let mean = values.iter().sum::<f32>() / values.len() as f32;
    let centred: Vec<f32> = values.iter().map(|v| v - mean).collect();
    let norm = centred.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-6);
    centred.iter().map(|v| v / norm).collect()
}

#[test]
fn thumbnails_find_the_revisits_of_a_synthetic_sequence() {
    let config = SynthConfig { frames: 450, laps: 3, width: 64, height: 48, seed: 11, ..SynthConfig::default() };
    let scene = Scene::new(config).unwrap();
    let stamps: Vec<Stamp> = (0..scene.len()).map(|i| scene.stamp(i)).collect();
    let poses: Vec<_> = (0..scene.len()).map(|i| (scene.stamp(i), scene.pose(i))).collect();
    // 5 s per lap; a 2.5 s gap leaves only earlier laps as history.
    let criteria =
        PoseLoopCriteria { max_distance_m: 0.5, max_angle_deg: 20.0, min_gap_s: 2.5, ..PoseLoopCriteria::default() };
    let truth = loop_truth_from_poses(&stamps, &poses, &criteria);
    let descriptors: Vec<Vec<f32>> = (0..scene.len()).map(|i| thumbnail(&scene.render(i))).collect();
    let gap = (2.5 * 30.0) as usize;
    let recognise = |q: usize, similarity: &dyn Fn(usize, usize) -> f32| QueryResult {
        query: q,
        best: (0..q.saturating_sub(gap)).map(|m| (m, similarity(q, m))).max_by(|a, b| a.1.total_cmp(&b.1)),
    };
    let cosine = |q: usize, m: usize| descriptors[q].iter().zip(&descriptors[m]).map(|(a, b)| a * b).sum::<f32>();
    let results: Vec<QueryResult> = (0..scene.len()).map(|q| recognise(q, &cosine)).collect();
    let metrics = evaluate(&results, &truth).unwrap();
    eprintln!("thumbnail recogniser: {}", ecm_lcd::eval::summary_json(&metrics, &[]));
    assert!(metrics.positives > 250, "laps 2 and 3 revisit lap 1: {} positives", metrics.positives);
    assert!(metrics.recall_at_1.unwrap() > 0.8, "{}", ecm_lcd::eval::summary_json(&metrics, &[]));
    assert!(metrics.average_precision.unwrap() > 0.7, "{}", ecm_lcd::eval::summary_json(&metrics, &[]));
    // Control: a "recogniser" that matches by a hash of the indexes, not the images.
    let blind = |q: usize, m: usize| ((q * 7919 + m * 104_729) % 1000) as f32;
    let results: Vec<QueryResult> = (0..scene.len()).map(|q| recognise(q, &blind)).collect();
    let control = evaluate(&results, &truth).unwrap();
    assert!(control.recall_at_1.unwrap() < 0.2, "{}", ecm_lcd::eval::summary_json(&control, &[]));
    assert!(control.average_precision.unwrap() < 0.2, "{}", ecm_lcd::eval::summary_json(&control, &[]));
}
