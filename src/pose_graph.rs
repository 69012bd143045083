//! The back end that uses the loops: SE(3) pose-graph optimisation of an odometry trajectory with the
//! verified loop candidates (the paper's Fig. 11: a tracker's drift removed by loop closure).
//!
//! - Nodes: odometry poses, at most [`PoseGraphParams::max_nodes`] of them (every k-th pose, and every
//!   pose a loop ends at); the first is held fixed (the map's origin).
//! - Odometry edges: the odometry's own motion between consecutive nodes.
//! - Loop edges: each candidate's relative pose (the query camera in the match camera's frame, metres).
//!   A pose verified up to scale (a monocular camera: no depth) gives the rotation and the direction of
//!   the translation, not its length. Candidates without a verified pose are left out (counted).
//! - Solved in two stages, as rotation-then-translation initialisation does (Carlone et al., ICRA
//!   2015), and as global structure from motion does with relative directions:
//!   1. rotations alone: kornia-3d's pose-graph Levenberg-Marquardt (residual `log(T_meas⁻¹ T_b
//!      T_a⁻¹)`, each edge scaled by its weight) with every translation left out (zero);
//!   2. positions for those rotations, by linear least squares: odometry edges `p_b - p_a = R_a t`,
//!      metric loops `p_q - p_m = R_m t`, and loops up to scale as bearings, `(I - u uᵀ)(p_q - p_m) =
//!      0` with `u = R_m d`: only the part of the estimated translation across the measured direction
//!      counts, so no length is needed, the map's own units serve (a monocular tracker's), and a wrong
//!      direction costs in proportion to the baseline. Along a loop's own direction only the odometry
//!      places its cameras.
//!
//!   Solving both at once, in one stage, measured as well on the synthetic sequence but diverged
//!   where wrong loops with metric poses came in (the hard preset).
//! - Robust kernel: a Cauchy kernel on the loop edges, applied by iteratively reweighted least squares
//!   (edge weights `sqrt(ρ'(r²))` from the last solution). In stage one with graduated non-convexity:
//!   the kernel's scale starts at the largest loop rotation residual of the odometry and halves each
//!   round down to [`PoseGraphParams::robust_rotation_scale`], so true loops are not discarded for the
//!   drift they are there to remove, while a false loop, inconsistent with the others, ends with a
//!   weight near zero. In stage two likewise on translation, from half the largest translation
//!   residual of its first solution down to [`PoseGraphParams::robust_scale`] (rotation over
//!   `robust_rotation_scale`), then until the weights settle.
//! - Every odometry pose is then moved with the node before it (its odometry offset from that node
//!   kept), so the corrected trajectory has the odometry's stamps.

use std::collections::BTreeSet;
use std::ops::{AddAssign, SubAssign};

use anyhow::{bail, ensure, Context, Result};
use kornia_3d::pgo::{pose_graph_optimize, PgoEdge, PgoParams};
use kornia_3d::pose::Pose3d;
use kornia_algebra::{Mat3F64, QuatF32, Vec3AF32, Vec3F64, SE3F32};
use nalgebra::{DMatrix, DVector, Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::types::{nearest_stamp, LoopCandidate, Stamp};

/// A loop constraint: where the query camera is in the match camera's frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopConstraint {
    pub query_stamp: Stamp,
    pub match_stamp: Stamp,
    /// `p_match = relative * p_query`; the translation is in metres where `metric`, else a unit
    /// direction (verified up to scale).
    pub relative: Isometry3<f64>,
    pub metric: bool,
}

