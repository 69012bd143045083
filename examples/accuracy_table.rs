//! The accuracy table over every development set: each descriptor mode, single-image and sequence
//! matching, with recall@1, recall at 100% precision, AP, precision and recall at the default
//! threshold, bytes and milliseconds per keyframe; then geometric verification on each set (the
//! true loops retrieval finds at a permissive threshold, how many verification keeps, the false
//! ones it lets through, its time) and, where real poses exist, the relative pose's error. A
//! program that measures and prints (the README's table), not a test.
//!
//!     cargo run --release --example accuracy_table
//!
//! Sets: Gardens Point day/night and the TUM desk orbit from `../shared/data/real`, Gardens Point
//! again at 64x48 and 32x24 grayscale (degraded here, in a temporary folder: low-resolution
//! cameras; `ACCURACY_CUTS=1` adds the hard night lap's cut at 32x24 too), the TUM
//! fr3 two-pass and the synthetic sequences of `examples/common/mod.rs`; in the database/query mode
//! the two-pass's second pass against its first (also at 64x48 gray), the hard one's night and day
//! laps against its first, and the Gardens Point gray copy and the night lap with their queries
//! shuffled; for verification also both synthetic sequences rendered with depth (metric poses, their
//! errors against the covariance, and those of the loops outside the truth's place rule).

mod common;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use ecm_lcd::config::Params;
use ecm_lcd::eval::{evaluate, images_in_name_order, read_loops, LoopTruth, Metrics};
use ecm_lcd::model::weights::resolve::{self, Resolved};
use ecm_lcd::pipeline::Pipeline;
use ecm_lcd::preprocess::read_image;
use ecm_lcd::replay::{run_database_queries, run_source};
use ecm_lcd::synth::SynthConfig;
use rand::{rngs::StdRng, seq::SliceRandom, SeedableRng};

/// A development set: a sequence replayed (truth from poses or a loops file) or a database/query pair.
enum Data {
    Sequence(common::EvalSet, Option<PathBuf>),
    DatabaseQueries { database: PathBuf, queries: PathBuf, loops: PathBuf },
}

struct DevSet {
    name: String,
    data: Data,
}

/// The images of `from`, shrunk to `width`x`height` grayscale (a low-resolution camera), written
/// to `to` under the same names.
fn degrade_folder(from: &Path, to: &Path, (width, height): (u32, u32)) -> Result<()> {
    std::fs::create_dir_all(to)?;
    for path in images_in_name_order(from)? {
        let image = read_image(&path)?;
        let small = image::imageops::resize(&image, width, height, image::imageops::FilterType::Triangle);
        let gray = image::DynamicImage::ImageLuma8(image::imageops::grayscale(&small));
        gray.save(to.join(path.file_name().context("image name")?).with_extension("png"))?;
    }
    Ok(())
}

