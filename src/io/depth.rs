//! Depth images from bags: decoding `sensor_msgs/Image` depth encodings, and pairing a bag's depth
//! topic with its colour topic as both stream past.
//!
//! Interpretations written down once:
//! - `16UC1` (and `mono16`, as some drivers label it) holds millimetres, the ROS depth convention
//!   (REP 118); `32FC1` holds metres. 0, NaN and infinities are unknown depth.
//! - A colour frame takes the depth message whose header stamp is nearest its own, within
//!   [`DEPTH_ASSOCIATION`] (TUM's `associate.py` rule, as for TUM folders); otherwise it has none.
//! - Bags are read in record order, and a depth message can be recorded after the colour frame it
//!   belongs to, so a frame is held back until a depth message stamped past its window arrives, a
//!   colour frame [`MAX_HOLD`] newer arrives, [`MAX_HELD_FRAMES`] frames wait behind it (colour
//!   stamps that do not advance: all 0, or repeated), or the bag ends. Depth messages are kept only
//!   while a held or future frame could still take them, so memory stays bounded by that lag.

use std::collections::VecDeque;

use anyhow::{bail, Result};

use super::image_msg::{checked_layout, ImageMessage};
use super::msgs::Image;
pub use super::tum::DEPTH_ASSOCIATION;
use super::TopicInfo;
use crate::types::{DepthImage, Frame, Stamp};

/// How long a colour frame waits for its depth message, in colour-stamp time.
pub const MAX_HOLD: Stamp = Stamp::from_nanos(1_000_000_000);

/// Depth messages kept at most while no colour frame arrives (a bag whose colour topic stops).
const MAX_KEPT_DEPTHS: usize = 64;

/// Colour frames held at most, whatever their stamps say (module doc).
pub const MAX_HELD_FRAMES: usize = 64;

/// Millimetres per metre in `16UC1` depth images.
const UNITS_PER_METRE_16UC1: f32 = 1000.0;

/// A depth topic whose images are in an encoding that is no depth: a topic chosen wrongly (a colour
/// topic), which ends the replay, where one depth image that does not decode is passed over.
#[derive(Debug, thiserror::Error)]
#[error("unsupported depth encoding {0:?} (supported: 16UC1 in millimetres, 32FC1 in metres)")]
pub struct UnsupportedDepthEncoding(pub String);

/// A depth message of a bag that does not decode: [`BagMessage::UnreadableDepth`], or the error
/// itself where its encoding is no depth encoding ([`UnsupportedDepthEncoding`]).
pub(crate) fn unreadable_depth(error: anyhow::Error) -> Result<BagMessage> {
    match error.downcast_ref::<UnsupportedDepthEncoding>() {
        Some(_) => Err(error),
        None => Ok(BagMessage::UnreadableDepth(error)),
    }
}

/// Decodes a depth `sensor_msgs/Image` (module doc) to metres.
pub fn depth_from_image(msg: &Image) -> Result<DepthImage> {
    let encoding = msg.encoding.as_str();
    let bytes_per_pixel = match encoding {
        "16UC1" | "mono16" => 2,
        "32FC1" => 4,
        _ => return Err(UnsupportedDepthEncoding(encoding.to_string()).into()),
    };
    let (row_bytes, step) = checked_layout(msg, bytes_per_pixel, &format!("{encoding} depth image"))?;
    let (width, height) = (msg.width as usize, msg.height as usize);
    let big_endian = msg.is_bigendian != 0;
    let known = |m: f32| if m.is_finite() && m > 0.0 { m } else { 0.0 };
    let mut metres = Vec::with_capacity(width * height);
    for row in msg.data.chunks_exact(step) {
        let pixels = &row[..row_bytes];
        if bytes_per_pixel == 2 {
            metres.extend(pixels.chunks_exact(2).map(|p| {
                let units =
                    if big_endian { u16::from_be_bytes([p[0], p[1]]) } else { u16::from_le_bytes([p[0], p[1]]) };
                units as f32 / UNITS_PER_METRE_16UC1
            }));
        } else {
            metres.extend(pixels.chunks_exact(4).map(|p| {
                let bytes = [p[0], p[1], p[2], p[3]];
                known(if big_endian { f32::from_be_bytes(bytes) } else { f32::from_le_bytes(bytes) })
            }));
        }
    }
    Ok(DepthImage { width: msg.width, height: msg.height, metres })
}

