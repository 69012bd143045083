//! Command-line interface: one sub-module per sub-command, each a thin shell over the library.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

pub mod eval;
pub mod synth;

#[derive(Parser, Debug)]
#[command(name = "ecm-lcd", version, about = "Loop-closure detection for visual SLAM with ECMobileNet descriptors")]
pub struct Cli {
    /// Compute threads (default: number of CPUs).
    #[arg(long, global = true)]
    pub threads: Option<usize>,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Render a synthetic looping indoor sequence (TUM folder with exact ground truth).
    Synth(synth::Args),
}

/// Parses the command line, runs the command and turns an error into one line on stderr.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("info"))
        .format_timestamp_millis()
        .init();
    crate::runtime::init_threads(cli.threads);
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
        Command::Synth(args) => synth::run(args),
    }
}
