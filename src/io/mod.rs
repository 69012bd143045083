//! Sources of frames to replay: TUM folders, image folders, ROS 1 bags, ROS 2 bags (sqlite3
//! and MCAP), the ROS image messages inside them, and writers for the bag formats.
//!
//! [`open_source`] picks the reader from the path (see its doc). Every source yields frames in
//! replay order with [`Frame::index`] counting from 0, and turns a bad input into an `Err` item
//! naming the file and where it went wrong. A frame whose image alone cannot be decoded (a cut
//! image file, a message whose pixels do not fit its size) is an [`UnreadableFrame`] error with its
//! index, and the source goes on with the next frame, as a camera driver drops a bad frame; after
//! any other `Err` (a damaged bag, a missing file) a source yields nothing more.

pub mod candidates;
pub mod depth;
pub mod image_msg;
pub mod msgs;
pub mod output;
pub mod ros1bag;
pub mod ros2bag;
pub mod tum;

use anyhow::{bail, Context, Result};
use std::path::Path;

use crate::types::{Frame, Stamp};
use image_msg::ImageKind;

/// A frame whose container was read but whose image cannot be decoded: the source goes on after
/// it (module doc). Callers find it with [`unreadable_frame`].
#[derive(Debug, thiserror::Error)]
#[error("frame {index} (stamp {stamp}) cannot be read: {reason}")]
pub struct UnreadableFrame {
    /// The frame's index in the source: the frames after it keep theirs.
    pub index: usize,
    /// The frame's stamp where its message header could be read, else the time the bag recorded it
    /// or the stamp its file name or `rgb.txt` gives.
    pub stamp: Stamp,
    /// Why, with where it lies in the source.
    pub reason: String,
}

impl UnreadableFrame {
    /// The error for frame `index` (`stamp`) that `error` keeps from being read.
    pub fn error(index: usize, stamp: Stamp, error: &anyhow::Error) -> anyhow::Error {
        UnreadableFrame { index, stamp, reason: format!("{error:#}") }.into()
    }
}

/// The [`UnreadableFrame`] that `error` is (under any context added since), if it is one: a frame
/// to skip, where any other error ends the source.
pub fn unreadable_frame(error: &anyhow::Error) -> Option<&UnreadableFrame> {
    error.downcast_ref::<UnreadableFrame>()
}

/// The frames a run skipped because their images could not be decoded ([`UnreadableFrame`]): each is
/// counted, and named in the log as [`crate::types::Recurring`] says (the first and every hundredth).
#[derive(Debug, Default)]
pub struct UnreadableFrames {
    /// Their indexes in the source, in the order met.
    pub indexes: Vec<usize>,
    /// The first one's reason.
    first_reason: Option<String>,
    logged: crate::types::Recurring,
}

impl UnreadableFrames {
    pub fn count(&self) -> usize {
        self.indexes.len()
    }

    pub fn skip(&mut self, source: &Path, frame: &UnreadableFrame) {
        self.indexes.push(frame.index);
        if let Some(n) = self.logged.occurred() {
            log::warn!(
                "{}: skipping frame {} (stamp {}): {} ({n} unreadable so far)",
                source.display(),
                frame.index,
                frame.stamp,
                frame.reason
            );
        }
        self.first_reason.get_or_insert_with(|| frame.reason.clone());
    }

    /// The summary's words for them, e.g. "2 unreadable frames skipped (the first, frame 7: ...)",
    /// where `frames` names one and several of them; `None` where there were none.
    pub fn summary(&self, (one, several): (&str, &str)) -> Option<String> {
        let (index, reason) = (self.indexes.first()?, self.first_reason.as_deref().unwrap_or_default());
        let (count, noun) = (self.count(), if self.count() == 1 { one } else { several });
        Some(format!("{count} unreadable {noun} skipped (the first, frame {index}: {reason})"))
    }

    /// The error for a source none of whose `frames` frames could be read.
    pub fn none_readable(&self, source: &Path, frames: usize) -> anyhow::Error {
        let reason = self.first_reason.as_deref().unwrap_or_default();
        match frames {
            1 => anyhow::anyhow!("the one frame of {} cannot be read: {reason}", source.display()),
            _ => {
                anyhow::anyhow!("none of the {frames} frames of {} can be read; the first: {reason}", source.display())
            }
        }
    }
}