/// `depth` as a `32FC1` `sensor_msgs/Image` in metres, NaN where unknown (as TUM's bags carry it).
pub fn depth_image_message(stamp: Stamp, frame_id: &str, depth: &DepthImage) -> Image {
    let data =
        depth.metres.iter().flat_map(|&m| if m.is_finite() && m > 0.0 { m } else { f32::NAN }.to_le_bytes()).collect();
    Image {
        header: super::msgs::Header { stamp: stamp.into(), frame_id: frame_id.to_string() },
        height: depth.height,
        width: depth.width,
        encoding: "32FC1".into(),
        is_bigendian: 0,
        step: depth.width * 4,
        data,
    }
}

/// A depth message read from a bag as a [`BagMessage`].
pub(crate) fn depth_message(msg: &ImageMessage) -> Result<BagMessage> {
    match msg {
        ImageMessage::Raw(image) => Ok(BagMessage::Depth(msg.stamp(), depth_from_image(image)?)),
        ImageMessage::Compressed(_) => bail!("a depth topic must carry sensor_msgs/Image"),
    }
}

/// e.g. "ROS 1 bag x.bag, topic /rgb (798 messages), depth /depth (797 messages)"
pub(crate) fn describe_topics(bag: &str, colour: &str, colour_count: usize, depth: Option<&TopicInfo>) -> String {
    let mut out = format!("{bag}, topic {colour} ({colour_count} messages)");
    if let Some(depth) = depth {
        out.push_str(&format!(", depth {} ({} messages)", depth.name, depth.count));
    }
    out
}

/// The item of `stamped` whose stamp is nearest `stamp`, within [`DEPTH_ASSOCIATION`] (the earlier
/// one on a tie).
pub fn nearest_within_window<T>(stamped: &VecDeque<(Stamp, T)>, stamp: Stamp) -> Option<&(Stamp, T)> {
    let offset = |other: &Stamp| other.nanos.abs_diff(stamp.nanos);
    stamped
        .iter()
        .filter(|(other, _)| offset(other) <= DEPTH_ASSOCIATION.nanos.unsigned_abs())
        .min_by_key(|(other, _)| offset(other))
}

/// One message of a bag's replayed topics, in record order.
pub enum BagMessage {
    /// A frame of the colour topic (its index counts colour frames only; no depth yet).
    Colour(Frame),
    /// A depth image and its header stamp.
    Depth(Stamp, DepthImage),
    /// A message of the depth topic that does not decode, in an intact bag: passed over
    /// ([`UnreadableDepths`]).
    UnreadableDepth(anyhow::Error),
}

/// Depth images that cannot be decoded: a frame that would have taken one goes on without depth
/// (unverified, or verified up to scale), as one unreadable colour frame is skipped and the rest
/// replayed. Each is counted, and named in the log as [`crate::types::Recurring`] says.
#[derive(Debug, Default)]
pub struct UnreadableDepths {
    count: crate::types::Recurring,
    reported: bool,
}

impl UnreadableDepths {
    pub fn skip(&mut self, error: &anyhow::Error) {
        if let Some(n) = self.count.occurred() {
            log::warn!("a depth image cannot be read, so it is passed over: {error:#} ({n} so far)");
        }
    }

    /// Says, once, at the end of a source, how many were passed over in all.
    pub fn report_end(&mut self) {
        if self.count.count() > 0 && !self.reported {
            log::warn!("{} depth images could not be read; their frames went on without depth", self.count.count());
        }
        self.reported = true;
    }
}

/// A bag reader's messages of its colour topic and, if chosen, its depth topic.
pub trait MessageSource: Iterator<Item = Result<BagMessage>> + Send {
    /// e.g. "ROS 1 bag foo.bag, topic /camera/rgb/image_color (798 messages)"
    fn describe(&self) -> String;
    /// Number of colour frames if known up front.
    fn len_hint(&self) -> Option<usize>;
    /// The calibration beside the colour topic, if the bag has one.
    fn intrinsics(&self) -> Option<super::SourceIntrinsics> {
        None
    }
}

