//! `ecm-lcd param get|set NODE NAME [VALUE]`: reads or changes a parameter of a running node through the
//! standard ROS 2 parameter services, like `ros2 param get|set` (for machines without a ROS 2 install).
//! VALUE is read as `-p` reads it (YAML scalar: `true`, `3`, `0.4`, `text`) and must be of the
//! parameter's type, with the node's few conversions (`crate::config`'s module doc: an integer serves a
//! double, `yes` a bool). A refused value is an error that carries the node's reason (exit status 1).

use anyhow::{bail, Context as _, Result};

use ecm_lcd::ros::args::parse_param_value;
use ecm_lcd::ros::params::{from_ros, to_ros};
use ecm_lcd::ros::peer::ParamClient;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    pub action: Action,
    /// Seconds to wait for the node's service to appear and answer.
    #[arg(long, global = true, default_value_t = 10.0)]
    pub timeout: f64,
}

#[derive(clap::Subcommand, Debug)]
pub enum Action {
    /// Print a parameter's value.
    Get {
        /// Fully qualified node name, e.g. /ecm_lcd.
        node: String,
        name: String,
    },
    /// Set a parameter (validated by the node; a refusal prints its reason).
    Set {
        /// Fully qualified node name, e.g. /ecm_lcd.
        node: String,
        name: String,
        value: String,
    },
}

pub fn run(args: Args) -> Result<()> {
    if args.timeout.is_nan() || args.timeout <= 0.0 {
        bail!("--timeout must be a positive number of seconds, got {}", args.timeout);
    }
    let timeout = super::seconds_arg("--timeout", args.timeout)?;
    let context = ros2_client::Context::new().context("creating the DDS participant")?;
    match args.action {
        Action::Get { node, name } => {
            let client = ParamClient::new(&context, &node, timeout)?;
            let value = client.get(&name)?;
            match from_ros(&value) {
                Ok(value) => println!("{value}"),
                Err(_) if matches!(value, ros2_client::ParameterValue::NotSet) => {
                    bail!("node {node} has no parameter {name}")
                }
                Err(reason) => bail!("{node} {name}: {reason}"),
            }
        }
        Action::Set { node, name, value } => {
            let parsed = parse_param_value(&value)?;
            let client = ParamClient::new(&context, &node, timeout)?;
            match client.set(&name, to_ros(&parsed))? {
                Ok(()) => println!("set {node} {name} = {parsed}"),
                Err(reason) => bail!("node {node} refused {name} = {parsed}: {reason}"),
            }
        }
    }
    Ok(())
}
