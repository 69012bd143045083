//! The loop-closure objective: the network learns to make the detector's own descriptor (the
//! configured mode, tap, grid and pooling) close for two views of one place and far for two places.
//!
//! Interpretation, written down once:
//! - **Data**: sequences with ground-truth poses (TUM folders with `groundtruth.txt`, such as `synth`
//!   output). Two frames of one sequence are the **same place** by `eval`'s rule
//!   ([`PoseLoopCriteria`]: centres within `max_distance_m`, optical axes within `max_angle_deg`) and
//!   at least `min_gap_s` apart in time, so a positive pair is a revisit and not a neighbour. They are
//!   **different places** when their centres are more than twice that distance apart or their axes
//!   more than twice that angle. Pairs in between, and pairs from different sequences (which may
//!   show the same room), are neither and never enter the loss.
//! - **Batches** ("batch-hard" triplets, Hermans et al. 2017): `batch` anchors (frames that have a
//!   revisit, each once per epoch), one random revisit of each, and as many random frames again as
//!   extra negatives. Each anchor's loss is `max(0, margin + d²(a, p) - min_n d²(a, n))` over the
//!   batch's images that are different places from it; the anchor's positive is scored against its
//!   hardest negative only.
//! - **Descriptor**: computed as the detector does ([`Descriptor::compute`]) but with tensor ops so
//!   gradients flow: `regional` (each grid cell pooled, power- and L2-normalised, scaled by
//!   1/grid), `l2` and `power` (the global average). The signed square root is `x / sqrt(|x| + ε)`,
//!   equal to `sign(x) sqrt(|x|)` up to ε and differentiable at 0. Other modes are refused.
//! - **Network**: folded weights with BatchNorm frozen ([`Mode::FineTune`]; see the module doc of
//!   [`super`]); only the layers up to the tap receive gradients. Augmentation: colour jitter and a
//!   mild crop, no flip (a mirrored place is not the same place).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use candle_core::{Device, Tensor, D};
use image::RgbImage;
use nalgebra::Vector3;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use super::data::{augmented_chw, shrink_to_short_side, Augment};
use super::{learning_rate, progress_bar, trainable_params, training_form, write_json, Optimisation, Trainable};
use crate::descriptor::{grid_cell, Descriptor, DescriptorMode, Pooling};
use crate::eval::truth::{poses_at_stamps, PoseLoopCriteria};
use crate::model::layers::Mode;
use crate::model::weights::Weights;
use crate::model::{check_input_size, Arch, Tap};
use crate::preprocess::Preprocessor;

/// ε of the differentiable signed square root.
const POWER_EPS: f64 = 1e-6;

/// A place-training run.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PlaceConfig {
    /// Sequences with ground truth (TUM folders with `groundtruth.txt`).
    pub data: Vec<PathBuf>,
    pub arch: Arch,
    /// Where the descriptor reads the network, and how it aggregates (from the detector's parameters).
    pub tap: String,
    pub descriptor: String,
    pub size: usize,
    /// `batch` is the number of anchors per step; an epoch takes every anchor once.
    #[serde(flatten)]
    pub opt: Optimisation,
    /// Triplet margin on squared distances of unit descriptors (which lie in [0, 4]).
    pub margin: f64,
    pub max_distance_m: f64,
    pub max_angle_deg: f64,
    pub min_gap_s: f64,
    pub out: PathBuf,
    #[serde(skip)]
    pub progress: bool,
}

/// What a place-training run did.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PlaceReport {
    pub command: String,
    pub init: String,
    pub config: PlaceConfig,
    pub frames: usize,
    pub anchors: usize,
    pub steps: usize,
    /// Per epoch: mean triplet loss, and the fraction of anchors whose revisit was nearer than
    /// their hardest negative.
    pub epoch_loss: Vec<f64>,
    pub epoch_triplet_accuracy: Vec<f64>,
    pub seconds: f64,
}

/// A frame with its ground-truth pose.
struct PosedFrame {
    image: RgbImage,
    sequence: usize,
    seconds: f64,
    centre: Vector3<f64>,
    axis: Vector3<f64>,
}

/// How two frames relate under the same-place rule.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Relation {
    Revisit,
    Different,
    Neither,
}

