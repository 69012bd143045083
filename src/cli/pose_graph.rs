//! `ecm-lcd pose-graph`: an odometry trajectory and the loop candidates of a replay in, the trajectory
//! corrected by SE(3) pose-graph optimisation out ([`ecm_lcd::pose_graph`]), with the absolute trajectory
//! error before and after against ground truth and a figure like the paper's Fig. 11.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use nalgebra::Vector3;

use ecm_lcd::eval::trajectory::absolute_trajectory_error;
use ecm_lcd::eval::{plot_trajectories, TrajectoryPlot};
use ecm_lcd::io::candidates::read_candidates_csv;
use ecm_lcd::io::output::ensure_not_an_input;
use ecm_lcd::io::tum::{read_groundtruth, write_trajectory};
use ecm_lcd::pose_graph::{optimise, LoopConstraint, PoseGraphParams};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Odometry trajectory, TUM format (`timestamp tx ty tz qx qy qz qw`, camera-to-world), e.g. a
    /// tracker's keyframe poses or `synth`'s `odometry.txt`.
    #[arg(long)]
    pub odometry: PathBuf,
    /// Loop candidates CSV of `ecm-lcd replay` (those with a verified relative pose are used: metric
    /// ones in full, those up to scale for their rotation and translation direction).
    #[arg(long)]
    pub candidates: PathBuf,
    /// Use only the loops with a metric relative pose (verified with depth).
    #[arg(long)]
    pub metric_only: bool,
    /// Corrected trajectory, TUM format.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Ground truth (TUM format) to measure the ATE before and after against.
    #[arg(long)]
    pub groundtruth: Option<PathBuf>,
    /// Draw ground truth, odometry, corrected trajectory and loop edges into this PNG.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Print a JSON summary on stdout instead of text.
    #[arg(long)]
    pub json: bool,
    /// Most nodes in the graph.
    #[arg(long, default_value_t = PoseGraphParams::default().max_nodes as u32, value_parser = clap::value_parser!(u32).range(2..=2000))]
    pub max_nodes: u32,
    /// Final scale of the robust (Cauchy) kernel on the loops' translation, in the odometry's units.
    #[arg(long, default_value_t = PoseGraphParams::default().robust_scale)]
    pub robust_scale: f64,
    /// Final scale of the robust (Cauchy) kernel on the loops' rotation, radians.
    #[arg(long, default_value_t = PoseGraphParams::default().robust_rotation_scale)]
    pub robust_rotation_scale: f64,
    /// Weight of a loop edge against an odometry edge's 1.
    #[arg(long, default_value_t = PoseGraphParams::default().loop_weight)]
    pub loop_weight: f64,
}

