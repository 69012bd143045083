//! The other side of the node, for tools and tests: a small ROS 2 participant that publishes frames as
//! Keyframe / Image / CompressedImage messages (the tracker stand-in) and one that prints the
//! LoopCandidates it receives (both with the node's QoS so they match it), and a client of the node's
//! parameter services (`ecm-lcd param`).

use anyhow::{Context as _, Result};
use ros2_client::dds::rustdds::mio1::{Events, Interest, Poll, Token};
use ros2_client::rcl_interfaces::{
    GetParametersRequest, GetParametersResponse, SetParametersRequest, SetParametersResponse,
};
use ros2_client::{
    Client, Context, Message, Name, Node, NodeName, NodeOptions, Parameter, ParameterValue, Publisher, QosProfile,
    ServiceMapping, ServiceTypeName, Subscription,
};
use std::time::{Duration, Instant};

use super::msgs::{self, Keyframe, LoopCandidate};
use super::node::{output_qos, InputQos};
use crate::io::image_msg::{jpeg_message, rgb8_message};
use crate::io::msgs::{CompressedImage, Image};
use crate::types::Frame;

/// How frames go on the wire.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum SendAs {
    /// ecm_lcd_msgs/Keyframe (id = the frame's index).
    #[default]
    Keyframe,
    /// sensor_msgs/Image, rgb8.
    Image,
    /// sensor_msgs/CompressedImage, JPEG quality 90.
    Compressed,
}

impl SendAs {
    /// The topic the node listens on for this kind.
    pub fn default_topic(self) -> &'static str {
        match self {
            SendAs::Keyframe => "/keyframes",
            SendAs::Image => "/image",
            SendAs::Compressed => "/image/compressed",
        }
    }
}

enum AnyPublisher {
    Keyframe(Publisher<Keyframe>),
    Image(Publisher<Image>),
    Compressed(Publisher<CompressedImage>),
}

/// Publishes frames on one topic, and their depth images on another where asked.
pub struct FramePublisher {
    node: Node,
    publisher: AnyPublisher,
    /// Depth images (`32FC1`) and their topic.
    depth: Option<(Publisher<Image>, String)>,
    frame_id: String,
    topic: String,
}

