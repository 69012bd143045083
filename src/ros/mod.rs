//! The ROS 2 node: a thin layer over [`crate::pipeline`] on ros2-client.
//!
//! [`node`] runs the node around a [`node::KeyframeProcessor`]; [`args`] reads `--ros-args`;
//! [`params`] declares and validates the parameters; [`msgs`] holds the `ecm_lcd_msgs` types;
//! [`queue`] is the bounded drop-oldest queue in front of the worker; [`peer`] holds the other side
//! (tracker stand-in, candidate listener, parameter client) for tools and tests; [`service`] serves
//! both request framings RMWs use (the parameter services run on it); [`netns`] makes the
//! private network namespaces that tests and the benchmark run their DDS participants in.

pub mod args;
pub mod msgs;
pub mod netns;
pub mod node;
pub mod param_services;
pub mod params;
pub mod peer;
pub mod queue;
pub mod service;

pub use node::{run_node, CountersSnapshot, InputQos, KeyframeProcessor, NodeCounters, NodeSettings};