/// [`UnreadableFrames::summary`]'s words for a replayed source's frames.
pub const FRAMES: (&str, &str) = ("frame", "frames");

/// `frames` less the [`UnreadableFrame`]s, each passed over as [`UnreadableFrames::skip`] says, for
/// tools that want images rather than every index; any other error still ends them.
pub fn skip_unreadable<'a>(
    frames: impl Iterator<Item = Result<Frame>> + 'a,
    source: &'a Path,
) -> impl Iterator<Item = Result<Frame>> + 'a {
    let mut skipped = UnreadableFrames::default();
    frames.filter_map(move |frame| {
        let error = match frame {
            Ok(frame) => return Some(Ok(frame)),
            Err(error) => error,
        };
        if let Some(unreadable) = unreadable_frame(&error) {
            skipped.skip(source, unreadable);
            return None;
        }
        Some(Err(error))
    })
}

/// `error` with `context` added, unless it is an [`UnreadableFrame`]: its reason says where it lies,
/// and a source's "damage" context would misstate a frame that is only skipped.
pub(crate) fn context_unless_unreadable<C>(error: anyhow::Error, context: impl FnOnce() -> C) -> anyhow::Error
where
    C: std::fmt::Display + Send + Sync + 'static,
{
    if unreadable_frame(&error).is_some() {
        error
    } else {
        error.context(context())
    }
}

/// A replayable stream of frames.
pub trait FrameSource: Iterator<Item = Result<Frame>> + Send {
    /// e.g. "ROS 1 bag foo.bag, topic /camera/rgb/image_color (798 messages)"
    fn describe(&self) -> String;
    /// Number of frames if known up front (for progress bars).
    fn len_hint(&self) -> Option<usize>;
    /// The camera intrinsics the source carries ([`SourceIntrinsics`]), if any.
    fn intrinsics(&self) -> Option<SourceIntrinsics> {
        None
    }
}

/// Camera intrinsics that come with a source: a bag's `sensor_msgs/CameraInfo` beside the image topic
/// ([`camera_info_topic`]), or the TUM camera a TUM folder's name gives
/// ([`tum::intrinsics_from_folder_name`]).
#[derive(Clone, Debug, PartialEq)]
pub struct SourceIntrinsics {
    pub intrinsics: crate::verification::Intrinsics,
    /// Where they were found, for the log: e.g. "topic /camera/rgb/camera_info".
    pub origin: String,
}

/// The calibration topic of the image topic `image` among a bag's `topics`, by image_transport's
/// convention: a `sensor_msgs/CameraInfo` topic named `camera_info` in the image topic's namespace
/// (`/camera/rgb/image_color` and its `/camera/rgb/image_color/compressed` both have
/// `/camera/rgb/camera_info`).
pub(crate) fn camera_info_topic<'a>(topics: &'a [TopicInfo], image: &str) -> Option<&'a TopicInfo> {
    let wanted = camera_info_topic_name(image);
    topics.iter().find(|t| {
        t.name == wanted && matches!(t.type_name.as_str(), "sensor_msgs/CameraInfo" | "sensor_msgs/msg/CameraInfo")
    })
}

/// The name of the image topic `image`'s calibration topic ([`camera_info_topic`]'s convention).
pub(crate) fn camera_info_topic_name(image: &str) -> String {
    let base = image.strip_suffix("/compressed").unwrap_or(image);
    let namespace = base.rsplit_once('/').map_or("", |(namespace, _)| namespace);
    format!("{namespace}/camera_info")
}

/// The intrinsics of `decoded`, the first message of `topic` in the bag described by `bag`. A message
/// that does not decode, or an uncalibrated camera's (all-zero `K`), is said in the log and left out:
/// the images replay without it.
pub(crate) fn intrinsics_from_camera_info(
    bag: &str,
    topic: &str,
    decoded: Result<msgs::CameraInfo>,
) -> Option<SourceIntrinsics> {
    let origin = format!("topic {topic}");
    match decoded {
        Ok(info) => {
            let intrinsics = info.intrinsics();
            if intrinsics.is_none() {
                log::warn!("{bag}: {topic} holds no usable calibration (K = {:?}); not used", info.k);
            }
            intrinsics.map(|intrinsics| SourceIntrinsics { intrinsics, origin })
        }
        Err(err) => {
            log::warn!("{bag}: the first message of {topic} cannot be read, so it is not used: {err:#}");
            None
        }
    }
}

