//! The `ecm-lcd` command line: one sub-module per sub-command, each a thin shell over the library.

pub mod db;
pub mod demo;
pub mod distill;
pub mod eval;
#[cfg(test)]
mod launch_file;
pub mod learn_projection;
pub mod listen;
pub mod matching;
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

#[derive(Parser, Debug)]
#[command(name = "ecm-lcd", version, about = "Loop-closure detection for visual SLAM with ECMobileNet descriptors")]
pub struct Cli {
    /// Compute threads, 1 to 1024 (default: number of CPUs).
    #[arg(long, global = true, value_parser = ecm_lcd::runtime::parse_threads)]
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
    /// Place each query frame on a map made before, without ground truth: match, score, verified pose (CSV).
    Match(matching::Args),
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

/// `seconds` as a duration, refused naming `flag` where it is negative, not a number, or longer than a
/// duration holds (a plain conversion would panic).
fn seconds_arg(flag: &str, seconds: f64) -> anyhow::Result<std::time::Duration> {
    std::time::Duration::try_from_secs_f64(seconds)
        .map_err(|_| anyhow::anyhow!("{flag} must be a number of seconds from 0 up, got {seconds}"))
}

/// Parses the command line, runs the command and turns an error into one line on stderr.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    ecm_lcd::runtime::init_process(cli.threads);
    match run(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
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
        Command::Match(args) => matching::run(args),
        Command::PoseGraph(args) => pose_graph::run(args),
        Command::LearnProjection(args) => learn_projection::run(args),
        Command::Db(args) => db::run(args),
        Command::Train(args) => train::run(args),
        Command::Distill(args) => distill::run(args),
        Command::TrainPlace(args) => train_place::run(args),
    }
}
