//! The node layer over DDS, with a small recording processor instead of the pipeline: Keyframe, Image and
//! CompressedImage input, candidates out, malformed messages counted and skipped, parameters set through
//! the standard `set_parameters` service (valid accepted and applied, invalid refused with a reason),
//! `camera_info` intrinsics passed on once per change (an uncalibrated one ignored).
//!
//! Network rule: each test re-runs itself inside a private network namespace (loopback only, see
//! `ros_support`), so every DDS participant lives there; the outer test only checks the inner run's result.

mod ros_support;

use ecm_lcd::config::{ParamValue, Params};
use ecm_lcd::io::msgs::{CameraInfo, CompressedImage, Header, Image};
use ecm_lcd::pipeline::Input;
use ecm_lcd::ros::msgs::{self, Keyframe, LoopCandidate};
use ecm_lcd::ros::node::Processed;
use ecm_lcd::ros::{run_node, KeyframeProcessor, NodeCounters, NodeSettings};
use ecm_lcd::types::{self, DepthImage, Stamp};
use ros2_client::rcl_interfaces::{
    DescribeParametersRequest, DescribeParametersResponse, SetParametersRequest, SetParametersResponse,
};
use ros2_client::{
    Context, Name, NodeName, NodeOptions, Parameter, ParameterValue, QosProfile, ServiceMapping, ServiceTypeName,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What the processor saw.
#[derive(Default)]
struct Seen {
    calls: Vec<(Option<u64>, Stamp, u32, u32)>,
    params: Vec<(String, ParamValue)>,
    camera_info: Vec<ecm_lcd::verification::Intrinsics>,
    /// (keyframe id, depth value in metres, whether it came with the image or was attached after).
    depths: Vec<(u64, f32, &'static str)>,
}

/// A real, tiny place recogniser: a frame's "place" is its mean colour; a query matches every earlier
/// frame whose mean colour is within the score threshold (`detector.min_score`, score = 1 - |Δmean|/255).
struct MeanColourProcessor {
    seen: Arc<Mutex<Seen>>,
    history: Vec<(u64, Stamp, f32)>,
    next_id: u64,
    min_score: f32,
}

impl KeyframeProcessor for MeanColourProcessor {
    fn process(&mut self, input: &Input) -> anyhow::Result<Processed> {
        let Input { id, stamp, image, depth, .. } = *input;
        self.seen.lock().unwrap().calls.push((id, stamp, image.width(), image.height()));
        let id = id.unwrap_or_else(|| {
            self.next_id += 1;
            1000 + self.next_id
        });
        if let Some(depth) = depth {
            self.seen.lock().unwrap().depths.push((id, depth.metres[0], "with"));
        }
        let mean = image.as_raw().iter().map(|&v| v as f32).sum::<f32>() / image.as_raw().len() as f32;
        let mut found: Vec<types::LoopCandidate> = self
            .history
            .iter()
            .map(|&(mid, mstamp, m)| {
                let distance = (mean - m).abs();
                (mid, mstamp, distance, 1.0 - distance / 255.0)
            })
            .filter(|&(_, _, _, score)| score >= self.min_score)
            .map(|(match_id, match_stamp, distance, score)| types::LoopCandidate {
                query_id: id,
                query_stamp: stamp,
                match_id,
                match_stamp,
                distance,
                score,
                rank: 0,
                verified: None,
            })
            .collect();
        found.sort_by(|a, b| b.score.total_cmp(&a.score));
        for (rank, c) in found.iter_mut().enumerate() {
            c.rank = rank as u32;
        }
        self.history.push((id, stamp, mean));
        Ok(Processed { keyframe: Some(id), candidates: found })
    }

    fn attach_depth(&mut self, keyframe: u64, depth: &DepthImage) -> anyhow::Result<bool> {
        self.seen.lock().unwrap().depths.push((keyframe, depth.metres[0], "after"));
        Ok(true)
    }

    fn set_param(&mut self, name: &str, value: &ParamValue) -> Result<(), ecm_lcd::config::ParamError> {
        self.seen.lock().unwrap().params.push((name.to_string(), value.clone()));
        if let ("detector.min_score", ParamValue::Double(v)) = (name, value) {
            self.min_score = *v as f32;
        }
        Ok(())
    }

    fn set_camera_info(&mut self, intrinsics: ecm_lcd::verification::Intrinsics) -> anyhow::Result<bool> {
        self.seen.lock().unwrap().camera_info.push(intrinsics);
        Ok(true)
    }
}

fn solid(width: u32, height: u32, value: u8) -> image::RgbImage {
    image::RgbImage::from_pixel(width, height, image::Rgb([value, value, value]))
}

fn header(secs: i32) -> Header {
    Header { stamp: ecm_lcd::io::msgs::Time { sec: secs, nanosec: 500 }, frame_id: "camera".into() }
}

fn keyframe(id: u64, secs: i32, value: u8) -> Keyframe {
    let img = solid(32, 24, value);
    Keyframe {
        header: header(secs),
        id,
        image: Image {
            header: header(secs),
            height: 24,
            width: 32,
            encoding: "rgb8".into(),
            is_bigendian: 0,
            step: 96,
            data: img.into_raw(),
        },
        has_pose: false,
        pose: Default::default(),
    }
}

#[test]
fn node_layer_over_dds() {
    if !ros_support::inside() {
        return ros_support::check_inner_run("node_layer_over_dds");
    }
    let seen = Arc::new(Mutex::new(Seen::default()));
    let initial = Params::default();
    let ParamValue::Double(min_score) = initial.get("detector.min_score").unwrap() else { panic!() };
    let processor =
        MeanColourProcessor { seen: seen.clone(), history: Vec::new(), next_id: 0, min_score: min_score as f32 };
    let counters = Arc::new(NodeCounters::default());
    let stop = Arc::new(AtomicBool::new(false));
    let settings = NodeSettings {
        ros_args: ecm_lcd::ros::args::RosArgs::parse(&["--ros-args", "-r", "__ns:=/t"], "ecm_lcd").unwrap(),
        status_period: Duration::from_millis(500),
        ..NodeSettings::default()
    };
    let node_thread = {
        let (counters, stop) = (counters.clone(), stop.clone());
        std::thread::spawn(move || run_node(&settings, initial, Some(false), Box::new(processor), counters, stop))
    };

    // The peer: publishers on the node's inputs, a subscription on its output, a set_parameters client.
    let context = Context::new().unwrap();
    let mut peer =
        context.new_node(NodeName::new("/t", "peer").unwrap(), NodeOptions::new().enable_rosout(false)).unwrap();
    let reliable = ecm_lcd::ros::node::InputQos::Reliable.profile();
    let topic = |peer: &mut ros2_client::Node, name: &str, ty| {
        peer.create_topic(&Name::parse(name).unwrap(), ty, &reliable).unwrap()
    };
    let kf_topic = topic(&mut peer, "/t/keyframes", msgs::keyframe_type());
    let img_topic = topic(&mut peer, "/t/image", msgs::image_type());
    let cmp_topic = topic(&mut peer, "/t/image/compressed", msgs::compressed_image_type());
    let out_topic = peer
        .create_topic(
            &Name::parse("/t/loop_candidates").unwrap(),
            msgs::loop_candidate_type(),
            &ecm_lcd::ros::node::output_qos(),
        )
        .unwrap();
    let info_topic = topic(&mut peer, "/t/camera_info", msgs::camera_info_type());
    let info_pub = peer.create_publisher::<CameraInfo>(&info_topic, None).unwrap();
    let kf_pub = peer.create_publisher::<Keyframe>(&kf_topic, None).unwrap();
    let img_pub = peer.create_publisher::<Image>(&img_topic, None).unwrap();
    let cmp_pub = peer.create_publisher::<CompressedImage>(&cmp_topic, None).unwrap();
    // Wrong bytes on the image topic: a plain string under the Image type name does not deserialise.
    let garbage_pub = peer.create_publisher::<String>(&img_topic, None).unwrap();
    let out_sub = peer.create_subscription::<LoopCandidate>(&out_topic, None).unwrap();
    let service_qos = QosProfile::publisher_default().history(ros2_client::qos::History::KeepLast { depth: 1 });
    let set_client = peer
        .create_client::<SetParametersRequest, SetParametersResponse>(
            ServiceMapping::Enhanced,
            &Name::new("/t/ecm_lcd", "set_parameters").unwrap(),
            &ServiceTypeName::new("rcl_interfaces", "SetParameters"),
            service_qos.clone(),
            service_qos.clone(),
        )
        .unwrap();
    let describe_client = peer
        .create_client::<DescribeParametersRequest, DescribeParametersResponse>(
            ServiceMapping::Enhanced,
            &Name::new("/t/ecm_lcd", "describe_parameters").unwrap(),
            &ServiceTypeName::new("rcl_interfaces", "DescribeParameters"),
            service_qos.clone(),
            service_qos,
        )
        .unwrap();
    let spinner = peer.spinner().unwrap();
    std::thread::spawn(move || futures::executor::block_on(spinner.spin()));

    // Wait until the node's subscriptions and our subscription are matched.
    let deadline = Instant::now() + Duration::from_secs(20);
    while (kf_pub.get_subscription_count(&peer) == 0
        || img_pub.get_subscription_count(&peer) == 0
        || cmp_pub.get_subscription_count(&peer) == 0
        || info_pub.get_subscription_count(&peer) == 0)
        && Instant::now() < deadline
    {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(kf_pub.get_subscription_count(&peer) > 0, "node's keyframe subscription never matched");
    std::thread::sleep(Duration::from_millis(500));

    let collect = |want: usize, within: Duration| -> Vec<LoopCandidate> {
        let mut got = Vec::new();
        let end = Instant::now() + within;
        while Instant::now() < end && got.len() < want {
            while let Ok(Some((c, _))) = out_sub.take() {
                got.push(c);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        // Anything extra that is already on its way.
        std::thread::sleep(Duration::from_millis(300));
        while let Ok(Some((c, _))) = out_sub.take() {
            got.push(c);
        }
        got
    };

    // 1. Keyframes: places 10, 200, 10, 200 -> 2 loops at the default threshold (identical colours).
    for (i, value) in [10u8, 200, 10, 200].into_iter().enumerate() {
        kf_pub.publish(keyframe(i as u64 + 1, 100 + i as i32, value)).unwrap();
    }
    let got = collect(2, Duration::from_secs(15));
    let pairs: Vec<(u64, u64)> = got.iter().map(|c| (c.query_id, c.match_id)).collect();
    assert_eq!(pairs, vec![(3, 1), (4, 2)]);
    assert_eq!(got[0].header.stamp.sec, 102);
    assert_eq!(got[0].match_stamp.sec, 100);
    assert_eq!(got[0].header.frame_id, "camera");
    assert_eq!(got[0].num_candidates, 1);
    let Some(ParamValue::String(mode)) = Params::default().get("descriptor.mode") else { panic!("descriptor.mode") };
    assert_eq!(got[0].descriptor_mode, mode);

    // camera_info: an uncalibrated one (K all zero) is ignored; the calibrated one reaches the
    // processor once, however often the driver repeats it.
    info_pub.publish(CameraInfo { header: header(103), width: 640, height: 480, ..Default::default() }).unwrap();
    let calibrated = CameraInfo {
        k: [535.4, 0.0, 320.1, 0.0, 539.2, 247.6, 0.0, 0.0, 1.0],
        ..CameraInfo { header: header(103), width: 640, height: 480, ..Default::default() }
    };
    for _ in 0..3 {
        info_pub.publish(calibrated.clone()).unwrap();
    }
    let deadline = Instant::now() + Duration::from_secs(10);
    while seen.lock().unwrap().camera_info.is_empty() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(
        seen.lock().unwrap().camera_info,
        ecm_lcd::verification::Intrinsics::preset("tum_fr3").into_iter().collect::<Vec<_>>()
    );

    // 2. Malformed messages: each logged, counted and skipped.
    let mut short = keyframe(9, 0, 1).image;
    short.data.truncate(10);
    let mut odd = keyframe(9, 0, 1).image;
    odd.encoding = "yuv422_weird".into();
    let empty = Image { encoding: "rgb8".into(), ..Default::default() };
    img_pub.publish(short).unwrap();
    img_pub.publish(odd).unwrap();
    img_pub.publish(empty).unwrap();
    cmp_pub
        .publish(CompressedImage { header: header(5), format: "jpeg".into(), data: vec![0xff, 0xd8, 1, 2, 3] })
        .unwrap();
    garbage_pub.publish("not an image".to_string()).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    while counters.snapshot().malformed < 5 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(counters.snapshot().malformed, 5, "{}", counters.snapshot());

    // 3. Still answering: a plain image is processed (id from the processor's counter) ...
    img_pub
        .publish(ecm_lcd::io::image_msg::rgb8_message(Stamp::from_sec_nsec(200, 0), "camera", &solid(32, 24, 200)))
        .unwrap();
    let got = collect(2, Duration::from_secs(10));
    assert_eq!(got.iter().map(|c| (c.query_id, c.match_id)).collect::<Vec<_>>(), vec![(1001, 2), (1001, 4)]);

    // ... and the parameter service works: an invalid threshold is refused with a reason, a valid one applied.
    let call = |name: &str, value: ParameterValue| -> (bool, String) {
        futures::executor::block_on(async {
            set_client.wait_for_service(&peer).await;
            let req = SetParametersRequest { parameter: vec![Parameter { name: name.into(), value }.into()] };
            let id = set_client.async_send_request(req).await.unwrap();
            let resp = set_client.async_receive_response(id).await.unwrap();
            (resp.results[0].successful, resp.results[0].reason.clone())
        })
    };
    let (ok, reason) = call("detector.min_score", ParameterValue::Double(7.0));
    assert!(!ok);
    assert!(reason.contains("detector.min_score"), "{reason}");
    let (ok, reason) = call("detector.min_score", ParameterValue::String("high".into()));
    assert!(!ok, "{reason}");
    let (ok, reason) = call("detector.min_score", ParameterValue::Double(0.5));
    assert!(ok, "{reason}");
    // The node's conversions hold at run time too: an integer for a double (`ros2 param set ...
    // selection.min_period 0`), `yes` for a bool; the store keeps the parameter's own type.
    let (ok, reason) = call("selection.min_period", ParameterValue::Integer(0));
    assert!(ok, "{reason}");
    let (ok, reason) = call("detector.consistency.delayed", ParameterValue::String("no".into()));
    assert!(ok, "{reason}");
    let (ok, reason) = call("selection.min_period", ParameterValue::Double(0.5));
    assert!(ok, "the double stays a double: {reason}");
    let (ok, reason) = call("detector.consistency.delayed", ParameterValue::String("yes".into()));
    assert!(ok, "{reason}");
    // describe_parameters carries the table's description and range.
    let described = futures::executor::block_on(async {
        describe_client.wait_for_service(&peer).await;
        let req = DescribeParametersRequest { names: vec!["detector.min_score".into(), "use_sim_time".into()] };
        let id = describe_client.async_send_request(req).await.unwrap();
        describe_client.async_receive_response(id).await.unwrap()
    });
    let spec = ecm_lcd::config::param_spec("detector.min_score").unwrap();
    assert_eq!(described.values[0].description, spec.description);
    assert_eq!(described.values[0].floating_point_range.len(), 1);
    assert_eq!(described.values[0].r#type, 3); // PARAMETER_DOUBLE
    assert_eq!(described.values[1].r#type, 1); // PARAMETER_BOOL
                                               // With the lower threshold a grey of 100 now matches 10 and 200 (scores 0.65, 0.61).
    kf_pub.publish(keyframe(50, 300, 100)).unwrap();
    let got = collect(5, Duration::from_secs(10));
    let mut matched: Vec<u64> = got.iter().map(|c| c.match_id).collect();
    matched.sort();
    assert_eq!(matched, vec![1, 2, 3, 4, 1001]);
    assert!(got.iter().all(|c| c.query_id == 50 && c.num_candidates == 5));

    stop.store(true, Ordering::Relaxed);
    let final_counters = node_thread.join().unwrap().unwrap();
    let seen = seen.lock().unwrap();
    assert_eq!(seen.calls.len(), 6, "{:?}", seen.calls);
    assert_eq!(seen.calls[0], (Some(1), Stamp::from_sec_nsec(100, 500), 32, 24));
    assert_eq!(seen.calls[4].0, None);
    let applied = [
        ("detector.min_score", ParamValue::Double(0.5)),
        ("selection.min_period", ParamValue::Double(0.0)),
        ("detector.consistency.delayed", ParamValue::Bool(false)),
        ("selection.min_period", ParamValue::Double(0.5)),
        ("detector.consistency.delayed", ParamValue::Bool(true)),
    ];
    assert_eq!(seen.params, applied.clone().map(|(name, value)| (name.to_string(), value)));
    assert_eq!(final_counters.processed, 6);
    assert_eq!(final_counters.malformed, 5);
    assert_eq!(final_counters.received, 10);
    assert_eq!(final_counters.candidates, 9);
    assert_eq!(final_counters.param_changes, applied.len() as u64);
    println!("INNER-DONE {final_counters}");
}

/// `run_node` over a processor on a thread, with the default settings and parameters.
struct DefaultNode {
    thread: std::thread::JoinHandle<anyhow::Result<ecm_lcd::ros::CountersSnapshot>>,
    stop: Arc<AtomicBool>,
}

impl DefaultNode {
    fn start(processor: MeanColourProcessor) -> DefaultNode {
        Self::start_with(NodeSettings::default(), processor)
    }

    fn start_with(settings: NodeSettings, processor: MeanColourProcessor) -> DefaultNode {
        let (counters, stop) = (Arc::new(NodeCounters::default()), Arc::new(AtomicBool::new(false)));
        let node_stop = stop.clone();
        let thread = std::thread::spawn(move || {
            run_node(&settings, Params::default(), None, Box::new(processor), counters, node_stop)
        });
        DefaultNode { thread, stop }
    }

    /// Stops the node; its final counters.
    fn stop(self) -> ecm_lcd::ros::CountersSnapshot {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.join().unwrap().unwrap()
    }
}

/// A spinning peer node with reliable publishers of `/keyframes` and of an Image topic.
fn keyframe_and_image_publishers(
    context: &Context,
    image_topic: &str,
) -> (ros2_client::Node, ros2_client::Publisher<Keyframe>, ros2_client::Publisher<Image>) {
    let mut peer =
        context.new_node(NodeName::new("/", "peer").unwrap(), NodeOptions::new().enable_rosout(false)).unwrap();
    let reliable = ecm_lcd::ros::node::InputQos::Reliable.profile();
    let kf_topic = peer.create_topic(&Name::parse("/keyframes").unwrap(), msgs::keyframe_type(), &reliable).unwrap();
    let image_topic = peer.create_topic(&Name::parse(image_topic).unwrap(), msgs::image_type(), &reliable).unwrap();
    let kf_pub = peer.create_publisher::<Keyframe>(&kf_topic, None).unwrap();
    let image_pub = peer.create_publisher::<Image>(&image_topic, None).unwrap();
    let spinner = peer.spinner().unwrap();
    std::thread::spawn(move || futures::executor::block_on(spinner.spin()));
    (peer, kf_pub, image_pub)
}

/// With `--input keyframes` (the launch file's default beside a tracker) the node takes the tracker's
/// keyframes and leaves the camera's frames alone: a camera image published beside them neither takes a
/// keyframe id nor reaches the processor.
#[test]
fn a_node_on_keyframes_only_leaves_camera_frames_alone() {
    if !ros_support::inside() {
        return ros_support::check_inner_run("a_node_on_keyframes_only_leaves_camera_frames_alone");
    }
    let seen = Arc::new(Mutex::new(Seen::default()));
    let processor = MeanColourProcessor { seen: seen.clone(), history: Vec::new(), next_id: 0, min_score: 0.99 };
    let settings = NodeSettings { inputs: ecm_lcd::ros::node::FrameInputs::Keyframes, ..NodeSettings::default() };
    let node = DefaultNode::start_with(settings, processor);
    let context = Context::new().unwrap();
    let (peer, kf_pub, img_pub) = keyframe_and_image_publishers(&context, "/image");
    let deadline = Instant::now() + Duration::from_secs(20);
    while kf_pub.get_subscription_count(&peer) == 0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(kf_pub.get_subscription_count(&peer) > 0, "node's keyframe subscription never matched");
    std::thread::sleep(Duration::from_millis(500));
    img_pub.publish(keyframe(0, 9, 50).image).unwrap();
    kf_pub.publish(keyframe(7, 10, 10)).unwrap();
    let end = Instant::now() + Duration::from_secs(10);
    while seen.lock().unwrap().calls.is_empty() && Instant::now() < end {
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(img_pub.get_subscription_count(&peer), 0, "the node subscribed the camera's frames");
    let counters = node.stop();
    let calls: Vec<Option<u64>> = seen.lock().unwrap().calls.iter().map(|c| c.0).collect();
    assert_eq!(calls, [Some(7)], "{counters}");
    assert_eq!(counters.received, 1, "{counters}");
    println!("INNER-DONE {counters}");
}

/// A 32x24 `16UC1` depth image of `millimetres` everywhere, stamped `secs` + `nanos`.
fn depth_message(secs: i32, nanos: u32, encoding: &str, millimetres: u16) -> Image {
    Image {
        header: Header { stamp: ecm_lcd::io::msgs::Time { sec: secs, nanosec: nanos }, frame_id: "depth".into() },
        height: 24,
        width: 32,
        encoding: encoding.into(),
        is_bigendian: 0,
        step: 64,
        data: millimetres.to_le_bytes().repeat(32 * 24),
    }
}

/// The node pairs `depth` images with keyframes by stamp (within 20 ms), whichever arrives first: one
/// sent before its keyframe goes with it to the processor, one sent after is attached to the processed
/// keyframe; one 30 ms off pairs with nothing, and one of a colour encoding is counted as malformed.
#[test]
fn depth_images_reach_their_keyframes_whichever_comes_first() {
    if !ros_support::inside() {
        return ros_support::check_inner_run("depth_images_reach_their_keyframes_whichever_comes_first");
    }
    let seen = Arc::new(Mutex::new(Seen::default()));
    // Far-apart colours: no loop candidates, only depth pairing is under test.
    let processor = MeanColourProcessor { seen: seen.clone(), history: Vec::new(), next_id: 0, min_score: 0.99 };
    let node = DefaultNode::start(processor);
    let context = Context::new().unwrap();
    let (peer, kf_pub, depth_pub) = keyframe_and_image_publishers(&context, "/depth");
    let deadline = Instant::now() + Duration::from_secs(20);
    while (kf_pub.get_subscription_count(&peer) == 0 || depth_pub.get_subscription_count(&peer) == 0)
        && Instant::now() < deadline
    {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(depth_pub.get_subscription_count(&peer) > 0, "node's depth subscription never matched");
    std::thread::sleep(Duration::from_millis(500));
    let calls = |n: usize| {
        let end = Instant::now() + Duration::from_secs(10);
        while seen.lock().unwrap().calls.len() < n && Instant::now() < end {
            std::thread::sleep(Duration::from_millis(20));
        }
        std::thread::sleep(Duration::from_millis(300));
    };

    // Before its keyframe (5 ms after the keyframe's stamp).
    depth_pub.publish(depth_message(10, 5_000_500, "16UC1", 1000)).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    kf_pub.publish(keyframe(1, 10, 10)).unwrap();
    calls(1);
    // After its keyframe (5 ms before the keyframe's stamp).
    kf_pub.publish(keyframe(2, 11, 90)).unwrap();
    calls(2);
    depth_pub.publish(depth_message(10, 995_000_500, "16UC1", 2000)).unwrap();
    // 30 ms off: no pair; a colour encoding on the depth topic: malformed.
    depth_pub.publish(depth_message(12, 30_000_500, "16UC1", 3000)).unwrap();
    depth_pub.publish(depth_message(13, 500, "rgb8", 4000)).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    kf_pub.publish(keyframe(3, 12, 170)).unwrap();
    calls(3);
    // Whatever is left in the inbox reaches the worker within its next wait.
    std::thread::sleep(Duration::from_millis(500));
    // A keyframe published after 20 depth images at 30 Hz (0.63 s), the first of them its own: a
    // tracker's keyframe comes some time after its image.
    for k in 0..20u32 {
        depth_pub.publish(depth_message(20, k * 33_000_000 + 500, "16UC1", if k == 0 { 5000 } else { 6000 })).unwrap();
        std::thread::sleep(Duration::from_millis(33));
    }
    std::thread::sleep(Duration::from_millis(300));
    kf_pub.publish(keyframe(4, 20, 250)).unwrap();
    calls(4);
    let counters = node.stop();
    let seen = seen.lock().unwrap();
    assert_eq!(seen.depths, vec![(1, 1.0, "with"), (2, 2.0, "after"), (4, 5.0, "with")], "{counters}");
    assert_eq!(seen.calls.len(), 4);
    assert_eq!(counters.malformed, 1, "{counters}");
    assert_eq!(counters.processed, 4, "{counters}");
    println!("INNER-DONE {counters}");
}

#[test]
fn cyclone_dds_peer_sends_images_and_receives_candidates() {
    if !ros_support::inside() {
        // Network-free preparation outside the namespace (PyPI must be reachable the first time).
        ros_support::cyclone_python();
        return ros_support::check_inner_run("cyclone_dds_peer_sends_images_and_receives_candidates");
    }
    let seen = Arc::new(Mutex::new(Seen::default()));
    let processor = MeanColourProcessor { seen: seen.clone(), history: Vec::new(), next_id: 0, min_score: 0.95 };
    let node = DefaultNode::start(processor);
    let script = ros_support::cyclone_peer_script();
    let out = std::process::Command::new(ros_support::cyclone_python())
        .arg(&script)
        .args(["2", "10", "200", "10", "200"])
        .output()
        .expect("running the Cyclone DDS peer");
    let text = String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    let final_counters = node.stop();
    assert!(out.status.success(), "peer failed:\n{text}");
    let candidates: Vec<&str> = text.lines().filter(|l| l.starts_with("CANDIDATE ")).collect();
    assert_eq!(
        candidates,
        vec![
            "CANDIDATE 1003 1001 0 1.000 502 500 cyclone_cam 0 0",
            "CANDIDATE 1004 1002 0 1.000 503 501 cyclone_cam 0 0"
        ],
        "{text}"
    );
    assert_eq!(final_counters.processed, 4, "{final_counters}");
    assert_eq!(final_counters.malformed, 0);
    // /diagnostics, as the Cyclone peer decoded it: the node's health with its counters and timings.
    let diag =
        text.lines().find(|l| l.starts_with("DIAG ")).unwrap_or_else(|| panic!("no /diagnostics received:\n{text}"));
    assert!(diag.starts_with("DIAG 0 /ecm_lcd ok "), "{diag}");
    for key in [
        "queue_depth=",
        "queue_capacity=4",
        "received=4",
        "processed=4",
        "candidates=2",
        "malformed=0",
        "dropped=0",
        "failed=0",
        "decode_ms_mean=",
        "process_ms_mean=",
    ] {
        assert!(diag.contains(key), "{key} missing from {diag}");
    }
    assert_eq!(seen.lock().unwrap().calls.iter().filter(|c| c.0.is_none() && c.2 == 32).count(), 4);
    println!("INNER-DONE {final_counters}");
}

#[test]
fn cyclone_dds_parameter_clients_of_both_rmw_framings_are_answered() {
    if !ros_support::inside() {
        ros_support::cyclone_python();
        return ros_support::check_inner_run("cyclone_dds_parameter_clients_of_both_rmw_framings_are_answered");
    }
    let seen = Arc::new(Mutex::new(Seen::default()));
    let processor = MeanColourProcessor { seen, history: Vec::new(), next_id: 0, min_score: 0.95 };
    let node = DefaultNode::start(processor);
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/ros_support/cyclone_params.py");
    let mut outputs = Vec::new();
    // rmw_fastrtps's bare requests and rmw_cyclonedds_cpp's header-framed ones, one client after the other.
    for framing in ["bare", "cyclone"] {
        let out = std::process::Command::new(ros_support::cyclone_python())
            .arg(&script)
            .args([framing, "ecm_lcd"])
            .output()
            .expect("running the Cyclone DDS parameter client");
        let text = String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
        outputs.push((framing, out.status.success(), text));
    }
    let final_counters = node.stop();
    for (framing, success, text) in &outputs {
        assert!(success, "{framing} client failed:\n{text}");
        let lines: Vec<&str> = text.lines().filter(|l| !l.starts_with("PEER-DONE")).collect();
        assert!(!lines.iter().any(|l| l.starts_with("PEER-ERROR")), "{framing}:\n{text}");
        assert!(lines[0].starts_with("LIST ") && lines[0].ends_with(" yes"), "{framing}: {}", lines[0]);
        assert!(lines[1].starts_with("DESCRIBE detector.min_score yes 0.0..1.0"), "{framing}: {}", lines[1]);
        // The invalid value is refused with its reason, the valid one applied and read back.
        assert!(lines[2].starts_with("SET 0 ") && lines[2].contains("min_score"), "{framing}: {}", lines[2]);
        assert_eq!(lines[3], "SET 1 ", "{framing}");
        assert_eq!(lines[4], "GET 3 0.85", "{framing}");
        assert_eq!(lines.len(), 5, "{framing}:\n{text}");
    }
    assert!(final_counters.param_changes >= 1, "{final_counters}");
    println!("INNER-DONE {final_counters}");
}

#[test]
fn play_keyframes_and_listen_processes_talk_to_the_node() {
    if !ros_support::inside() {
        return ros_support::check_inner_run("play_keyframes_and_listen_processes_talk_to_the_node");
    }
    // A looped sequence in TUM form: places 10, 200, 10, 200, 10.
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    let mut writer = ecm_lcd::io::tum::TumWriter::create(&seq).unwrap();
    for (i, grey) in [10u8, 200, 10, 200, 10].into_iter().enumerate() {
        writer.write_frame(Stamp::from_sec_nsec(1000 + i as i64, 0), &solid(40, 30, grey)).unwrap();
    }
    writer.finish().unwrap();

    let seen = Arc::new(Mutex::new(Seen::default()));
    let processor = MeanColourProcessor { seen: seen.clone(), history: Vec::new(), next_id: 0, min_score: 0.95 };
    let node = DefaultNode::start(processor);
    let exe = env!("CARGO_BIN_EXE_ecm-lcd");
    // The two cross-keyframe pairs of the first loop and the three of the second: 2->0, 3->1, 4->2, 4->0.
    let listener = ros_support::Listener::start(4);
    let player = std::process::Command::new(exe)
        .args(["play-keyframes"])
        .arg(&seq)
        .args(["--rate", "20", "--as", "keyframe", "--linger", "1"])
        .output()
        .unwrap();
    assert!(player.status.success(), "{}", String::from_utf8_lossy(&player.stderr));
    assert!(String::from_utf8_lossy(&player.stderr).contains("published 5 frames"));
    let csv = listener.finish();
    let final_counters = node.stop();
    let rows: Vec<(u64, u64)> = csv
        .lines()
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[0].parse().unwrap(), f[2].parse().unwrap())
        })
        .collect();
    assert_eq!(rows, vec![(2, 0), (3, 1), (4, 0), (4, 2)], "{csv}");
    assert!(csv.lines().next().unwrap().starts_with("2,1002.000000000,0,1000.000000000,"), "{csv}");
    assert_eq!(final_counters.processed, 5, "{final_counters}");
    assert_eq!(
        seen.lock().unwrap().calls.iter().map(|c| c.0).collect::<Vec<_>>(),
        (0..5).map(Some).collect::<Vec<_>>()
    );
    println!("INNER-DONE {final_counters}");
}
