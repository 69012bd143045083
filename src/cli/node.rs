//! `ecm-lcd node [OPTIONS] [--ros-args ...]`: runs the loop-closure detector as the ROS 2 node
//! `/ecm_lcd` (see [`ecm_lcd::ros::node`] for topics, QoS, parameters and the drop policy). ROS arguments
//! follow `--ros-args` as `ros2 run`/`ros2 launch` pass them (see [`ecm_lcd::ros::args`]).
//!
//! SIGINT (Ctrl-C, `ros2 launch` shutdown) and SIGTERM (`kill`, systemd) stop the node cleanly: the
//! keyframes already queued are processed and published, then it logs its final counters and exits 0.
//! A second signal while it is stopping ends the process at once.

use anyhow::{Context as _, Result};
use signal_hook::consts::{SIGINT, SIGTERM};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use ecm_lcd::config::Params;
use ecm_lcd::ros::args::RosArgs;
use ecm_lcd::ros::node::{
    run_node, FrameInputs, InputQos, KeyframeProcessor, NodeCounters, NodeSettings, DEFAULT_NODE_NAME,
};
use ecm_lcd::ros::params::initial_params;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// QoS of the input subscriptions.
    #[arg(long, value_enum, default_value_t = InputQos::Reliable)]
    pub input_qos: InputQos,
    /// Frame topics to subscribe: `keyframes` beside a tracker, `image` or `compressed` on a camera
    /// alone (one camera stream: raw and compressed are the same frames twice).
    #[arg(long, value_enum, default_value_t = FrameInputs::All)]
    pub input: FrameInputs,
    /// Capacity of the queue in front of the worker (full: the oldest message is dropped and counted).
    #[arg(long, default_value_t = 4)]
    pub queue: usize,
    /// Weights file (default: the usual resolution, see README "Weights").
    #[arg(long)]
    pub weights: Option<std::path::PathBuf>,
    /// Persistent keyframe database (SQLite; created if missing): stored keyframes are the starting
    /// history, counted ids continue after the largest stored id, and every keyframe is committed
    /// before its candidates are published.
    #[arg(long, value_name = "PATH")]
    pub db: Option<std::path::PathBuf>,
    /// ROS arguments: `--ros-args -p name:=value -r from:=to --params-file FILE -r __ns:=/ns ...`.
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, value_name = "ROS_ARGS")]
    pub ros_args: Vec<String>,
}

/// Runs the node over the full pipeline (network, descriptor, selection, detector).
pub fn run(args: Args) -> Result<()> {
    let weights = args.weights.clone();
    let db = args.db.clone();
    run_with(args, move |params| {
        let mut pipeline = ecm_lcd::pipeline::Pipeline::new(params.clone(), weights.as_deref())?;
        // The node publishes candidates only: no check of a best match that is not one.
        pipeline.set_verify_best(false);
        if let Some(db) = &db {
            pipeline.open_store(db)?;
        }
        Ok(Box::new(pipeline))
    })
}

/// Runs the node with the processor `make_processor` builds from the starting parameters.
pub fn run_with(args: Args, make_processor: impl FnOnce(&Params) -> Result<Box<dyn KeyframeProcessor>>) -> Result<()> {
    let ros_args = RosArgs::parse(&args.ros_args, DEFAULT_NODE_NAME).context("reading the ROS arguments")?;
    // `--log-level` also set the logger's filter at start when RUST_LOG is unset (`cli::main`); here
    // it caps the level under a RUST_LOG that asks for more.
    if let Some(level) = ros_args.log_level {
        log::set_max_level(level);
    }
    for flag in &ros_args.ignored {
        log::info!("ROS argument {flag} has no effect in ecm-lcd");
    }
    let fqn = ros_args.fully_qualified_node_name(DEFAULT_NODE_NAME);
    let (params, use_sim_time) = initial_params(&ros_args, &fqn)?;
    let processor = make_processor(&params)?;
    let settings = NodeSettings {
        ros_args,
        input_qos: args.input_qos,
        inputs: args.input,
        queue_capacity: args.queue,
        ..Default::default()
    };
    let counters = Arc::new(NodeCounters::default());
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [SIGINT, SIGTERM] {
        // Registered first, so it sees the flag as it was before this signal: set means a second signal.
        signal_hook::flag::register_conditional_shutdown(signal, 1, stop.clone())
            .with_context(|| format!("installing the handler for signal {signal}"))?;
        signal_hook::flag::register(signal, stop.clone())
            .with_context(|| format!("installing the handler for signal {signal}"))?;
    }
    run_node(&settings, params, use_sim_time, processor, counters, stop)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Wrapper {
        #[command(flatten)]
        args: Args,
    }

    #[test]
    fn ros_arguments_pass_through_clap() {
        let w = Wrapper::try_parse_from([
            "node",
            "--input-qos",
            "sensor-data",
            "--input",
            "keyframes",
            "--ros-args",
            "-r",
            "__ns:=/r",
            "-p",
            "detector.min_score:=0.5",
            "--params-file",
            "p.yaml",
        ])
        .unwrap();
        assert_eq!(w.args.input_qos, InputQos::SensorData);
        assert_eq!(w.args.input, FrameInputs::Keyframes);
        let ros = RosArgs::parse(&w.args.ros_args, DEFAULT_NODE_NAME).unwrap();
        assert_eq!(ros.namespace(), "/r");
        assert_eq!(ros.params.len(), 1);
        assert_eq!(ros.params_files.len(), 1);
    }
}
