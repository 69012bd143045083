//! `ecm-lcd listen`: prints the LoopCandidates published on a topic as CSV: the columns of `replay`'s
//! candidates CSV (ids, stamps, distance, score, inliers, relative pose, `metric`, covariance), so that
//! `pose-graph` reads a live run's loops too, then `rank` and `loop_type` (as in LoopCandidate.msg: 0
//! appearance only, 1 verified, 2 with a pose up to scale, 3 metric).

use std::time::{Duration, Instant};

use anyhow::{Context as _, Result};

use ecm_lcd::io::candidates::{columns, fields};
use ecm_lcd::ros::peer::CandidateListener;

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
    let wait_publisher = args.wait_publisher.map(|wait| super::seconds_arg("--wait-publisher", wait)).transpose()?;
    let idle_timeout = args.idle_timeout.map(|idle| super::seconds_arg("--idle-timeout", idle)).transpose()?;
    let context = ros2_client::Context::new().context("creating the DDS participant")?;
    let listener = CandidateListener::new(&context, &args.topic)?;
    if let (Some(wait), Some(waiting)) = (args.wait_publisher, wait_publisher) {
        if !listener.wait_for_publisher(waiting) {
            anyhow::bail!("no publisher on {} after {wait} s", args.topic);
        }
        log::info!("matched a publisher on {}", args.topic);
    }
    let mut out = csv::WriterBuilder::new().has_headers(false).from_writer(std::io::stdout().lock());
    let ros_columns = ["rank", "loop_type"].map(String::from);
    out.write_record(columns().into_iter().chain(ros_columns))?;
    out.flush()?;
    let mut received = 0usize;
    let mut last = Instant::now();
    loop {
        for c in listener.wait(Duration::from_millis(100))? {
            let ros_fields = [c.rank.to_string(), c.loop_type.to_string()];
            out.write_record(fields(&c.to_candidate()).into_iter().chain(ros_fields))?;
            out.flush()?;
            received += 1;
            last = Instant::now();
            if args.count.is_some_and(|n| received >= n) {
                return Ok(());
            }
        }
        if idle_timeout.is_some_and(|t| last.elapsed() >= t) {
            log::info!("no candidate for {} s; received {received}", args.idle_timeout.unwrap_or_default());
            return Ok(());
        }
    }
}