/// Colour frames of a [`MessageSource`] with their depth attached (module doc); a source without a
/// depth topic passes its frames straight through.
pub struct DepthPaired<S> {
    inner: S,
    /// Whether the source has a depth topic (without one, frames pass straight through).
    paired: bool,
    /// Colour frames waiting for their depth, and unreadable frames ([`super::UnreadableFrame`])
    /// kept in their place among them.
    pending: VecDeque<Result<Frame>>,
    depths: VecDeque<(Stamp, DepthImage)>,
    /// Newest colour stamp seen.
    newest_colour: Option<Stamp>,
    ended: bool,
    error: Option<anyhow::Error>,
    unreadable_depths: UnreadableDepths,
}

impl<S: MessageSource> DepthPaired<S> {
    pub fn new(inner: S, paired: bool) -> Self {
        DepthPaired {
            inner,
            paired,
            pending: VecDeque::new(),
            depths: VecDeque::new(),
            newest_colour: None,
            ended: false,
            error: None,
            unreadable_depths: UnreadableDepths::default(),
        }
    }

    /// Whether the oldest held frame can no longer be given a nearer depth message.
    fn front_is_ready(&self) -> bool {
        let Some(front) = self.pending.front() else { return false };
        // An unreadable frame takes no depth: it goes out as soon as it is first.
        let Ok(front) = front else { return true };
        let window_end = front.stamp.nanos.saturating_add(DEPTH_ASSOCIATION.nanos);
        !self.paired
            || self.ended
            || self.pending.len() > MAX_HELD_FRAMES
            || self.depths.back().is_some_and(|(stamp, _)| stamp.nanos > window_end)
            || self.newest_colour.is_some_and(|s| s.nanos.saturating_sub(front.stamp.nanos) > MAX_HOLD.nanos)
    }

    /// The oldest held frame with the nearest depth message within the window, if any.
    fn release_front(&mut self) -> Option<Result<Frame>> {
        let mut frame = match self.pending.pop_front()? {
            Ok(frame) => frame,
            unreadable => return Some(unreadable),
        };
        frame.depth = nearest_within_window(&self.depths, frame.stamp).map(|(_, depth)| depth.clone());
        self.forget_old_depths();
        Some(Ok(frame))
    }

    /// Drops depth messages no held or later colour frame can take.
    fn forget_old_depths(&mut self) {
        let oldest_wanted = self.pending.iter().find_map(|f| f.as_ref().ok()).map(|f| f.stamp).or(self.newest_colour);
        if let Some(oldest) = oldest_wanted {
            let cutoff = oldest.nanos.saturating_sub(DEPTH_ASSOCIATION.nanos);
            while self.depths.front().is_some_and(|(stamp, _)| stamp.nanos < cutoff) {
                self.depths.pop_front();
            }
        }
        while self.depths.len() > MAX_KEPT_DEPTHS {
            self.depths.pop_front();
        }
    }
}

impl<S: MessageSource> Iterator for DepthPaired<S> {
    type Item = Result<Frame>;

    fn next(&mut self) -> Option<Result<Frame>> {
        loop {
            if self.front_is_ready() {
                return self.release_front();
            }
            if self.ended {
                self.unreadable_depths.report_end();
                // Every held frame is out; a read error comes after them, so nothing read is lost.
                return self.error.take().map(Err);
            }
            match self.inner.next() {
                None => self.ended = true,
                Some(Err(err)) if super::unreadable_frame(&err).is_some() => self.pending.push_back(Err(err)),
                Some(Err(err)) => {
                    self.ended = true;
                    self.error = Some(err);
                }
                Some(Ok(BagMessage::Colour(frame))) => {
                    self.newest_colour = Some(self.newest_colour.map_or(frame.stamp, |s| s.max(frame.stamp)));
                    self.pending.push_back(Ok(frame));
                }
                Some(Ok(BagMessage::Depth(stamp, depth))) => {
                    self.depths.push_back((stamp, depth));
                    self.forget_old_depths();
                }
                Some(Ok(BagMessage::UnreadableDepth(error))) => self.unreadable_depths.skip(&error),
            }
        }
    }
}

