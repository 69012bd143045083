//! The `ecm_lcd` ROS 2 node: subscribes keyframes (`keyframes`, ecm_lcd_msgs/Keyframe) or plain images
//! (`image`, sensor_msgs/Image; `image/compressed`, sensor_msgs/CompressedImage), hands them to a
//! [`KeyframeProcessor`] on a worker thread, and publishes `loop_candidates` (ecm_lcd_msgs/LoopCandidate).
//!
//! Threads: the DDS receive loop (main thread) only takes messages and queues them; a worker thread
//! decodes and processes them behind a bounded [`DropOldestQueue`] (full queue: the oldest waiting
//! message is dropped and counted); a spinner thread serves discovery and the parameter services.
//! Malformed messages (bytes that do not deserialise, unknown encoding, `step*height != data` length,
//! empty image, undecodable JPEG/PNG) are logged with their index on the topic, counted and skipped.
//! Parameters are declared from [`crate::config::param_specs`] and served by [`super::param_services`]
//! (descriptions and ranges included); a `set_parameters` request is validated
//! against the table (a refused value keeps the old one and the reply carries the reason) and then
//! reaches the processor through the queue's control lane, before the next keyframe.
//! `camera_info` (sensor_msgs/CameraInfo) gives the intrinsics for geometric verification when the
//! `camera.*` parameters give none; the first calibrated one, and any change, reaches the processor
//! through the same lane (a 30 Hz camera_info is not queued 30 times a second).
//! `depth` (sensor_msgs/Image, `16UC1` millimetres or `32FC1` metres, registered to the colour image)
//! gives verification metric poses. A depth image pairs with the keyframe stamped nearest to it within
//! [`crate::io::depth::DEPTH_ASSOCIATION`], whichever arrives first ([`DepthMatcher`]): a keyframe waits for nothing,
//! and a depth image that comes after its keyframe is attached to the keyframe's kept features, which
//! is where verification uses depth (on the match side, later).
//! `/diagnostics` (diagnostic_msgs/DiagnosticArray) carries the node's health every second: OK, or WARN
//! while messages are dropped or fail, with the queue, the counters and the mean worker times.
//! QoS: frame inputs reliable, keep last 10 (default) or sensor data (best effort, keep last 5) with
//! `--input-qos sensor-data`; `camera_info` and `depth` sensor data always (it matches any
//! publisher); output reliable, keep last 100, volatile.
//! `--input` limits the frame subscriptions to one of `keyframes`, `image` and `image/compressed`
//! ([`FrameInputs`]): a tracker's keyframes and the camera's frames are two numberings of the same frames,
//! and a raw and a compressed stream of one camera are the same frames twice.

use anyhow::{Context as _, Result};
use log::{debug, error, info, warn};
use ros2_client::{
    dds::rustdds::mio1::{Events, Interest, Poll, Token},
    qos::{Durability, History, WhenFull},
    Context, Name, Node, NodeName, NodeOptions, Publisher, QosProfile, Subscription,
};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::args::RosArgs;
use super::msgs::{self, DiagnosticArray, DiagnosticStatus, KeyValue, Keyframe, LoopCandidate, MarkerArray};
use super::param_services::ParamServices;
use super::params;
use super::queue::{DropOldestQueue, Next};
use crate::config::{ParamError, ParamValue, Params};
use crate::io::depth::{depth_from_image, nearest_within_window};
use crate::io::image_msg::{decode_compressed_image, decode_image};
use crate::io::msgs::{CameraInfo, CompressedImage, Header, Image};
use crate::pipeline::{Input, InputProblems};
use crate::types::{self, DepthImage, Stamp};
use crate::verification::Intrinsics;
use nalgebra::Isometry3;

/// The node's name unless `-r __node:=...` says otherwise.
pub const DEFAULT_NODE_NAME: &str = crate::config::NODE_NAME;
/// Topic names before remapping (relative: they live in the node's namespace).
pub const KEYFRAMES_TOPIC: &str = "keyframes";
pub const IMAGE_TOPIC: &str = "image";
pub const COMPRESSED_TOPIC: &str = "image/compressed";
pub const CANDIDATES_TOPIC: &str = "loop_candidates";
/// The camera driver's calibration (`sensor_msgs/CameraInfo`): intrinsics for geometric verification.
pub const CAMERA_INFO_TOPIC: &str = "camera_info";
pub const DEPTH_TOPIC: &str = "depth";
/// Where ROS nodes publish their health (absolute, as the ROS tools expect).
pub const DIAGNOSTICS_TOPIC: &str = "/diagnostics";
/// Loop edges for RViz (`visualization_msgs/MarkerArray`), where keyframes carry poses.
pub const MARKERS_TOPIC: &str = "loop_markers";

/// What became of one image in a [`KeyframeProcessor`].
#[derive(Clone, Debug, Default)]
pub struct Processed {
    /// The keyframe id, when the image was taken as a keyframe.
    pub keyframe: Option<u64>,
    pub candidates: Vec<types::LoopCandidate>,
}

/// What the node runs each keyframe through (the pipeline implements it).
pub trait KeyframeProcessor: Send + 'static {
    /// `input.id`: Some(tracker's keyframe id) for Keyframe messages (selection bypassed); None for
    /// plain images (the processor assigns ids from a counter and applies keyframe selection).
    /// `input.depth`: the image's depth, where it arrived first.
    fn process(&mut self, input: &Input) -> Result<Processed>;
    /// A depth image that arrived after its keyframe was processed; returns whether it was taken.
    fn attach_depth(&mut self, _keyframe: u64, _depth: &DepthImage) -> Result<bool> {
        Ok(false)
    }
    /// The camera frame and tracker pose of each keyframe of the history kept from an earlier run
    /// (a database), oldest first.
    fn stored_frames(&self) -> Result<Vec<(u64, (String, Option<Isometry3<f64>>))>> {
        Ok(Vec::new())
    }
    /// Apply a validated runtime parameter change.
    fn set_param(&mut self, name: &str, value: &ParamValue) -> Result<(), ParamError>;
    /// Camera intrinsics from `camera_info`; returns whether geometric verification is on afterwards.
    /// A processor without verification has no use for them.
    fn set_camera_info(&mut self, _intrinsics: Intrinsics) -> Result<bool> {
        Ok(false)
    }
    /// Keyframes in the history searched for loops, if the processor keeps one (for `/diagnostics`).
    fn keyframes(&self) -> Option<u64> {
        None
    }
    /// Inputs so far that were well formed but could not be used as they came (for `/diagnostics`).
    fn input_problems(&self) -> InputProblems {
        InputProblems::default()
    }
}

