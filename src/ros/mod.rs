//! The ROS 2 node: a thin layer over [`crate::pipeline`] on ros2-client.
//!
//! [`node`] runs the node around a [`node::KeyframeProcessor`]; [`args`] reads `--ros-args`;
//! [`params`] declares and validates the parameters; [`msgs`] holds the `ecm_lcd_msgs` types;
//! [`queue`] is the bounded drop-oldest queue in front of the worker.

pub mod args;
pub mod msgs;
pub mod node;
pub mod param_services;
pub mod params;
pub mod peer;
pub mod queue;

pub use node::{run_node, CountersSnapshot, InputQos, KeyframeProcessor, NodeCounters, NodeSettings};