/// What to read from a source beside its images: the colour image topic of a bag (default: the
/// bag's one image topic), optionally a depth image topic whose messages are paired with the colour
/// frames ([`depth`]), and optionally the tracker's poses of the frames from a file. Folders have no
/// topics (a TUM folder's depth comes from its `depth.txt`).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Topics {
    pub image: Option<String>,
    pub depth: Option<String>,
    /// A TUM trajectory (`timestamp tx ty tz qx qy qz qw`, camera-to-world) of the tracker: each
    /// frame takes the pose at the nearest stamp within [`TRACKER_POSE_MAX_OFFSET`].
    pub poses: Option<std::path::PathBuf>,
}

/// How far a tracker pose's stamp may lie from its frame's (as a depth image's).
pub const TRACKER_POSE_MAX_OFFSET: Stamp = Stamp::from_nanos(20_000_000);

impl Topics {
    /// Only a colour topic (or the default one).
    pub fn image(topic: Option<&str>) -> Topics {
        Topics { image: topic.map(str::to_string), ..Topics::default() }
    }
}

/// Opens any supported source; `topic` picks the image topic of a bag (default: the one image
/// topic, else an error listing the candidates with their types and counts).
///
/// Detection: a directory with `rgb.txt` is a TUM folder; a directory with `metadata.yaml` is a
/// ROS 2 bag (its `.db3` or `.mcap` file is read); `*.bag` is a ROS 1 bag, `*.db3` a ROS 2
/// sqlite3 bag, `*.mcap` an MCAP file; any other directory with png/jpg/jpeg/bmp files is an
/// image folder replayed in name order (numbers by value).
pub fn open_source(path: &Path, topic: Option<&str>) -> Result<Box<dyn FrameSource>> {
    open_source_topics(path, &Topics::image(topic))
}

/// Whether `path` is a plain folder of images: a folder that is neither a TUM folder (`rgb.txt`)
/// nor a ROS 2 bag folder (`metadata.yaml`).
pub fn is_image_folder(path: &Path) -> bool {
    path.is_dir() && !path.join("rgb.txt").is_file() && !path.join("metadata.yaml").is_file()
}

/// [`open_source`] with a depth topic too, for bags.
pub fn open_source_topics(path: &Path, topics: &Topics) -> Result<Box<dyn FrameSource>> {
    let named = topics.image.as_deref().or(topics.depth.as_deref());
    if path.is_dir() {
        if path.join("rgb.txt").is_file() {
            if let Some(topic) = named {
                bail!(
                    "{} is a TUM folder, which has no topics (asked for {topic}; its depth comes from depth.txt)",
                    path.display()
                );
            }
            return Ok(Box::new(tum::ImageFilesSource::open_tum(path)?));
        }
        if path.join("metadata.yaml").is_file() {
            let storage = ros2bag::storage_file_of_bag_dir(path)?;
            return open_source_topics(&storage, topics);
        }
        if let Some(topic) = named {
            bail!("{} is an image folder, which has no topics (asked for {topic})", path.display());
        }
        return Ok(Box::new(tum::ImageFilesSource::open_image_folder(path)?));
    }
    if !path.exists() {
        bail!("{} does not exist", path.display());
    }
    let mut extension = path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase());
    // `rosbag record` names the bag it is still writing (or was killed writing) `NAME.bag.active`:
    // a ROS 1 bag without its index, which the reader walks.
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_ascii_lowercase();
    if name.ends_with(".bag.active") {
        extension = Some("bag".into());
    }
    Ok(match extension.as_deref() {
        Some("bag") => {
            Box::new(depth::DepthPaired::new(ros1bag::Ros1BagSource::open(path, topics)?, topics.depth.is_some()))
        }
        Some("db3") => {
            Box::new(depth::DepthPaired::new(ros2bag::SqliteBagSource::open(path, topics)?, topics.depth.is_some()))
        }
        Some("mcap") => {
            Box::new(depth::DepthPaired::new(ros2bag::McapSource::open(path, topics)?, topics.depth.is_some()))
        }
        _ => bail!(
            "{}: unsupported source (expected a TUM folder, image folder, ROS 2 bag folder, .bag, .db3 or .mcap)",
            path.display()
        ),
    })
}