impl<S: MessageSource> super::FrameSource for DepthPaired<S> {
    fn describe(&self) -> String {
        self.inner.describe()
    }

    fn len_hint(&self) -> Option<usize> {
        self.inner.len_hint()
    }

    fn intrinsics(&self) -> Option<super::SourceIntrinsics> {
        self.inner.intrinsics()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: i64) -> Stamp {
        Stamp::from_nanos(n * 1_000_000)
    }

    fn depth_of(value: f32) -> DepthImage {
        DepthImage { width: 1, height: 1, metres: vec![value] }
    }

    fn colour(index: usize, stamp: Stamp) -> BagMessage {
        BagMessage::Colour(Frame { index, stamp, image: image::RgbImage::new(1, 1), depth: None })
    }

    struct Scripted(std::vec::IntoIter<Result<BagMessage>>);

    impl Iterator for Scripted {
        type Item = Result<BagMessage>;
        fn next(&mut self) -> Option<Result<BagMessage>> {
            self.0.next()
        }
    }

    impl MessageSource for Scripted {
        fn describe(&self) -> String {
            "scripted".into()
        }
        fn len_hint(&self) -> Option<usize> {
            None
        }
    }

    fn paired(messages: Vec<Result<BagMessage>>) -> Vec<Result<Frame>> {
        DepthPaired::new(Scripted(messages.into_iter()), true).collect()
    }

    /// The depth value each frame received (None: no depth), in order.
    fn depths(frames: &[Result<Frame>]) -> Vec<Option<f32>> {
        frames.iter().map(|f| f.as_ref().unwrap().depth.as_ref().map(|d| d.metres[0])).collect()
    }

    #[test]
    fn each_frame_takes_the_nearest_depth_within_the_window() {
        let frames = paired(vec![
            Ok(colour(0, ms(1000))),
            // Recorded after the frame but stamped 7 ms after it: taken.
            Ok(BagMessage::Depth(ms(1007), depth_of(1.0))),
            Ok(BagMessage::Depth(ms(1995), depth_of(2.5))),
            Ok(BagMessage::Depth(ms(2003), depth_of(2.0))),
            Ok(colour(1, ms(2000))),
            // Frame 2 has no depth within 20 ms (the nearest is 30 ms away).
            Ok(colour(2, ms(3000))),
            Ok(BagMessage::Depth(ms(3030), depth_of(3.0))),
            // Depth recorded before its frame.
            Ok(BagMessage::Depth(ms(3990), depth_of(4.0))),
            Ok(colour(3, ms(4000))),
        ]);
        assert_eq!(depths(&frames), vec![Some(1.0), Some(2.0), None, Some(4.0)]);
        let indexes: Vec<usize> = frames.iter().map(|f| f.as_ref().unwrap().index).collect();
        assert_eq!(indexes, vec![0, 1, 2, 3]);
    }

    #[test]
    fn a_read_error_comes_after_every_frame_read_before_it() {
        let frames = paired(vec![
            Ok(colour(0, ms(0))),
            Ok(colour(1, ms(100))),
            Ok(BagMessage::Depth(ms(101), depth_of(1.0))),
            Err(anyhow::anyhow!("damaged chunk")),
        ]);
        assert_eq!(frames.len(), 3);
        assert_eq!(depths(&frames[..2]), vec![None, Some(1.0)]);
        assert!(frames[2].as_ref().unwrap_err().to_string().contains("damaged chunk"));
    }