impl KeyframeProcessor for crate::pipeline::Pipeline {
    fn process(&mut self, input: &Input) -> Result<Processed> {
        let outcome = self.process_input(input)?;
        let stamp = input.stamp;
        if let Some(id) = outcome.keyframe {
            let t = outcome.timings;
            log::debug!(
                "keyframe {id} at {stamp}: network {:.1} ms, descriptor {:.2} ms, detector {:.2} ms, {} candidate(s)",
                t.network_ms,
                t.descriptor_ms,
                t.detector_ms,
                outcome.candidates.len()
            );
        }
        Ok(Processed { keyframe: outcome.keyframe, candidates: outcome.candidates })
    }

    fn attach_depth(&mut self, keyframe: u64, depth: &DepthImage) -> Result<bool> {
        crate::pipeline::Pipeline::attach_depth(self, keyframe, depth)
    }

    fn stored_frames(&self) -> Result<Vec<(u64, (String, Option<Isometry3<f64>>))>> {
        crate::pipeline::Pipeline::stored_frames(self)
    }

    fn set_param(&mut self, name: &str, value: &ParamValue) -> Result<(), ParamError> {
        crate::pipeline::Pipeline::set_param(self, name, value.clone())
    }

    fn set_camera_info(&mut self, intrinsics: Intrinsics) -> Result<bool> {
        crate::pipeline::Pipeline::set_camera_info(self, intrinsics)
    }

    fn input_problems(&self) -> InputProblems {
        crate::pipeline::Pipeline::input_problems(self)
    }

    fn keyframes(&self) -> Option<u64> {
        Some(self.detector().db().len() as u64)
    }
}

/// Which frame topics the node subscribes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum FrameInputs {
    /// All three: whichever a publisher feeds (one, normally).
    #[default]
    All,
    /// A tracker's keyframes only (`keyframes`).
    Keyframes,
    /// Raw camera frames only (`image`); the node selects keyframes.
    Image,
    /// Compressed camera frames only (`image/compressed`); the node selects keyframes.
    Compressed,
}

impl FrameInputs {
    /// Whether the frame topic `name` ([`KEYFRAMES_TOPIC`], [`IMAGE_TOPIC`], [`COMPRESSED_TOPIC`]) is
    /// subscribed.
    pub fn subscribes(self, name: &str) -> bool {
        match self {
            FrameInputs::All => true,
            FrameInputs::Keyframes => name == KEYFRAMES_TOPIC,
            FrameInputs::Image => name == IMAGE_TOPIC,
            FrameInputs::Compressed => name == COMPRESSED_TOPIC,
        }
    }
}

/// Input QoS.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum InputQos {
    /// Reliable, keep last 10: no keyframe is lost on the wire (trackers publish few keyframes).
    #[default]
    Reliable,
    /// Best effort, keep last 5 (rclcpp's SensorDataQoS): for camera drivers that publish best effort.
    SensorData,
}

impl InputQos {
    pub fn profile(self) -> QosProfile {
        match self {
            InputQos::Reliable => QosProfile::publisher_default()
                .reliability_reliable(WhenFull::DEFAULT)
                .durability(Durability::Volatile)
                .history(History::KeepLast { depth: 10 }),
            InputQos::SensorData => QosProfile::subscription_default()
                .reliability_best_effort()
                .durability(Durability::Volatile)
                .history(History::KeepLast { depth: 5 }),
        }
    }
}

/// The output QoS: reliable, keep last 100 (a back end must not miss a loop).
pub fn output_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 100 })
}

/// How the node is set up, besides its parameters.
#[derive(Clone, Debug)]
pub struct NodeSettings {
    pub ros_args: RosArgs,
    pub input_qos: InputQos,
    /// The frame topics subscribed.
    pub inputs: FrameInputs,
    /// Capacity of the queue between the receive loop and the worker.
    pub queue_capacity: usize,
    /// How often a status line with the counters is logged (when they changed).
    pub status_period: Duration,
    /// How often `/diagnostics` is published.
    pub diagnostics_period: Duration,
}

impl Default for NodeSettings {
    fn default() -> Self {
        NodeSettings {
            ros_args: RosArgs::default(),
            input_qos: InputQos::Reliable,
            inputs: FrameInputs::All,
            queue_capacity: 4,
            status_period: Duration::from_secs(5),
            diagnostics_period: Duration::from_secs(1),
        }
    }
}

/// Running totals, shared by the receive loop, the worker and the caller.
#[derive(Debug, Default)]
pub struct NodeCounters {
    pub received: AtomicU64,
    pub malformed: AtomicU64,
    pub dropped: AtomicU64,
    pub processed: AtomicU64,
    pub failed: AtomicU64,
    pub candidates: AtomicU64,
    pub param_changes: AtomicU64,
    /// Summed worker time in microseconds over the processed messages: decoding, and the processor
    /// (network, descriptor, detector, verification).
    pub decode_us: AtomicU64,
    pub process_us: AtomicU64,
    /// The processor's keyframe history after the last message (see [`KeyframeProcessor::keyframes`]).
    pub keyframes: AtomicU64,
    /// Inputs the processor could not use as they came ([`KeyframeProcessor::input_problems`]).
    pub input_problems: Mutex<InputProblems>,
}

/// A copy of [`NodeCounters`] at one moment.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CountersSnapshot {
    pub received: u64,
    pub malformed: u64,
    pub dropped: u64,
    pub processed: u64,
    pub failed: u64,
    pub candidates: u64,
    pub param_changes: u64,
    pub input_problems: InputProblems,
}

impl NodeCounters {
    pub fn snapshot(&self) -> CountersSnapshot {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        CountersSnapshot {
            received: get(&self.received),
            malformed: get(&self.malformed),
            dropped: get(&self.dropped),
            processed: get(&self.processed),
            failed: get(&self.failed),
            candidates: get(&self.candidates),
            param_changes: get(&self.param_changes),
            input_problems: *self.input_problems.lock().unwrap_or_else(|e| e.into_inner()),
        }
    }
}