impl LoopConstraint {
    /// The constraints of the candidates that carry a verified relative pose (only the metric ones
    /// with `metric_only`), and how many candidates were left out.
    pub fn from_candidates(candidates: &[LoopCandidate], metric_only: bool) -> (Vec<LoopConstraint>, usize) {
        let constraints: Vec<LoopConstraint> = candidates
            .iter()
            .filter_map(|c| {
                let pose = c.verified?.pose.filter(|p| p.metric || !metric_only)?;
                let direction = pose.translation.try_normalize(1e-12);
                let translation = if pose.metric { pose.translation } else { direction? };
                Some(LoopConstraint {
                    query_stamp: c.query_stamp,
                    match_stamp: c.match_stamp,
                    relative: Isometry3::from_parts(Translation3::from(translation), pose.rotation),
                    metric: pose.metric,
                })
            })
            .collect();
        let skipped = candidates.len() - constraints.len();
        (constraints, skipped)
    }
}

/// How the graph is built and solved.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseGraphParams {
    /// Most nodes in the graph (the solver's normal equations are dense: 6 per node).
    pub max_nodes: usize,
    /// Weight of a loop edge against an odometry edge's 1.
    pub loop_weight: f64,
    /// Final scale of the Cauchy kernel on the loops' translation, in the odometry's units (metres,
    /// or a monocular map's own): loop residuals well beyond it count little.
    pub robust_scale: f64,
    /// Final scale of the Cauchy kernel on the loops' rotation, radians.
    pub robust_rotation_scale: f64,
    /// Largest stamp difference between a loop's keyframe and the odometry pose it is tied to, seconds.
    pub max_stamp_offset_s: f64,
    /// Levenberg-Marquardt iterations per reweighting round.
    pub iterations: usize,
}

impl Default for PoseGraphParams {
    fn default() -> Self {
        PoseGraphParams {
            max_nodes: 200,
            loop_weight: 1.0,
            robust_scale: 0.1,
            robust_rotation_scale: 0.1,
            max_stamp_offset_s: 0.05,
            iterations: 20,
        }
    }
}

/// The optimised trajectory and what the graph held.
#[derive(Clone, Debug)]
pub struct PoseGraphResult {
    /// Corrected camera-to-world poses at the odometry's stamps.
    pub trajectory: Vec<(Stamp, Isometry3<f64>)>,
    /// The loop edges as (query, match) indexes into `trajectory`, with their final robust weight
    /// (1 = fully trusted, near 0 = rejected as inconsistent).
    pub loops: Vec<(usize, usize, f64)>,
    /// Loops whose keyframes have no odometry pose within the stamp tolerance (not used).
    pub unmatched_loops: usize,
    /// Loops whose two keyframes are tied to one odometry pose (no edge to add; not used).
    pub self_loops: usize,
    /// Loops that cannot be a relative pose within this map (not used, [`plausible`]).
    pub implausible_loops: usize,
    /// Of `loops`, those up to scale (a bearing, not a metric translation).
    pub loops_up_to_scale: usize,
    pub nodes: usize,
}

/// Whether `constraint` can be a relative pose between two cameras of a map whose odometry spans
/// `extent` (the farthest any pose is from the first): finite, and a metric translation no longer than
/// twice the extent plus one unit (the odometry's scale may be off). A loop far beyond that (a
/// corrupted row, a stray unit) would set the robust kernel's first scale and drag the whole map
/// before the kernel could reject it.
fn plausible(constraint: &LoopConstraint, extent: f64) -> bool {
    let relative = &constraint.relative;
    let finite = relative.translation.vector.iter().chain(relative.rotation.coords.iter()).all(|v| v.is_finite());
    finite && (!constraint.metric || relative.translation.vector.norm() <= 2.0 * extent + 1.0)
}

/// Most rounds of reweighting in stage two (positions), which stops sooner once the kernel's scale is
/// final and no weight moves by more than [`WEIGHT_TOLERANCE`].
const MAX_POSITION_ROUNDS: usize = 20;
const WEIGHT_TOLERANCE: f64 = 1e-3;

