//! Command-line interface: one sub-module per sub-command, each a thin shell over the library.

pub mod db;
pub mod demo;
pub mod distill;
pub mod eval;
pub mod learn_projection;
pub mod listen;
pub mod model;
pub mod node;
pub mod param;
pub mod play_keyframes;
pub mod pose_graph;
pub mod replay;
pub mod synth;
pub mod train;
pub mod train_place;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// `--threads`: 1 to 1024. (A `usize`, as the subcommands that take their own `--threads` lists
/// read the same argument id.)
pub fn parse_threads(text: &str) -> Result<usize, String> {
    match text.parse::<usize>() {
        Ok(n) if (1..=1024).contains(&n) => Ok(n),
        _ => Err(format!("{text:?} is not a thread count from 1 to 1024")),
    }
}

#[derive(Parser, Debug)]
#[command(name = "ecm-lcd", version, about = "Loop-closure detection for visual SLAM with ECMobileNet descriptors")]
pub struct Cli {
    /// Compute threads, 1 to 1024 (default: number of CPUs).
    #[arg(long, global = true, value_parser = parse_threads)]
    pub threads: Option<usize>,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// The main job: replay the bundled sample (bags/), print loop candidates and precision-recall.
    Demo(demo::Args),
    /// Import MobileNetV2 weights from a TFLite model into safetensors.
    ImportWeights(model::ImportArgs),
    /// Parameter count and multiply-accumulates of a network.
    ModelInfo(model::InfoArgs),
    /// Top ImageNet classes of images (checks the weights).
    Classify(model::ClassifyArgs),
    /// The pooled 1280-d descriptor of images, as CSV.
    Embed(model::EmbedArgs),
    /// The ROS 2 node: keyframes in, loop candidates out (ROS arguments after --ros-args).
    Node(node::Args),
    /// Tracker stand-in: publish the frames of a replay source as ROS 2 keyframes or images.
    PlayKeyframes(play_keyframes::Args),
    /// Print the loop candidates published on a topic, as CSV.
    Listen(listen::Args),
    /// Replay a source (TUM folder, ROS 1/2 bag, image folder) offline; loop candidates as CSV.
    Replay(replay::Args),
    /// Replay a source and score the detector against ground truth (precision-recall).
    Eval(eval::Args),
    /// Get or set a parameter of a running node (like `ros2 param get|set`).
    Param(param::Args),
    /// Render a synthetic looping indoor sequence (TUM folder with exact ground truth).
    Synth(synth::Args),
    /// Correct an odometry trajectory with the loop candidates (SE(3) pose graph); ATE and a Fig. 11 plot.
    PoseGraph(pose_graph::Args),
    /// Learn a PCA projection of the descriptor from images (no labels) for descriptor.projection.
    LearnProjection(learn_projection::Args),
    /// Inspect, export and merge persistent keyframe databases (--db).
    Db(db::Args),
    /// Train ECMobileNet or MobileNetV2 on an image folder (the paper's classification recipe).
    Train(train::Args),
    /// Distil a MobileNetV2 teacher's descriptor into ECMobileNet on unlabelled images.
    Distill(distill::Args),
    /// Train the network for loop closure: the detector's descriptor, triplets of revisits and other places.
    TrainPlace(train_place::Args),
}

/// Parses the command line, runs the command and turns an error into one line on stderr.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    init_process(cli.threads);
    match run(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

/// What every program of the crate sets up first: the log (see [`default_log_filter`]), the compute
/// threads and the allocator's handling of freed memory.
pub fn init_process(threads: Option<usize>) {
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or(default_log_filter(std::env::args())))
        .format_timestamp_millis()
        .init();
    crate::runtime::init_threads(threads);
    crate::runtime::keep_freed_memory();
}

/// The log filter when `RUST_LOG` is unset: ecm-lcd's own lines at `info` (or at the level of a ROS
/// `--log-level LEVEL` among the arguments), dependencies at `warn`, RustDDS at `error` (it logs
/// protocol details as `info` and `warn`, hundreds of lines a second with some peers), and
/// ros2-client's ROS_DISTRO check at `error` (ecm-lcd needs no ROS install).
fn default_log_filter(args: impl Iterator<Item = String>) -> String {
    let args: Vec<String> = args.collect();
    let level = args
        .windows(2)
        .filter(|pair| pair[0] == "--log-level")
        .filter_map(|pair| {
            // `[logger:=]LEVEL`; rcl's `fatal` is `error` here.
            let level = pair[1].rsplit(":=").next()?.to_ascii_lowercase();
            match level.as_str() {
                "debug" | "info" | "warn" | "error" => Some(level),
                "fatal" => Some("error".to_string()),
                _ => None,
            }
        })
        .next_back()
        .unwrap_or_else(|| "info".to_string());
    format!("ecm_lcd={level},rustdds=error,ros2_client::distributions=error,warn")
}

fn run(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Demo(args) => demo::run(args),
        Command::ImportWeights(args) => model::import_weights(args),
        Command::ModelInfo(args) => model::model_info(args),
        Command::Classify(args) => model::classify(args),
        Command::Embed(args) => model::embed(args),
        Command::Node(args) => node::run(args),
        Command::PlayKeyframes(args) => play_keyframes::run(args),
        Command::Listen(args) => listen::run(args),
        Command::Param(args) => param::run(args),
        Command::Synth(args) => synth::run(args),
        Command::Replay(args) => replay::run(args),
        Command::Eval(args) => eval::run(args),
        Command::PoseGraph(args) => pose_graph::run(args),
        Command::LearnProjection(args) => learn_projection::run(args),
        Command::Db(args) => db::run(args),
        Command::Train(args) => train::run(args),
        Command::Distill(args) => distill::run(args),
        Command::TrainPlace(args) => train_place::run(args),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn logs_are_ours_at_info_and_dependencies_at_warn_unless_a_level_is_asked_for() {
        let args = |list: &[&str]| list.iter().map(|s| s.to_string()).collect::<Vec<_>>().into_iter();
        let ours = |filter: String| filter.split(',').next().unwrap().to_string();
        let filter = default_log_filter(args(&["ecm-lcd", "node"]));
        assert_eq!(filter, "ecm_lcd=info,rustdds=error,ros2_client::distributions=error,warn");
        assert_eq!(
            ours(default_log_filter(args(&["ecm-lcd", "node", "--ros-args", "--log-level", "debug"]))),
            "ecm_lcd=debug"
        );
        assert_eq!(
            ours(default_log_filter(args(&["ecm-lcd", "node", "--ros-args", "--log-level", "ecm_lcd:=WARN"]))),
            "ecm_lcd=warn"
        );
        assert_eq!(
            ours(default_log_filter(args(&["ecm-lcd", "node", "--ros-args", "--log-level", "fatal"]))),
            "ecm_lcd=error"
        );
        assert_eq!(
            ours(default_log_filter(args(&["ecm-lcd", "node", "--ros-args", "--log-level", "loud"]))),
            "ecm_lcd=info"
        );
    }
}
