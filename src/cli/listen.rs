//! `ecm-lcd listen`: prints the LoopCandidates published on a topic as CSV
//! (`query_id,query_stamp,match_id,match_stamp,distance,score,rank,loop_type,inliers`; `loop_type` as
//! in LoopCandidate.msg: 0 appearance only, 1 verified, 2 with a pose up to scale, 3 metric), for checks
//! and demos.

use anyhow::{Context as _, Result};
use std::io::Write;
use std::time::{Duration, Instant};

use ecm_lcd::ros::peer::CandidateListener;
use ecm_lcd::types::Stamp;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Topic to listen on.
    #[arg(long, default_value = "/loop_candidates")]
    pub topic: String,
    /// Exit after this many candidates.
    #[arg(long)]
    pub count: Option<usize>,
    /// Exit after this many seconds without a new candidate (default: never).
    #[arg(long)]
    pub idle_timeout: Option<f64>,
    /// Before printing the CSV header, wait up to this many seconds until a publisher (the node) is
    /// matched, and fail if none is: the header then tells a script that candidates will arrive.
    #[arg(long)]
    pub wait_publisher: Option<f64>,
}

pub fn run(args: Args) -> Result<()> {
    let context = ros2_client::Context::new().context("creating the DDS participant")?;
    let listener = CandidateListener::new(&context, &args.topic)?;
    if let Some(wait) = args.wait_publisher {
        if !listener.wait_for_publisher(Duration::from_secs_f64(wait.max(0.0))) {
            anyhow::bail!("no publisher on {} after {wait} s", args.topic);
        }
        log::info!("matched a publisher on {}", args.topic);
    }
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    writeln!(out, "query_id,query_stamp,match_id,match_stamp,distance,score,rank,loop_type,inliers")?;
    out.flush()?;
    let mut received = 0usize;
    let mut last = Instant::now();
    loop {
        for c in listener.wait(Duration::from_millis(100))? {
            writeln!(
                out,
                "{},{},{},{},{},{},{},{},{}",
                c.query_id,
                Stamp::from(c.header.stamp),
                c.match_id,
                Stamp::from(c.match_stamp),
                c.distance,
                c.score,
                c.rank,
                c.loop_type,
                c.inliers
            )?;
            out.flush()?;
            received += 1;
            last = Instant::now();
            if args.count.is_some_and(|n| received >= n) {
                return Ok(());
            }
        }
        if args.idle_timeout.is_some_and(|t| last.elapsed() >= Duration::from_secs_f64(t)) {
            log::info!("no candidate for {} s; received {received}", args.idle_timeout.unwrap_or_default());
            return Ok(());
        }
    }
}
