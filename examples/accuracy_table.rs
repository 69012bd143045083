//! The accuracy table over every development set: each descriptor mode, single-image and sequence
//! matching, with recall@1, recall at 100% precision, AP, precision and recall at the default
//! threshold, bytes and milliseconds per keyframe. A program that measures and prints (the README's
//! table), not a test.
//!
//!     cargo run --release --example accuracy_table
//!
//! Sets: Gardens Point day/night and the TUM desk orbit from `../shared/data/real`, Gardens Point
//! again at 64x48 grayscale (degraded here, in a temporary folder: low-resolution cameras), the TUM
//! fr3 two-pass and the synthetic sequences of `examples/common/mod.rs`.

mod common;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use ecm_lcd::config::Params;
use ecm_lcd::eval::{evaluate, images_in_name_order, read_loops, Metrics};
use ecm_lcd::model::weights::resolve::{self, Resolved};
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::preprocess::read_image;
use ecm_lcd::replay::{run_database_queries, run_source};

/// A development set: a sequence replayed (truth from poses or a loops file) or a database/query pair.
enum Data {
    Sequence(common::EvalSet, Option<PathBuf>),
    DatabaseQueries { database: PathBuf, queries: PathBuf, loops: PathBuf },
}

struct DevSet {
    name: String,
    data: Data,
}

/// The images of `from`, shrunk to 64x48 grayscale, written to `to` under the same names.
fn degrade_folder(from: &Path, to: &Path) -> Result<()> {
    std::fs::create_dir_all(to)?;
    for path in images_in_name_order(from)? {
        let image = read_image(&path)?;
        let small = image::imageops::resize(&image, 64, 48, image::imageops::FilterType::Triangle);
        let gray = image::DynamicImage::ImageLuma8(image::imageops::grayscale(&small));
        gray.save(to.join(path.file_name().context("image name")?).with_extension("png"))?;
    }
    Ok(())
}

fn dev_sets(tmp: &Path, sequences: Vec<common::EvalSet>) -> Result<Vec<DevSet>> {
    let shared = ecm_lcd::runtime::shared_dirs().into_iter().next().context("the shared data folder (../shared) is needed")?;
    let real = shared.join("data/real");
    let gp = real.join("gardens_point_day_night");
    let mut sets = vec![DevSet {
        name: "Gardens Point day/night (real)".into(),
        data: Data::DatabaseQueries { database: gp.join("ref"), queries: gp.join("query"), loops: gp.join("loops.csv") },
    }];
    let degraded = tmp.join("gardens_point_64x48_gray");
    degrade_folder(&gp.join("ref"), &degraded.join("ref"))?;
    degrade_folder(&gp.join("query"), &degraded.join("query"))?;
    sets.push(DevSet {
        name: "Gardens Point 64x48 gray (real, degraded)".into(),
        data: Data::DatabaseQueries { database: degraded.join("ref"), queries: degraded.join("query"), loops: gp.join("loops.csv") },
    });
    let orbit = real.join("tum_fr3_desk_orbit");
    sets.push(DevSet {
        name: "TUM desk orbit (real)".into(),
        data: Data::Sequence(
            common::EvalSet {
                name: "TUM desk orbit (real)",
                path: orbit.join("rgb"),
                criteria: Default::default(),
                overrides: &[("detector.min_history", "2"), ("detector.exclude_recent.count", "3"), ("detector.exclude_recent.seconds", "0")],
            },
            Some(orbit.join("loops.csv")),
        ),
    });
    for set in sequences {
        sets.push(DevSet { name: set.name.to_string(), data: Data::Sequence(set, None) });
    }
    Ok(sets)
}

/// What one configuration measured on one set.
struct Row {
    metrics: Metrics,
    ms_per_keyframe: f64,
    /// The detector's default score threshold.
    min_score: f32,
}

