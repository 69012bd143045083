//! The other side of the node, for tools and tests: a small ROS 2 participant that publishes frames as
//! Keyframe / Image / CompressedImage messages (the tracker stand-in) and one that prints the
//! LoopCandidates it receives. Both use the node's QoS so they match it.

use anyhow::{Context as _, Result};
use ros2_client::{Context, Name, Node, NodeName, NodeOptions, Publisher, Subscription};
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

/// Publishes frames on one topic.
pub struct FramePublisher {
    node: Node,
    publisher: AnyPublisher,
    frame_id: String,
    topic: String,
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
        Ok(FramePublisher { node, publisher, frame_id: frame_id.to_string(), topic: topic.to_string() })
    }

    /// Number of matched subscriptions.
    pub fn subscribers(&self) -> usize {
        match &self.publisher {
            AnyPublisher::Keyframe(p) => p.get_subscription_count(&self.node),
            AnyPublisher::Image(p) => p.get_subscription_count(&self.node),
            AnyPublisher::Compressed(p) => p.get_subscription_count(&self.node),
        }
    }

    /// Waits until at least one subscriber matched; false on timeout.
    pub fn wait_for_subscriber(&self, timeout: Duration) -> bool {
        let end = Instant::now() + timeout;
        while self.subscribers() == 0 {
            if Instant::now() >= end {
                return false;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        true
    }

    /// Publishes one frame (Keyframe id = `frame.index`).
    pub fn publish(&self, frame: &Frame) -> Result<()> {
        let ctx = || format!("publishing frame {} on {}", frame.index, self.topic);
        match &self.publisher {
            AnyPublisher::Keyframe(p) => {
                let image = rgb8_message(frame.stamp, &self.frame_id, &frame.image);
                let msg = Keyframe {
                    header: image.header.clone(),
                    id: frame.index as u64,
                    image,
                    has_pose: false,
                    pose: Default::default(),
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
pub struct CandidateListener {
    _node: Node,
    subscription: Subscription<LoopCandidate>,
}

impl CandidateListener {
    pub fn new(context: &Context, topic: &str) -> Result<Self> {
        let mut node = spinning_node(context, &format!("ecm_lcd_listen_{}", std::process::id()))?;
        let t = node
            .create_topic(&topic_name(topic)?, msgs::loop_candidate_type(), &output_qos())
            .map_err(|e| anyhow::anyhow!("topic {topic}: {e:?}"))?;
        let subscription =
            node.create_subscription(&t, None).map_err(|e| anyhow::anyhow!("subscribing {topic}: {e:?}"))?;
        Ok(CandidateListener { _node: node, subscription })
    }

    /// Every candidate that has arrived, without waiting. Undecodable messages are an error.
    pub fn take_all(&self) -> Result<Vec<LoopCandidate>> {
        let mut out = Vec::new();
        while let Some((msg, _)) = self.subscription.take().map_err(|e| anyhow::anyhow!("receiving: {e:?}"))? {
            out.push(msg);
        }
        Ok(out)
    }
}