impl std::fmt::Display for CountersSnapshot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "received {} processed {} candidates {} malformed {} dropped {} failed {} param_changes {}",
            self.received,
            self.processed,
            self.candidates,
            self.malformed,
            self.dropped,
            self.failed,
            self.param_changes
        )
    }
}

/// One received message, waiting for the worker.
enum Incoming {
    Keyframe(Keyframe),
    Image(Image),
    Compressed(CompressedImage),
}

struct Queued {
    message: Incoming,
    /// Position on its topic, from 0 (for log lines about this message).
    index: u64,
    received_at: Instant,
}

/// What reaches the worker besides images, in order and never dropped.
enum Control {
    /// A validated parameter change.
    Param(String, ParamValue),
    /// New intrinsics from `camera_info`, with the image size it gives (sent only when they change).
    CameraInfo(Intrinsics),
}

/// Runs the node until `stop` is set: creates the DDS participant, the subscriptions and the publisher,
/// declares the parameters with `initial` values (and `use_sim_time`), and processes keyframes with
/// `processor`. Returns the final counters. Must run inside the intended network (see the crate's
/// network rule: tests use a private namespace).
pub fn run_node(
    settings: &NodeSettings,
    initial: Params,
    use_sim_time: Option<bool>,
    processor: Box<dyn KeyframeProcessor>,
    counters: Arc<NodeCounters>,
    stop: Arc<AtomicBool>,
) -> Result<CountersSnapshot> {
    let args = &settings.ros_args;
    let node_name = args.node_name(DEFAULT_NODE_NAME).to_string();
    let fqn = args.fully_qualified_node_name(DEFAULT_NODE_NAME);
    let live = Arc::new(Mutex::new(initial.clone()));
    let queue: Arc<DropOldestQueue<Queued, Control>> = Arc::new(DropOldestQueue::new(settings.queue_capacity));

    // The parameter services are ours (see `param_services`): they describe parameters from the table.
    let mut options = NodeOptions::new().enable_rosout(true).start_parameter_services(false);
    for (name, value) in params::declarations(&initial)? {
        options = options.declare_parameter(name, value);
    }
    if let Some(sim) = use_sim_time {
        options = options.declare_parameter(params::USE_SIM_TIME, ros2_client::ParameterValue::Boolean(sim));
    }
    let validator_params = live.clone();
    let validator_fqn = fqn.clone();
    options = options.parameter_validator(Box::new(move |name, value| {
        let current = validator_params.lock().unwrap_or_else(|e| e.into_inner()).clone();
        params::validate_change(&current, name, value).map(|_| ()).map_err(|reason| {
            warn!("[{validator_fqn}] refused parameter change {name} = {value:?}: {reason}");
            reason.to_string()
        })
    }));
    let action_params = live.clone();
    let action_queue = queue.clone();
    let action_counters = counters.clone();
    let action_fqn = fqn.clone();
    options = options.parameter_set_action(Box::new(move |name, value| {
        let mut current = action_params.lock().unwrap_or_else(|e| e.into_inner());
        let new = params::validate_change(&current, name, value).map_err(|e| e.to_string())?;
        if current.get(name).as_ref() == Some(&new) {
            return Ok(()); // the initial declarations, or a no-op set
        }
        current.set(name, new.clone()).map_err(|e| e.to_string())?;
        drop(current);
        info!("[{action_fqn}] parameter {name} = {new}");
        action_counters.param_changes.fetch_add(1, Ordering::Relaxed);
        action_queue.push_control(Control::Param(name.to_string(), new));
        Ok(())
    }));

    let context = Context::new().context("creating the DDS participant")?;
    let mut node = context
        .new_node(NodeName::new(args.namespace(), &node_name).with_context(|| format!("node name {fqn}"))?, options)
        .map_err(|e| anyhow::anyhow!("creating node {fqn}: {e:?}"))?;

    let topic = |node: &mut Node, name: &str, ty: ros2_client::MessageTypeName, qos: &QosProfile| -> Result<_> {
        let resolved = args.resolve_topic(name, DEFAULT_NODE_NAME)?;
        let ros_name = Name::parse(&resolved).with_context(|| format!("topic name {resolved}"))?;
        let topic =
            node.create_topic(&ros_name, ty, qos).map_err(|e| anyhow::anyhow!("creating topic {resolved}: {e:?}"))?;
        Ok((topic, resolved))
    };
    let input_qos = settings.input_qos.profile();
    let (kf_topic, kf_name) = topic(&mut node, KEYFRAMES_TOPIC, msgs::keyframe_type(), &input_qos)?;
    let (img_topic, img_name) = topic(&mut node, IMAGE_TOPIC, msgs::image_type(), &input_qos)?;
    let (cmp_topic, cmp_name) = topic(&mut node, COMPRESSED_TOPIC, msgs::compressed_image_type(), &input_qos)?;
    let (out_topic, out_name) = topic(&mut node, CANDIDATES_TOPIC, msgs::loop_candidate_type(), &output_qos())?;
    // A camera driver's calibration and depth: best effort whatever --input-qos says, since that
    // matches reliable and best-effort publishers alike, and a lost depth image costs one metric pose.
    let camera_qos = InputQos::SensorData.profile();
    let (info_topic, info_name) = topic(&mut node, CAMERA_INFO_TOPIC, msgs::camera_info_type(), &camera_qos)?;
    let (depth_topic, depth_name) = topic(&mut node, DEPTH_TOPIC, msgs::image_type(), &camera_qos)?;
    let (markers_topic, markers_name) = topic(&mut node, MARKERS_TOPIC, msgs::marker_array_type(), &output_qos())?;
    let (diag_topic, diag_name) =
        topic(&mut node, DIAGNOSTICS_TOPIC, msgs::diagnostic_array_type(), &diagnostics_qos())?;
    let sub_err = |what: &str| {
        let what = what.to_string();
        move |e| anyhow::anyhow!("subscribing {what}: {e:?}")
    };
    let inputs = settings.inputs;
    let mut kf_sub: Option<Subscription<Keyframe>> = inputs
        .subscribes(KEYFRAMES_TOPIC)
        .then(|| node.create_subscription(&kf_topic, None).map_err(sub_err(&kf_name)))
        .transpose()?;
    let mut img_sub: Option<Subscription<Image>> = inputs
        .subscribes(IMAGE_TOPIC)
        .then(|| node.create_subscription(&img_topic, None).map_err(sub_err(&img_name)))
        .transpose()?;
    let mut cmp_sub: Option<Subscription<CompressedImage>> = inputs
        .subscribes(COMPRESSED_TOPIC)
        .then(|| node.create_subscription(&cmp_topic, None).map_err(sub_err(&cmp_name)))
        .transpose()?;
    let mut info_sub: Subscription<CameraInfo> =
        node.create_subscription(&info_topic, None).map_err(sub_err(&info_name))?;
    let mut depth_sub: Subscription<Image> =
        node.create_subscription(&depth_topic, None).map_err(sub_err(&depth_name))?;
    let depth_inbox = Arc::new(DepthInbox::default());
    let publisher: Publisher<LoopCandidate> =
        node.create_publisher(&out_topic, None).map_err(|e| anyhow::anyhow!("creating publisher {out_name}: {e:?}"))?;
    let markers: Publisher<MarkerArray> = node
        .create_publisher(&markers_topic, None)
        .map_err(|e| anyhow::anyhow!("creating publisher {markers_name}: {e:?}"))?;
    let markers_frame = match live.lock().unwrap_or_else(|e| e.into_inner()).get("markers.frame_id") {
        Some(ParamValue::String(frame)) => frame,
        _ => "map".to_string(),
    };
    let diagnostics: Publisher<DiagnosticArray> = node
        .create_publisher(&diag_topic, None)
        .map_err(|e| anyhow::anyhow!("creating publisher {diag_name}: {e:?}"))?;

    let spinner = node.spinner().map_err(|e| anyhow::anyhow!("starting the spinner: {e:?}"))?;
    let spinner_thread = std::thread::Builder::new()
        .name("ros-spinner".into())
        .spawn(move || futures::executor::block_on(spinner.spin()))
        .context("starting the spinner thread")?;

    info!(
        "[{fqn}] listening on {kf_name} (Keyframe), {img_name} (Image), {cmp_name} (CompressedImage), \
         {info_name} (CameraInfo), {depth_name} (Image, depth) with {:?} QoS; publishing {out_name}; queue capacity {}",
        settings.input_qos, settings.queue_capacity
    );

    let worker = {
        let queue = queue.clone();
        let counters = counters.clone();
        let fqn = fqn.clone();
        let live = live.clone();
        let depths = depth_inbox.clone();
        std::thread::Builder::new()
            .name("lcd-worker".into())
            // On a rayon worker for its whole life: see `runtime::on_worker`.
            .spawn(move || {
                let outputs = Outputs { candidates: &publisher, markers: &markers, markers_frame: &markers_frame };
                let inputs = Inputs { queue: &queue, depths: &depths };
                crate::runtime::on_worker(|| worker_loop(&fqn, processor, inputs, outputs, &counters, &live))
            })
            .context("starting the worker thread")?
    };

    let mut poll = Poll::new().context("creating the poll")?;
    let (kf_token, img_token, cmp_token, info_token, depth_token) = (Token(1), Token(2), Token(3), Token(4), Token(5));
    if let Some(sub) = &mut kf_sub {
        poll.registry().register(sub, kf_token, Interest::READABLE).context("polling keyframes")?;
    }
    if let Some(sub) = &mut img_sub {
        poll.registry().register(sub, img_token, Interest::READABLE).context("polling images")?;
    }
    if let Some(sub) = &mut cmp_sub {
        poll.registry().register(sub, cmp_token, Interest::READABLE).context("polling compressed images")?;
    }
    poll.registry().register(&mut info_sub, info_token, Interest::READABLE).context("polling camera_info")?;
    poll.registry().register(&mut depth_sub, depth_token, Interest::READABLE).context("polling depth")?;
    // The last intrinsics passed on (with the image size they hold for), and whether an uncalibrated
    // camera_info was reported.
    let mut camera_info: (Option<Intrinsics>, bool) = (None, false);
    let mut services = ParamServices::create(&context, &fqn)?;
    services.register(poll.registry(), 10).context("polling the parameter services")?;
    let mut events = Events::with_capacity(16);
    let mut indices = [0u64; 4];
    let mut last_status = (Instant::now(), counters.snapshot());
    let mut last_diagnostics = (Instant::now(), counters.snapshot());
    let started = Instant::now();
    let enqueue = |message: Incoming, index: u64| {
        counters.received.fetch_add(1, Ordering::Relaxed);
        if let Some(old) = queue.push(Queued { message, index, received_at: Instant::now() }) {
            counters.dropped.fetch_add(1, Ordering::Relaxed);
            warn!(
                "[{fqn}] worker busy: dropped the oldest queued message (#{} after {:.0} ms waiting; {} dropped so far)",
                old.index,
                old.received_at.elapsed().as_secs_f64() * 1e3,
                queue.dropped()
            );
        }
    };
    let malformed = |topic: &str, index: u64, reason: String| {
        note_malformed(&counters, &fqn, topic, &format!("#{index} "), &reason)
    };
    while !stop.load(Ordering::Relaxed) {
        if let Err(e) = poll.poll(&mut events, Some(Duration::from_millis(100))) {
            if e.kind() != std::io::ErrorKind::Interrupted {
                return Err(e).context("polling the subscriptions");
            }
        }
        // Edge-triggered: drain every subscription each round (cheap when empty).
        drain(kf_sub.as_ref(), &mut indices[0], Incoming::Keyframe, &enqueue, |i, r| malformed(&kf_name, i, r));
        drain(img_sub.as_ref(), &mut indices[1], Incoming::Image, &enqueue, |i, r| malformed(&img_name, i, r));
        drain(cmp_sub.as_ref(), &mut indices[2], Incoming::Compressed, &enqueue, |i, r| malformed(&cmp_name, i, r));
        loop {
            let index = indices[3];
            match depth_sub.take() {
                Ok(Some((msg, _))) => match depth_from_image(&msg) {
                    Ok(depth) => depth_inbox.push(Stamp::from(msg.header.stamp), depth),
                    Err(e) => malformed(&depth_name, index, format!("{e:#}")),
                },
                Ok(None) => break,
                Err(e) => malformed(&depth_name, index, format!("{e:?}")),
            }
            indices[3] += 1;
        }
        loop {
            match info_sub.take() {
                Ok(Some((info, _))) => match info.intrinsics() {
                    Some(calibration) if camera_info.0 != Some(calibration) => {
                        camera_info.0 = Some(calibration);
                        queue.push_control(Control::CameraInfo(calibration));
                    }
                    Some(_) => {}
                    None if !camera_info.1 => {
                        camera_info.1 = true;
                        warn!("[{fqn}] {info_name}: the camera is not calibrated (K is zero or not finite); ignored");
                    }
                    None => {}
                },
                Ok(None) => break,
                Err(e) => note_malformed(&counters, &fqn, &info_name, "", &format!("{e:?}")),
            }
        }
        services.serve(&node, &live);
        if last_status.0.elapsed() >= settings.status_period {
            let now = counters.snapshot();
            if now != last_status.1 {
                info!("[{fqn}] status: {now}");
            }
            last_status = (Instant::now(), now);
        }
        if last_diagnostics.0.elapsed() >= settings.diagnostics_period {
            let now = counters.snapshot();
            let (queue_use, uptime) = ((queue.len(), settings.queue_capacity), started.elapsed());
            let status = diagnostic_status(&fqn, &counters, &last_diagnostics.1, queue_use, uptime);
            let array = DiagnosticArray {
                header: Header { stamp: Stamp::now().into(), frame_id: String::new() },
                status: vec![status],
            };
            if let Err(e) = diagnostics.publish(array) {
                warn!("[{fqn}] publishing {diag_name} failed: {e:?}");
            }
            last_diagnostics = (Instant::now(), now);
        }
    }

    // What arrived since the last round: a reliable publisher counts it delivered and will not send
    // it again. Queued as the worker makes room (within a bound), so the stop drops none of it.
    let patience = Instant::now() + Duration::from_secs(10);
    let enqueue_when_room = |message: Incoming, index: u64| {
        while queue.len() >= settings.queue_capacity.max(1) && Instant::now() < patience {
            std::thread::sleep(Duration::from_millis(5));
        }
        enqueue(message, index);
    };
    drain(kf_sub.as_ref(), &mut indices[0], Incoming::Keyframe, &enqueue_when_room, |i, r| malformed(&kf_name, i, r));
    drain(img_sub.as_ref(), &mut indices[1], Incoming::Image, &enqueue_when_room, |i, r| malformed(&img_name, i, r));
    drain(cmp_sub.as_ref(), &mut indices[2], Incoming::Compressed, &enqueue_when_room, |i, r| {
        malformed(&cmp_name, i, r)
    });
    info!("[{fqn}] stopping: finishing {} queued message(s)", queue.len());
    queue.close();
    let _ = worker.join();
    // Dropping the node signals its spinner to stop (a manual stop_spinner before the drop makes the
    // drop's second signal fail with an ERROR line on every clean stop).
    drop(node);
    let _ = spinner_thread.join();
    let final_counters = counters.snapshot();
    info!("[{fqn}] stopped: {final_counters}");
    Ok(final_counters)
}

