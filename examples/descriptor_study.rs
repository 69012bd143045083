//! Which network tap and aggregation carry place best: every combination on the real development
//! sets and the hard synthetic preset (as a sequence, and its second and third laps as queries
//! against its first, the database/query mode), in memory (maps computed once per image). A
//! program that measures and prints.
//!
//!     cargo run --release --example descriptor_study [-- ARCH SIZE]
//!
//! Environment: `STUDY_TAPS=12,16` (block indexes; default the last few), `STUDY_AGGS=grid3-mac,...`,
//! and `STUDY_CALIBRATE="blocks.16 grid3-mac"` to print, pooled over every set, the recall at 100%
//! precision of one threshold on the raw score and on per-query calibrated statistics (z-score,
//! margin over the second-best place, ...). Post-processing: `l2`, `pl2` (power first), a trailing
//! `c` centres on the database mean, `l2pN` projects on N principal axes learned from synthetic
//! frames, `l2hN` on N axes learned from the database itself, `l2qK` stores each value with K
//! levels (`l2qsgn`: its sign), `l2dK` corrects each score for hubness (less half the reference's and
//! half the query's mean K best scores, as CSLS does), `l2xK` scores a grid against the reference
//! shifted by up to K columns too and keeps the best (`STUDY_SHIFT_FILL=f`: a cell shifted out counts
//! as cosine f; unset, the overlap's mean), `l2eK` expands the query with its K best references
//! weighted by cosine^alpha (alpha-QE; `STUDY_QE_ALPHA`, default 3) and scores again, `l2fK` lets
//! the expanded query pick among the `STUDY_QE_SHORTLIST` (10) best but keeps the raw score, `l2bK`
//! adds to each reference its K nearest others weighted the same way (database-side augmentation) and
//! `l2tK` its K neighbours in time on each side; `STUDY_POSTS=l2,l2q8` picks them. `STUDY_PHOTO=equalise` (or
//! `stretch`, `gamma`, `standardise`) normalises every image's brightness before the network, and
//! `STUDY_DUMP=FILE` appends each calibrated query's scores and true matches as JSON lines.
//! `STUDY_COMBOS="12:grid4-mac+16:grid2-mac;..."` also measures combinations of taps (each part
//! unit-normalised, then concatenated; `16:grid3-mac*0.5` weighs a part), as `f32` and six-level codes.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use ecm_lcd::descriptor::{grid_cell, l2_normalise, power_normalise, Projection};
use ecm_lcd::eval::{
    evaluate, loop_truth_from_poses, read_loops, revisit::write_two_pass, LoopTruth, PoseLoopCriteria, QueryResult,
};
use ecm_lcd::io::open_source;
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::model::embedder::Embedder;
use ecm_lcd::model::weights::resolve;
use ecm_lcd::model::{Arch, Tap};
use ecm_lcd::preprocess::read_image;
use ecm_lcd::types::{FeatureMap, Stamp};
use image::RgbImage;

/// Database images, query images, and for each query the database indexes it may match.
struct Set {
    name: String,
    database: Vec<RgbImage>,
    queries: Vec<RgbImage>,
    /// `None`: every database image; `Some(k)`: database images `0..k` (a sequence's history).
    eligible: Vec<Option<usize>>,
    truth: LoopTruth,
}

fn degrade(image: &RgbImage) -> RgbImage {
    let small = image::imageops::resize(image, 64, 48, image::imageops::FilterType::Triangle);
    let gray = image::imageops::grayscale(&small);
    let gray = image::DynamicImage::ImageLuma8(gray).to_rgb8();
    image::imageops::resize(&gray, image.width(), image.height(), image::imageops::FilterType::Triangle)
}

