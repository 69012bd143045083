//! Trajectory error against ground truth: the absolute trajectory error (ATE) as the TUM RGB-D
//! benchmark and `evo_ape tum GT EST -a` compute it.
//!
//! Each estimated pose is paired with the ground-truth pose nearest in time, within
//! [`MAX_STAMP_OFFSET_S`] (evo's default); the estimated positions are aligned to the ground truth by
//! the rigid motion that fits them best (Umeyama's closed form, no scale: evo's `-a`); the ATE is the
//! root mean square of the remaining position differences.

use anyhow::{ensure, Result};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use super::truth::poses_at_stamps;
use crate::types::Stamp;

/// Largest stamp difference of an estimated and a ground-truth pose that are paired (seconds).
pub const MAX_STAMP_OFFSET_S: f64 = 0.01;

/// The absolute trajectory error of an estimate.
#[derive(Clone, Debug, PartialEq)]
pub struct TrajectoryError {
    /// Root mean square of the position errors after alignment, metres.
    pub rmse: f64,
    pub mean: f64,
    pub max: f64,
    /// Poses paired with ground truth.
    pub pairs: usize,
    /// The rigid motion that maps the estimate onto the ground truth.
    pub alignment: Isometry3<f64>,
}

/// The rotation and translation that move `points` onto `targets` with the least squared error
/// (Umeyama 1991, without scale; the reflection case handled).
pub fn umeyama_alignment(points: &[Vector3<f64>], targets: &[Vector3<f64>]) -> Isometry3<f64> {
    let n = points.len().max(1) as f64;
    let mean = |v: &[Vector3<f64>]| v.iter().sum::<Vector3<f64>>() / n;
    let (mean_p, mean_t) = (mean(points), mean(targets));
    let covariance: Matrix3<f64> =
        points.iter().zip(targets).map(|(p, t)| (t - mean_t) * (p - mean_p).transpose()).sum::<Matrix3<f64>>() / n;
    let svd = covariance.svd(true, true);
    let (u, v_t) = (svd.u.expect("asked for U"), svd.v_t.expect("asked for V^T"));
    let mut s = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(u * s * v_t));
    let translation = mean_t - rotation * mean_p;
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

/// The ATE of `estimate` against `groundtruth` (module doc). Needs at least three paired poses.
pub fn absolute_trajectory_error(
    estimate: &[(Stamp, Isometry3<f64>)],
    groundtruth: &[(Stamp, Isometry3<f64>)],
) -> Result<TrajectoryError> {
    let stamps: Vec<Stamp> = estimate.iter().map(|(s, _)| *s).collect();
    let truth = poses_at_stamps(&stamps, groundtruth, MAX_STAMP_OFFSET_S);
    let (points, targets): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = estimate
        .iter()
        .zip(&truth)
        .filter_map(|((_, e), t)| t.map(|t| (e.translation.vector, t.translation.vector)))
        .unzip();
    ensure!(
        points.len() >= 3,
        "only {} of {} estimated poses have a ground-truth pose within {MAX_STAMP_OFFSET_S} s (at least 3 needed)",
        points.len(),
        estimate.len()
    );
    let alignment = umeyama_alignment(&points, &targets);
    let errors: Vec<f64> = points
        .iter()
        .zip(&targets)
        .map(|(p, t)| (alignment * nalgebra::Point3::from(*p) - nalgebra::Point3::from(*t)).norm())
        .collect();
    let n = errors.len() as f64;
    Ok(TrajectoryError {
        rmse: (errors.iter().map(|e| e * e).sum::<f64>() / n).sqrt(),
        mean: errors.iter().sum::<f64>() / n,
        max: errors.iter().copied().fold(0.0, f64::max),
        pairs: errors.len(),
        alignment,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trajectory(n: usize, f: impl Fn(f64) -> Vector3<f64>) -> Vec<(Stamp, Isometry3<f64>)> {
        (0..n)
            .map(|i| {
                (
                    Stamp::from_nanos(i as i64 * 100_000_000),
                    Isometry3::translation(f(i as f64).x, f(i as f64).y, f(i as f64).z),
                )
            })
            .collect()
    }

    #[test]
    fn a_moved_copy_has_no_error_and_a_known_offset_its_size() {
        let truth = trajectory(50, |i| Vector3::new((i * 0.2).cos() * 3.0, (i * 0.2).sin() * 2.0, 0.01 * i));
        let motion = Isometry3::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.1, 0.2, -0.3));
        let moved: Vec<_> = truth.iter().map(|(s, p)| (*s, motion * p)).collect();
        let error = absolute_trajectory_error(&moved, &truth).unwrap();
        assert_eq!(error.pairs, 50);
        assert!(error.rmse < 1e-9, "{}", error.rmse);
        assert!((error.alignment * motion).translation.vector.norm() < 1e-9);
        // Corners of a square, lifted by 0.1 m where x * y > 0 and lowered where x * y < 0: no rigid
        // motion reduces that saddle (a small rotation moves z linearly in x and y), so the best
        // alignment is the identity and every error is 0.1 m.
        let corners = |i: f64| {
            let k = i as usize % 4;
            Vector3::new(if k < 2 { 1.0 } else { -1.0 }, if k.is_multiple_of(2) { 1.0 } else { -1.0 }, 0.0)
        };
        let flat = trajectory(40, corners);
        let saddle: Vec<_> = flat
            .iter()
            .map(|(s, p)| (*s, Isometry3::translation(0.0, 0.0, 0.1 * p.translation.x * p.translation.y) * p))
            .collect();
        let error = absolute_trajectory_error(&saddle, &flat).unwrap();
        assert!((error.rmse - 0.1).abs() < 1e-9 && (error.max - 0.1).abs() < 1e-9, "{error:?}");
    }

    #[test]
    fn poses_without_ground_truth_are_not_counted_and_too_few_pairs_fail() {
        let truth = trajectory(10, |i| Vector3::new(i, 0.0, 0.0));
        let late: Vec<_> = truth.iter().map(|(s, p)| (Stamp::from_nanos(s.nanos + 50_000_000), *p)).collect();
        let err = absolute_trajectory_error(&late, &truth).unwrap_err().to_string();
        assert!(err.contains("0 of 10"), "{err}");
    }
}
