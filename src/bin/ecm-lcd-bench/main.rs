//! `ecm-lcd-bench`: the developer's measuring programs, apart from the user's `ecm-lcd` binary:
//! `speed` (the speed goals side by side: network, ONNX Runtime, preprocessing, search, end to end,
//! memory), `node` (the node's publish -> candidate latency over DDS) and `load-test` (a keyframe
//! burst into the node). Programs that measure and print, not tests; the node-facing ones start the
//! `ecm-lcd` binary beside this one inside a private network namespace.

mod load_test;
mod node;
mod speed;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context as _;
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(name = "ecm-lcd-bench", version, about = "ecm-lcd's measuring programs (not tests)")]
struct Cli {
    /// Compute threads, 1 to 1024 (default: number of CPUs).
    #[arg(long, global = true, value_parser = ecm_lcd::runtime::parse_threads)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// The speed goals side by side: network forward per thread count, ONNX Runtime, preprocessing,
    /// search, end to end and memory.
    Speed(speed::BenchArgs),
    /// The node's latency from keyframe publish to candidate receipt (private network namespace).
    Node(node::Args),
    /// A 10x keyframe burst into the node, parameter calls during it, drops and memory.
    LoadTest(load_test::Args),
}

/// The `ecm-lcd` binary beside this one (the node the programs measure).
fn user_binary() -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe().context("finding this program")?;
    let user = exe.with_file_name(format!("ecm-lcd{}", std::env::consts::EXE_SUFFIX));
    anyhow::ensure!(
        user.is_file(),
        "{} not found beside {} (cargo build --release builds both)",
        user.display(),
        exe.display()
    );
    Ok(user)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    ecm_lcd::runtime::init_process(cli.threads);
    let result = match cli.command {
        Command::Speed(args) => speed::run(args),
        Command::Node(args) => node::run(args),
        Command::LoadTest(args) => load_test::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}