/// A topic of a bag, for choosing the image topic and for error messages.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TopicInfo {
    pub name: String,
    pub type_name: String,
    pub count: usize,
}

impl TopicInfo {
    fn listing(topics: &[&TopicInfo]) -> String {
        if topics.is_empty() {
            return "none".to_string();
        }
        topics
            .iter()
            .map(|t| format!("{} ({}, {} messages)", t.name, t.type_name, t.count))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// Picks the image topic to replay from `topics` of the bag described by `bag`.
pub(crate) fn choose_image_topic(
    bag: &str,
    topics: &[TopicInfo],
    wanted: Option<&str>,
) -> Result<(TopicInfo, ImageKind)> {
    let image_topics: Vec<&TopicInfo> =
        topics.iter().filter(|t| ImageKind::from_type_name(&t.type_name).is_some()).collect();
    let chosen = match wanted {
        Some(name) => {
            // A topic of several types (ROS 1 allows it) is taken by its image type.
            let named = || topics.iter().filter(|t| t.name == name);
            let found = named().find(|t| ImageKind::from_type_name(&t.type_name).is_some()).or_else(|| named().next());
            let found = found.with_context(|| {
                format!("{bag} has no topic {name}; image topics: {}", TopicInfo::listing(&image_topics))
            })?;
            if ImageKind::from_type_name(&found.type_name).is_none() {
                bail!(
                    "topic {name} in {bag} has type {}, not sensor_msgs Image or CompressedImage; image topics: {}",
                    found.type_name,
                    TopicInfo::listing(&image_topics)
                );
            }
            found
        }
        None => match image_topics.as_slice() {
            [only] => *only,
            [] => bail!(
                "{bag} has no sensor_msgs Image or CompressedImage topic; topics: {}",
                TopicInfo::listing(&topics.iter().collect::<Vec<_>>())
            ),
            several => bail!(
                "{bag} has {} image topics, pick one with --topic: {}",
                several.len(),
                TopicInfo::listing(several)
            ),
        },
    };
    let kind = ImageKind::from_type_name(&chosen.type_name).context("checked above")?;
    Ok((chosen.clone(), kind))
}

/// The colour topic (and its message kind) and, where asked for, the depth topic of the bag described
/// by `bag` ([`Topics`]).
pub(crate) fn choose_topics(
    bag: &str,
    topics: &[TopicInfo],
    wanted: &Topics,
) -> Result<(TopicInfo, ImageKind, Option<TopicInfo>)> {
    let (chosen, kind) = choose_image_topic(bag, topics, wanted.image.as_deref())?;
    let depth = wanted.depth.as_deref().map(|d| choose_depth_topic(bag, topics, d, &chosen.name)).transpose()?;
    Ok((chosen, kind, depth))
}

/// Picks the depth topic `wanted` of the bag described by `bag`: a raw `sensor_msgs/Image` topic other
/// than the colour topic `colour`.
pub(crate) fn choose_depth_topic(bag: &str, topics: &[TopicInfo], wanted: &str, colour: &str) -> Result<TopicInfo> {
    let raw = |t: &&TopicInfo| ImageKind::from_type_name(&t.type_name) == Some(ImageKind::Raw);
    let raw_topics: Vec<&TopicInfo> = topics.iter().filter(raw).collect();
    let named = || topics.iter().filter(|t| t.name == wanted);
    let found = named().find(raw).or_else(|| named().next()).with_context(|| {
        format!("{bag} has no depth topic {wanted}; raw image topics: {}", TopicInfo::listing(&raw_topics))
    })?;
    if !raw(&found) {
        bail!(
            "depth topic {wanted} in {bag} has type {}, not sensor_msgs Image; raw image topics: {}",
            found.type_name,
            TopicInfo::listing(&raw_topics)
        );
    }
    if found.name == colour {
        bail!("{wanted} in {bag} is the colour topic; the depth topic must be another one");
    }
    Ok(found.clone())
}

/// Checks that `read`, a source's items, are the `expected` frames in order with the one at
/// `unreadable` an [`UnreadableFrame`] of its index and `recorded` stamp whose reason holds `reason`,
/// and every other frame read with its own index, stamp and image.
#[cfg(test)]
pub(crate) fn assert_skips_unreadable(
    read: Vec<Result<Frame>>,
    expected: &[(Stamp, image::RgbImage)],
    unreadable: usize,
    recorded: Stamp,
    reason: &str,
) {
    assert_eq!(read.len(), expected.len(), "every frame has an item");
    for (i, (item, (stamp, image))) in read.into_iter().zip(expected).enumerate() {
        match item {
            Ok(frame) => {
                assert_ne!(i, unreadable, "frame {i} should be unreadable");
                assert_eq!((frame.index, frame.stamp, &frame.image), (i, *stamp, image));
            }
            Err(err) => {
                let skipped = unreadable_frame(&err).unwrap_or_else(|| panic!("frame {i} ended the source: {err:#}"));
                assert_eq!((i, skipped.index, skipped.stamp), (unreadable, unreadable, recorded));
                assert!(skipped.reason.contains(reason), "{reason:?} not in {}", skipped.reason);
            }
        }
    }
}

/// Small distinct test frames one second apart from `first`.
#[cfg(test)]
pub(crate) fn test_frames(
    n: usize,
    width: u32,
    height: u32,
    first: crate::types::Stamp,
) -> Vec<(crate::types::Stamp, image::RgbImage)> {
    (0..n)
        .map(|i| {
            let img = image::RgbImage::from_fn(width, height, |x, y| {
                image::Rgb([(x * 30) as u8, (y * 40) as u8, (i * 20) as u8])
            });
            (crate::types::Stamp::from_nanos(first.nanos + i as i64 * 1_000_000_000), img)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn topic(name: &str, type_name: &str, count: usize) -> TopicInfo {
        TopicInfo { name: name.into(), type_name: type_name.into(), count }
    }

    #[test]
    fn the_calibration_topic_sits_beside_the_image_topic() {
        let topics = vec![
            topic("/camera/rgb/camera_info", "sensor_msgs/CameraInfo", 3),
            topic("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", 3),
            topic("/camera_info", "sensor_msgs/msg/CameraInfo", 3),
            topic("/other/camera_info", "std_msgs/String", 3),
        ];
        let found = |image: &str| camera_info_topic(&topics, image).map(|t| t.name.as_str());
        assert_eq!(found("/camera/rgb/image_color"), Some("/camera/rgb/camera_info"));
        assert_eq!(found("/camera/rgb/image_color/compressed"), Some("/camera/rgb/camera_info"));
        assert_eq!(found("/camera/depth/image"), Some("/camera/depth/camera_info"));
        assert_eq!(found("/image_raw"), Some("/camera_info"));
        assert_eq!(found("/other/image"), None, "not a CameraInfo");
        assert_eq!(found("/left/image_raw"), None, "none in its namespace");
    }

    #[test]
    fn topic_choice_lists_candidates() {
        let topics = vec![
            topic("/rgb", "sensor_msgs/Image", 3),
            topic("/tf", "tf2_msgs/TFMessage", 9),
            topic("/rgb/compressed", "sensor_msgs/CompressedImage", 3),
        ];
        let err = choose_image_topic("bag x", &topics, None).unwrap_err().to_string();
        assert!(err.contains("2 image topics") && err.contains("/rgb (sensor_msgs/Image, 3 messages)"), "{err}");
        assert!(err.contains("/rgb/compressed (sensor_msgs/CompressedImage, 3 messages)"), "{err}");
        let err = choose_image_topic("bag x", &topics, Some("/depth")).unwrap_err().to_string();
        assert!(err.contains("bag x has no topic /depth; image topics: /rgb (sensor_msgs/Image"), "{err}");
        let err = choose_image_topic("bag x", &topics, Some("/tf")).unwrap_err().to_string();
        assert!(err.contains("type tf2_msgs/TFMessage"), "{err}");
        let (chosen, kind) = choose_image_topic("bag x", &topics, Some("/rgb/compressed")).unwrap();
        assert_eq!((chosen.name.as_str(), kind), ("/rgb/compressed", ImageKind::Compressed));
        let (chosen, kind) = choose_image_topic("bag x", &topics[..2], None).unwrap();
        assert_eq!((chosen.name.as_str(), kind), ("/rgb", ImageKind::Raw));
        let err = choose_image_topic("bag x", &topics[1..2], None).unwrap_err().to_string();
        assert!(err.contains("no sensor_msgs Image") && err.contains("/tf (tf2_msgs/TFMessage, 9 messages)"), "{err}");
        // A ROS 1 topic of two types is taken by its image type, named or not.
        let mixed = vec![topic("/cam", "std_msgs/String", 1), topic("/cam", "sensor_msgs/Image", 4)];
        for wanted in [None, Some("/cam")] {
            let (chosen, kind) = choose_image_topic("bag x", &mixed, wanted).unwrap();
            assert_eq!((chosen.type_name.as_str(), chosen.count, kind), ("sensor_msgs/Image", 4, ImageKind::Raw));
        }
    }
}

/// Whole-file reads with a size limit: a file (or `/dev/zero`) larger than `limit` bytes is an
/// error naming it and the limit, after reading at most `limit + 1` bytes.
pub fn read_capped(path: &std::path::Path, limit: u64, what: &str) -> anyhow::Result<Vec<u8>> {
    use anyhow::Context;
    use std::io::Read;
    let file = std::fs::File::open(path).with_context(|| format!("cannot read {what} {}", path.display()))?;
    let mut bytes = Vec::new();
    file.take(limit + 1).read_to_end(&mut bytes).with_context(|| format!("cannot read {what} {}", path.display()))?;
    anyhow::ensure!(
        bytes.len() as u64 <= limit,
        "{what} {} is larger than {} MiB, the most this program reads as one",
        path.display(),
        limit >> 20
    );
    Ok(bytes)
}

/// As [`read_capped`], as UTF-8 text; invalid UTF-8 names the line it is on.
pub fn read_capped_text(path: &std::path::Path, limit: u64, what: &str) -> anyhow::Result<String> {
    let bytes = read_capped(path, limit, what)?;
    let mut text = String::from_utf8(bytes).map_err(|e| {
        let valid = e.utf8_error().valid_up_to();
        let line = e.as_bytes()[..valid].iter().filter(|&&b| b == b'\n').count() + 1;
        anyhow::anyhow!("{what} {}: line {line} is not valid UTF-8", path.display())
    })?;
    // The byte-order mark that Windows editors and spreadsheets put first is not text.
    if text.starts_with('\u{feff}') {
        text.drain(..'\u{feff}'.len_utf8());
    }
    Ok(text)
}

/// Size limits of whole-file reads.
pub mod limits {
    /// Parameter files (`--config`).
    pub const PARAMS_FILE: u64 = 1 << 20;
    /// Weights (safetensors, TFLite): MobileNetV2 in f32 with a classifier is about 14 MB.
    pub const WEIGHTS_FILE: u64 = 128 << 20;
    /// Text lists: `rgb.txt`, ground truth, loops, labels, training lists.
    pub const TEXT_LIST: u64 = 64 << 20;
}

/// At most `max` characters of `text` for an error message, marked when cut.
pub fn excerpt(text: &str, max: usize) -> String {
    match text.char_indices().nth(max) {
        Some((cut, _)) => format!("{:?}... ({} bytes)", &text[..cut], text.len()),
        None => format!("{text:?}"),
    }
}

#[cfg(test)]
mod capped_tests {
    #[test]
    fn reads_are_capped_and_errors_quote_an_excerpt() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("list.txt");
        std::fs::write(&path, b"a\nb\xffc\n").unwrap();
        let err = super::read_capped_text(&path, 100, "list").unwrap_err().to_string();
        assert!(err.contains("line 2") && err.contains("UTF-8"), "{err}");
        // A byte-order mark (Windows editors, spreadsheets) is not part of the text.
        std::fs::write(&path, "\u{feff}9,0\r\n").unwrap();
        assert_eq!(super::read_capped_text(&path, 100, "list").unwrap(), "9,0\r\n");
        std::fs::write(&path, vec![b'x'; 3 << 20]).unwrap();
        let err = super::read_capped(&path, 2 << 20, "weights file").unwrap_err().to_string();
        assert!(err.contains("list.txt") && err.contains("2 MiB"), "{err}");
        #[cfg(unix)]
        assert!(super::read_capped(std::path::Path::new("/dev/zero"), 1 << 20, "params file").is_err());
        assert_eq!(super::excerpt("short", 10), "\"short\"");
        let long = "y".repeat(1000);
        let cut = super::excerpt(&long, 20);
        assert!(cut.len() < 50 && cut.contains("1000 bytes"), "{cut}");
    }
}