fn dev_sets(tmp: &Path, sequences: Vec<common::EvalSet>) -> Result<Vec<DevSet>> {
    let shared =
        ecm_lcd::runtime::shared_dirs().into_iter().next().context("the shared data folder (../shared) is needed")?;
    let real = shared.join("data/real");
    let gp = real.join("gardens_point_day_night");
    let mut sets = vec![DevSet {
        name: "Gardens Point day/night (real)".into(),
        data: Data::DatabaseQueries {
            database: gp.join("ref"),
            queries: gp.join("query"),
            loops: gp.join("loops.csv"),
        },
    }];
    for (width, height) in [(64, 48), (32, 24)] {
        let degraded = tmp.join(format!("gardens_point_{width}x{height}_gray"));
        degrade_folder(&gp.join("ref"), &degraded.join("ref"), (width, height))?;
        degrade_folder(&gp.join("query"), &degraded.join("query"), (width, height))?;
        sets.push(DevSet {
            name: format!("Gardens Point {width}x{height} gray (real, degraded)"),
            data: Data::DatabaseQueries {
                database: degraded.join("ref"),
                queries: degraded.join("query"),
                loops: gp.join("loops.csv"),
            },
        });
    }
    let orbit = real.join("tum_fr3_desk_orbit");
    sets.push(DevSet {
        name: "TUM desk orbit (real)".into(),
        data: Data::Sequence(
            common::EvalSet {
                name: "TUM desk orbit (real)",
                path: orbit.join("rgb"),
                criteria: Default::default(),
                overrides: &[
                    ("detector.min_history", "2"),
                    ("detector.exclude_recent.count", "3"),
                    ("detector.exclude_recent.seconds", "0"),
                ],
            },
            Some(orbit.join("loops.csv")),
        ),
    });
    let hard = sequences.iter().find(|s| s.name.contains("hard")).map(|s| s.path.clone());
    for set in sequences {
        if set.name.starts_with("TUM") {
            // The real indoor revisit at a low-resolution grayscale camera's 64x48.
            let degraded = tmp.join("fr3_two_pass_64x48_gray");
            degrade_folder(&set.path.join("rgb"), &degraded.join("rgb"), (64, 48))?;
            for file in ["rgb.txt", "groundtruth.txt"] {
                std::fs::copy(set.path.join(file), degraded.join(file))?;
            }
            let name = "TUM fr3 two-pass 64x48 gray (real, degraded)";
            let degraded = common::EvalSet { name, path: degraded, ..set };
            // The same revisit as a map and a relocalisation: the first pass the database, the
            // second pass, walked the other way, the queries.
            let frames = ecm_lcd::io::open_source(&set.path, None)?.count();
            let first_pass = frames / 2;
            let second_pass: Vec<usize> = (first_pass..frames).collect();
            let mut cuts = Vec::new();
            for (label, source) in [("", &set.path), (" 64x48 gray", &degraded.path)] {
                let folder = tmp.join(format!("fr3_passes{}", label.replace(' ', "_")));
                let (database, queries, loops) =
                    cut_database_and_queries(source, &(0..first_pass).collect::<Vec<_>>(), &second_pass, &folder)?;
                cuts.push(DevSet {
                    name: format!("TUM fr3 second pass against first{label} (real)"),
                    data: Data::DatabaseQueries { database, queries, loops },
                });
            }
            sets.push(DevSet { name: set.name.to_string(), data: Data::Sequence(set, None) });
            sets.push(DevSet { name: name.to_string(), data: Data::Sequence(degraded, None) });
            sets.extend(cuts);
            continue;
        }
        sets.push(DevSet { name: set.name.to_string(), data: Data::Sequence(set, None) });
    }
    if let Some(hard) = hard {
        let lap = ecm_lcd::io::open_source(&hard, None)?.count() / 3;
        let first: Vec<usize> = (0..lap).collect();
        let (night, day): (Vec<usize>, Vec<usize>) = ((lap..2 * lap).collect(), (2 * lap..3 * lap).collect());
        let mut cuts = vec![
            ("night lap against first lap".to_string(), first.clone(), night.clone()),
            ("day lap against first lap".to_string(), first.clone(), day.clone()),
        ];
        if extra_cuts() {
            // Walks along a part of the database: 30 queries every 40 of each lap.
            for (name, queries) in [("night", &night), ("day", &day)] {
                for from in (0..queries.len().saturating_sub(30)).step_by(40) {
                    let part = queries[from..from + 30].to_vec();
                    cuts.push((
                        format!("{name} lap's queries {from}-{} against first lap", from + 29),
                        first.clone(),
                        part,
                    ));
                }
            }
            // Sampled unlike the database: queries or references left out.
            for (step, nth) in [(2, "second"), (3, "third"), (4, "fourth")] {
                let every = |frames: &[usize]| frames.iter().copied().step_by(step).collect::<Vec<_>>();
                cuts.push((format!("night lap, every {nth} query, against first lap"), first.clone(), every(&night)));
                cuts.push((format!("night lap against every {nth} frame of first lap"), every(&first), night.clone()));
            }
            for (name, kept) in [("4 of every 5", 5), ("2 of every 3", 3)] {
                let queries = night.iter().copied().filter(|q| q % kept != kept - 1).collect();
                cuts.push((format!("night lap, {name} queries, against first lap"), first.clone(), queries));
            }
        }
        for (index, (name, database, queries)) in cuts.into_iter().enumerate() {
            let folder = tmp.join(format!("synthetic_hard_cut_{index}"));
            let (database, queries, loops) = cut_database_and_queries(&hard, &database, &queries, &folder)?;
            let night_lap = (index == 0 && extra_cuts()).then(|| (database.clone(), queries.clone(), loops.clone()));
            sets.push(DevSet {
                name: format!("synthetic hard preset, {name}"),
                data: Data::DatabaseQueries { database, queries, loops },
            });
            if let Some((database, queries, loops)) = night_lap {
                // The night lap seen by a 32x24 camera, where some keyframes look like every query.
                let small = tmp.join("synthetic_hard_night_32x24");
                degrade_folder(&database, &small.join("ref"), (32, 24))?;
                degrade_folder(&queries, &small.join("query"), (32, 24))?;
                sets.push(DevSet {
                    name: format!("synthetic hard preset, {name}, 32x24"),
                    data: Data::DatabaseQueries { database: small.join("ref"), queries: small.join("query"), loops },
                });
            }
        }
    }
    // Queries that are not a walk (photos in no order): what the sequence rows cost there.
    let mut shuffled = Vec::new();
    for set in &sets {
        if set.name.starts_with("Gardens Point 64x48")
            || set.name == "synthetic hard preset, night lap against first lap"
        {
            let folder = tmp.join(format!("shuffled_{}", shuffled.len()));
            let data = with_shuffled_queries(&set.data, 7, &folder)?;
            shuffled.push(DevSet { name: format!("{}, queries shuffled", set.name), data });
        }
    }
    sets.extend(shuffled);
    Ok(sets)
}