/// Checks `ready` every 50 ms until it holds (true) or `timeout` passed (false).
fn wait_until(timeout: Duration, mut ready: impl FnMut() -> bool) -> bool {
    let end = Instant::now() + timeout;
    while !ready() {
        if Instant::now() >= end {
            return false;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    true
}

/// A node with its spinner running on a thread (discovery needs it).
fn spinning_node(context: &Context, name: &str) -> Result<Node> {
    let mut node = context
        .new_node(NodeName::new("/", name).context("node name")?, NodeOptions::new().enable_rosout(false))
        .map_err(|e| anyhow::anyhow!("creating node {name}: {e:?}"))?;
    let spinner = node.spinner().map_err(|e| anyhow::anyhow!("spinner: {e:?}"))?;
    std::thread::Builder::new()
        .name(format!("{name}-spinner"))
        .spawn(move || futures::executor::block_on(spinner.spin()))
        .context("spinner thread")?;
    Ok(node)
}

fn topic_name(topic: &str) -> Result<Name> {
    Name::parse(topic).map_err(|e| anyhow::anyhow!("invalid topic name {topic:?}: {e:?}"))
}

impl FramePublisher {
    pub fn new(context: &Context, topic: &str, send_as: SendAs, qos: InputQos, frame_id: &str) -> Result<Self> {
        let mut node = spinning_node(context, &format!("ecm_lcd_play_{}", std::process::id()))?;
        let name = topic_name(topic)?;
        let ty = match send_as {
            SendAs::Keyframe => msgs::keyframe_type(),
            SendAs::Image => msgs::image_type(),
            SendAs::Compressed => msgs::compressed_image_type(),
        };
        let t = node.create_topic(&name, ty, &qos.profile()).map_err(|e| anyhow::anyhow!("topic {topic}: {e:?}"))?;
        let err = |e| anyhow::anyhow!("publisher on {topic}: {e:?}");
        let publisher = match send_as {
            SendAs::Keyframe => AnyPublisher::Keyframe(node.create_publisher(&t, None).map_err(err)?),
            SendAs::Image => AnyPublisher::Image(node.create_publisher(&t, None).map_err(err)?),
            SendAs::Compressed => AnyPublisher::Compressed(node.create_publisher(&t, None).map_err(err)?),
        };
        Ok(FramePublisher { node, publisher, depth: None, frame_id: frame_id.to_string(), topic: topic.to_string() })
    }

    /// Also publishes each frame's depth image, where it has one, on `topic` (just before the frame).
    pub fn add_depth_topic(&mut self, topic: &str, qos: InputQos) -> Result<()> {
        let name = topic_name(topic)?;
        let t = self
            .node
            .create_topic(&name, msgs::image_type(), &qos.profile())
            .map_err(|e| anyhow::anyhow!("topic {topic}: {e:?}"))?;
        let publisher =
            self.node.create_publisher(&t, None).map_err(|e| anyhow::anyhow!("publisher on {topic}: {e:?}"))?;
        self.depth = Some((publisher, topic.to_string()));
        Ok(())
    }

    /// Number of matched subscriptions.
    pub fn subscribers(&self) -> usize {
        match &self.publisher {
            AnyPublisher::Keyframe(p) => p.get_subscription_count(&self.node),
            AnyPublisher::Image(p) => p.get_subscription_count(&self.node),
            AnyPublisher::Compressed(p) => p.get_subscription_count(&self.node),
        }
    }

    /// Waits until at least one subscriber matched (on the depth topic too, where there is one); false
    /// on timeout.
    pub fn wait_for_subscriber(&self, timeout: Duration) -> bool {
        let depth_matched = || self.depth.as_ref().is_none_or(|(p, _)| p.get_subscription_count(&self.node) > 0);
        wait_until(timeout, || self.subscribers() > 0 && depth_matched())
    }

    /// Publishes one frame (Keyframe id = `frame.index`).
    pub fn publish(&self, frame: &Frame) -> Result<()> {
        self.publish_with_pose(frame, None)
    }

    /// Publishes one frame; a Keyframe carries `pose` (the camera in the tracker's map) where given.
    pub fn publish_with_pose(&self, frame: &Frame, pose: Option<msgs::Pose>) -> Result<()> {
        let ctx = || format!("publishing frame {} on {}", frame.index, self.topic);
        if let (Some((publisher, topic)), Some(depth)) = (&self.depth, &frame.depth) {
            publisher
                .publish(crate::io::depth::depth_image_message(frame.stamp, &self.frame_id, depth))
                .map_err(|e| anyhow::anyhow!("{e:?}"))
                .with_context(|| format!("publishing the depth of frame {} on {topic}", frame.index))?;
        }
        match &self.publisher {
            AnyPublisher::Keyframe(p) => {
                let image = rgb8_message(frame.stamp, &self.frame_id, &frame.image);
                let msg = Keyframe {
                    header: image.header.clone(),
                    id: frame.index as u64,
                    image,
                    has_pose: pose.is_some(),
                    pose: pose.unwrap_or_default(),
                };
                p.publish(msg).map_err(|e| anyhow::anyhow!("{e:?}")).with_context(ctx)
            }
            AnyPublisher::Image(p) => p
                .publish(rgb8_message(frame.stamp, &self.frame_id, &frame.image))
                .map_err(|e| anyhow::anyhow!("{e:?}"))
                .with_context(ctx),
            AnyPublisher::Compressed(p) => p
                .publish(jpeg_message(frame.stamp, &self.frame_id, &frame.image, 90)?)
                .map_err(|e| anyhow::anyhow!("{e:?}"))
                .with_context(ctx),
        }
    }
}

/// Receives LoopCandidates.
pub type CandidateListener = Listener<LoopCandidate>;

/// Receives the node's messages of one type on one topic (with the node's output QoS).
pub struct Listener<M: Message + serde::de::DeserializeOwned + 'static> {
    _node: Node,
    subscription: Subscription<M>,
    /// Wakes [`Listener::wait`] when data arrives (the subscription is registered with it).
    poll: std::sync::Mutex<(Poll, Events)>,
}

impl Listener<LoopCandidate> {
    pub fn new(context: &Context, topic: &str) -> Result<Self> {
        Self::of_type(context, topic, msgs::loop_candidate_type())
    }
}

impl Listener<msgs::MarkerArray> {
    /// The loop-edge markers (`visualization_msgs/MarkerArray`).
    pub fn markers(context: &Context, topic: &str) -> Result<Self> {
        Self::of_type(context, topic, msgs::marker_array_type())
    }
}

impl<M: Message + serde::de::DeserializeOwned + 'static> Listener<M> {
    fn of_type(context: &Context, topic: &str, type_name: ros2_client::MessageTypeName) -> Result<Self> {
        // Each listener is its own node: unique names, so several can share one context.
        static LISTENERS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = LISTENERS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut node = spinning_node(context, &format!("ecm_lcd_listen_{}_{n}", std::process::id()))?;
        let t = node
            .create_topic(&topic_name(topic)?, type_name, &output_qos())
            .map_err(|e| anyhow::anyhow!("topic {topic}: {e:?}"))?;
        let mut subscription: Subscription<M> =
            node.create_subscription(&t, None).map_err(|e| anyhow::anyhow!("subscribing {topic}: {e:?}"))?;
        let poll = Poll::new().context("creating the poll")?;
        poll.registry()
            .register(&mut subscription, Token(0), Interest::READABLE)
            .context("polling the subscription")?;
        Ok(Listener { _node: node, subscription, poll: std::sync::Mutex::new((poll, Events::with_capacity(4))) })
    }

    /// The messages that arrived, waiting at most `timeout` for the first (empty on timeout). Wakes on
    /// arrival, so it adds no polling delay to a latency measurement.
    pub fn wait(&self, timeout: Duration) -> Result<Vec<M>> {
        let got = self.take_all()?;
        if !got.is_empty() {
            return Ok(got);
        }
        let mut guard = self.poll.lock().unwrap_or_else(|e| e.into_inner());
        let (poll, events) = &mut *guard;
        if let Err(e) = poll.poll(events, Some(timeout)) {
            if e.kind() != std::io::ErrorKind::Interrupted {
                return Err(e).context("waiting for messages");
            }
        }
        self.take_all()
    }

    /// Number of matched publishers (the node's, once discovery has run).
    pub fn publishers(&self) -> usize {
        self.subscription.get_publisher_count(&self._node)
    }

    /// Waits until at least one publisher matched; false on timeout.
    pub fn wait_for_publisher(&self, timeout: Duration) -> bool {
        wait_until(timeout, || self.publishers() > 0)
    }

    /// Every message that has arrived, without waiting. Undecodable messages are an error.
    pub fn take_all(&self) -> Result<Vec<M>> {
        let mut out = Vec::new();
        while let Some((msg, _)) = self.subscription.take().map_err(|e| anyhow::anyhow!("receiving: {e:?}"))? {
            out.push(msg);
        }
        Ok(out)
    }
}