    #[test]
    fn an_unreadable_frame_keeps_its_place_and_the_frames_after_it_come_out() {
        let unreadable = |index, stamp| crate::io::UnreadableFrame::error(index, stamp, &anyhow::anyhow!("cut short"));
        let frames = paired(vec![
            Ok(colour(0, ms(0))),
            Err(unreadable(1, ms(100))),
            Ok(colour(2, ms(200))),
            Ok(BagMessage::Depth(ms(201), depth_of(2.0))),
            Ok(BagMessage::Depth(ms(102), depth_of(1.0))),
        ]);
        let order: Vec<String> = frames
            .iter()
            .map(|f| match f {
                Ok(frame) => format!("frame {} depth {:?}", frame.index, frame.depth.as_ref().map(|d| d.metres[0])),
                Err(err) => format!("unreadable {}", crate::io::unreadable_frame(err).unwrap().index),
            })
            .collect();
        assert_eq!(order, ["frame 0 depth None", "unreadable 1", "frame 2 depth Some(2.0)"]);
        // A depth message that does not decode is passed over; the frames go on.
        let frames = paired(vec![
            Ok(colour(0, ms(0))),
            Ok(BagMessage::UnreadableDepth(anyhow::anyhow!("cut short"))),
            Ok(BagMessage::Depth(ms(101), depth_of(1.0))),
            Ok(colour(1, ms(100))),
        ]);
        assert_eq!(depths(&frames), vec![None, Some(1.0)]);
    }

    #[test]
    fn frames_are_not_held_for_depth_that_never_comes() {
        // Colour only (no depth topic, or a silent one): every frame comes out once MAX_HOLD of
        // newer colour has passed, without waiting for the end.
        let frames = || (0..100).map(|i| Ok(colour(i, ms(i as i64 * 100)))).collect::<Vec<_>>().into_iter();
        // Without a depth topic nothing is held at all.
        let mut plain = DepthPaired::new(Scripted(frames()), false);
        assert_eq!(plain.next().unwrap().unwrap().index, 0);
        assert!(plain.pending.is_empty());
        let mut source = DepthPaired::new(Scripted(frames()), true);
        let first = source.next().unwrap().unwrap();
        assert_eq!(first.index, 0);
        assert!(source.pending.len() <= (MAX_HOLD.nanos / ms(100).nanos) as usize + 1, "{}", source.pending.len());
        assert_eq!(source.count(), 99);
        // Colour stamps that never advance (all 0): held by count instead, each frame still out.
        let stuck = (0..1000).map(|i| Ok(colour(i, Stamp::default()))).collect::<Vec<_>>();
        let mut source = DepthPaired::new(Scripted(stuck.into_iter()), true);
        assert_eq!(source.next().unwrap().unwrap().index, 0);
        assert!(source.pending.len() <= MAX_HELD_FRAMES, "{}", source.pending.len());
        assert_eq!(source.count(), 999);
    }

    #[test]
    fn depth_encodings_decode_to_metres() {
        let image = |encoding: &str, big: u8, step: u32, data: Vec<u8>| Image {
            width: 2,
            height: 2,
            encoding: encoding.into(),
            is_bigendian: big,
            step,
            data,
            ..Default::default()
        };
        // 16UC1 millimetres, little-endian, two bytes of row padding.
        let mut data = Vec::new();
        for row in [[1500u16, 0], [65535, 250]] {
            row.iter().for_each(|v| data.extend_from_slice(&v.to_le_bytes()));
            data.extend_from_slice(&[0xAB, 0xAB]);
        }
        let got = depth_from_image(&image("16UC1", 0, 6, data)).unwrap();
        assert_eq!(got.metres, vec![1.5, 0.0, 65.535, 0.25]);
        // 32FC1 metres, big-endian, with NaN and a negative value as unknown.
        let mut data = Vec::new();
        [2.25f32, f32::NAN, -1.0, 0.5].iter().for_each(|v| data.extend_from_slice(&v.to_be_bytes()));
        let got = depth_from_image(&image("32FC1", 1, 8, data)).unwrap();
        assert_eq!(got.metres, vec![2.25, 0.0, 0.0, 0.5]);
        let err = depth_from_image(&image("rgb8", 0, 6, vec![0; 12])).unwrap_err().to_string();
        assert!(err.contains("unsupported depth encoding \"rgb8\""), "{err}");
        let err = depth_from_image(&image("32FC1", 0, 8, vec![0; 15])).unwrap_err().to_string();
        assert!(err.contains("data has 15 bytes"), "{err}");
    }
}