/// A database/query set cut from the sequence at `sequence` (replay order): its frames `database`
/// written to `out/ref` and its frames `queries`, in the order given, to `out/query`, each numbered
/// from 0 (but those without a pose), and `out/loops.csv` listing for each query every database
/// frame within the default pose rule, however recent (a lap's last frames are where the next one
/// starts).
fn cut_database_and_queries(
    sequence: &Path,
    database: &[usize],
    queries: &[usize],
    out: &Path,
) -> Result<(PathBuf, PathBuf, PathBuf)> {
    let frames: Vec<_> = ecm_lcd::io::open_source(sequence, None)?.collect::<Result<_>>()?;
    let stamps: Vec<_> = frames.iter().map(|f| f.stamp).collect();
    let groundtruth = ecm_lcd::io::tum::read_groundtruth(&sequence.join("groundtruth.txt"))?;
    let any_age = ecm_lcd::eval::PoseLoopCriteria { min_gap_s: 0.0, ..Default::default() };
    let truth = ecm_lcd::eval::loop_truth_from_poses(&stamps, &groundtruth, &any_age);
    // A loops file cannot say "unknown": frames without a pose are left out of the queries.
    let queries: Vec<usize> = queries.iter().copied().filter(|&q| truth.matches(q).is_some()).collect();
    let (database_dir, queries_dir) = (out.join("ref"), out.join("query"));
    std::fs::create_dir_all(&database_dir)?;
    std::fs::create_dir_all(&queries_dir)?;
    for (index, &frame) in database.iter().enumerate() {
        frames[frame].image.save(database_dir.join(format!("{index:04}.png")))?;
    }
    for (index, &frame) in queries.iter().enumerate() {
        frames[frame].image.save(queries_dir.join(format!("{index:04}.png")))?;
    }
    // Each query's true matches among the database frames, numbered as written.
    let mut cut = LoopTruth::default();
    for (q, &frame) in queries.iter().enumerate() {
        for matched in truth.matches(frame).into_iter().flatten() {
            if let Some(index) = database.iter().position(|d| d == matched) {
                cut.insert(q, index);
            }
        }
    }
    let loops_path = out.join("loops.csv");
    write_loops(&cut, queries.len(), &loops_path)?;
    Ok((database_dir, queries_dir, loops_path))
}

/// `ACCURACY_CUTS=1`: more database/query cuts of the hard preset (walks along a part of the
/// database, and laps sampled unlike it).
fn extra_cuts() -> bool {
    std::env::var_os("ACCURACY_CUTS").is_some()
}

/// The loops file of `truth` for `queries` queries.
fn write_loops(truth: &LoopTruth, queries: usize, path: &Path) -> Result<()> {
    let mut loops = String::new();
    for query in 0..queries {
        let matches: Vec<String> = truth.matches(query).into_iter().flatten().map(usize::to_string).collect();
        loops.push_str(&format!("{query},{}\n", matches.join(" ")));
    }
    Ok(std::fs::write(path, loops)?)
}

/// The database/query set `data` with its queries in a seeded random order (copied to `out/query`
/// under new names, the loops file renumbered to `out/loops.csv`): queries that are not a walk.
fn with_shuffled_queries(data: &Data, seed: u64, out: &Path) -> Result<Data> {
    let Data::DatabaseQueries { database, queries, loops } = data else {
        anyhow::bail!("only a database/query set has queries to shuffle");
    };
    let paths = images_in_name_order(queries)?;
    let mut order: Vec<usize> = (0..paths.len()).collect();
    order.shuffle(&mut StdRng::seed_from_u64(seed));
    let queries_dir = out.join("query");
    std::fs::create_dir_all(&queries_dir)?;
    for (index, &from) in order.iter().enumerate() {
        let extension = paths[from].extension().context("image extension")?;
        std::fs::copy(&paths[from], queries_dir.join(format!("{index:04}")).with_extension(extension))?;
    }
    let loops_path = out.join("loops.csv");
    write_loops(&read_loops(loops)?.between(order, 0..usize::MAX), paths.len(), &loops_path)?;
    Ok(Data::DatabaseQueries { database: database.clone(), queries: queries_dir, loops: loops_path })
}

/// What one configuration measured on one set.
struct Row {
    metrics: Metrics,
    ms_per_keyframe: f64,
    /// Mean geometric verification time per keyframe (0 when off; `None` where not timed: the
    /// database/query mode times whole images).
    verification_ms: Option<f64>,
    /// The detector's default score threshold.
    min_score: f32,
    /// Candidates of a replayed sequence with its ground-truth poses (none for database/query sets).
    candidates: Vec<ecm_lcd::types::LoopCandidate>,
    groundtruth: Vec<(ecm_lcd::types::Stamp, nalgebra::Isometry3<f64>)>,
}