fn relation(a: &PosedFrame, b: &PosedFrame, config: &PlaceConfig) -> Relation {
    if a.sequence != b.sequence {
        return Relation::Neither;
    }
    let distance = (a.centre - b.centre).norm();
    let angle = a.axis.dot(&b.axis).clamp(-1.0, 1.0).acos().to_degrees();
    if distance > 2.0 * config.max_distance_m || angle > 2.0 * config.max_angle_deg {
        Relation::Different
    } else if distance <= config.max_distance_m
        && angle <= config.max_angle_deg
        && (a.seconds - b.seconds).abs() >= config.min_gap_s
    {
        Relation::Revisit
    } else {
        Relation::Neither
    }
}

/// Every frame of `sources` that has a ground-truth pose, shrunk so its short side is `keep_side`.
fn load_posed(sources: &[PathBuf], keep_side: u32, max_offset_s: f64) -> Result<Vec<PosedFrame>> {
    let mut out = Vec::new();
    for (sequence, dir) in sources.iter().enumerate() {
        let truth_path = dir.join("groundtruth.txt");
        ensure!(truth_path.is_file(), "{} has no groundtruth.txt: place training needs poses", dir.display());
        let truth = crate::io::tum::read_groundtruth(&truth_path)?;
        let frames: Vec<crate::types::Frame> = crate::io::skip_unreadable(crate::io::open_source(dir, None)?, dir)
            .collect::<Result<_>>()
            .with_context(|| format!("reading {}", dir.display()))?;
        let stamps: Vec<_> = frames.iter().map(|f| f.stamp).collect();
        let poses = poses_at_stamps(&stamps, &truth, max_offset_s);
        for (frame, pose) in frames.into_iter().zip(poses) {
            let Some(pose) = pose else { continue };
            out.push(PosedFrame {
                image: shrink_to_short_side(frame.image, keep_side),
                sequence,
                seconds: frame.stamp.nanos as f64 * 1e-9,
                centre: pose.translation.vector,
                axis: pose.rotation * Vector3::z(),
            });
        }
    }
    Ok(out)
}

/// The signed square root `x / sqrt(|x| + ε)`.
fn signed_sqrt(x: &Tensor) -> candle_core::Result<Tensor> {
    x.broadcast_div(&(x.abs()? + POWER_EPS)?.sqrt()?)
}

/// Each row of `[B, N]` divided by its L2 norm (a zero row stays zero).
fn l2_rows(x: &Tensor) -> candle_core::Result<Tensor> {
    let norm = x.sqr()?.sum_keepdim(1)?.sqrt()?.clamp(1e-12, f64::MAX)?;
    x.broadcast_div(&norm)
}

/// One channel per row pooled over a `[B, C, h, w]` region.
fn pool(region: &Tensor, pooling: Pooling) -> candle_core::Result<Tensor> {
    match pooling {
        Pooling::Gap => region.mean((2, 3)),
        Pooling::Mac => region.max(3)?.max(2),
        Pooling::Gem => {
            let cubed = region.relu()?.powf(3.0)?.mean((2, 3))?;
            // The cube root of a zero mean has no gradient: nudge it by a negligible amount.
            (cubed + 1e-12)?.powf(1.0 / 3.0)
        }
    }
}

/// The detector's descriptor of each map of `maps` (`[B, C, H, W]`) as differentiable tensor ops:
/// `[B, dim]`, equal to [`Descriptor::compute`] of each map up to the ε of the signed square root.
pub fn descriptor_tensor(maps: &Tensor, descriptor: &Descriptor) -> Result<Tensor> {
    let (_, channels, height, width) = maps.dims4()?;
    ensure!(
        channels == descriptor.channels,
        "map of {channels} channels for a {}-channel descriptor",
        descriptor.channels
    );
    Ok(match descriptor.mode {
        DescriptorMode::L2 => l2_rows(&maps.mean((2, 3))?)?,
        DescriptorMode::Power => l2_rows(&signed_sqrt(&maps.mean((2, 3))?)?)?,
        DescriptorMode::Regional => {
            let grid = descriptor.grid;
            let mut cells = Vec::with_capacity(grid * grid);
            for cell_row in 0..grid {
                let rows = grid_cell(height, grid, cell_row);
                for cell_col in 0..grid {
                    let cols = grid_cell(width, grid, cell_col);
                    let region = maps.narrow(2, rows.start, rows.len())?.narrow(3, cols.start, cols.len())?;
                    let cell = l2_rows(&signed_sqrt(&pool(&region, descriptor.pooling)?)?)?;
                    cells.push((cell / grid as f64)?);
                }
            }
            Tensor::cat(&cells, 1)?
        }
        mode => bail!("place training learns the l2, power or regional descriptor, not {mode}"),
    })
}