/// Camera-to-world to kornia's world-to-camera pose.
fn to_kornia(camera_to_world: &Isometry3<f64>) -> Pose3d {
    let world_to_camera = camera_to_world.inverse();
    let r = world_to_camera.rotation.to_rotation_matrix();
    let columns: Vec<f64> = r.matrix().iter().copied().collect();
    let t = world_to_camera.translation.vector;
    Pose3d::new(Mat3F64::from_cols_array(&columns.try_into().expect("3x3")), Vec3F64::new(t.x, t.y, t.z))
}

fn from_kornia(pose: &Pose3d) -> Isometry3<f64> {
    let columns =
        [pose.rotation.col(0), pose.rotation.col(1), pose.rotation.col(2)].map(|c| Vector3::new(c.x, c.y, c.z));
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&Matrix3::from_columns(&columns)));
    let t = Vector3::new(pose.translation.x, pose.translation.y, pose.translation.z);
    Isometry3::from_parts(Translation3::from(t), rotation).inverse()
}

fn to_se3(motion: &Isometry3<f64>) -> SE3F32 {
    let q = motion.rotation.quaternion();
    let t = motion.translation.vector;
    SE3F32::from_qxyz(
        QuatF32::from_xyzw(q.i as f32, q.j as f32, q.k as f32, q.w as f32),
        Vec3AF32::new(t.x as f32, t.y as f32, t.z as f32),
    )
}

/// The loop's measurement after stage two: one up to scale with the length of the estimate's
/// translation along its direction (none where it points the other way), so that its residual is the
/// part of the estimated translation across the measured direction.
fn bearing_measurement(constraint: &LoopConstraint, from: &Isometry3<f64>, to: &Isometry3<f64>) -> Isometry3<f64> {
    if constraint.metric {
        return constraint.relative;
    }
    let direction = constraint.relative.translation.vector;
    let length = (to.inverse() * from).translation.vector.dot(&direction).max(0.0);
    Isometry3::from_parts(Translation3::from(direction * length), constraint.relative.rotation)
}

/// Stage two: the node positions for stage one's rotations, by linear least squares (module doc). Each
/// edge is `(a, b, projection, offset, weight)`, for the residual `weight * projection * (p_b - p_a -
/// offset)` (`projection` the identity, or `I - u uᵀ` for a bearing); the first node keeps `first`.
fn positions_for_rotations(
    first: Vector3<f64>,
    nodes: usize,
    edges: &[(usize, usize, Matrix3<f64>, Vector3<f64>, f64)],
) -> Result<Vec<Vector3<f64>>> {
    // Normal equations of every node's position; node 0's block is then moved to the right side.
    let mut h = DMatrix::<f64>::zeros(3 * nodes, 3 * nodes);
    let mut g = DVector::<f64>::zeros(3 * nodes);
    for &(a, b, projection, offset, weight) in edges {
        let information = projection * (weight * weight);
        for (i, j, sign) in [(a, a, 1.0), (b, b, 1.0), (a, b, -1.0), (b, a, -1.0)] {
            let mut block = h.fixed_view_mut::<3, 3>(3 * i, 3 * j);
            block += information * sign;
        }
        let pull = information * offset;
        g.fixed_rows_mut::<3>(3 * b).add_assign(&pull);
        g.fixed_rows_mut::<3>(3 * a).sub_assign(&pull);
    }
    let free = 3 * (nodes - 1);
    let rhs = g.rows(3, free) - h.view((3, 0), (free, 3)) * first;
    let cholesky = h
        .view((3, 3), (free, free))
        .into_owned()
        .cholesky()
        .context("the positions are not fixed by the graph (a node without an edge to the rest)")?;
    let solved = cholesky.solve(&rhs);
    Ok(std::iter::once(first).chain((0..nodes - 1).map(|k| solved.fixed_rows::<3>(3 * k).into_owned())).collect())
}