fn sets(shared: &Path, tmp: &Path) -> Result<Vec<Set>> {
    let mut out = Vec::new();
    let gp = shared.join("data/real/gardens_point_day_night");
    let read_dir = |dir: &Path| -> Result<Vec<RgbImage>> {
        ecm_lcd::eval::images_in_name_order(dir)?.iter().map(|p| read_image(p)).collect()
    };
    let (database, queries) = (read_dir(&gp.join("ref"))?, read_dir(&gp.join("query"))?);
    let truth = read_loops(&gp.join("loops.csv"))?;
    out.push(Set {
        name: "gardens point".into(),
        eligible: vec![None; queries.len()],
        database: database.clone(),
        queries: queries.clone(),
        truth: truth.clone(),
    });
    out.push(Set {
        name: "gardens point low-res gray".into(),
        eligible: vec![None; queries.len()],
        database: database.iter().map(degrade).collect(),
        queries: queries.iter().map(degrade).collect(),
        truth,
    });

    // Sequences: every frame is a query against the frames at least `gap` before it.
    let orbit = shared.join("data/real/tum_fr3_desk_orbit");
    let frames = read_dir(&orbit.join("rgb"))?;
    let truth = read_loops(&orbit.join("loops.csv"))?;
    let eligible = (0..frames.len()).map(|i| Some(i.saturating_sub(3))).collect::<Vec<_>>();
    out.push(Set { name: "tum desk orbit".into(), database: frames.clone(), queries: frames, eligible, truth });

    let two_pass = tmp.join("fr3_two_pass");
    write_two_pass(&shared.join("data/tum/fr3_long_office_household"), &two_pass, 1.0, 0.05)?;
    let frames: Vec<_> = open_source(&two_pass, None)?.collect::<Result<_>>()?;
    let stamps: Vec<Stamp> = frames.iter().map(|f| f.stamp).collect();
    let criteria = PoseLoopCriteria { min_gap_s: 2.0, ..PoseLoopCriteria::default() };
    let truth = loop_truth_from_poses(&stamps, &read_groundtruth(&two_pass.join("groundtruth.txt"))?, &criteria);
    let images: Vec<RgbImage> = frames.into_iter().map(|f| f.image).collect();
    let eligible = (0..images.len()).map(|i| Some(i.saturating_sub(2))).collect::<Vec<_>>();
    out.push(Set { name: "tum fr3 two-pass".into(), database: images.clone(), queries: images, eligible, truth });

    // The hard synthetic preset, every second frame (2.5 Hz): queries against frames 10 s older.
    let hard = tmp.join("synthetic_hard");
    let config =
        ecm_lcd::synth::SynthConfig { frames: 600, laps: 3, rate_hz: 5.0, ..ecm_lcd::synth::SynthConfig::hard() };
    ecm_lcd::synth::write_tum_folder(&ecm_lcd::synth::Scene::new(config)?, &hard)?;
    let frames: Vec<_> = open_source(&hard, None)?.step_by(2).collect::<Result<_>>()?;
    let stamps: Vec<Stamp> = frames.iter().map(|f| f.stamp).collect();
    let truth =
        loop_truth_from_poses(&stamps, &read_groundtruth(&hard.join("groundtruth.txt"))?, &PoseLoopCriteria::default());
    let images: Vec<RgbImage> = frames.into_iter().map(|f| f.image).collect();
    let eligible = (0..images.len()).map(|i| Some(i.saturating_sub(25))).collect::<Vec<_>>();
    // The same frames as database/query sets (the mode of a map built beforehand): the first lap is
    // the database, the second lap (at night) or the third (by day, offset) the queries; a query's
    // truth is every first-lap frame within the pose rule, however recent (the lap's end is its start).
    let lap = images.len() / 3;
    let any_age = PoseLoopCriteria { min_gap_s: 0.0, ..PoseLoopCriteria::default() };
    let any_age = loop_truth_from_poses(&stamps, &read_groundtruth(&hard.join("groundtruth.txt"))?, &any_age);
    for (name, laps) in [("synth hard db/query night", lap..2 * lap), ("synth hard db/query day", 2 * lap..3 * lap)] {
        out.push(Set {
            name: name.into(),
            database: images[..lap].to_vec(),
            queries: images[laps.clone()].to_vec(),
            eligible: vec![None; lap],
            truth: any_age.between(laps, 0..lap),
        });
    }
    out.push(Set { name: "synth hard".into(), database: images.clone(), queries: images, eligible, truth });
    Ok(out)
}

/// Per-channel aggregate of the map over the rows `r` and columns `c`.
fn pool(fm: &FeatureMap, rows: std::ops::Range<usize>, cols: std::ops::Range<usize>, how: &str) -> Vec<f32> {
    let plane = fm.height * fm.width;
    let n = (rows.len() * cols.len()) as f32;
    fm.data
        .chunks_exact(plane)
        .map(|ch| {
            let values =
                rows.clone().flat_map(|r| ch[r * fm.width + cols.start..r * fm.width + cols.end].iter().copied());
            match how {
                "gap" => values.sum::<f32>() / n,
                "gem" => (values.map(|x| x.max(0.0).powi(3)).sum::<f32>() / n).cbrt(),
                "mac" => values.fold(f32::NEG_INFINITY, f32::max),
                "abs" => values.map(f32::abs).sum::<f32>() / n,
                _ => unreachable!(),
            }
        })
        .collect()
}

/// R-MAC-style regions: the whole map and square regions at two more scales, each L2-normalised, summed.
fn rmac(fm: &FeatureMap, how: &str) -> Vec<f32> {
    let mut total = vec![0.0f32; fm.channels];
    let (h, w) = (fm.height, fm.width);
    for level in 1..=3usize {
        let side = (2 * h.min(w)) / (level + 1);
        let side = side.max(1);
        let steps_y = if h > side { level } else { 1 };
        let steps_x = if w > side { level + 1 } else { 1 };
        for sy in 0..steps_y {
            for sx in 0..steps_x {
                let y0 = if steps_y > 1 { sy * (h - side) / (steps_y - 1) } else { 0 };
                let x0 = if steps_x > 1 { sx * (w - side) / (steps_x - 1) } else { 0 };
                let (rows, cols) = if level == 1 { (0..h, 0..w) } else { (y0..y0 + side.min(h), x0..x0 + side.min(w)) };
                let mut v = pool(fm, rows, cols, how);
                l2_normalise(&mut v);
                total.iter_mut().zip(&v).for_each(|(t, x)| *t += x);
            }
        }
    }
    total
}

fn grid(fm: &FeatureMap, how: &str, cells: usize) -> Vec<f32> {
    let mut out = Vec::new();
    for gy in 0..cells {
        for gx in 0..cells {
            let mut v = pool(fm, grid_cell(fm.height, cells, gy), grid_cell(fm.width, cells, gx), how);
            power_normalise(&mut v);
            l2_normalise(&mut v);
            out.extend(v);
        }
    }
    out
}

