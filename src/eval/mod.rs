//! Evaluation against ground truth: loop ground truth from poses or lists, precision-recall, plots.
//!
//! The caller runs the detector over a source and hands in one [`QueryResult`] per query; this
//! module decides which of those are right ([`truth`]), scores them ([`metrics`]) and writes the
//! curve, plot and summary ([`report`]). [`trajectory`] measures a corrected trajectory (ATE).

pub mod metrics;
pub mod report;
pub mod revisit;
pub mod trajectory;
pub mod truth;

pub use metrics::{evaluate, Metrics, PrPoint, QueryResult};
pub use report::{plot_pr_curve, plot_trajectories, summary_json, write_curve_csv, TrajectoryPlot};
pub use truth::{
    images_in_name_order, loop_truth_from_poses, parse_loops, poses_at_stamps, read_loops, LoopTruth, PoseLoopCriteria,
};