/// Runs `future` on this thread for at most `timeout`; None when the time ran out.
fn block_on_with_timeout<F: std::future::Future>(future: F, timeout: Duration) -> Option<F::Output> {
    let (alarm, rang) = futures::channel::oneshot::channel::<()>();
    std::thread::spawn(move || {
        std::thread::sleep(timeout);
        let _ = alarm.send(());
    });
    futures::executor::block_on(async {
        match futures::future::select(std::pin::pin!(future), rang).await {
            futures::future::Either::Left((output, _)) => Some(output),
            futures::future::Either::Right(_) => None,
        }
    })
}

/// A client of another node's parameter services (`get_parameters`, `set_parameters`), as `ros2 param`.
pub struct ParamClient {
    node: Node,
    get: Client<GetParametersRequest, GetParametersResponse>,
    set: Client<SetParametersRequest, SetParametersResponse>,
    target: String,
    timeout: Duration,
}

impl ParamClient {
    /// `target`: the node's fully qualified name (`/ecm_lcd`, `/robot1/lcd`). Each call waits at most
    /// `timeout` for the service to appear and answer.
    pub fn new(context: &Context, target: &str, timeout: Duration) -> Result<Self> {
        let mut node = spinning_node(context, &format!("ecm_lcd_param_{}", std::process::id()))?;
        let target = if target.starts_with('/') { target.to_string() } else { format!("/{target}") };
        let get = Self::client(&mut node, &target, "get_parameters", "GetParameters")?;
        let set = Self::client(&mut node, &target, "set_parameters", "SetParameters")?;
        Ok(ParamClient { node, get, set, target, timeout })
    }

    fn client<Req: Message + Clone + 'static, Resp: Message + Clone + 'static>(
        node: &mut Node,
        target: &str,
        service: &str,
        type_name: &str,
    ) -> Result<Client<Req, Resp>> {
        let qos = QosProfile::publisher_default().history(ros2_client::qos::History::KeepLast { depth: 1 });
        let name = topic_name(&format!("{target}/{service}"))?;
        node.create_client(
            ServiceMapping::Enhanced,
            &name,
            &ServiceTypeName::new("rcl_interfaces", type_name),
            qos.clone(),
            qos,
        )
        .map_err(|e| anyhow::anyhow!("creating a client of {target}/{service}: {e:?}"))
    }

    fn call<Req: Message + Clone + 'static, Resp: Message + Clone + 'static>(
        &self,
        client: &Client<Req, Resp>,
        service: &str,
        request: Req,
    ) -> Result<Resp> {
        let call = async {
            client.wait_for_service(&self.node).await;
            client.async_call_service(request).await
        };
        match block_on_with_timeout(call, self.timeout) {
            Some(Ok(response)) => Ok(response),
            Some(Err(e)) => Err(anyhow::anyhow!("calling {}/{service}: {e:?}", self.target)),
            None => Err(anyhow::anyhow!(
                "no answer from {}/{service} within {:.1} s (is the node running, in this ROS domain?)",
                self.target,
                self.timeout.as_secs_f64()
            )),
        }
    }

    /// Sets one parameter. Outer error: the call failed; inner error: the node refused, with its reason.
    pub fn set(&self, name: &str, value: ParameterValue) -> Result<std::result::Result<(), String>> {
        let request = SetParametersRequest { parameter: vec![Parameter { name: name.to_string(), value }.into()] };
        let response = self.call(&self.set, "set_parameters", request)?;
        let result =
            response.results.first().with_context(|| format!("{} sent an empty set_parameters answer", self.target))?;
        Ok(if result.successful { Ok(()) } else { Err(result.reason.clone()) })
    }

    /// The current value of one parameter (`ParameterValue::NotSet` when the node has no such parameter).
    pub fn get(&self, name: &str) -> Result<ParameterValue> {
        let response =
            self.call(&self.get, "get_parameters", GetParametersRequest { names: vec![name.to_string()] })?;
        let value = response
            .values
            .into_iter()
            .next()
            .with_context(|| format!("{} sent an empty get_parameters answer", self.target))?;
        Ok(value.into())
    }
}