fn aggregate(fm: &FeatureMap, agg: &str) -> Vec<f32> {
    let (kind, how) = agg.split_once('-').unwrap_or((agg, "gap"));
    match kind {
        "global" => pool(fm, 0..fm.height, 0..fm.width, how),
        "rmac" => rmac(fm, how),
        "grid2" => grid(fm, how, 2),
        "grid3" => grid(fm, how, 3),
        "grid4" => grid(fm, how, 4),
        _ => unreachable!(),
    }
}

/// The best over horizontal shifts of up to `shifts` cells of a grid descriptor (`cells` x `cells`
/// unit cells, the whole L2-normalised): the mean cosine of the cells that overlap.
/// `fill`: the cosine a cell shifted out counts as (`None`: the mean of those that overlap).
fn shift_tolerant(query: &[f32], reference: &[f32], cells: usize, shifts: usize, fill: Option<f32>) -> f32 {
    let channels = query.len() / (cells * cells);
    let (query_cells, reference_cells): (Vec<&[f32]>, Vec<&[f32]>) =
        (query.chunks_exact(channels).collect(), reference.chunks_exact(channels).collect());
    let all = (cells * cells) as f32;
    let mut best = f32::NEG_INFINITY;
    for shift in -(shifts as isize)..=shifts as isize {
        let (mut sum, mut n) = (0.0f32, 0usize);
        for gy in 0..cells {
            for gx in 0..cells {
                let Some(rx) = gx.checked_add_signed(shift).filter(|&rx| rx < cells) else { continue };
                let (a, b) = (query_cells[gy * cells + gx], reference_cells[gy * cells + rx]);
                sum += a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
                n += 1;
            }
        }
        let score = match fill {
            Some(fill) => (sum * all + fill * (all - n as f32)) / all,
            None => sum * all / n as f32,
        };
        best = best.max(score);
    }
    best
}

fn cosine_scores(query: &[f32], database: &[Vec<f32>]) -> Vec<f32> {
    database.iter().map(|d| d.iter().zip(query).map(|(a, b)| a * b).sum()).collect()
}

/// Post-processing: `pl2` power + L2; `c` subtracts the database mean first (centring learned from
/// the history, no labels).
fn finish(mut raw: Vec<Vec<f32>>, post: &str, mean: Option<&[f32]>) -> Vec<Vec<f32>> {
    for v in &mut raw {
        if post.contains('p') {
            power_normalise(v);
        }
        l2_normalise(v);
        if let Some(m) = mean {
            v.iter_mut().zip(m).for_each(|(x, m)| *x -= m);
            l2_normalise(v);
        }
    }
    raw
}

/// `v` stored with `levels` uniform levels per value over +-2.5 RMS ("sgn": its signs), as the
/// reconstruction, L2-normalised. 8 levels take 3 bits; 6 levels pack three values in a byte.
fn quantised(v: &[f32], levels: &str) -> Vec<f32> {
    let mut out: Vec<f32> = if levels == "sgn" {
        v.iter().map(|x| if *x >= 0.0 { 1.0 } else { -1.0 }).collect()
    } else {
        let levels: f32 = levels.parse().unwrap();
        let rms = (v.iter().map(|x| x * x).sum::<f32>() / v.len() as f32).sqrt();
        let clip = 2.5 * rms;
        let step = 2.0 * clip / levels;
        v.iter().map(|x| ((x.clamp(-clip, clip - 1e-6) + clip) / step).floor() * step - clip + step / 2.0).collect()
    };
    l2_normalise(&mut out);
    out
}

fn mean_of(vs: &[Vec<f32>]) -> Vec<f32> {
    let mut m = vec![0.0; vs[0].len()];
    for v in vs {
        m.iter_mut().zip(v).for_each(|(a, b)| *a += b / vs.len() as f32);
    }
    m
}

/// Images of our own making to learn centring and whitening from: synthetic frames of several worlds.
fn learning_images() -> Result<Vec<RgbImage>> {
    let mut images = Vec::new();
    for seed in 11..17u64 {
        let base = if seed % 2 == 0 { ecm_lcd::synth::SynthConfig::hard() } else { Default::default() };
        let scene = ecm_lcd::synth::Scene::new(ecm_lcd::synth::SynthConfig { frames: 80, laps: 1, seed, ..base })?;
        images.extend((0..scene.len()).map(|i| scene.render(i)));
    }
    Ok(images)
}

/// Mean and PCA (whitened or not) learned from `vs`: the library's [`Projection`].
type Whitening = Projection;

fn learn_whitening(vs: &[Vec<f32>], dim: usize) -> Whitening {
    learn_projection(vs, dim, true)
}

/// PCA onto `dim` axes (at most the sample count minus one, and the descriptor's length); with `whiten`, unit variance per axis.
fn learn_projection(vs: &[Vec<f32>], dim: usize, whiten: bool) -> Whitening {
    Projection::learn(vs, dim.min(vs.len() - 1).min(vs[0].len()), whiten, "study").expect("descriptors to learn from")
}

fn whiten(w: &Whitening, v: &[f32]) -> Vec<f32> {
    w.apply(v)
}

