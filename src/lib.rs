//! ecm-lcd: loop-closure detection for visual SLAM with ECMobileNet global descriptors.
//!
//! Data flows one way, and the modules follow it:
//! image ([`io`], [`preprocess`]) -> tensor -> network ([`model`]) -> descriptor ([`descriptor`])
//! -> keyframe database and detector ([`detector`]) -> geometric verification ([`verification`]) -> loop
//! candidate -> publisher ([`ros`], CSV).
//! [`pipeline`] wires those stages together for the offline commands and the node alike;
//! [`pose_graph`] is a back end that uses the candidates (drift removed from an odometry trajectory);
//! [`eval`] measures the result against ground truth and [`synth`] makes test sequences.
//! Nothing below [`ros`] needs DDS.

pub mod config;
pub mod descriptor;
pub mod detector;
pub mod eval;
pub mod io;
pub mod model;
pub mod pipeline;
pub mod pose_graph;
pub mod preprocess;
pub mod replay;
pub mod ros;
pub mod runtime;
pub mod synth;
pub mod train;
pub mod types;
pub mod verification;
