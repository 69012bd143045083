//! The ROS 2 node: a thin layer over [`crate::pipeline`] on ros2-client.

pub mod args;
pub mod msgs;
pub mod queue;