/// Counts a message that did not decode, and logs it: the first ten, then every hundredth (a camera
/// in an encoding the node does not read sends dozens a second).
fn note_malformed(counters: &NodeCounters, fqn: &str, topic: &str, index: &str, reason: &str) {
    let n = counters.malformed.fetch_add(1, Ordering::Relaxed) + 1;
    if n <= 10 || n.is_multiple_of(100) {
        warn!("[{fqn}] malformed message {index}on {topic} skipped: {reason} ({n} malformed so far)");
    }
}

/// How long after its start a node that has received nothing says so in `/diagnostics`.
const NO_INPUT_WARNING: Duration = Duration::from_secs(10);

/// The node's `/diagnostics` entry: `WARN` while messages are being dropped or failing, or come in a
/// way the processor cannot use as they are ([`InputProblems`], since `previous`), else `OK`; the
/// counters, the queue and the mean worker time per message as values.
fn diagnostic_status(
    fqn: &str,
    counters: &NodeCounters,
    previous: &CountersSnapshot,
    (queue_depth, queue_capacity): (usize, usize),
    uptime: Duration,
) -> DiagnosticStatus {
    let now = counters.snapshot();
    let (dropping, failing) = (now.dropped > previous.dropped, now.failed > previous.failed);
    // Inputs not usable as they came, in the last period.
    let (counts, before) = (now.input_problems.named(), previous.input_problems.named());
    let mut problems: Vec<String> = counts
        .iter()
        .zip(&before)
        .filter(|((_, count, _), (_, earlier, _))| count > earlier)
        .map(|((_, count, what), (_, earlier, _))| format!("{} {what}", count - earlier))
        .collect();
    // Messages that did not decode (an encoding the node does not read, a cut payload) are lost
    // inputs as much as dropped ones.
    // Nothing at all since the start: a topic not remapped, or a reliable subscription to a
    // best-effort publisher, which never match. (A quiet spell later is a robot standing still.)
    if now.received + now.malformed == 0 && uptime >= NO_INPUT_WARNING {
        problems.push(format!(
            "no frame received in the {:.0} s since the start (are the frame topics remapped, and does \
             --input-qos suit the publisher? a reliable subscription never matches a best-effort one)",
            uptime.as_secs_f64()
        ));
    }
    if now.malformed > previous.malformed {
        problems.insert(
            0,
            format!("{} malformed messages (not decoded; the log says why)", now.malformed - previous.malformed),
        );
    }
    let (level, message) = match (dropping, failing, problems.is_empty()) {
        (false, false, true) => (DiagnosticStatus::OK, "ok".to_string()),
        (false, false, false) => (DiagnosticStatus::WARN, format!("in the last period: {}", problems.join("; "))),
        _ => (
            DiagnosticStatus::WARN,
            format!(
                "{} dropped, {} failed in the last period{}",
                now.dropped - previous.dropped,
                now.failed - previous.failed,
                problems.iter().map(|p| format!("; {p}")).collect::<String>()
            ),
        ),
    };
    let per_message = |us: &AtomicU64| {
        let done = now.processed + now.failed;
        if done == 0 {
            0.0
        } else {
            us.load(Ordering::Relaxed) as f64 / 1e3 / done as f64
        }
    };
    let values = [
        ("queue_depth", queue_depth.to_string()),
        ("queue_capacity", queue_capacity.to_string()),
        ("received", now.received.to_string()),
        ("processed", now.processed.to_string()),
        ("keyframes", counters.keyframes.load(Ordering::Relaxed).to_string()),
        ("candidates", now.candidates.to_string()),
        ("malformed", now.malformed.to_string()),
        ("dropped", now.dropped.to_string()),
        ("failed", now.failed.to_string()),
        ("decode_ms_mean", format!("{:.2}", per_message(&counters.decode_us))),
        ("process_ms_mean", format!("{:.2}", per_message(&counters.process_us))),
    ];
    let values = values.into_iter().chain(counts.iter().map(|&(name, count, _)| (name, count.to_string())));
    DiagnosticStatus {
        level,
        name: format!("{}: loop closure", fqn.trim_start_matches('/')),
        message,
        hardware_id: fqn.to_string(),
        values: values.map(|(key, value)| KeyValue { key: key.to_string(), value }).collect(),
    }
}