/// One configuration on one set; `tracker_poses`: a trajectory file whose poses the frames carry
/// (`replay --poses`).
fn measure(
    set: &DevSet,
    overrides: &[(&str, &str)],
    tracker_poses: Option<&Path>,
    weights: &Resolved,
) -> Result<(Row, usize)> {
    let mut params = Params::default();
    let set_overrides: &[(&str, &str)] = match &set.data {
        Data::Sequence(s, _) => s.overrides,
        Data::DatabaseQueries { .. } => &[],
    };
    for (k, v) in set_overrides.iter().chain(overrides) {
        params.set_from_str(k, v).map_err(anyhow::Error::msg)?;
    }
    // As `ecm-lcd eval` scores against poses: no match younger than the truth's gap.
    if let Data::Sequence(s, None) = &set.data {
        s.criteria.exclude_younger_than_the_gap(&mut params)?;
    }
    let threshold = params.detector().threshold;
    let consistent_reports_only = params.detector().consistency_queries > 1;
    let mut pipeline = Pipeline::with_weights(params, weights.clone())?;
    let mut row = Row {
        metrics: Metrics::default(),
        ms_per_keyframe: 0.0,
        verification_ms: None,
        min_score: 0.0,
        candidates: Vec::new(),
        groundtruth: Vec::new(),
    };
    let (results, truth) = match &set.data {
        Data::DatabaseQueries { database, queries, loops } => {
            let run = run_database_queries(&mut pipeline, database, queries, &Default::default(), false)?;
            row.ms_per_keyframe = run.per_image_ms;
            (run.results, read_loops(loops)?)
        }
        Data::Sequence(s, loops) => {
            let topics = ecm_lcd::io::Topics { poses: tracker_poses.map(Path::to_path_buf), ..Default::default() };
            let run = run_source(&mut pipeline, &s.path, &topics, false)?;
            let truth = match loops {
                Some(loops) => read_loops(loops)?,
                None => {
                    row.groundtruth = ecm_lcd::io::tum::read_groundtruth(&s.path.join("groundtruth.txt"))?;
                    ecm_lcd::eval::loop_truth_from_poses(&run.frame_stamps, &row.groundtruth, &s.criteria)
                }
            };
            let t = run.mean();
            row.ms_per_keyframe = t.network_ms + t.descriptor_ms + t.detector_ms + t.verification_ms;
            row.verification_ms = Some(t.verification_ms);
            row.candidates = run.candidates.clone();
            // Evaluation's best match ignores temporal consistency, which acts on reports.
            let results = if consistent_reports_only { run.reported_results() } else { run.query_results() };
            (results, truth)
        }
    };
    let min_score = match threshold {
        ecm_lcd::detector::Threshold::MinScore(s) => s,
        ecm_lcd::detector::Threshold::MaxDistance(_) => anyhow::bail!("the table assumes a score threshold"),
    };
    row.metrics = evaluate(&results, &truth)?;
    row.min_score = min_score;
    Ok((row, pipeline.detector().row_bytes()))
}