fn measure(set: &DevSet, overrides: &[(&str, &str)], weights: &Resolved) -> Result<(Row, usize)> {
    let mut params = Params::default();
    let set_overrides: &[(&str, &str)] = match &set.data {
        Data::Sequence(s, _) => s.overrides,
        Data::DatabaseQueries { .. } => &[],
    };
    for (k, v) in set_overrides.iter().chain(overrides) {
        params.set_from_str(k, v).map_err(anyhow::Error::msg)?;
    }
    let threshold = params.detector().threshold;
    let mut pipeline = Pipeline::with_weights(params, weights.clone())?;
    let (results, truth, ms) = match &set.data {
        Data::DatabaseQueries { database, queries, loops } => {
            let (results, timings) = run_database_queries(&mut pipeline, &images_in_name_order(database)?, &images_in_name_order(queries)?)?;
            (results, read_loops(loops)?, timings[0].1)
        }
        Data::Sequence(s, loops) => {
            let run = run_source(&mut pipeline, &s.path, None, false)?;
            let truth = match loops {
                Some(loops) => read_loops(loops)?,
                None => {
                    let groundtruth = ecm_lcd::io::tum::read_groundtruth(&s.path.join("groundtruth.txt"))?;
                    ecm_lcd::eval::loop_truth_from_poses(&run.frame_stamps, &groundtruth, &s.criteria)
                }
            };
            let ms = run.mean_timings().iter().map(|(_, ms)| ms).sum();
            (run.query_results(), truth, ms)
        }
    };
    let min_score = match threshold {
        ecm_lcd::detector::Threshold::MinScore(s) => s,
        ecm_lcd::detector::Threshold::MaxDistance(_) => anyhow::bail!("the table assumes a score threshold"),
    };
    let row = Row { metrics: evaluate(&results, &truth)?, ms_per_keyframe: ms, min_score };
    Ok((row, pipeline.descriptor().dim() * std::mem::size_of::<f32>()))
}

fn main() -> Result<()> {
    let (dir, sequences) = common::start()?;
    let sets = dev_sets(dir.path(), sequences)?;
    let weights = resolve::resolve(None)?;
    let sequence_length = "3";
    let defaults = Params::default();
    println!(
        "Defaults: descriptor {}, centring on the history {}, threshold {:?}; sequence rows: detector.sequence.length {sequence_length}.",
        defaults.descriptor_mode(),
        defaults.detector().centre_on_history,
        defaults.detector().threshold
    );
    println!();
    println!("| data | descriptor | centred | policy | queries (with loop) | recall@1 | recall@100%P | AP | P / R at threshold | highest false score | bytes/keyframe | ms/keyframe |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for set in &sets {
        for mode in ["paper", "l2", "spatial", "power"] {
            for centred in ["false", "true"] {
                if mode == "paper" && centred == "true" {
                    continue; // centring leaves the paper's descriptor alone
                }
                for (policy, length) in [("single", "1"), ("sequence", sequence_length)] {
                    let overrides = [
                        ("descriptor.mode", mode),
                        ("detector.centre_on_history", centred),
                        ("detector.sequence.length", length),
                    ];
                    let (row, bytes) = measure(set, &overrides, &weights)?;
                    let f = common::figure;
                    let m = &row.metrics;
                    // Nothing above the threshold: precision undefined, recall 0.
                    let (precision, recall) =
                        m.at_threshold(row.min_score).map_or((None, Some(0.0)), |p| (Some(p.precision), Some(p.recall)));
                    println!(
                        "| {} | {mode} | {} | {policy} | {} ({}) | {} | {} | {} | {} / {} | {} | {bytes} | {:.1} |",
                        set.name,
                        if centred == "true" { "yes" } else { "no" },
                        m.queries,
                        m.positives,
                        f(m.recall_at_1),
                        f(m.recall_at_100_precision),
                        f(m.average_precision),
                        f(precision),
                        f(recall.filter(|_| m.positives > 0)),
                        m.highest_false_score().map(|s| format!("{s:.4}")).unwrap_or_else(|| "-".into()),
                        row.ms_per_keyframe
                    );
                }
            }
        }
    }
    Ok(())
}