pub fn run(args: Args) -> Result<()> {
    let mut inputs = vec![args.odometry.as_path(), args.candidates.as_path()];
    inputs.extend(args.groundtruth.as_deref());
    ensure_not_an_input(&args.output, &inputs)?;
    let mut outputs = vec![("-o", args.output.as_path())];
    if let Some(plot) = &args.plot {
        ensure_not_an_input(plot, &inputs)?;
        ecm_lcd::io::output::ensure_png(plot, "--plot")?;
        outputs.push(("--plot", plot));
    }
    ecm_lcd::io::output::ensure_writable_outputs(&outputs)?;
    for (name, value) in [
        ("--robust-scale", args.robust_scale),
        ("--robust-rotation-scale", args.robust_rotation_scale),
        ("--loop-weight", args.loop_weight),
    ] {
        if !(value.is_finite() && value > 0.0 && value <= 1e6) {
            bail!("{name} must be positive and finite, got {value}");
        }
    }
    let odometry = read_groundtruth(&args.odometry)
        .with_context(|| format!("reading the odometry {}", args.odometry.display()))?;
    let candidates = read_candidates_csv(&args.candidates)?;
    let groundtruth = match &args.groundtruth {
        Some(path) => {
            Some(read_groundtruth(path).with_context(|| format!("reading the ground truth {}", path.display()))?)
        }
        None => None,
    };
    let (loops, left_out) = LoopConstraint::from_candidates(&candidates, args.metric_only);
    if left_out > 0 {
        let pose = if args.metric_only { "metric relative pose (no depth" } else { "relative pose (not verified" };
        log::warn!("{left_out} of {} candidates have no {pose}, or no intrinsics) and are not used", candidates.len());
    }
    let params = PoseGraphParams {
        max_nodes: args.max_nodes as usize,
        robust_scale: args.robust_scale,
        robust_rotation_scale: args.robust_rotation_scale,
        loop_weight: args.loop_weight,
        ..PoseGraphParams::default()
    };
    let started = std::time::Instant::now();
    let result =
        optimise(&odometry, &loops, &params).with_context(|| format!("the odometry {}", args.odometry.display()))?;
    let seconds = started.elapsed().as_secs_f64();
    if result.unmatched_loops > 0 {
        log::warn!(
            "{} loops name keyframes with no odometry pose within {} s; not used",
            result.unmatched_loops,
            params.max_stamp_offset_s
        );
    }
    if result.self_loops > 0 {
        log::warn!(
            "{} loops tie both their keyframes to one odometry pose (within {} s of it); not used",
            result.self_loops,
            params.max_stamp_offset_s
        );
    }
    if result.implausible_loops > 0 {
        log::warn!(
            "{} loops are no relative pose within this map (not finite, or metric and longer than twice the \
             odometry's extent); not used",
            result.implausible_loops
        );
    }
    if !candidates.is_empty() && result.loops.is_empty() {
        let stamps = |poses: &[(ecm_lcd::types::Stamp, _)]| format!("{} to {}", poses[0].0, poses[poses.len() - 1].0);
        let mut candidate_stamps: Vec<_> = candidates.iter().flat_map(|c| [c.query_stamp, c.match_stamp]).collect();
        candidate_stamps.sort();
        bail!(
            "none of the {} candidates in {} gives a loop edge, so nothing would be corrected: {left_out} carry no \
             {}, {} name keyframes with no odometry pose within {} s (the odometry runs from {}, the candidates' \
             keyframes from {} to {}: stamps in another time base?), {} tie both keyframes to one pose, {} are \
             implausible",
            candidates.len(),
            args.candidates.display(),
            if args.metric_only { "metric relative pose" } else { "relative pose (replay with camera intrinsics)" },
            result.unmatched_loops,
            params.max_stamp_offset_s,
            stamps(&odometry),
            candidate_stamps[0],
            candidate_stamps[candidate_stamps.len() - 1],
            result.self_loops,
            result.implausible_loops
        );
    }
    let kept = result.loops.iter().filter(|&&(_, _, w)| w >= 0.5).count();
    // Everything that can fail is done before the outputs are written; the corrected trajectory,
    // the main output, is written first, so that a failing -o leaves no plot of it.
    let errors = match &groundtruth {
        Some(truth) => {
            Some((absolute_trajectory_error(&odometry, truth)?, absolute_trajectory_error(&result.trajectory, truth)?))
        }
        None => None,
    };
    write_trajectory(&args.output, &result.trajectory)?;
    if let Some(path) = &args.plot {
        let positions = |poses: &[(ecm_lcd::types::Stamp, nalgebra::Isometry3<f64>)],
                         alignment: nalgebra::Isometry3<f64>|
         -> Vec<Vector3<f64>> {
            poses.iter().map(|(_, p)| (alignment * p).translation.vector).collect()
        };
        let identity = nalgebra::Isometry3::identity();
        let (odometry_alignment, corrected_alignment) =
            errors.as_ref().map_or((identity, identity), |(b, a)| (b.alignment, a.alignment));
        let corrected = positions(&result.trajectory, corrected_alignment);
        let loop_lines: Vec<_> =
            result.loops.iter().filter(|&&(_, _, w)| w >= 0.5).map(|&(q, m, _)| (corrected[q], corrected[m])).collect();
        let title = match &errors {
            Some((before, after)) => {
                format!("ATE RMSE {:.3} m (odometry) -> {:.3} m (corrected), {kept} loops", before.rmse, after.rmse)
            }
            None => format!("corrected with {kept} loops"),
        };
        plot_trajectories(
            &TrajectoryPlot {
                title: &title,
                groundtruth: &groundtruth.as_deref().map(|t| positions(t, identity)).unwrap_or_default(),
                odometry: &positions(&odometry, odometry_alignment),
                corrected: &corrected,
                loops: &loop_lines,
            },
            path,
        )?;
    }
    if args.json {
        let summary = serde_json::json!({
            "poses": result.trajectory.len(),
            "nodes": result.nodes,
            "candidates": candidates.len(),
            "loops": result.loops.len(),
            "loops_kept": kept,
            "loops_up_to_scale": result.loops_up_to_scale,
            "loops_not_used": left_out,
            "loops_unmatched": result.unmatched_loops,
            "loops_implausible": result.implausible_loops,
            "loops_on_one_pose": result.self_loops,
            "seconds": seconds,
            "ate_rmse_before_m": errors.as_ref().map(|(b, _)| b.rmse),
            "ate_rmse_after_m": errors.as_ref().map(|(_, a)| a.rmse),
        });
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!(
            "{} poses, {} nodes, {} loop edges ({} up to scale; {kept} kept by the robust kernel), {:.2} s; \
             corrected trajectory in {}",
            result.trajectory.len(),
            result.nodes,
            result.loops.len(),
            result.loops_up_to_scale,
            seconds,
            args.output.display()
        );
        if let Some((before, after)) = &errors {
            println!(
                "ATE RMSE against ground truth: {:.4} m before, {:.4} m after ({:.1}x lower; {} poses paired)",
                before.rmse,
                after.rmse,
                before.rmse / after.rmse.max(1e-12),
                after.pairs
            );
        }
    }
    Ok(())
}