/// `/diagnostics` QoS: reliable, keep last 10, as rclcpp's diagnostic_updater publishes it.
fn diagnostics_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 })
}

/// Takes every message waiting on `subscription` (if subscribed): good ones are queued,
/// undeserialisable ones reported; `index` counts the messages seen on the topic.
fn drain<M: 'static + serde::de::DeserializeOwned>(
    subscription: Option<&Subscription<M>>,
    index: &mut u64,
    wrap: fn(M) -> Incoming,
    enqueue: &impl Fn(Incoming, u64),
    malformed: impl Fn(u64, String),
) {
    let Some(subscription) = subscription else { return };
    loop {
        match subscription.take() {
            Ok(Some((msg, _))) => enqueue(wrap(msg), *index),
            Ok(None) => return,
            Err(e) => malformed(*index, format!("{e:?}")),
        }
        *index += 1;
    }
}

/// The `frame_id` of each keyframe a candidate may match, for `LoopCandidate.match_frame_id`, and its
/// position in the tracker's map where the keyframe carried a pose (for the loop-edge markers):
/// bounded by the keyframes the processor keeps (the oldest go first), each distinct name stored once
/// (a tracker sends the same one with every keyframe).
#[derive(Default)]
struct FrameIds {
    order: std::collections::VecDeque<u64>,
    names: HashMap<u64, Arc<str>>,
    positions: HashMap<u64, msgs::Point>,
}