/// Batch-hard triplet loss over descriptors `[n, dim]`: for anchor `i` (the first `anchors` rows)
/// with its revisit at row `anchors + i`, `max(0, margin + d²(a, p) - min d²(a, n))` over the rows
/// `negatives[i]` marks. Returns the mean loss and how many anchors had their revisit nearer than
/// their hardest negative.
fn batch_hard_loss(
    descriptors: &Tensor,
    anchors: usize,
    negatives: &[Vec<f32>],
    margin: f64,
) -> Result<(Tensor, usize)> {
    let n = descriptors.dim(0)?;
    let a = descriptors.narrow(0, 0, anchors)?;
    let p = descriptors.narrow(0, anchors, anchors)?;
    // Unit vectors: d² = 2 - 2 cos.
    let positive = (((&a * &p)?.sum(1)? * -2.0)? + 2.0)?;
    let similarity = a.matmul(&descriptors.t()?)?;
    let mask = Tensor::from_vec(negatives.concat(), (anchors, n), &Device::Cpu)?;
    // Non-negatives pushed below any cosine so that the max picks a negative.
    let hardest = similarity.broadcast_add(&((mask.clone() - 1.0)? * 10.0)?)?.max(D::Minus1)?;
    let negative = ((hardest * -2.0)? + 2.0)?;
    let loss = ((&positive - &negative)? + margin)?.relu()?.mean_all()?;
    // An anchor with no negative in the batch has nothing to be nearer than: not counted as won.
    let nearer = positive.lt(&negative)?.to_vec1::<u8>()?;
    let won = nearer.iter().zip(negatives).filter(|(&n, row)| n > 0 && row.iter().any(|&m| m > 0.0)).count();
    Ok((loss, won))
}

