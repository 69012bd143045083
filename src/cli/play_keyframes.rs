//! `ecm-lcd play-keyframes`: a tracker stand-in. Publishes the frames of any replay source (TUM folder,
//! image folder, ROS 1/2 bag) as ecm_lcd_msgs/Keyframe (id = frame index), sensor_msgs/Image or
//! sensor_msgs/CompressedImage at a fixed rate, after waiting for a subscriber; with `--depth-topic`,
//! each frame's depth image (a TUM folder's `depth.txt`, a bag's `--bag-depth-topic`) too; with
//! `--poses`, each Keyframe carries the tracker's pose.

use anyhow::{Context as _, Result};
use std::path::PathBuf;
use std::time::Instant;

use ecm_lcd::io::tum::TrackerPoses;
use ecm_lcd::ros::msgs::Pose;
use ecm_lcd::ros::node::InputQos;
use ecm_lcd::ros::peer::{FramePublisher, SendAs};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Replay source: TUM folder, image folder, .bag, .db3, .mcap or ROS 2 bag folder.
    pub source: PathBuf,
    /// Frames per second to publish.
    #[arg(long, default_value_t = 2.0)]
    pub rate: f64,
    /// Topic to publish on (default: /keyframes, /image or /image/compressed by --as).
    #[arg(long)]
    pub topic: Option<String>,
    /// Message type to send.
    #[arg(long = "as", value_enum, default_value_t = SendAs::Keyframe)]
    pub send_as: SendAs,
    /// Image topic inside a bag source (default: its only image topic).
    #[arg(long)]
    pub bag_topic: Option<String>,
    /// Depth topic inside a bag source, paired with its images (as `replay --depth-topic`).
    #[arg(long)]
    pub bag_depth_topic: Option<String>,
    /// Also publish each frame's depth image (32FC1 metres) on this topic, just before the frame (the
    /// node listens on /depth).
    #[arg(long)]
    pub depth_topic: Option<String>,
    /// QoS of the publisher (match the node's --input-qos).
    #[arg(long, value_enum, default_value_t = InputQos::Reliable)]
    pub qos: InputQos,
    /// frame_id written into the headers.
    #[arg(long, default_value = "camera")]
    pub frame_id: String,
    /// Skip this many frames at the start of the source (ids stay the source's frame indices).
    #[arg(long, default_value_t = 0)]
    pub start: usize,
    /// Publish at most this many frames.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Seconds to wait for a subscriber before publishing (then publish anyway, with a warning).
    #[arg(long, default_value_t = 10.0)]
    pub wait: f64,
    /// The tracker's poses: a TUM trajectory (camera-to-world); each Keyframe carries the pose within
    /// 20 ms of its stamp (`has_pose`), as a tracker's would (`--as keyframe` only).
    #[arg(long, value_name = "FILE")]
    pub poses: Option<PathBuf>,
    /// Seconds to stay up after the last frame so reliable delivery completes.
    #[arg(long, default_value_t = 2.0)]
    pub linger: f64,
}

pub fn run(args: Args) -> Result<()> {
    anyhow::ensure!(args.rate > 0.0 && args.rate.is_finite(), "--rate must be a positive number, got {}", args.rate);
    let period = super::seconds_arg("the period 1 / --rate", 1.0 / args.rate)?;
    let (wait, linger) = (super::seconds_arg("--wait", args.wait)?, super::seconds_arg("--linger", args.linger)?);
    let topics =
        ecm_lcd::io::Topics { image: args.bag_topic.clone(), depth: args.bag_depth_topic.clone(), poses: None };
    let source = ecm_lcd::io::open_source_topics(&args.source, &topics)
        .with_context(|| format!("opening {}", args.source.display()))?;
    anyhow::ensure!(
        args.poses.is_none() || args.send_as == SendAs::Keyframe,
        "--poses needs --as keyframe: only Keyframe messages carry a pose"
    );
    let mut poses = match &args.poses {
        Some(path) => Some(TrackerPoses::read(path).context("reading --poses")?),
        None => None,
    };
    let topic = args.topic.clone().unwrap_or_else(|| args.send_as.default_topic().to_string());
    let context = ros2_client::Context::new().context("creating the DDS participant")?;
    let mut publisher = FramePublisher::new(&context, &topic, args.send_as, args.qos, &args.frame_id)?;
    if let Some(depth_topic) = &args.depth_topic {
        publisher.add_depth_topic(depth_topic, args.qos)?;
    }
    log::info!("publishing {} on {topic} as {:?} at {} Hz", source.describe(), args.send_as, args.rate);
    if !publisher.wait_for_subscriber(wait) {
        log::warn!("no subscriber on {topic} after {} s; publishing anyway", args.wait);
    }
    let start = Instant::now();
    let mut published = 0usize;
    let frames = source.skip(args.start).take(args.limit.unwrap_or(usize::MAX));
    for frame in ecm_lcd::io::skip_unreadable(frames, &args.source) {
        let frame = frame.with_context(|| format!("reading {}", args.source.display()))?;
        let due = start + period.mul_f64(published as f64);
        if let Some(wait) = due.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        let pose = poses.as_mut().and_then(|poses| poses.at(frame.stamp));
        publisher.publish_with_pose(&frame, pose.as_ref().map(Pose::from_isometry))?;
        log::debug!("published frame {} stamp {}", frame.index, frame.stamp);
        published += 1;
    }
    std::thread::sleep(linger);
    log::info!("published {published} frames on {topic}");
    if let Some(poses) = &poses {
        poses.report(published);
    }
    Ok(())
}