impl FrameIds {
    /// The bound when the processor does not say how many keyframes it keeps.
    const DEFAULT_CAPACITY: usize = 100_000;

    fn insert(&mut self, id: u64, frame_id: &str) {
        let shared =
            self.order.back().and_then(|last| self.names.get(last)).filter(|name| &***name == frame_id).cloned();
        let name = shared.unwrap_or_else(|| Arc::from(frame_id));
        if self.names.insert(id, name).is_none() {
            self.order.push_back(id);
        }
    }

    fn keep_newest(&mut self, n: usize) {
        while self.order.len() > n.max(1) {
            if let Some(id) = self.order.pop_front() {
                self.names.remove(&id);
                self.positions.remove(&id);
            }
        }
    }

    /// Records where keyframe `id` (already inserted) was in the tracker's map.
    fn set_position(&mut self, id: u64, position: msgs::Point) {
        if self.names.contains_key(&id) {
            self.positions.insert(id, position);
        }
    }

    fn position(&self, id: u64) -> Option<msgs::Point> {
        self.positions.get(&id).copied()
    }

    fn get(&self, id: u64) -> Option<&str> {
        self.names.get(&id).map(|name| &**name)
    }
}

/// Where the worker publishes.
struct Outputs<'a> {
    candidates: &'a Publisher<LoopCandidate>,
    markers: &'a Publisher<MarkerArray>,
    /// The tracker's map frame, in which keyframe poses are given (`markers.frame_id`).
    markers_frame: &'a str,
}

/// Depth images received on `depth`, decoded, waiting for the worker: the newest
/// [`DEPTH_IMAGES_KEPT`] (the worker takes them within its wait for the next message).
#[derive(Default)]
struct DepthInbox {
    images: Mutex<std::collections::VecDeque<(Stamp, DepthImage)>>,
}

impl DepthInbox {
    fn push(&self, stamp: Stamp, depth: DepthImage) {
        let mut images = self.images.lock().unwrap_or_else(|e| e.into_inner());
        push_bounded(&mut images, (stamp, depth), DEPTH_IMAGES_KEPT);
    }