fn main() -> Result<()> {
    let (dir, sequences) = common::start()?;
    let mut sets = dev_sets(dir.path(), sequences)?;
    // Narrow to some sets while exploring: ACCURACY_SETS="TUM fr3,synthetic 600" (parts of names).
    if let Ok(wanted) = std::env::var("ACCURACY_SETS") {
        sets.retain(|set| wanted.split(',').any(|part| set.name.contains(part.trim())));
    }
    let weights = resolve::resolve(None)?;
    let sequence_length = "10";
    let defaults = Params::default();
    println!(
        "Defaults: descriptor {}, centring on the history {}, threshold {:?}; sequence rows: detector.sequence.length {sequence_length}.",
        defaults.descriptor_mode(),
        defaults.detector().centre_on_history,
        defaults.detector().threshold
    );
    println!();
    // Narrow the table while exploring: ACCURACY_ARCHES=mobilenetv2 ACCURACY_MODES=power,regional.
    let list = |var: &str, all: &[&str]| -> Vec<String> {
        std::env::var(var)
            .map(|v| v.split(',').map(str::to_string).collect())
            .unwrap_or_else(|_| all.iter().map(|s| s.to_string()).collect())
    };
    // Extra parameters on every row: ACCURACY_PARAMS=descriptor.projection=p.safetensors;detector.min_score=0.9
    let extra: Vec<(String, String)> = std::env::var("ACCURACY_PARAMS")
        .map(|v| {
            v.split(';')
                .filter_map(|a| a.split_once('='))
                .map(|(n, v)| (n.trim().to_string(), v.trim().to_string()))
                .collect()
        })
        .unwrap_or_default();
    let centring = list("ACCURACY_CENTRED", &["false", "true"]);
    let arches = list("ACCURACY_ARCHES", ecm_lcd::config::ARCHES);
    let modes = list("ACCURACY_MODES", &ecm_lcd::descriptor::DescriptorMode::NAMES);
    println!("| data | network | descriptor | centred | policy | queries (with loop) | recall@1 | recall@100%P | AP | P / R at threshold | highest false score | bytes/keyframe | ms/keyframe |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for set in &sets {
        for (arch, mode) in arches.iter().flat_map(|a| modes.iter().map(move |m| (a.as_str(), m.as_str()))) {
            for centred in centring.iter().map(String::as_str) {
                if mode == "paper" && centred == "true" {
                    continue; // centring leaves the paper's descriptor alone
                }
                let default_row = matches!(set.data, Data::DatabaseQueries { .. });
                let policies = [("single", "1"), ("sequence", sequence_length), ("default", "0")];
                for (policy, length) in policies.into_iter().take(if default_row { 3 } else { 2 }) {
                    let mut overrides = vec![
                        ("arch", arch),
                        ("descriptor.mode", mode),
                        ("detector.centre_on_history", centred),
                        ("detector.sequence.length", length),
                    ];
                    overrides.extend(extra.iter().map(|(n, v)| (n.as_str(), v.as_str())));
                    let (row, bytes) = measure(set, &overrides, None, &weights)?;
                    // Exploring a threshold: ACCURACY_THRESHOLDS=0.88,0.9 prints P / R at each to stderr.
                    if let Ok(list) = std::env::var("ACCURACY_THRESHOLDS") {
                        let at: Vec<String> = list
                            .split(',')
                            .map(|t| {
                                let t: f32 = t.parse().unwrap_or(1.0);
                                let (p, r) = row
                                    .metrics
                                    .at_threshold(t)
                                    .map_or((None, Some(0.0)), |p| (Some(p.precision), Some(p.recall)));
                                format!("{t}: {}/{}", common::figure(p), common::figure(r))
                            })
                            .collect();
                        eprintln!("{} {arch} {mode} centred {centred} {policy}: {}", set.name, at.join("  "));
                    }
                    let f = common::figure;
                    let m = &row.metrics;
                    // Nothing above the threshold: precision undefined, recall 0.
                    let (precision, recall) = m
                        .at_threshold(row.min_score)
                        .map_or((None, Some(0.0)), |p| (Some(p.precision), Some(p.recall)));
                    println!(
                        "| {} | {arch} | {mode} | {} | {policy} | {} ({}) | {} | {} | {} | {} / {} | {} | {bytes} | {:.1} |",
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
    if std::env::var_os("ACCURACY_SKIP_VERIFICATION").is_some() {
        return Ok(());
    }
    let extra: Vec<(&str, &str)> = extra.iter().map(|(n, v)| (n.as_str(), v.as_str())).collect();
    verification_table(&sets, &weights, &extra)
}

/// Geometric verification on each set: retrieval at a permissive threshold (every top-1 match is a
/// candidate), then the same with verification on. TUM sets use the published fr3 intrinsics and the
/// synthetic set its renderer's camera (so the relative pose is estimated too); Gardens Point runs
/// without intrinsics. `extra`: parameters set first on every row.
fn verification_table(sets: &[DevSet], weights: &Resolved, extra: &[(&str, &str)]) -> Result<()> {
    println!();
    println!("Geometric verification (`verification.mode`), every top-1 match a candidate (`detector.min_score` 0):");
    println!();
    println!("| data | intrinsics | true top-1 matches of retrieval | true loops after verification | false top-1 matches | false loops after verification | precision after | verification ms/keyframe | relative pose: median rotation error (deg) / translation direction error (deg) / metric translation error, pairs |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for set in sets {
        if (set.name.starts_with("TUM") && set.name.contains("64x48")) || set.name.contains("32x24") {
            // Too small for ORB, and the intrinsics (TUM's, the renderer's) are those of the
            // full-size frames.
            continue;
        }
        if set.name.ends_with("queries shuffled") {
            continue; // the walk's images in another order
        }
        let tum = set.name.starts_with("TUM");
        // The synthetic camera: focal length from the scene, principal point at the image centre
        // (pixel index coordinates).
        let synthetic = if set.name.contains("hard") {
            ecm_lcd::synth::SynthConfig::hard()
        } else {
            ecm_lcd::synth::SynthConfig::default()
        };
        let focal = ecm_lcd::synth::Scene::new(synthetic.clone())?.focal_length().to_string();
        let (cx, cy) =
            ((synthetic.width as f64 / 2.0 - 0.5).to_string(), (synthetic.height as f64 / 2.0 - 0.5).to_string());
        let synthetic_camera = [
            ("camera.fx", focal.as_str()),
            ("camera.fy", &focal),
            ("camera.cx", &cx),
            ("camera.cy", &cy),
            ("verification.mode", "on"),
        ];
        let verification: &[(&str, &str)] = if tum {
            &[("camera.preset", "tum_fr3"), ("verification.mode", "on")]
        } else if set.name.starts_with("synthetic") {
            &synthetic_camera
        } else {
            &[("verification.mode", "on")]
        };
        let permissive: Vec<(&str, &str)> = extra.iter().copied().chain([("detector.min_score", "0")]).collect();
        let unverified: Vec<(&str, &str)> = permissive.iter().copied().chain([("verification.mode", "off")]).collect();
        let (before, _) = measure(set, &unverified, None, weights)?;
        let overrides: Vec<(&str, &str)> = permissive.iter().chain(verification).copied().collect();
        print_verification_row(&set.name, &before, &measure(set, &overrides, None, weights)?.0, tum);
        // XFeat instead of ORB, where its weights are given: XFEAT_WEIGHTS=.../xfeat.pt.
        let xfeat = std::env::var("XFEAT_WEIGHTS").ok();
        let learned: Option<Vec<(&str, &str)>> = xfeat.as_deref().map(|xfeat| {
            overrides
                .iter()
                .copied()
                .chain([("verification.local_features", "xfeat"), ("verification.xfeat_weights", xfeat)])
                .collect()
        });
        if let Some(learned) = &learned {
            let name = format!("{} + `verification.local_features` xfeat", set.name);
            print_verification_row(&name, &before, &measure(set, learned, None, weights)?.0, tum);
            let more: Vec<(&str, &str)> = learned.iter().copied().chain([("verification.features", "1500")]).collect();
            let name = format!("{name}, `verification.features` 1500");
            print_verification_row(&name, &before, &measure(set, &more, None, weights)?.0, tum);
        }
        let Data::Sequence(sequence, _) = &set.data else { continue };
        let consistent: Vec<(&str, &str)> = overrides.iter().copied().chain([CONSISTENCY]).collect();
        let name = format!("{} + `detector.consistency.queries` 2", set.name);
        print_verification_row(&name, &before, &measure(set, &consistent, None, weights)?.0, tum);
        let dropping: Vec<(&str, &str)> = consistent.iter().copied().chain([DROPPING]).collect();
        let name = format!("{name}, `detector.consistency.delayed` false");
        print_verification_row(&name, &before, &measure(set, &dropping, None, weights)?.0, tum);
        let checked_row = |name: String, overrides: &[(&str, &str)], odometry: &Path| -> Result<()> {
            let checked: Vec<(&str, &str)> =
                overrides.iter().copied().chain([("verification.max_drift", "0.1")]).collect();
            let name = format!("{name} + odometry check (`max_drift` 0.1, {})", odometry_source(odometry));
            print_verification_row(&name, &before, &measure(set, &checked, Some(odometry), weights)?.0, tum);
            // And the verified relative rotation against the tracker's (the synthetic odometry drifts
            // 1 degree per metre in heading).
            let rotation: Vec<(&str, &str)> =
                checked.iter().copied().chain([("verification.max_rotation_drift", "1.5")]).collect();
            let name = format!("{name}, `max_rotation_drift` 1.5");
            print_verification_row(&name, &before, &measure(set, &rotation, Some(odometry), weights)?.0, tum);
            // And temporal consistency (DBoW2's, before verification): a match is tried only when
            // the previous keyframe's best match lies near it.
            let consistent: Vec<(&str, &str)> = rotation.iter().copied().chain([CONSISTENCY]).collect();
            let name = format!("{name}, `detector.consistency.queries` 2");
            print_verification_row(&name, &before, &measure(set, &consistent, Some(odometry), weights)?.0, tum);
            let dropping: Vec<(&str, &str)> = consistent.iter().copied().chain([DROPPING]).collect();
            let name = format!("{name}, `detector.consistency.delayed` false");
            print_verification_row(&name, &before, &measure(set, &dropping, Some(odometry), weights)?.0, tum);
            Ok(())
        };
        if set.name.starts_with("synthetic") {
            // The synthetic sequences carry a drifted odometry (`odometry.txt`): the tracker poses of
            // the odometry check, with equalised ORB (which alone lets look-alike rooms through).
            let equalised: Vec<(&str, &str)> =
                overrides.iter().copied().chain([("verification.equalise", "true")]).collect();
            let name = format!("{} + `verification.equalise`", set.name);
            print_verification_row(&name, &before, &measure(set, &equalised, None, weights)?.0, tum);
            checked_row(name, &equalised, &sequence.path.join("odometry.txt"))?;
            if let Some(learned) = &learned {
                let name = format!("{} + `verification.local_features` xfeat", set.name);
                checked_row(name, learned, &sequence.path.join("odometry.txt"))?;
            }
            // The same sequence rendered with depth: metric relative poses by PnP. On the hard
            // preset with its best checks: are the loops the place rule counts as wrong right as
            // pose-graph edges?
            let hard = set.name.contains("hard");
            let (base, name, checks): (SynthConfig, &'static str, &[(&str, &str)]) = if hard {
                (
                    SynthConfig::hard(),
                    "synthetic hard preset, with depth (`depth.txt`) + `verification.equalise` + odometry check \
                     (`max_drift` 0.1, `max_rotation_drift` 1.5, `--poses` the synthetic odometry)",
                    &[
                        ("verification.equalise", "true"),
                        ("verification.max_drift", "0.1"),
                        ("verification.max_rotation_drift", "1.5"),
                    ],
                )
            } else {
                (SynthConfig::default(), "synthetic 600 frames, 3 laps, with depth (`depth.txt`)", &[])
            };
            let dir = tempfile::tempdir()?;
            let scene = ecm_lcd::synth::Scene::new(SynthConfig { depth: true, ..common::synthetic_sequence(base) })?;
            ecm_lcd::synth::write_tum_folder(&scene, dir.path())?;
            let with_depth = DevSet {
                name: name.into(),
                data: Data::Sequence(
                    common::EvalSet {
                        name,
                        path: dir.path().to_path_buf(),
                        criteria: sequence.criteria,
                        overrides: sequence.overrides,
                    },
                    None,
                ),
            };
            let checked: Vec<(&str, &str)> = overrides.iter().chain(checks).copied().collect();
            let odometry = dir.path().join("odometry.txt");
            let tracker_poses = hard.then_some(odometry.as_path());
            print_verification_row(name, &before, &measure(&with_depth, &checked, tracker_poses, weights)?.0, tum);
            if hard {
                let consistent: Vec<(&str, &str)> = checked.iter().copied().chain([CONSISTENCY]).collect();
                let name = format!("{name}, `detector.consistency.queries` 2");
                let row = measure(&with_depth, &consistent, tracker_poses, weights)?.0;
                print_verification_row(&name, &before, &row, tum);
                let dropping: Vec<(&str, &str)> = consistent.iter().copied().chain([DROPPING]).collect();
                let name = format!("{name}, `detector.consistency.delayed` false");
                let row = measure(&with_depth, &dropping, tracker_poses, weights)?.0;
                print_verification_row(&name, &before, &row, tum);
            }
        } else if tum && sequence.path.join("groundtruth.txt").is_file() {
            // Real frames: the ground truth with `synth`'s drift injected as the tracker's poses.
            let mut truth = ecm_lcd::io::tum::read_groundtruth(&sequence.path.join("groundtruth.txt"))?;
            truth.sort_by_key(|(stamp, _)| *stamp);
            let poses: Vec<_> = truth.iter().map(|(_, pose)| *pose).collect();
            let drifted = ecm_lcd::synth::OdometryDrift::default().apply(&poses, 1);
            let odometry = sequence.path.join("drifted_groundtruth.txt");
            let stamped: Vec<_> = truth.iter().map(|(stamp, _)| *stamp).zip(drifted).collect();
            ecm_lcd::io::tum::write_trajectory(&odometry, &stamped)?;
            checked_row(set.name.clone(), &overrides, &odometry)?;
            // Half the features the frame size gives TUM's 640x480 frames (the fixed count before):
            // fewer matches on the wide-baseline revisits.
            let fewer: Vec<(&str, &str)> =
                overrides.iter().copied().chain([("verification.features", "500")]).collect();
            let name = format!("{} + `verification.features` 500", set.name);
            print_verification_row(&name, &before, &measure(set, &fewer, None, weights)?.0, tum);
            let consistent: Vec<(&str, &str)> = fewer.iter().copied().chain([CONSISTENCY]).collect();
            let name = format!("{name}, `detector.consistency.queries` 2");
            print_verification_row(&name, &before, &measure(set, &consistent, None, weights)?.0, tum);
            checked_row(format!("{} + `verification.features` 500", set.name), &fewer, &odometry)?;
            if let Some(learned) = &learned {
                checked_row(format!("{} + `verification.local_features` xfeat", set.name), learned, &odometry)?;
            }
        }
    }
    Ok(())
}

/// Where the tracker poses of an odometry-check row come from, for its name.
fn odometry_source(path: &Path) -> &'static str {
    if path.ends_with("odometry.txt") {
        "`--poses` the synthetic odometry"
    } else {
        "`--poses` the ground truth with the synthetic odometry's drift"
    }
}

/// Temporal consistency on the verification table's rows that measure it: each match must lie within
/// `detector.consistency.window` keyframes of the previous keyframe's best match.
const CONSISTENCY: (&str, &str) = ("detector.consistency.queries", "2");

/// Temporal consistency as DBoW2 applies it: a match held back is dropped, not reported late.
const DROPPING: (&str, &str) = ("detector.consistency.delayed", "false");

/// One row of the verification table: `before` without verification, `after` with it.
fn print_verification_row(name: &str, before: &Row, after: &Row, tum: bool) {
    let (found_before, false_before) = (before.metrics.true_reports, before.metrics.false_reports);
    let (found_after, false_after) = (after.metrics.true_reports, after.metrics.false_reports);
    let precision = if found_after + false_after > 0 {
        format!("{:.3}", found_after as f64 / (found_after + false_after) as f64)
    } else {
        "-".into()
    };
    println!(
        "| {} | {} | {found_before} | {found_after} | {false_before} | {false_after} | {precision} | {} | {} |",
        name,
        if tum {
            "TUM fr3"
        } else if name.starts_with("synthetic") {
            "synthetic camera"
        } else {
            "none"
        },
        after.verification_ms.map_or("-".into(), |ms| format!("{ms:.1}")),
        pose_errors(after)
    );
}

/// Median rotation and translation-direction errors of the estimated relative poses against the
/// ground truth's, over the verified candidates of a sequence with poses.
fn pose_errors(row: &Row) -> String {
    let pose_at = |stamp: ecm_lcd::types::Stamp| {
        row.groundtruth.iter().find(|(s, _)| (s.nanos - stamp.nanos).abs() < 50_000_000).map(|(_, p)| *p)
    };
    let mut rotation = Vec::new();
    let mut direction = Vec::new();
    let mut baseline = Vec::new();
    let mut true_rotation = Vec::new();
    // Metric translation errors, and each metric pose's errors in units of its covariance.
    let mut metric_error = Vec::new();
    // The metric errors (cm, degrees) of pairs outside the place rule (the truth's 1 m and 30
    // degrees): are the loops it counts as wrong worse pose-graph edges than the others?
    let place = ecm_lcd::eval::PoseLoopCriteria::default();
    let mut outside = Vec::new();
    let mut normalised = Vec::new();
    for c in &row.candidates {
        let (Some(pose), Some(query), Some(matched)) =
            (c.verified.and_then(|v| v.pose), pose_at(c.query_stamp), pose_at(c.match_stamp))
        else {
            continue;
        };
        // World poses of the cameras: the query camera in the match camera's frame.
        let truth = matched.inverse() * query;
        rotation.push(pose.rotation.angle_to(&truth.rotation).to_degrees());
        baseline.push(truth.translation.vector.norm());
        true_rotation.push(truth.rotation.angle().to_degrees());
        if pose.metric {
            let error_cm = 100.0 * (pose.translation - truth.translation.vector).norm();
            metric_error.push(error_cm);
            let axes_deg = (truth.rotation * nalgebra::Vector3::z()).angle(&nalgebra::Vector3::z()).to_degrees();
            if truth.translation.vector.norm() > place.max_distance_m || axes_deg > place.max_angle_deg {
                outside.push(format!("{error_cm:.0}/{:.1}", pose.rotation.angle_to(&truth.rotation).to_degrees()));
            }
        }
        normalised.extend(pose.normalised_squared_errors(&truth));
        if truth.translation.vector.norm() > 0.05 {
            direction.push(pose.translation.angle(&truth.translation.vector).to_degrees());
        }
    }
    if rotation.is_empty() {
        return "-".into();
    }
    let direction = if direction.is_empty() { "-".into() } else { format!("{:.1}", median(&mut direction)) };
    let metric = if metric_error.is_empty() {
        String::new()
    } else {
        let outside = if outside.is_empty() {
            String::new()
        } else {
            format!("; outside the place rule, cm/deg: {}", outside.join(", "))
        };
        format!(" / {:.1} cm ({} metric{outside})", median(&mut metric_error), metric_error.len())
    };
    let calibration = if normalised.is_empty() {
        String::new()
    } else {
        // Chi-square with 3 degrees of freedom: median 2.37, 95% point 7.81.
        let share = |count: usize| 100.0 * count as f64 / normalised.len() as f64;
        let (mut rotation_nees, mut translation_nees): (Vec<f64>, Vec<f64>) = normalised.iter().copied().unzip();
        format!(
            "; against the metric covariance, of {}: median normalised squared error rotation {:.1}, translation \
             {:.1} (2.4 if right), inside its 95% ellipsoid {:.0}% / {:.0}%",
            normalised.len(),
            median(&mut rotation_nees),
            median(&mut translation_nees),
            share(normalised.iter().filter(|(r, _)| *r <= 7.815).count()),
            share(normalised.iter().filter(|(_, t)| *t <= 7.815).count()),
        )
    };
    format!(
        "{:.2} / {direction}{metric} ({} pairs, {} with over 5 cm baseline; median true rotation {:.1} deg, baseline {:.2} m{calibration})",
        median(&mut rotation),
        rotation.len(),
        baseline.iter().filter(|&&b| b > 0.05).count(),
        median(&mut true_rotation),
        median(&mut baseline),
    )
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}