/// The size of a relative-pose residual: its translation (metres) and rotation angle (radians).
fn residual(measured: &Isometry3<f64>, from: &Isometry3<f64>, to: &Isometry3<f64>) -> (f64, f64) {
    // Poses are camera-to-world; the edge's prediction maps `from`'s camera frame into `to`'s.
    let predicted = to.inverse() * from;
    let error = measured.inverse() * predicted;
    (error.translation.vector.norm(), error.rotation.angle())
}

/// Optimises `odometry` (camera-to-world, in time order) with `loops` (module doc).
pub fn optimise(
    odometry: &[(Stamp, Isometry3<f64>)],
    loops: &[LoopConstraint],
    params: &PoseGraphParams,
) -> Result<PoseGraphResult> {
    ensure!(odometry.len() >= 2, "the odometry has {} pose(s); a pose graph needs at least 2", odometry.len());
    if let Some(i) = odometry.windows(2).position(|w| w[0].0 >= w[1].0) {
        bail!(
            "the odometry's stamps must increase: pose {} is stamped {}, pose {} {}",
            i + 1,
            odometry[i].0,
            i + 2,
            odometry[i + 1].0
        );
    }
    ensure!(params.max_nodes >= 2, "a pose graph needs at least 2 nodes");
    ensure!(
        params.robust_scale > 0.0 && params.robust_rotation_scale > 0.0 && params.loop_weight > 0.0,
        "the robust scales and the loop weight must be positive"
    );
    let stamps: Vec<Stamp> = odometry.iter().map(|(s, _)| *s).collect();
    let max_offset = Stamp::from_nanos((params.max_stamp_offset_s * 1e9).round() as i64);
    let index_of = |stamp: Stamp| nearest_stamp(&stamps, stamp, max_offset);
    let mut tied: Vec<(usize, usize, LoopConstraint)> = Vec::new();
    let (mut unmatched_loops, mut self_loops) = (0, 0);
    let first = odometry[0].1.translation.vector;
    let extent = odometry.iter().map(|(_, pose)| (pose.translation.vector - first).norm()).fold(0.0, f64::max);
    let (loops, implausible): (Vec<&LoopConstraint>, Vec<&LoopConstraint>) =
        loops.iter().partition(|constraint| plausible(constraint, extent));
    for constraint in loops {
        match (index_of(constraint.query_stamp), index_of(constraint.match_stamp)) {
            (Some(q), Some(m)) if q != m => tied.push((q, m, *constraint)),
            (Some(_), Some(_)) => self_loops += 1,
            _ => unmatched_loops += 1,
        }
    }
    let ends: BTreeSet<usize> = tied.iter().flat_map(|&(q, m, _)| [q, m]).collect();
    if ends.len() + 2 > params.max_nodes {
        bail!("{} loop ends need more than the {} nodes allowed (raise the node limit)", ends.len(), params.max_nodes);
    }
    // Every `spacing`-th pose, the loop ends and the last pose: at most `max_nodes` in all.
    let spacing = odometry.len().div_ceil(params.max_nodes - ends.len() - 1).max(1);
    let mut nodes: BTreeSet<usize> = (0..odometry.len()).step_by(spacing).collect();
    nodes.extend(&ends);
    nodes.insert(odometry.len() - 1);
    let nodes: Vec<usize> = nodes.into_iter().collect();
    let node_of = |index: usize| nodes.binary_search(&index).expect("loop ends are nodes");

    let bearing_measurements = |estimate: &[Isometry3<f64>]| -> Vec<Isometry3<f64>> {
        tied.iter()
            .map(|(q, m, constraint)| bearing_measurement(constraint, &estimate[node_of(*q)], &estimate[node_of(*m)]))
            .collect()
    };
    let loop_residuals = |estimate: &[Isometry3<f64>], measured: &[Isometry3<f64>]| -> Vec<(f64, f64)> {
        tied.iter()
            .zip(measured)
            .map(|(&(q, m, _), measured)| residual(measured, &estimate[node_of(q)], &estimate[node_of(m)]))
            .collect()
    };
    // Cauchy: rho'(r^2) = 1 / (1 + r^2 / c^2), the residual in units of the kernel's scale; the solver
    // scales residuals, hence the root.
    let cauchy = |scaled_residual: f64| (1.0 / (1.0 + scaled_residual.powi(2))).sqrt();
    let mut estimate: Vec<Isometry3<f64>> = nodes.iter().map(|&i| odometry[i].1).collect();
    let mut weights = vec![1.0; tied.len()];
    if !tied.is_empty() {
        // Stage one, rotations: every translation, measured and estimated, is left at zero, and stays
        // there (its gradient is zero).
        let rotation_only = |pose: Isometry3<f64>| Isometry3::from_parts(Translation3::identity(), pose.rotation);
        let measured: Vec<Isometry3<f64>> =
            tied.iter().map(|(_, _, constraint)| rotation_only(constraint.relative)).collect();
        // Kornia's edge: T_ab = T_b T_a⁻¹ for world-to-camera poses, i.e. a's camera frame into b's.
        let mut edges: Vec<PgoEdge> = nodes
            .windows(2)
            .enumerate()
            .map(|(k, w)| PgoEdge {
                pose_a: k,
                pose_b: k + 1,
                t_ab_meas: to_se3(&rotation_only(odometry[w[1]].1.inverse() * odometry[w[0]].1)),
                weight: 1.0,
            })
            .collect();
        let first_loop_edge = edges.len();
        edges.extend(tied.iter().zip(&measured).map(|(&(q, m, _), measured)| PgoEdge {
            pose_a: node_of(q),
            pose_b: node_of(m),
            t_ab_meas: to_se3(measured),
            weight: params.loop_weight as f32,
        }));
        let solver = PgoParams { max_iterations: params.iterations, ..PgoParams::default() };
        let mut poses: Vec<Pose3d> = estimate.iter().map(|&pose| to_kornia(&rotation_only(pose))).collect();
        let mut rotations: Vec<Isometry3<f64>> = poses.iter().map(from_kornia).collect();
        let largest = loop_residuals(&rotations, &measured).into_iter().map(|(_, r)| r).fold(0.0, f64::max);
        let mut scale = largest.max(params.robust_rotation_scale);
        loop {
            for (edge, w) in edges[first_loop_edge..].iter_mut().zip(&weights) {
                edge.weight = (params.loop_weight * w) as f32;
            }
            let solved = pose_graph_optimize(&poses, &edges, &[0], &solver)
                .map_err(|e| anyhow::anyhow!("{e}"))
                .context("pose-graph optimisation")?;
            poses = solved.poses;
            rotations = poses.iter().map(from_kornia).collect();
            weights = loop_residuals(&rotations, &measured).iter().map(|&(_, r)| cauchy(r / scale)).collect();
            if scale <= params.robust_rotation_scale {
                break;
            }
            scale = (scale / 2.0).max(params.robust_rotation_scale);
        }
        for (pose, solved) in estimate.iter_mut().zip(&rotations) {
            pose.rotation = solved.rotation;
        }

        // Stage two, positions for those rotations; loops up to scale as bearings.
        // The rotations are fixed now, so are the edges; only the loops' weights change between rounds.
        let odometry_edges: Vec<_> = nodes
            .windows(2)
            .enumerate()
            .map(|(k, w)| {
                let step = (odometry[w[0]].1.inverse() * odometry[w[1]].1).translation.vector;
                (k, k + 1, Matrix3::identity(), estimate[k].rotation * step)
            })
            .collect();
        let loop_edges: Vec<_> = tied
            .iter()
            .map(|&(q, m, constraint)| {
                // The measured translation, or direction, turned into the world by the match camera.
                let in_world = estimate[node_of(m)].rotation * constraint.relative.translation.vector;
                let (projection, offset) = if constraint.metric {
                    (Matrix3::identity(), in_world)
                } else {
                    (Matrix3::identity() - in_world * in_world.transpose(), Vector3::zeros())
                };
                (node_of(m), node_of(q), projection, offset)
            })
            .collect();
        let first = estimate[0].translation.vector;
        // Graduated as in stage one: from the largest translation residual of the first solution.
        let mut translation_scale = f64::INFINITY;
        for _ in 0..MAX_POSITION_ROUNDS {
            let weighted: Vec<_> = odometry_edges
                .iter()
                .map(|&(a, b, projection, offset)| (a, b, projection, offset, 1.0))
                .chain(
                    loop_edges
                        .iter()
                        .zip(&weights)
                        .map(|(&(a, b, projection, offset), w)| (a, b, projection, offset, params.loop_weight * w)),
                )
                .collect();
            let positions = positions_for_rotations(first, nodes.len(), &weighted)?;
            for (pose, position) in estimate.iter_mut().zip(positions) {
                pose.translation = Translation3::from(position);
            }
            let residuals = loop_residuals(&estimate, &bearing_measurements(&estimate));
            if translation_scale.is_infinite() {
                translation_scale = residuals.iter().map(|&(t, _)| t).fold(0.0, f64::max);
            }
            translation_scale = (translation_scale / 2.0).max(params.robust_scale);
            let renewed: Vec<f64> = residuals
                .iter()
                .map(|&(t, r)| cauchy((t / translation_scale).hypot(r / params.robust_rotation_scale)))
                .collect();
            let moved = renewed.iter().zip(&weights).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            weights = renewed;
            if moved < WEIGHT_TOLERANCE && translation_scale <= params.robust_scale {
                break;
            }
        }
    }
    // Every odometry pose moves with the node before it.
    let mut trajectory = Vec::with_capacity(odometry.len());
    let mut k = 0;
    for (i, (stamp, pose)) in odometry.iter().enumerate() {
        while k + 1 < nodes.len() && nodes[k + 1] <= i {
            k += 1;
        }
        let node = nodes[k];
        trajectory.push((*stamp, estimate[k] * (odometry[node].1.inverse() * pose)));
    }
    let loops = tied.iter().zip(&weights).map(|(&(q, m, _), &w)| (q, m, w)).collect();
    let implausible_loops = implausible.len();
    let loops_up_to_scale = tied.iter().filter(|(_, _, constraint)| !constraint.metric).count();
    Ok(PoseGraphResult {
        trajectory,
        loops,
        unmatched_loops,
        self_loops,
        implausible_loops,
        loops_up_to_scale,
        nodes: nodes.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::trajectory::absolute_trajectory_error;

    /// Two laps of a circle (radius 3 m), camera-to-world, looking along the path.
    fn circle(n: usize) -> Vec<(Stamp, Isometry3<f64>)> {
        (0..n)
            .map(|i| {
                let a = std::f64::consts::TAU * 2.0 * i as f64 / n as f64;
                let position = Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.0);
                let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), a + std::f64::consts::FRAC_PI_2);
                (
                    Stamp::from_nanos(i as i64 * 100_000_000),
                    Isometry3::from_parts(Translation3::from(position), rotation),
                )
            })
            .collect()
    }

    /// The truth with a heading error accumulating along the path.
    fn drifted(truth: &[(Stamp, Isometry3<f64>)]) -> Vec<(Stamp, Isometry3<f64>)> {
        let mut pose = truth[0].1;
        let mut out = vec![(truth[0].0, pose)];
        for w in truth.windows(2) {
            let step = w[0].1.inverse() * w[1].1;
            let error = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.004);
            pose *= Isometry3::from_parts(Translation3::from(step.translation.vector * 1.02), error * step.rotation);
            out.push((w[1].0, pose));
        }
        out
    }

    fn true_loop(truth: &[(Stamp, Isometry3<f64>)], query: usize, matched: usize) -> LoopConstraint {
        LoopConstraint {
            query_stamp: truth[query].0,
            match_stamp: truth[matched].0,
            relative: truth[matched].1.inverse() * truth[query].1,
            metric: true,
        }
    }

    #[test]
    fn true_loops_remove_the_drift_and_a_false_one_is_outweighed() {
        let truth = circle(120);
        let odometry = drifted(&truth);
        let before = absolute_trajectory_error(&odometry, &truth).unwrap().rmse;
        let mut loops: Vec<LoopConstraint> = (60..120).step_by(4).map(|q| true_loop(&truth, q, q - 60)).collect();
        // A false loop: a place on the other side of the circle claimed to be right here.
        loops.push(LoopConstraint { relative: Isometry3::identity(), ..true_loop(&truth, 90, 0) });
        let params = PoseGraphParams { max_nodes: 60, ..PoseGraphParams::default() };
        let result = optimise(&odometry, &loops, &params).unwrap();
        let after = absolute_trajectory_error(&result.trajectory, &truth).unwrap().rmse;
        assert!(before > 0.3, "the drift is large: {before}");
        // The loops fix the heading; the odometry's 2% scale error, the same on both laps, they cannot.
        assert!(after * 5.0 < before, "ATE {before} -> {after}");
        assert_eq!(result.trajectory.len(), truth.len());
        assert!(result.nodes <= params.max_nodes, "{} nodes", result.nodes);
        // The node limit holds with and without loop ends among the nodes.
        for (max_nodes, loops) in [(2, &loops[..0]), (7, &loops[..0]), (40, &loops[..])] {
            let params = PoseGraphParams { max_nodes, ..PoseGraphParams::default() };
            let nodes = optimise(&odometry, loops, &params).unwrap().nodes;
            assert!((2..=max_nodes).contains(&nodes), "{nodes} nodes for at most {max_nodes}");
        }
        let (_, _, false_weight) = *result.loops.last().unwrap();
        assert!(false_weight < 0.1, "the false loop keeps weight {false_weight}");
        assert!(result.loops[..result.loops.len() - 1].iter().all(|&(_, _, w)| w > 0.5), "{:?}", result.loops);
    }

    /// Loops that cannot be relative poses within the map (a corrupted row: a translation of 1e15, or
    /// not finite) are left out and counted; the map is corrected as without them.
    #[test]
    fn loops_far_beyond_the_map_are_left_out() {
        let truth = circle(120);
        let odometry = drifted(&truth);
        let loops: Vec<LoopConstraint> = (60..120).step_by(4).map(|q| true_loop(&truth, q, q - 60)).collect();
        let params = PoseGraphParams { max_nodes: 60, ..PoseGraphParams::default() };
        let clean = optimise(&odometry, &loops, &params).unwrap();
        let mut corrupted = loops.clone();
        for bad in [1e15, f64::NAN] {
            let mut row = true_loop(&truth, 90, 30);
            row.relative.translation.vector.x = bad;
            corrupted.push(row);
        }
        let result = optimise(&odometry, &corrupted, &params).unwrap();
        assert_eq!((result.implausible_loops, clean.implausible_loops), (2, 0));
        assert_eq!(result.trajectory, clean.trajectory);
    }

    /// A monocular tracker's loops: rotation and translation direction, no length.
    fn up_to_scale(constraint: LoopConstraint) -> LoopConstraint {
        let direction = constraint.relative.translation.vector.normalize();
        LoopConstraint {
            relative: Isometry3::from_parts(Translation3::from(direction), constraint.relative.rotation),
            metric: false,
            ..constraint
        }
    }

    #[test]
    fn loops_up_to_scale_remove_the_drift_in_the_maps_own_units() {
        let truth = circle(120);
        let before = absolute_trajectory_error(&drifted(&truth), &truth).unwrap().rmse;
        // Each second-lap pose matched to the first-lap pose two steps ahead (0.63 m away), and a
        // false loop: a place on the other side of the circle claimed to be just ahead.
        let mut loops: Vec<LoopConstraint> =
            (60..118).step_by(4).map(|q| up_to_scale(true_loop(&truth, q, q - 58))).collect();
        loops.push(LoopConstraint {
            relative: Isometry3::translation(0.0, 0.0, -1.0),
            ..up_to_scale(true_loop(&truth, 90, 0))
        });
        let params = PoseGraphParams { max_nodes: 60, ..PoseGraphParams::default() };
        let exact = optimise(&truth, &loops[..loops.len() - 1], &params).unwrap();
        assert!(absolute_trajectory_error(&exact.trajectory, &truth).unwrap().rmse < 1e-4, "exact odometry is kept");
        for units in [1.0, 10.0] {
            // The same odometry in a map ten times larger: directions have no scale.
            let scaled = |poses: &[(Stamp, Isometry3<f64>)]| -> Vec<(Stamp, Isometry3<f64>)> {
                poses
                    .iter()
                    .map(|&(s, p)| (s, Isometry3::from_parts((p.translation.vector * units).into(), p.rotation)))
                    .collect()
            };
            let params = PoseGraphParams { max_nodes: 60, robust_scale: 0.1 * units, ..PoseGraphParams::default() };
            let result = optimise(&scaled(&drifted(&truth)), &loops, &params).unwrap();
            let after = absolute_trajectory_error(&result.trajectory, &scaled(&truth)).unwrap().rmse / units;
            assert!(after * 5.0 < before, "{units}x units: ATE {before} -> {after}");
            let (true_loops, false_loop) = result.loops.split_at(result.loops.len() - 1);
            assert!(false_loop[0].2 < 0.1, "the false loop keeps weight {}", false_loop[0].2);
            assert!(true_loops.iter().all(|&(_, _, w)| w > 0.5), "{:?}", result.loops);
            // The graph gave the true loops their lengths, in the map's units (along a loop's own
            // direction only the odometry places its cameras, so not exactly).
            for &(q, m, _) in true_loops {
                let length = (result.trajectory[m].1.inverse() * result.trajectory[q].1).translation.vector.norm();
                let true_length = (truth[m].1.inverse() * truth[q].1).translation.vector.norm() * units;
                assert!(
                    (length - true_length).abs() < 0.2 * true_length,
                    "loop {q} -> {m}: {length} against {true_length}"
                );
            }
        }
    }

    #[test]
    fn without_loops_the_odometry_is_returned_and_bad_input_is_refused() {
        let truth = circle(20);
        let result = optimise(&truth, &[], &PoseGraphParams::default()).unwrap();
        assert!(result
            .trajectory
            .iter()
            .zip(&truth)
            .all(|(a, b)| a.0 == b.0 && (a.1.translation.vector - b.1.translation.vector).norm() < 1e-9));
        let far = LoopConstraint { query_stamp: Stamp::from_nanos(1 << 50), ..true_loop(&truth, 10, 0) };
        assert_eq!(optimise(&truth, &[far], &PoseGraphParams::default()).unwrap().unmatched_loops, 1);
        // Both ends on one pose: counted apart, not as a missing pose.
        let itself = LoopConstraint { match_stamp: truth[10].0, ..true_loop(&truth, 10, 0) };
        let result = optimise(&truth, &[itself], &PoseGraphParams::default()).unwrap();
        assert_eq!((result.self_loops, result.unmatched_loops), (1, 0));
        assert!(optimise(&truth[..1], &[], &PoseGraphParams::default()).is_err());
        let mut swapped = truth.clone();
        swapped.swap(3, 4);
        let err = optimise(&swapped, &[], &PoseGraphParams::default()).unwrap_err().to_string();
        assert!(err.contains("pose 4 is stamped") && err.contains("pose 5"), "{err}");
    }
}