fn main() -> Result<()> {
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    ecm_lcd::runtime::init_threads(None);
    let args: Vec<String> = std::env::args().collect();
    let arch: Arch = args.get(1).map(String::as_str).unwrap_or("ecmobilenet").parse()?;
    let size: usize = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(224);
    let shared = ecm_lcd::runtime::shared_dirs().into_iter().next().context("../shared is needed")?;
    let tmp = tempfile::tempdir()?;
    let mut sets = sets(&shared, tmp.path())?;
    if let Ok(how) = std::env::var("STUDY_PHOTO") {
        for set in &mut sets {
            for image in set.database.iter_mut().chain(set.queries.iter_mut()) {
                *image = photometric(image, &how);
            }
        }
    }
    let weights = resolve::resolve(None)?;
    let mut embedder = Embedder::new(weights.weights.for_arch(arch)?.network(false)?, size)?;
    // Multi-scale: `STUDY_SCALES=320,160` also runs the network at those input sizes, and each
    // aggregate becomes the sum of the unit aggregates at every size (the grid's cells cover the
    // same part of the image at each).
    let mut more_scales: Vec<Embedder> = std::env::var("STUDY_SCALES")
        .unwrap_or_default()
        .split(',')
        .filter(|s| !s.is_empty())
        .map(|s| Embedder::new(weights.weights.for_arch(arch)?.network(false)?, s.parse()?))
        .collect::<Result<_>>()?;
    let blocks = arch.spec().blocks().len();
    let taps_env = std::env::var("STUDY_TAPS")
        .unwrap_or_else(|_| format!("{},{},{},{},{}", blocks - 9, blocks - 6, blocks - 4, blocks - 2, blocks - 1));
    let mut taps: Vec<Tap> = taps_env.split(',').map(|t| t.parse().map(Tap::Block)).collect::<Result<_, _>>()?;
    taps.push(Tap::Head);
    let aggs: Vec<String> = std::env::var("STUDY_AGGS")
        .unwrap_or_else(|_| {
            "global-gap,global-gem,global-mac,rmac-mac,grid2-gap,grid2-mac,grid3-mac,grid4-mac,grid3-gem".into()
        })
        .split(',')
        .map(str::to_string)
        .collect();
    let aggs: Vec<&str> = aggs.iter().map(String::as_str).collect();
    let posts_env = std::env::var("STUDY_POSTS").unwrap_or_else(|_| "l2,l2c,l2p128,l2p256,l2h64,l2h128".into());
    let posts: Vec<&str> = posts_env.split(',').collect();
    // Query expansion's and database-side augmentation's weight exponent, and the expanded query's
    // shortlist (`l2fK`).
    let alpha: f32 = std::env::var("STUDY_QE_ALPHA").ok().and_then(|a| a.parse().ok()).unwrap_or(3.0);
    let shortlist: usize = std::env::var("STUDY_QE_SHORTLIST").ok().and_then(|a| a.parse().ok()).unwrap_or(10);
    let learning = learning_images()?;
    let learning_maps: Vec<Vec<FeatureMap>> =
        learning.iter().map(|i| embedder.tapped_maps(i, &taps)).collect::<Result<_>>()?;
    let mut whitenings: BTreeMap<(usize, &str), (Vec<f32>, Whitening, Whitening, Whitening)> = BTreeMap::new();
    for t in 0..taps.len() {
        for &agg in &aggs {
            let raw: Vec<Vec<f32>> = learning_maps.iter().map(|m| aggregate(&m[t], agg)).collect();
            let finished = finish(raw, "pl2", None);
            let mean = mean_of(&finished);
            let full = learn_projection(&finished, 256, false);
            let cut = |d: usize| Whitening { rows: full.rows.iter().take(d).cloned().collect(), ..full.clone() };
            whitenings.insert((t, agg), (mean, cut(64), cut(128), full));
        }
    }
    // Combinations of taps: `STUDY_COMBOS="12:grid2-mac+16:grid3-mac;..."`, each part unit-normalised
    // then concatenated with weight `w` (`16:grid3-mac*2`), measured with the `l2` and `l2q6` posts.
    let combos: Vec<Vec<(usize, String, f32)>> = std::env::var("STUDY_COMBOS")
        .unwrap_or_default()
        .split(';')
        .filter(|c| !c.is_empty())
        .map(|combo| {
            combo
                .split('+')
                .map(|part| {
                    let (part, weight) = part.split_once('*').unwrap_or((part, "1"));
                    let (block, agg) = part.split_once(':').context("combo part is BLOCK:AGG")?;
                    let tap = Tap::Block(block.parse()?);
                    let t = taps.iter().position(|x| *x == tap).context("combo block must be in STUDY_TAPS")?;
                    Ok((t, agg.to_string(), weight.parse()?))
                })
                .collect::<Result<Vec<_>>>()
        })
        .collect::<Result<_>>()?;
    let combined = |maps: &[FeatureMap], combo: &[(usize, String, f32)]| -> Vec<f32> {
        let mut out = Vec::new();
        for (t, agg, weight) in combo {
            let mut v = aggregate(&maps[*t], agg);
            l2_normalise(&mut v);
            out.extend(v.iter().map(|x| x * weight));
        }
        out
    };
    let mut calibration: Vec<CalibrationRecord> = Vec::new();
    // (tap, agg, post) -> per set (r@1, r@100P)
    let mut table: BTreeMap<(String, String, String), Vec<(f64, f64)>> = BTreeMap::new();
    for set in &sets {
        let maps = |embedder: &mut Embedder, images: &[RgbImage]| -> Result<Vec<Vec<FeatureMap>>> {
            images.iter().map(|i| embedder.tapped_maps(i, &taps)).collect()
        };
        let db_maps = maps(&mut embedder, &set.database)?;
        let q_maps = maps(&mut embedder, &set.queries)?;
        let mut db_scaled = Vec::new();
        let mut q_scaled = Vec::new();
        for scale in &mut more_scales {
            db_scaled.push(maps(scale, &set.database)?);
            q_scaled.push(maps(scale, &set.queries)?);
        }
        // One image's aggregate: `maps` its taps at the first size, `scaled` at the other sizes.
        let multi_scale = |maps: &[FeatureMap], scaled: &[&Vec<FeatureMap>], t: usize, agg: &str| {
            let mut total = aggregate(&maps[t], agg);
            if !scaled.is_empty() {
                l2_normalise(&mut total);
                for other in scaled {
                    let mut v = aggregate(&other[t], agg);
                    l2_normalise(&mut v);
                    total.iter_mut().zip(&v).for_each(|(a, b)| *a += b);
                }
            }
            total
        };
        for combo in &combos {
            let name: Vec<String> = combo.iter().map(|(t, agg, w)| format!("{}:{agg}*{w}", taps[*t])).collect();
            let db = finish(db_maps.iter().map(|m| combined(m, combo)).collect(), "l2", None);
            let q = finish(q_maps.iter().map(|m| combined(m, combo)).collect(), "l2", None);
            for post in ["l2", "l2q6"] {
                let coded = |vs: &[Vec<f32>]| -> Vec<Vec<f32>> {
                    vs.iter().map(|v| if post == "l2q6" { quantised(v, "6") } else { v.clone() }).collect()
                };
                let (db, q) = (coded(&db), coded(&q));
                let results: Vec<QueryResult> = q
                    .iter()
                    .enumerate()
                    .map(|(qi, qv)| {
                        let limit = set.eligible[qi].unwrap_or(db.len());
                        let best = (limit > 0).then(|| {
                            cosine_scores(qv, &db[..limit])
                                .into_iter()
                                .enumerate()
                                .fold((0, f32::NEG_INFINITY), |b, (i, s)| if s > b.1 { (i, s) } else { b })
                        });
                        QueryResult { query: qi, best }
                    })
                    .collect();
                let m = evaluate(&results, &set.truth)?;
                table
                    .entry((name.join("+"), format!("{}d", db[0].len()), post.to_string()))
                    .or_default()
                    .push((m.recall_at_1.unwrap_or(0.0), m.recall_at_100_precision.unwrap_or(0.0)));
            }
        }
        for (t, tap) in taps.iter().enumerate() {
            for &agg in &aggs {
                let per_image = |maps: &[Vec<FeatureMap>], scaled: &[Vec<Vec<FeatureMap>>]| -> Vec<Vec<f32>> {
                    (0..maps.len())
                        .map(|i| {
                            let others: Vec<&Vec<FeatureMap>> = scaled.iter().map(|s| &s[i]).collect();
                            multi_scale(&maps[i], &others, t, agg)
                        })
                        .collect()
                };
                let db_raw = per_image(&db_maps, &db_scaled);
                let q_raw = per_image(&q_maps, &q_scaled);
                let learned = &whitenings[&(t, agg)];
                for &post in &posts {
                    let (db, q) = if let Some(dim) = post.strip_prefix("l2p") {
                        // PCA learned from synthetic frames (no whitening).
                        let w = match dim {
                            "64" => &learned.1,
                            "128" => &learned.2,
                            _ => &learned.3,
                        };
                        let db: Vec<_> = finish(db_raw.clone(), "l2", None).iter().map(|v| whiten(w, v)).collect();
                        let q: Vec<_> = finish(q_raw.clone(), "l2", None).iter().map(|v| whiten(w, v)).collect();
                        (db, q)
                    } else if let Some(dim) = post.strip_prefix("l2h") {
                        // PCA learned from the database itself (the history), no whitening.
                        let dbf = finish(db_raw.clone(), "l2", None);
                        let w = learn_projection(&dbf, dim.parse().unwrap(), false);
                        (
                            dbf.iter().map(|v| whiten(&w, v)).collect(),
                            finish(q_raw.clone(), "l2", None).iter().map(|v| whiten(&w, v)).collect(),
                        )
                    } else if let Some(dim) = post.strip_prefix("pl2w") {
                        let w = match dim {
                            "64" => &learned.1,
                            "128" => &learned.2,
                            _ => &learned.3,
                        };
                        let db: Vec<_> = finish(db_raw.clone(), "pl2", None).iter().map(|v| whiten(w, v)).collect();
                        let q: Vec<_> = finish(q_raw.clone(), "pl2", None).iter().map(|v| whiten(w, v)).collect();
                        (db, q)
                    } else if post == "pl2v128" {
                        // Whitening learned from the database itself (the history).
                        let dbf = finish(db_raw.clone(), "pl2", None);
                        let w = learn_whitening(&dbf, 128);
                        (
                            dbf.iter().map(|v| whiten(&w, v)).collect(),
                            finish(q_raw.clone(), "pl2", None).iter().map(|v| whiten(&w, v)).collect(),
                        )
                    } else if let Some(levels) = post.strip_prefix("l2q") {
                        let quantise =
                            |vs: Vec<Vec<f32>>| -> Vec<Vec<f32>> { vs.iter().map(|v| quantised(v, levels)).collect() };
                        (quantise(finish(db_raw.clone(), "l2", None)), quantise(finish(q_raw.clone(), "l2", None)))
                    } else if post == "pl2s" {
                        (
                            finish(db_raw.clone(), "pl2", Some(&learned.0)),
                            finish(q_raw.clone(), "pl2", Some(&learned.0)),
                        )
                    } else {
                        let plain = post.trim_end_matches('c');
                        let mean = post.ends_with('c').then(|| mean_of(&finish(db_raw.clone(), plain, None)));
                        (finish(db_raw.clone(), plain, mean.as_deref()), finish(q_raw.clone(), plain, mean.as_deref()))
                    };
                    // Hubness correction (`l2dK` both sides, `l2rK` the reference's density only, `l2uK`
                    // the query's level only): K, and which sides count.
                    let hubness = [("l2d", true, true), ("l2r", true, false), ("l2u", false, true)]
                        .into_iter()
                        .find_map(|(prefix, reference, query)| {
                            post.strip_prefix(prefix).map(|k| (k.parse::<usize>().unwrap_or(5), reference, query))
                        });
                    // The mean of the k best of `v`.
                    let top_mean = |mut v: Vec<f32>, k: usize| -> f32 {
                        v.sort_by(|a, b| b.total_cmp(a));
                        let n = k.min(v.len()).max(1);
                        v.iter().take(n).sum::<f32>() / n as f32
                    };
                    // Database-side augmentation (`l2bK`: each reference plus its K nearest other
                    // references weighted by cosine^alpha, as alpha-DBA does; `l2tK`: plus its K
                    // neighbours on each side in time) and query expansion (`l2eK`: the query plus its K
                    // best references, weighted the same way, scored again).
                    let parsed = |prefix: &str| post.strip_prefix(prefix).and_then(|k| k.parse::<usize>().ok());
                    let (nearest, temporal) = (parsed("l2b"), parsed("l2t"));
                    // `l2fK`: the expanded query ranks, but the best match keeps its raw score.
                    let (expansion, raw_score) = match (parsed("l2e"), parsed("l2f")) {
                        (Some(k), _) => (Some(k), false),
                        (None, k) => (k, k.is_some()),
                    };
                    let mut augmented_by_limit: BTreeMap<usize, Vec<Vec<f32>>> = BTreeMap::new();
                    // The references' scores against each other, and each reference's density among the
                    // first `limit` references (a sequence's history), worked out once per limit.
                    let gram: Vec<Vec<f32>> = if matches!(hubness, Some((_, true, _))) || nearest.is_some() {
                        db.iter().map(|r| cosine_scores(r, &db)).collect()
                    } else {
                        Vec::new()
                    };
                    let mut densities_by_limit: BTreeMap<usize, Vec<f32>> = BTreeMap::new();
                    // Shift-tolerant scores (`l2xK` on a `gridN` aggregate): K and N.
                    let shifted = post
                        .strip_prefix("l2x")
                        .and_then(|k| k.parse::<usize>().ok())
                        .zip(agg.strip_prefix("grid").and_then(|a| a.get(..1)?.parse::<usize>().ok()));
                    let fill = std::env::var("STUDY_SHIFT_FILL").ok().and_then(|f| f.parse::<f32>().ok());
                    let mut results = Vec::new();
                    for (qi, qv) in q.iter().enumerate() {
                        let limit = set.eligible[qi].unwrap_or(db.len());
                        if limit == 0 {
                            results.push(QueryResult { query: qi, best: None });
                            continue;
                        }
                        let refs: &[Vec<f32>] = if nearest.is_some() || temporal.is_some() {
                            augmented_by_limit
                                .entry(limit)
                                .or_insert_with(|| augment(&db[..limit], &gram, nearest, temporal, alpha))
                        } else {
                            &db[..limit]
                        };
                        let mut scores = cosine_scores(qv, refs);
                        if let Some(k) = expansion {
                            let mut order: Vec<usize> = (0..scores.len()).collect();
                            order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]));
                            let mut expanded = qv.clone();
                            for &r in order.iter().take(k) {
                                let w = scores[r].max(0.0).powf(alpha);
                                expanded.iter_mut().zip(&refs[r]).for_each(|(a, b)| *a += w * b);
                            }
                            l2_normalise(&mut expanded);
                            let raw = std::mem::replace(&mut scores, cosine_scores(&expanded, refs));
                            if raw_score {
                                let best = order
                                    .iter()
                                    .take(shortlist)
                                    .copied()
                                    .max_by(|&a, &b| scores[a].total_cmp(&scores[b]));
                                let best = best.unwrap_or(0);
                                scores = raw.iter().map(|s| s - 1.0).collect();
                                scores[best] = raw[best];
                            }
                        }
                        if let Some((shifts, cells)) = shifted {
                            for (s, r) in scores.iter_mut().zip(&db[..limit]) {
                                *s = shift_tolerant(qv, r, cells, shifts, fill);
                            }
                        }
                        if let Some((k, reference_side, query_side)) = hubness {
                            // Each score less half the reference's density (the mean of its k best scores
                            // against the other eligible references more than two away), as CSLS does with
                            // the other domain, and less half the query's level (its k best scores).
                            let query_level = if query_side { top_mean(scores.clone(), k) } else { 0.0 };
                            let densities = densities_by_limit.entry(limit).or_insert_with(|| {
                                (0..limit)
                                    .filter(|_| reference_side)
                                    .map(|r| {
                                        let others: Vec<f32> =
                                            (0..limit).filter(|&o| o.abs_diff(r) > 2).map(|o| gram[r][o]).collect();
                                        if others.is_empty() {
                                            0.0
                                        } else {
                                            top_mean(others, k)
                                        }
                                    })
                                    .collect()
                            });
                            for (i, s) in scores.iter_mut().enumerate() {
                                let density = densities.get(i).copied().unwrap_or(0.0);
                                *s = (2.0 * *s - query_level - density + 2.0) / 4.0;
                            }
                        }
                        let (best, score) = scores
                            .iter()
                            .copied()
                            .enumerate()
                            .fold((0, f32::NEG_INFINITY), |b, (i, s)| if s > b.1 { (i, s) } else { b });
                        if post == "l2" && Some(format!("{tap} {agg}")) == std::env::var("STUDY_CALIBRATE").ok() {
                            if let Some(matches) = set.truth.matches(qi) {
                                if let Ok(path) = std::env::var("STUDY_DUMP") {
                                    dump_scores(&path, &set.name, qi, matches, &scores)?;
                                }
                                let n = scores.len() as f32;
                                let mean = scores.iter().sum::<f32>() / n;
                                let sd =
                                    (scores.iter().map(|s| (s - mean) * (s - mean)).sum::<f32>() / n).sqrt().max(1e-6);
                                let second = scores
                                    .iter()
                                    .enumerate()
                                    .filter(|(i, _)| i.abs_diff(best) > 2)
                                    .map(|(_, s)| *s)
                                    .fold(f32::NEG_INFINITY, f32::max);
                                calibration.push(CalibrationRecord {
                                    set: set.name.clone(),
                                    positive: !matches.is_empty(),
                                    correct: matches.contains(&best),
                                    s1: score,
                                    mean,
                                    sd,
                                    second,
                                });
                            }
                        }
                        results.push(QueryResult { query: qi, best: Some((best, score)) });
                    }
                    let m = evaluate(&results, &set.truth)?;
                    table
                        .entry((tap.to_string(), agg.to_string(), post.to_string()))
                        .or_default()
                        .push((m.recall_at_1.unwrap_or(0.0), m.recall_at_100_precision.unwrap_or(0.0)));
                }
            }
        }
    }
    report_calibration(&calibration, &sets);
    let names: Vec<&str> = sets.iter().map(|s| s.name.as_str()).collect();
    println!("arch {arch}, input {size}; per set: recall@1 / recall@100%P ({})", names.join(" | "));
    let mut rows: Vec<_> = table.into_iter().collect();
    rows.sort_by(|a, b| {
        let key = |v: &Vec<(f64, f64)>| v.iter().map(|(r1, rp)| r1 + rp).sum::<f64>();
        key(&b.1).total_cmp(&key(&a.1))
    });
    for ((tap, agg, post), figures) in rows {
        let cells: Vec<String> = figures.iter().map(|(a, b)| format!("{a:.2}/{b:.2}")).collect();
        println!("{tap:10} {agg:11} {post:5} {}", cells.join("  "));
    }
    Ok(())
}