    fn take(&self) -> std::collections::VecDeque<(Stamp, DepthImage)> {
        std::mem::take(&mut *self.images.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

/// Depth images kept at most, waiting for their keyframes (as the offline pairing keeps).
const DEPTH_IMAGES_KEPT: usize = 64;

/// Appends a depth image, dropping those stamped more than [`crate::io::depth::MAX_HOLD`] before it
/// and the oldest beyond [`DEPTH_IMAGES_KEPT`].
fn push_recent_depth(images: &mut std::collections::VecDeque<(Stamp, DepthImage)>, item: (Stamp, DepthImage)) {
    // Aged from the image just pushed, not the newest stamp held: one stamped far ahead (a driver's
    // clock jump, a bag played in a loop) must not make every later image look stale.
    let pushed = item.0;
    push_bounded(images, item, DEPTH_IMAGES_KEPT);
    images.retain(|(stamp, _)| pushed.nanos - stamp.nanos <= crate::io::depth::MAX_HOLD.nanos);
}

/// Appends `item`, dropping the oldest beyond `capacity`.
fn push_bounded<T>(items: &mut std::collections::VecDeque<T>, item: T, capacity: usize) {
    items.push_back(item);
    while items.len() > capacity {
        items.pop_front();
    }
}

/// Pairs depth images with keyframes by stamp, whichever arrives first (module doc). Unclaimed depth
/// images are kept for the last [`crate::io::depth::MAX_HOLD`] of depth stamps, at most
/// [`DEPTH_IMAGES_KEPT`]: a tracker publishes a keyframe some hundred milliseconds after its image
/// was taken, so the depth it needs is among the oldest kept, whatever the camera's rate.
#[derive(Default)]
struct DepthMatcher {
    /// Depth images no keyframe has taken yet, newest last.
    unclaimed: std::collections::VecDeque<(Stamp, DepthImage)>,
    /// Keyframes processed without depth, newest last.
    waiting: std::collections::VecDeque<(Stamp, u64)>,
}

impl DepthMatcher {
    const CAPACITY: usize = 16;

    /// A new depth image: attached to the keyframe waiting for it, else kept for one to come.
    fn offer(&mut self, fqn: &str, stamp: Stamp, depth: DepthImage, processor: &mut dyn KeyframeProcessor) {
        let Some(&(_, keyframe)) = nearest_within_window(&self.waiting, stamp) else {
            push_recent_depth(&mut self.unclaimed, (stamp, depth));
            return;
        };
        self.waiting.retain(|&(_, id)| id != keyframe);
        match processor.attach_depth(keyframe, &depth) {
            Ok(taken) => debug!("[{fqn}] depth stamped {stamp} for keyframe {keyframe} after it: taken {taken}"),
            Err(e) => warn!("[{fqn}] depth stamped {stamp} refused for keyframe {keyframe}: {e:#}"),
        }
    }

    /// The depth image for a keyframe stamped `stamp`, if it came first.
    fn depth_for(&self, stamp: Stamp) -> Option<&DepthImage> {
        nearest_within_window(&self.unclaimed, stamp).map(|(_, depth)| depth)
    }

    /// A keyframe processed without depth waits for its depth image.
    fn wait(&mut self, stamp: Stamp, keyframe: u64) {
        push_bounded(&mut self.waiting, (stamp, keyframe), Self::CAPACITY);
    }
}

/// What the worker takes in: queued messages and controls, and depth images.
struct Inputs<'a> {
    queue: &'a DropOldestQueue<Queued, Control>,
    depths: &'a DepthInbox,
}

/// Decodes, processes and publishes queued messages until the queue closes.
fn worker_loop(
    fqn: &str,
    mut processor: Box<dyn KeyframeProcessor>,
    inputs: Inputs,
    outputs: Outputs,
    counters: &NodeCounters,
    live: &Mutex<Params>,
) {
    let queue = inputs.queue;
    let mut depths = DepthMatcher::default();
    let publisher = outputs.candidates;
    let mut frame_ids = FrameIds::default();
    // Keyframes from an earlier run (a database): their frames, and positions for the markers.
    match processor.stored_frames() {
        Ok(stored) => {
            for (id, (frame_id, pose)) in stored {
                frame_ids.insert(id, &frame_id);
                if let Some(pose) = pose {
                    let t = pose.translation.vector;
                    frame_ids.set_position(id, msgs::Point { x: t.x, y: t.y, z: t.z });
                }
            }
        }
        Err(e) => error!("[{fqn}] reading the stored keyframes' frames and poses failed: {e:#}"),
    }
    // Read-only while running: read once.
    let mode = match live.lock().unwrap_or_else(|e| e.into_inner()).get("descriptor.mode") {
        Some(ParamValue::String(mode)) => mode,
        _ => String::new(),
    };
    loop {
        let next = queue.pop(Duration::from_millis(200));
        for (stamp, depth) in inputs.depths.take() {
            depths.offer(fqn, stamp, depth, processor.as_mut());
        }
        let queued = match next {
            Next::Control(Control::Param(name, value)) => {
                if let Err(reason) = processor.set_param(&name, &value) {
                    error!("[{fqn}] the processor refused {name} = {value}: {reason}");
                }
                continue;
            }
            Next::Control(Control::CameraInfo(intrinsics)) => {
                match processor.set_camera_info(intrinsics) {
                    Ok(verifying) => info!(
                        "[{fqn}] camera intrinsics from camera_info: fx {:.1} fy {:.1} cx {:.1} cy {:.1}; geometric verification {}",
                        intrinsics.fx,
                        intrinsics.fy,
                        intrinsics.cx,
                        intrinsics.cy,
                        if verifying { "on" } else { "off" }
                    ),
                    Err(e) => error!("[{fqn}] camera intrinsics from camera_info refused: {e:#}"),
                }
                continue;
            }
            Next::Item(queued) => queued,
            Next::Timeout => continue,
            Next::Closed => return,
        };
        let started = Instant::now();
        let tracker_pose = match &queued.message {
            Incoming::Keyframe(kf) if kf.has_pose => Some(kf.pose),
            _ => None,
        };
        let (topic, id, header, decoded) = match &queued.message {
            Incoming::Keyframe(kf) => {
                let mut header = kf.header.clone();
                if header.stamp == Default::default() {
                    header.stamp = kf.image.header.stamp;
                }
                (KEYFRAMES_TOPIC, Some(kf.id), header, decode_image(&kf.image))
            }
            Incoming::Image(img) => (IMAGE_TOPIC, None, img.header.clone(), decode_image(img)),
            Incoming::Compressed(img) => (COMPRESSED_TOPIC, None, img.header.clone(), decode_compressed_image(img)),
        };
        let image = match decoded {
            Ok(image) => image,
            Err(e) => {
                note_malformed(counters, fqn, topic, &format!("#{} ", queued.index), &format!("{e:#}"));
                continue;
            }
        };
        let decode_ms = started.elapsed().as_secs_f64() * 1e3;
        counters.decode_us.fetch_add((decode_ms * 1e3) as u64, Ordering::Relaxed);
        let stamp = Stamp::from(header.stamp);
        let process_start = Instant::now();
        let depth = depths.depth_for(stamp);
        let had_depth = depth.is_some();
        let input = Input {
            id,
            stamp,
            image: &image,
            depth,
            frame_id: &header.frame_id,
            tracker_pose: tracker_pose.map(|p| p.to_isometry()),
        };
        let result = processor.process(&input);
        let process_ms = process_start.elapsed().as_secs_f64() * 1e3;
        counters.process_us.fetch_add((process_ms * 1e3) as u64, Ordering::Relaxed);
        let (keyframe, candidates) = match result {
            Ok(Processed { keyframe, candidates }) => {
                if let (Some(keyframe), false) = (keyframe, had_depth) {
                    depths.wait(stamp, keyframe);
                }
                (keyframe, candidates)
            }
            Err(e) => {
                counters.failed.fetch_add(1, Ordering::Relaxed);
                error!("[{fqn}] processing message #{} on {topic} (stamp {stamp}) failed: {e:#}", queued.index);
                continue;
            }
        };
        counters.processed.fetch_add(1, Ordering::Relaxed);
        if let Some(keyframes) = processor.keyframes() {
            counters.keyframes.store(keyframes, Ordering::Relaxed);
        }
        *counters.input_problems.lock().unwrap_or_else(|e| e.into_inner()) = processor.input_problems();
        if let Some(id) = id.or(keyframe) {
            frame_ids.insert(id, &header.frame_id);
            if let Some(pose) = tracker_pose {
                frame_ids.set_position(id, pose.position);
            }
        }
        // One entry per keyframe the processor keeps: a match can only be one of those.
        frame_ids.keep_newest(processor.keyframes().map_or(FrameIds::DEFAULT_CAPACITY, |n| n as usize));
        let messages = msgs::candidate_messages(&candidates, |id| frame_ids.get(id), &header.frame_id, &mode);
        for (candidate, msg) in candidates.iter().zip(messages) {
            match publisher.publish(msg) {
                Ok(()) => {
                    counters.candidates.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => error!(
                    "[{fqn}] publishing candidate {} -> {} failed: {e:?}",
                    candidate.query_id, candidate.match_id
                ),
            }
        }
        let markers =
            msgs::loop_edge_markers(&candidates, |id| frame_ids.position(id), outputs.markers_frame, header.stamp);
        if !markers.markers.is_empty() {
            let count = markers.markers.len();
            match outputs.markers.publish(markers) {
                Ok(()) => debug!("[{fqn}] published {count} loop-edge marker(s)"),
                Err(e) => warn!("[{fqn}] publishing loop-edge markers failed: {e:?}"),
            }
        } else if !candidates.is_empty() {
            debug!(
                "[{fqn}] no loop-edge markers: {} of {} keyframes have poses",
                frame_ids.positions.len(),
                frame_ids.order.len()
            );
        }
        debug!(
            "[{fqn}] {topic} #{} id {} stamp {stamp}: waited {:.1} ms, decode {decode_ms:.1} ms, process {process_ms:.1} ms, \
             {} candidate(s){}",
            queued.index,
            id.map_or("auto".to_string(), |i| i.to_string()),
            (started - queued.received_at).as_secs_f64() * 1e3,
            candidates.len(),
            candidates.first().map_or(String::new(), |c| format!(", best {} -> {} score {:.3}", c.query_id, c.match_id, c.score)),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::{diagnostic_status, DiagnosticStatus, FrameIds, InputProblems, NodeCounters};
    use std::time::Duration;

    #[test]
    fn diagnostics_warn_while_inputs_cannot_be_used() {
        let counters = NodeCounters::default();
        let before = counters.snapshot();
        assert_eq!(diagnostic_status("/lcd", &counters, &before, (0, 8), Duration::ZERO).level, DiagnosticStatus::OK);
        let problems = InputProblems { stamps_not_advancing: 3, blank_frames: 2, ..InputProblems::default() };
        *counters.input_problems.lock().unwrap() = problems;
        let status = diagnostic_status("/lcd", &counters, &before, (0, 8), Duration::ZERO);
        assert_eq!(status.level, DiagnosticStatus::WARN);
        let message = &status.message;
        assert!(
            message.contains("3 frames stamped no later") && message.contains("2 frames showing nothing"),
            "{message}"
        );
        assert!(!message.contains("depth"), "{message}");
        for (key, value) in [("stamps_not_advancing", "3"), ("blank_frames", "2"), ("misfit_sizes", "0")] {
            assert!(status.values.iter().any(|kv| kv.key == key && kv.value == value), "{key}: {:?}", status.values);
        }
        // Once they advance again, the next period is OK.
        let later = counters.snapshot();
        assert_eq!(diagnostic_status("/lcd", &counters, &later, (0, 8), Duration::ZERO).level, DiagnosticStatus::OK);
        // Messages that do not decode (say, a camera sending yuv422) warn too.
        counters.malformed.fetch_add(2, std::sync::atomic::Ordering::Relaxed);
        let status = diagnostic_status("/lcd", &counters, &later, (0, 8), Duration::ZERO);
        assert_eq!(status.level, DiagnosticStatus::WARN);
        assert!(status.message.contains("2 malformed messages"), "{}", status.message);
        // Nothing received for 10 s since the start: said; once anything came, not.
        let idle = NodeCounters::default();
        let quiet = idle.snapshot();
        assert_eq!(
            diagnostic_status("/lcd", &idle, &quiet, (0, 8), Duration::from_secs(9)).level,
            DiagnosticStatus::OK
        );
        let status = diagnostic_status("/lcd", &idle, &quiet, (0, 8), Duration::from_secs(10));
        assert_eq!(status.level, DiagnosticStatus::WARN);
        assert!(status.message.contains("no frame received in the 10 s"), "{}", status.message);
        idle.received.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let status = diagnostic_status("/lcd", &idle, &idle.snapshot(), (0, 8), Duration::from_secs(60));
        assert_eq!(status.level, DiagnosticStatus::OK);
    }

    #[test]
    fn depth_waits_a_second_of_stamps_even_after_a_stamp_far_ahead() {
        let depth = || crate::types::DepthImage { width: 1, height: 1, metres: vec![1.0] };
        let mut images = std::collections::VecDeque::new();
        let at = |ms: i64| crate::types::Stamp::from_nanos(ms * 1_000_000);
        super::push_recent_depth(&mut images, (at(1_000_000), depth()));
        for ms in [0, 500, 900, 1600] {
            super::push_recent_depth(&mut images, (at(ms), depth()));
        }
        let kept: Vec<i64> = images.iter().map(|(stamp, _)| stamp.nanos / 1_000_000).collect();
        assert_eq!(kept, [1_000_000, 900, 1600], "a second back from the newest pushed, whatever came before");
    }

    #[test]
    fn frame_ids_are_bounded_and_share_one_name() {
        let mut ids = FrameIds::default();
        for id in 0..1000 {
            ids.insert(id, "camera");
            ids.keep_newest(100);
        }
        assert_eq!(ids.order.len(), 100);
        assert_eq!((ids.get(899), ids.get(900), ids.get(999)), (None, Some("camera"), Some("camera")));
        // Consecutive equal names are one allocation.
        let (a, b) = (&ids.names[&998], &ids.names[&999]);
        assert!(std::sync::Arc::ptr_eq(a, b));
        ids.insert(1000, "left");
        assert_eq!(ids.get(1000), Some("left"));
        // Inserting an id again does not grow the order.
        ids.insert(1000, "left");
        ids.keep_newest(1000);
        assert_eq!(ids.order.len(), 101);
    }
}