/// Trains `init` (inference-form weights) with the loop-closure objective; writes the weights
/// (inference form) to `config.out` and the report as JSON beside it.
pub fn train_place(
    init: &Weights,
    init_name: &str,
    descriptor: &Descriptor,
    tap: Tap,
    config: &PlaceConfig,
) -> Result<PlaceReport> {
    let started = Instant::now();
    let report_path = super::report_beside(&config.out)?;
    check_input_size(config.size)?;
    ensure!(config.opt.batch >= 1, "--batch (anchors per step) must be at least 1");
    config.opt.check()?;
    ensure!(
        config.margin > 0.0 && config.margin <= 4.0,
        "--margin must be in (0, 4] (squared distances of unit descriptors), got {}",
        config.margin
    );
    ensure!(!config.data.is_empty(), "no training sequences");
    let mut tensors = training_form(&init.for_arch(config.arch)?.tensors)?;
    tensors.retain(|n, _| !n.starts_with("classifier."));
    let model = Trainable::new(config.arch, None, &tensors, config.opt.seed)?;

    let frames =
        load_posed(&config.data, (config.size as u32 * 5).div_ceil(4), PoseLoopCriteria::default().max_stamp_offset_s)?;
    let revisits: Vec<Vec<usize>> = (0..frames.len())
        .map(|i| (0..frames.len()).filter(|&j| relation(&frames[i], &frames[j], config) == Relation::Revisit).collect())
        .collect();
    let mut anchors: Vec<usize> = (0..frames.len()).filter(|&i| !revisits[i].is_empty()).collect();
    ensure!(
        anchors.len() >= config.opt.batch,
        "{} of {} posed frames have a revisit (within {} m and {}°, at least {} s later or earlier); a step needs {}",
        anchors.len(),
        frames.len(),
        config.max_distance_m,
        config.max_angle_deg,
        config.min_gap_s,
        config.opt.batch
    );
    ensure!(
        anchors.iter().any(|&a| frames.iter().any(|other| relation(&frames[a], other, config) == Relation::Different)),
        "no posed frame is of another place than the frames with a revisit (farther than {} m or {}° away): the \
         objective pushes other places away, and there are none",
        config.max_distance_m,
        config.max_angle_deg
    );
    let steps_per_epoch = anchors.len() / config.opt.batch;
    let total = steps_per_epoch * config.opt.epochs;
    let warmup = config.opt.warmup_steps(steps_per_epoch);
    let mut optimizer = config.opt.optimizer(trainable_params(&model.varmap))?;
    let augment = Augment { flip: false, ..config.opt.augment };
    let mut pre = Preprocessor::new(config.size);
    let mut rng = StdRng::seed_from_u64(config.opt.seed);
    let (mut epoch_loss, mut epoch_triplet_accuracy) = (Vec::new(), Vec::new());
    let mut step = 0;
    for epoch in 0..config.opt.epochs {
        let bar = progress_bar(
            config.progress,
            steps_per_epoch as u64,
            &format!("epoch {}/{}", epoch + 1, config.opt.epochs),
        );
        anchors.shuffle(&mut rng);
        let epoch_started = Instant::now();
        let (mut loss_sum, mut won, mut seen) = (0.0, 0usize, 0usize);
        for chunk in anchors.chunks_exact(config.opt.batch) {
            let positives: Vec<usize> =
                chunk.iter().map(|&a| revisits[a][rng.random_range(0..revisits[a].len())]).collect();
            let extra: Vec<usize> = (0..chunk.len()).map(|_| rng.random_range(0..frames.len())).collect();
            let batch: Vec<usize> = chunk.iter().chain(&positives).chain(&extra).copied().collect();
            let negatives: Vec<Vec<f32>> = chunk
                .iter()
                .map(|&a| {
                    batch
                        .iter()
                        .map(|&b| f32::from(u8::from(relation(&frames[a], &frames[b], config) == Relation::Different)))
                        .collect()
                })
                .collect();
            let mut data = Vec::with_capacity(batch.len() * 3 * config.size * config.size);
            for &i in &batch {
                data.extend(augmented_chw(&frames[i].image, &augment, &mut pre, &mut rng)?);
            }
            let x = Tensor::from_vec(data, (batch.len(), 3, config.size, config.size), &Device::Cpu)?;
            let maps = model.network.tapped_features(&x, Mode::FineTune, &[tap])?.pop().context("one map per tap")?;
            let d = descriptor_tensor(&maps, descriptor)?;
            let (loss, anchors_won) = batch_hard_loss(&d, chunk.len(), &negatives, config.margin)?;
            let lr = learning_rate(step, total, warmup, config.opt.lr);
            optimizer.step(&loss.backward()?, lr)?;
            step += 1;
            let l = loss.to_scalar::<f32>()? as f64;
            ensure!(l.is_finite(), "the place loss diverged at step {step}");
            loss_sum += l * chunk.len() as f64;
            won += anchors_won;
            seen += chunk.len();
            bar.set_message(format!(
                "loss {:.4} triplets right {:.1}% lr {lr:.2e}",
                loss_sum / seen as f64,
                100.0 * won as f64 / seen as f64
            ));
            bar.inc(1);
            if !config.progress && step % 25 == 0 {
                log::info!(
                    "step {step}/{total}: loss {:.4}, {:.1} s per step",
                    loss_sum / seen as f64,
                    epoch_started.elapsed().as_secs_f64() / (seen / chunk.len()) as f64
                );
            }
        }
        bar.finish();
        log::info!(
            "epoch {}/{}: loss {:.4}, revisit nearer than the hardest negative for {:.1}% of anchors",
            epoch + 1,
            config.opt.epochs,
            loss_sum / seen.max(1) as f64,
            100.0 * won as f64 / seen.max(1) as f64
        );
        epoch_loss.push(loss_sum / seen.max(1) as f64);
        epoch_triplet_accuracy.push(won as f64 / seen.max(1) as f64);
    }
    let weights = model.inference_weights(&format!("ecm-lcd train-place of {init_name}"))?;
    weights.check_finite().context("training diverged; nothing is saved (try a lower --lr)")?;
    weights.save(&config.out)?;
    let report = PlaceReport {
        command: "train-place".into(),
        init: init_name.to_string(),
        config: config.clone(),
        frames: frames.len(),
        anchors: anchors.len(),
        steps: step,
        epoch_loss,
        epoch_triplet_accuracy,
        seconds: started.elapsed().as_secs_f64(),
    };
    write_json(&report_path, &report)?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::FeatureMap;

    fn maps(b: usize, c: usize, h: usize, w: usize, seed: u64) -> Tensor {
        let mut rng = StdRng::seed_from_u64(seed);
        let data: Vec<f32> = (0..b * c * h * w).map(|_| rng.random_range(-3.0f32..6.0)).collect();
        Tensor::from_vec(data, (b, c, h, w), &Device::Cpu).unwrap()
    }

    #[test]
    fn tensor_descriptors_equal_the_detectors() {
        let (b, c, h, w) = (3, 16, 7, 5);
        let x = maps(b, c, h, w, 3);
        let mut cases = vec![Descriptor::new(DescriptorMode::L2, c), Descriptor::new(DescriptorMode::Power, c)];
        for pooling in Pooling::ALL {
            for grid in [1, 2, 3] {
                cases.push(Descriptor::regional(c, grid, pooling));
            }
        }
        for d in cases {
            let t = descriptor_tensor(&x, &d).unwrap().to_vec2::<f32>().unwrap();
            for (i, row) in t.iter().enumerate() {
                let map = x.get(i).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let reference = d.compute(&FeatureMap { channels: c, height: h, width: w, data: map }).unwrap();
                assert_eq!(row.len(), reference.len(), "{}", d.name());
                let worst = row.iter().zip(&reference).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                assert!(worst < 1e-3, "{} image {i}: differs by {worst}", d.name());
            }
        }
        assert!(descriptor_tensor(&x, &Descriptor::new(DescriptorMode::Paper, c)).is_err());
    }

    #[test]
    fn the_loss_takes_the_hardest_negative_and_is_zero_past_the_margin() {
        // Anchor 0 with revisit at row 2; rows 1 (a second anchor) and 3 (its revisit).
        let unit = |angle: f32| vec![angle.cos(), angle.sin()];
        let rows = [unit(0.0), unit(1.5), unit(0.1), unit(1.4), unit(0.3)].concat();
        let d = Tensor::from_vec(rows, (5, 2), &Device::Cpu).unwrap();
        // Anchor 0's negatives: rows 1 and 4 (4 is the harder); anchor 1's: row 0 only.
        let negatives = vec![vec![0.0, 1.0, 0.0, 0.0, 1.0], vec![1.0, 0.0, 0.0, 0.0, 0.0]];
        let d2 = |a: f32, b: f32| 2.0 - 2.0 * (a - b).cos();
        for margin in [0.0, 0.5] {
            let (loss, won) = batch_hard_loss(&d, 2, &negatives, margin as f64).unwrap();
            let expected = ((margin + d2(0.0, 0.1) - d2(0.0, 0.3)).max(0.0)
                + (margin + d2(1.5, 1.4) - d2(1.5, 0.0)).max(0.0))
                / 2.0;
            assert!((loss.to_scalar::<f32>().unwrap() - expected).abs() < 1e-5, "margin {margin}");
            assert_eq!(won, 2);
        }
        // An anchor with no negative in its batch is not counted as won.
        let none = vec![vec![0.0, 1.0, 0.0, 0.0, 1.0], vec![0.0; 5]];
        assert_eq!(batch_hard_loss(&d, 2, &none, 0.0).unwrap().1, 1);
    }

    #[test]
    fn relations_follow_the_same_place_rule() {
        let config = PlaceConfig {
            data: vec![],
            arch: Arch::MobileNetV2,
            tap: "auto".into(),
            descriptor: "regional".into(),
            size: 64,
            opt: Optimisation {
                epochs: 1,
                batch: 1,
                optimizer: super::super::OptimizerKind::Adamw,
                lr: 1e-4,
                momentum: 0.9,
                weight_decay: 0.0,
                warmup_epochs: 0.0,
                augment: Augment::NONE,
                seed: 1,
            },
            margin: 0.1,
            max_distance_m: 1.0,
            max_angle_deg: 30.0,
            min_gap_s: 20.0,
            out: PathBuf::new(),
            progress: false,
        };
        let frame = |sequence: usize, seconds: f64, x: f64, yaw_deg: f64| PosedFrame {
            image: RgbImage::new(1, 1),
            sequence,
            seconds,
            centre: Vector3::new(x, 0.0, 0.0),
            axis: Vector3::new(yaw_deg.to_radians().sin(), 0.0, yaw_deg.to_radians().cos()),
        };
        let a = frame(0, 0.0, 0.0, 0.0);
        assert_eq!(relation(&a, &frame(0, 30.0, 0.5, 10.0), &config), Relation::Revisit);
        assert_eq!(relation(&a, &frame(0, 5.0, 0.5, 10.0), &config), Relation::Neither, "too soon: a neighbour");
        assert_eq!(relation(&a, &frame(0, 30.0, 1.5, 10.0), &config), Relation::Neither, "between the rules");
        assert_eq!(relation(&a, &frame(0, 30.0, 2.5, 0.0), &config), Relation::Different);
        assert_eq!(relation(&a, &frame(0, 5.0, 0.0, 90.0), &config), Relation::Different);
        assert_eq!(relation(&a, &frame(1, 30.0, 0.0, 0.0), &config), Relation::Neither, "another sequence");
    }
}