/// `db` with each reference plus its `nearest` most similar other references (weighted by cosine to
/// the power `alpha`; `gram` holds the cosines) and its `temporal` neighbours on each side,
/// L2-normalised.
fn augment(
    db: &[Vec<f32>],
    gram: &[Vec<f32>],
    nearest: Option<usize>,
    temporal: Option<usize>,
    alpha: f32,
) -> Vec<Vec<f32>> {
    (0..db.len())
        .map(|i| {
            let mut v = db[i].clone();
            let mut add = |j: usize, w: f32| v.iter_mut().zip(&db[j]).for_each(|(a, b)| *a += w * b);
            if let Some(k) = nearest {
                let mut others: Vec<(usize, f32)> =
                    (0..db.len()).filter(|&j| j != i).map(|j| (j, gram[i][j])).collect();
                others.sort_by(|a, b| b.1.total_cmp(&a.1));
                for &(j, s) in others.iter().take(k) {
                    add(j, s.max(0.0).powf(alpha));
                }
            }
            if let Some(k) = temporal {
                for j in i.saturating_sub(k)..(i + k + 1).min(db.len()) {
                    if j != i {
                        add(j, 1.0);
                    }
                }
            }
            l2_normalise(&mut v);
            v
        })
        .collect()
}

/// A photometric normalisation of the whole image before the network (study only).
fn photometric(image: &RgbImage, how: &str) -> RgbImage {
    let luma = |p: &image::Rgb<u8>| 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32;
    let mut out = image.clone();
    match how {
        "equalise" => {
            let mut hist = [0usize; 256];
            for p in image.pixels() {
                hist[luma(p).round().clamp(0.0, 255.0) as usize] += 1;
            }
            let total = image.pixels().len() as f32;
            let mut cdf = [0f32; 256];
            let mut acc = 0usize;
            for (i, h) in hist.iter().enumerate() {
                acc += h;
                cdf[i] = acc as f32 / total * 255.0;
            }
            for p in out.pixels_mut() {
                let y = luma(p);
                let target = cdf[y.round().clamp(0.0, 255.0) as usize];
                let gain = target / y.max(1.0);
                for c in 0..3 {
                    p[c] = (p[c] as f32 * gain).round().clamp(0.0, 255.0) as u8;
                }
            }
        }
        "stretch" => {
            for c in 0..3 {
                let mut v: Vec<u8> = image.pixels().map(|p| p[c]).collect();
                v.sort_unstable();
                let lo = v[v.len() / 100] as f32;
                let hi = (v[v.len() * 99 / 100] as f32).max(lo + 1.0);
                for p in out.pixels_mut() {
                    p[c] = ((p[c] as f32 - lo) / (hi - lo) * 255.0).round().clamp(0.0, 255.0) as u8;
                }
            }
        }
        "gamma" => {
            let mean = image.pixels().map(luma).sum::<f32>() / image.pixels().len() as f32 / 255.0;
            let gamma = 0.45f32.ln() / mean.clamp(0.01, 0.99).ln();
            for p in out.pixels_mut() {
                for c in 0..3 {
                    p[c] = ((p[c] as f32 / 255.0).powf(gamma) * 255.0).round() as u8;
                }
            }
        }
        "standardise" => {
            for c in 0..3 {
                let n = image.pixels().len() as f32;
                let mean = image.pixels().map(|p| p[c] as f32).sum::<f32>() / n;
                let sd = (image.pixels().map(|p| (p[c] as f32 - mean).powi(2)).sum::<f32>() / n).sqrt().max(1.0);
                for p in out.pixels_mut() {
                    p[c] = (115.0 + (p[c] as f32 - mean) / sd * 60.0).round().clamp(0.0, 255.0) as u8;
                }
            }
        }
        _ => {}
    }
    out
}

/// Appends one query's scores against its eligible references and the true ones among them, as a
/// JSON line, for studying calibrations outside this program.
fn dump_scores(
    path: &str,
    set: &str,
    query: usize,
    matches: &std::collections::BTreeSet<usize>,
    scores: &[f32],
) -> Result<()> {
    use std::io::Write;
    let line = serde_json::json!({"set": set, "query": query, "matches": matches, "scores": scores});
    let mut file = std::fs::OpenOptions::new().create(true).append(true).open(path).context(path.to_string())?;
    writeln!(file, "{line}")?;
    Ok(())
}

/// One query's top-1 against its eligible references, for calibrating the score.
struct CalibrationRecord {
    set: String,
    positive: bool,
    correct: bool,
    s1: f32,
    mean: f32,
    sd: f32,
    /// Best score more than two references away from the top-1.
    second: f32,
}

/// Pooled over every set: the recall at 100% precision of one threshold on each candidate statistic.
fn report_calibration(records: &[CalibrationRecord], sets: &[Set]) {
    if records.is_empty() {
        return;
    }
    let stats: [(&str, fn(&CalibrationRecord) -> f32); 7] = [
        ("raw", |r| r.s1),
        ("z", |r| (r.s1 - r.mean) / r.sd),
        ("margin", |r| r.s1 - r.second.max(r.mean)),
        ("rel-mean", |r| (r.s1 - r.mean) / (1.0 - r.mean).max(1e-6)),
        ("rel-second", |r| (r.s1 - r.second.max(r.mean)) / (1.0 - r.second.max(r.mean)).max(1e-6)),
        ("dist-ratio", |r| -((1.0 - r.s1).max(0.0).sqrt() / (1.0 - r.second.max(r.mean)).max(1e-6).sqrt())),
        ("z*raw", |r| (r.s1 - r.mean) / r.sd * r.s1),
    ];
    let positives = records.iter().filter(|r| r.positive).count();
    for (name, f) in stats {
        let mut v: Vec<(f32, bool, &str)> = records.iter().map(|r| (f(r), r.correct, r.set.as_str())).collect();
        v.sort_by(|a, b| b.0.total_cmp(&a.0));
        let first_false = v.iter().position(|x| !x.1).unwrap_or(v.len());
        let threshold = if first_false < v.len() { v[first_false].0 } else { f32::NEG_INFINITY };
        let kept = &v[..first_false];
        let per_set: Vec<String> = sets
            .iter()
            .map(|s| {
                let pos = records.iter().filter(|r| r.set == s.name && r.positive).count();
                let tp = kept.iter().filter(|x| x.2 == s.name && x.0 > threshold).count();
                format!("{}/{}", tp, pos)
            })
            .collect();
        let trues: Vec<f32> = v.iter().filter(|x| x.1).map(|x| x.0).collect();
        println!(
            "calibration {name:10}: pooled recall@100%P {:.3} (threshold above {threshold:.4}; true range {:.3}..{:.3}); per set {}",
            kept.len() as f64 / positives as f64,
            trues.iter().cloned().fold(f32::INFINITY, f32::min),
            trues.iter().cloned().fold(f32::NEG_INFINITY, f32::max),
            per_set.join(" ")
        );
    }
}
