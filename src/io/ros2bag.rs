//! ROS 2 bags: rosbag2's sqlite3 storage (`.db3`, read with rusqlite) and MCAP (`.mcap`, read
//! with the `mcap` crate), both carrying CDR-serialised image messages; plus writers for both,
//! each with the `metadata.yaml` that makes the folder a rosbag2 bag.
//!
//! Replay order: sqlite3 messages by `timestamp` (receive time), ties by row id, as `ros2 bag
//! play` does; MCAP messages in file order, which is log-time order for files written by
//! rosbag2 and by our writer (MCAP has no cheap random access for a streaming reader, so an
//! out-of-order MCAP file replays in file order). The frame stamp is the header stamp.

use anyhow::{anyhow, bail, ensure, Context, Result};
use image::RgbImage;
use rusqlite::{Connection, OpenFlags, OptionalExtension};
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use super::depth::{depth_message, describe_topics, unreadable_depth, BagMessage, MessageSource};
use super::image_msg::{
    camera_info_from_cdr, written_messages, written_topics, ImageKind, ImageMessage, WireEncoding, WrittenKind,
    REGION_OF_INTEREST_DEFINITION,
};
use super::{
    camera_info_topic, choose_topics, context_unless_unreadable, intrinsics_from_camera_info, unreadable_frame,
    SourceIntrinsics, TopicInfo, Topics, UnreadableFrame,
};
use crate::types::{Frame, Stamp};
use crate::verification::Intrinsics;

/// A CDR message of the colour topic (as frame `index`, recorded at `recorded`) or of the depth topic.
/// A colour message that does not decode is an [`UnreadableFrame`] (`at` says where it lies): the
/// messages after it are read.
fn cdr_message(
    kind: ImageKind,
    is_depth: bool,
    index: usize,
    recorded: Stamp,
    payload: &[u8],
    at: impl Fn() -> String,
) -> Result<BagMessage> {
    if is_depth {
        let depth = ImageMessage::from_cdr(ImageKind::Raw, payload).and_then(|m| depth_message(&m));
        return depth.with_context(|| format!("{} (depth topic)", at())).or_else(unreadable_depth);
    }
    // from_cdr names the message type and size.
    let decoded = ImageMessage::from_cdr(kind, payload);
    // Its header's stamp where the header reads, else the time the bag recorded it.
    let stamp = decoded.as_ref().map_or(recorded, |message| message.stamp());
    let image = decoded.and_then(|message| message.to_rgb());
    let image = image.map_err(|err| UnreadableFrame::error(index, stamp, &err.context(at())))?;
    Ok(BagMessage::Colour(Frame { index, stamp, image, depth: None }))
}

/// Finds the storage file of a rosbag2 folder (one with `metadata.yaml`). A bag whose messages are
/// compressed one by one (`compression_mode: MESSAGE`) is refused: its payloads are zstd frames, not
/// CDR.
pub fn storage_file_of_bag_dir(dir: &Path) -> Result<PathBuf> {
    let metadata = crate::io::read_capped_text(&dir.join("metadata.yaml"), 1 << 20, "rosbag2 metadata")?;
    let field = |key: &str| {
        metadata.lines().find_map(|line| {
            let value = line.trim().strip_prefix(key)?.strip_prefix(':')?.trim().trim_matches(['"', '\'']);
            Some(value.to_string())
        })
    };
    if field("compression_mode").is_some_and(|mode| mode.eq_ignore_ascii_case("message")) {
        bail!(
            "{}: the messages of this rosbag2 are compressed one by one ({} compression_mode MESSAGE), which is not \
             supported; decompress with `ros2 bag convert`",
            dir.display(),
            field("compression_format").unwrap_or_default()
        );
    }
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))? {
        let path = entry.with_context(|| format!("cannot list {}", dir.display()))?.path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_string();
        if name.ends_with(".db3") || name.ends_with(".mcap") {
            files.push(path);
        } else if name.ends_with(".zstd") {
            bail!(
                "{}: compressed rosbag2 files ({name}) are not supported; decompress with `ros2 bag convert`",
                dir.display()
            );
        }
    }
    alphanumeric_sort::sort_path_slice(&mut files);
    match files.as_slice() {
        [one] => Ok(one.clone()),
        [] => bail!("ROS 2 bag folder {} has metadata.yaml but no .db3 or .mcap file", dir.display()),
        many => bail!(
            "ROS 2 bag folder {} is split into {} files; replay one of them directly: {}",
            dir.display(),
            many.len(),
            many.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ")
        ),
    }
}

/// Replays one image topic of a rosbag2 sqlite3 file, and optionally a depth topic beside it.
pub struct SqliteBagSource {
    path: PathBuf,
    db: Connection,
    description: String,
    kind: ImageKind,
    /// Row ids of the replayed messages in record order, each marked whether it is a depth message.
    message_ids: Vec<(i64, bool)>,
    colour_count: usize,
    intrinsics: Option<SourceIntrinsics>,
    next: usize,
    /// Colour frames read so far (the next frame's index).
    colour_read: usize,
    done: bool,
}

impl SqliteBagSource {
    pub fn open(path: &Path, wanted: &Topics) -> Result<SqliteBagSource> {
        let name = format!("ROS 2 sqlite3 bag {}", path.display());
        ensure!(path.is_file(), "{name} does not exist");
        let db = Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)
            .with_context(|| format!("cannot open {name}"))?;
        let topics =
            Self::topics(&db).with_context(|| format!("{name}: cannot read the topics and messages tables"))?;
        let infos: Vec<TopicInfo> = topics.values().map(|(info, _)| info.clone()).collect();
        let (chosen, kind, depth) = choose_topics(&name, &infos, wanted)?;
        let topic_id = |wanted: &TopicInfo| -> Result<i64> {
            let (id, format) = topics
                .iter()
                .find(|(_, (info, _))| info.name == wanted.name)
                .map(|(id, (_, format))| (*id, format.clone()))
                .context("chosen topic is listed")?;
            ensure!(
                format == "cdr",
                "{name}: topic {} is serialised as {format:?}, only cdr is supported",
                wanted.name
            );
            Ok(id)
        };
        let colour_id = topic_id(&chosen)?;
        // -1 matches no topic: no depth topic.
        let depth_id = depth.as_ref().map(&topic_id).transpose()?.unwrap_or(-1);
        let message_ids = (|| -> rusqlite::Result<Vec<(i64, bool)>> {
            let mut statement = db.prepare(
                "SELECT id, topic_id FROM messages WHERE topic_id = ?1 OR topic_id = ?2 ORDER BY timestamp, id",
            )?;
            let ids = statement
                .query_map([colour_id, depth_id], |row| Ok((row.get(0)?, row.get::<_, i64>(1)? == depth_id)))?
                .collect();
            ids
        })()
        .with_context(|| format!("{name}: cannot list the messages of {}", chosen.name))?;
        let colour_count = message_ids.iter().filter(|(_, is_depth)| !is_depth).count();
        let description = describe_topics(&name, &chosen.name, colour_count, depth.as_ref());
        let intrinsics = camera_info_topic(&infos, &chosen.name).and_then(|info_topic| {
            let decoded = topic_id(info_topic).and_then(|id| {
                let first: Vec<u8> = db
                    .query_row(
                        "SELECT data FROM messages WHERE topic_id = ?1 ORDER BY timestamp, id LIMIT 1",
                        [id],
                        |row| row.get(0),
                    )
                    .with_context(|| format!("{name}: cannot read {}", info_topic.name))?;
                camera_info_from_cdr(&first)
            });
            intrinsics_from_camera_info(&name, &info_topic.name, decoded)
        });
        Ok(SqliteBagSource {
            path: path.to_path_buf(),
            db,
            description,
            kind,
            message_ids,
            colour_count,
            intrinsics,
            next: 0,
            colour_read: 0,
            done: false,
        })
    }

    /// Topic id -> (info, serialization format).
    fn topics(db: &Connection) -> rusqlite::Result<HashMap<i64, (TopicInfo, String)>> {
        let mut counts: HashMap<i64, usize> = HashMap::new();
        let mut statement = db.prepare("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id")?;
        for row in statement.query_map([], |row| Ok((row.get::<_, i64>(0)?, row.get::<_, i64>(1)?)))? {
            let (id, count) = row?;
            counts.insert(id, count as usize);
        }
        let mut statement = db.prepare("SELECT id, name, type, serialization_format FROM topics ORDER BY name")?;
        let rows = statement.query_map([], |row| {
            let id: i64 = row.get(0)?;
            Ok((id, (TopicInfo { name: row.get(1)?, type_name: row.get(2)?, count: 0 }, row.get::<_, String>(3)?)))
        })?;
        let mut topics = HashMap::new();
        for row in rows {
            let (id, (mut info, format)) = row?;
            info.count = counts.get(&id).copied().unwrap_or(0);
            topics.insert(id, (info, format));
        }
        Ok(topics)
    }

    fn read_message(&self, position: usize, colour_index: usize) -> Result<BagMessage> {
        let (id, is_depth) = self.message_ids[position];
        let (recorded, payload): (i64, Vec<u8>) = self
            .db
            .query_row("SELECT timestamp, data FROM messages WHERE id = ?1", [id], |row| Ok((row.get(0)?, row.get(1)?)))
            .optional()?
            .with_context(|| format!("row id {id} vanished"))?;
        let at = || format!("ROS 2 sqlite3 bag {}: row id {id}", self.path.display());
        cdr_message(self.kind, is_depth, colour_index, Stamp::from_nanos(recorded), &payload, at)
            .map_err(|err| context_unless_unreadable(err, || format!("row id {id}")))
    }
}

impl Iterator for SqliteBagSource {
    type Item = Result<BagMessage>;

    fn next(&mut self) -> Option<Result<BagMessage>> {
        if self.done || self.next >= self.message_ids.len() {
            return None;
        }
        let (position, index) = (self.next, self.colour_read);
        self.next += 1;
        let message = self.read_message(position, index).map_err(|err| {
            context_unless_unreadable(err, || {
                format!(
                    "ROS 2 sqlite3 bag {}: message {index}; read {index} messages before the damage",
                    self.path.display()
                )
            })
        });
        match &message {
            Ok(BagMessage::Colour(_)) => self.colour_read += 1,
            Ok(BagMessage::Depth(..) | BagMessage::UnreadableDepth(_)) => {}
            Err(err) if unreadable_frame(err).is_some() => self.colour_read += 1,
            Err(_) => self.done = true,
        }
        Some(message)
    }
}

impl MessageSource for SqliteBagSource {
    fn describe(&self) -> String {
        self.description.clone()
    }

    fn len_hint(&self) -> Option<usize> {
        Some(self.colour_count)
    }

    fn intrinsics(&self) -> Option<SourceIntrinsics> {
        self.intrinsics.clone()
    }
}

/// Replays one image topic of an MCAP file, and optionally a depth topic beside it.
pub struct McapSource {
    path: PathBuf,
    reader: mcap::io::MessageReader<BufReader<File>>,
    description: String,
    topic: String,
    depth_topic: Option<String>,
    kind: ImageKind,
    count: usize,
    intrinsics: Option<SourceIntrinsics>,
    next: usize,
    done: bool,
}

/// Longest MCAP record we accept: a record in the file cannot be longer than the file, and
/// one inside a compressed chunk is an image message, far below 256 MiB. Without a limit a
/// corrupt length makes the reader try to allocate it and abort the process.
const MIN_MCAP_RECORD_LIMIT: u64 = 256 << 20;

fn open_mcap_reader(path: &Path) -> Result<mcap::io::MessageReader<BufReader<File>>> {
    let file = File::open(path).with_context(|| format!("cannot open MCAP file {}", path.display()))?;
    let file_len = file.metadata().with_context(|| format!("cannot stat MCAP file {}", path.display()))?.len();
    let limit = usize::try_from(file_len.max(MIN_MCAP_RECORD_LIMIT)).unwrap_or(usize::MAX);
    let options = mcap::sans_io::LinearReaderOptions::default().with_record_length_limit(limit);
    Ok(mcap::io::MessageReader::new_with_options(BufReader::with_capacity(1 << 20, file), options))
}

impl McapSource {
    /// Opens `path`; a first pass over the file counts the messages per topic.
    pub fn open(path: &Path, wanted: &Topics) -> Result<McapSource> {
        let name = format!("MCAP file {}", path.display());
        let mut topics: BTreeMap<String, TopicInfo> = BTreeMap::new();
        let mut encodings: HashMap<String, String> = HashMap::new();
        // The first message of each topic that may be a calibration topic.
        let mut first_camera_infos: HashMap<String, Vec<u8>> = HashMap::new();
        let mut damage = None;
        let mut total = 0usize;
        for message in open_mcap_reader(path)? {
            match message {
                Ok(message) => {
                    let channel = &message.channel;
                    let type_name = channel.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default();
                    topics
                        .entry(channel.topic.clone())
                        .or_insert_with(|| TopicInfo { name: channel.topic.clone(), type_name, count: 0 })
                        .count += 1;
                    encodings.insert(channel.topic.clone(), channel.message_encoding.clone());
                    if channel.topic.ends_with("camera_info") && !first_camera_infos.contains_key(&channel.topic) {
                        first_camera_infos.insert(channel.topic.clone(), message.data.into_owned());
                    }
                    total += 1;
                }
                Err(err) => {
                    damage = Some(anyhow!(err).context(format!("{name}: damaged after {total} messages")));
                    break;
                }
            }
        }
        let infos: Vec<TopicInfo> = topics.into_values().collect();
        let with_damage = |err: anyhow::Error| match &damage {
            Some(d) => err.context(format!("{d:#}")),
            None => err,
        };
        let (chosen, kind, depth) = choose_topics(&name, &infos, wanted).map_err(with_damage)?;
        for topic in std::iter::once(&chosen).chain(&depth) {
            let encoding = encodings.get(&topic.name).cloned().unwrap_or_default();
            ensure!(
                encoding == "cdr",
                "{name}: topic {} has message encoding {encoding:?}, only cdr is supported",
                topic.name
            );
        }
        let description = describe_topics(&name, &chosen.name, chosen.count, depth.as_ref());
        let intrinsics = camera_info_topic(&infos, &chosen.name).and_then(|info_topic| {
            let first = first_camera_infos.get(&info_topic.name).context("its first message was kept");
            intrinsics_from_camera_info(&name, &info_topic.name, first.and_then(|data| camera_info_from_cdr(data)))
        });
        Ok(McapSource {
            path: path.to_path_buf(),
            reader: open_mcap_reader(path)?,
            description,
            topic: chosen.name,
            depth_topic: depth.map(|d| d.name),
            kind,
            count: chosen.count,
            intrinsics,
            next: 0,
            done: false,
        })
    }
}

impl Iterator for McapSource {
    type Item = Result<BagMessage>;

    fn next(&mut self) -> Option<Result<BagMessage>> {
        if self.done {
            return None;
        }
        let index = self.next;
        let result = loop {
            match self.reader.next() {
                None => {
                    self.done = true;
                    return None;
                }
                Some(Ok(message)) => {
                    let is_depth = self.depth_topic.as_ref() == Some(&message.channel.topic);
                    if is_depth || message.channel.topic == self.topic {
                        let at = || {
                            format!(
                                "MCAP file {}: message {index} (log time {} ns)",
                                self.path.display(),
                                message.log_time
                            )
                        };
                        let recorded = Stamp::from_nanos(i64::try_from(message.log_time).unwrap_or(i64::MAX));
                        break cdr_message(self.kind, is_depth, index, recorded, &message.data, at).map_err(|err| {
                            context_unless_unreadable(err, || {
                                format!("message {index} (log time {} ns)", message.log_time)
                            })
                        });
                    }
                }
                Some(Err(err)) => break Err(anyhow!(err)),
            }
        };
        let unreadable = result.as_ref().err().and_then(unreadable_frame).is_some();
        if unreadable {
            self.next += 1;
            return Some(result);
        }
        if let Ok(BagMessage::Colour(_)) = result {
            self.next += 1;
        }
        self.done = result.is_err();
        Some(result.with_context(|| {
            format!("MCAP file {}: read {index} messages of {} before the damage", self.path.display(), self.topic)
        }))
    }
}

impl MessageSource for McapSource {
    fn describe(&self) -> String {
        self.description.clone()
    }

    fn len_hint(&self) -> Option<usize> {
        Some(self.count)
    }

    fn intrinsics(&self) -> Option<SourceIntrinsics> {
        self.intrinsics.clone()
    }
}

// ---------------------------------------------------------------------------------------------
// Writers

/// rosbag2 storage formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ros2Storage {
    Sqlite3,
    Mcap,
}

const IMAGE_MSG_DEFINITION: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n";
const COMPRESSED_IMAGE_MSG_DEFINITION: &str = "std_msgs/Header header\nstring format\nuint8[] data\n";
const HEADER_MSG_DEFINITION: &str = "builtin_interfaces/Time stamp\nstring frame_id\n";
const TIME_MSG_DEFINITION: &str = "int32 sec\nuint32 nanosec\n";
const CAMERA_INFO_MSG_DEFINITION: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nRegionOfInterest roi\n";

/// The `ros2msg` schema text rosbag2 stores in MCAP files.
fn ros2msg_definition(kind: WrittenKind) -> String {
    let line = "=".repeat(80);
    let (body, more) = match kind {
        WrittenKind::Image(ImageKind::Raw) => (IMAGE_MSG_DEFINITION, String::new()),
        WrittenKind::Image(ImageKind::Compressed) => (COMPRESSED_IMAGE_MSG_DEFINITION, String::new()),
        WrittenKind::CameraInfo => (
            CAMERA_INFO_MSG_DEFINITION,
            format!("\n{line}\nMSG: sensor_msgs/RegionOfInterest\n{REGION_OF_INTEREST_DEFINITION}"),
        ),
    };
    format!("{body}\n{line}\nMSG: std_msgs/Header\n{HEADER_MSG_DEFINITION}\n{line}\nMSG: builtin_interfaces/Time\n{TIME_MSG_DEFINITION}{more}")
}

/// Writes a rosbag2 folder `dir` (created; must not exist, as with `ros2 bag record -o`) with
/// one topic carrying `frames` in `encoding`; receive time = stamp. Returns the frame count.
pub fn write_ros2_bag(
    dir: &Path,
    storage: Ros2Storage,
    topic: &str,
    frames: impl IntoIterator<Item = (Stamp, RgbImage)>,
    encoding: WireEncoding,
) -> Result<usize> {
    write_ros2_bag_calibrated(dir, storage, topic, frames, encoding, None)
}

/// [`write_ros2_bag`], with a `sensor_msgs/msg/CameraInfo` of `camera` beside each frame on the
/// image topic's `camera_info` ([`written_topics`]) where it is given.
pub fn write_ros2_bag_calibrated(
    dir: &Path,
    storage: Ros2Storage,
    topic: &str,
    frames: impl IntoIterator<Item = (Stamp, RgbImage)>,
    encoding: WireEncoding,
    camera: Option<&Intrinsics>,
) -> Result<usize> {
    // Written in a folder beside it and renamed into place when complete: a writer killed half-way
    // leaves no bag under the final name.
    ensure!(!dir.exists(), "cannot write ROS 2 bag {}: it already exists", dir.display());
    let writing = crate::io::output::unused_name_beside(dir, "writing")?;
    let write = || -> Result<usize> {
        std::fs::create_dir_all(dir.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")))?;
        std::fs::create_dir(&writing)?;
        let base = dir.file_name().and_then(|n| n.to_str()).context("bag folder has no UTF-8 name")?;
        let topics = written_topics(topic, encoding, camera);
        let messages = written_messages(frames, encoding, camera)
            .map(|message| message.and_then(|(topic, stamp, message)| Ok((topic, stamp, message.to_cdr()?))));
        let (file_name, stamps) = match storage {
            Ros2Storage::Sqlite3 => {
                let file_name = format!("{base}_0.db3");
                (file_name.clone(), write_sqlite(&writing.join(&file_name), &topics, messages)?)
            }
            Ros2Storage::Mcap => {
                let file_name = format!("{base}_0.mcap");
                (file_name.clone(), write_mcap(&writing.join(&file_name), &topics, messages)?)
            }
        };
        let storage_name = if storage == Ros2Storage::Sqlite3 { "sqlite3" } else { "mcap" };
        std::fs::write(writing.join("metadata.yaml"), metadata_yaml(storage_name, &file_name, &topics, &stamps))?;
        std::fs::rename(&writing, dir).with_context(|| format!("renaming {} into place", writing.display()))?;
        Ok(stamps.iter().filter(|(topic, _)| *topic == 0).count())
    };
    let written = write();
    if written.is_err() {
        let _ = std::fs::remove_dir_all(&writing);
    }
    written.with_context(|| format!("cannot write ROS 2 bag {}", dir.display()))
}

/// Each message's topic index and stamp, in the order written.
type Written = Vec<(usize, Stamp)>;

fn write_sqlite(
    path: &Path,
    topics: &[(String, WrittenKind)],
    messages: impl Iterator<Item = Result<(usize, Stamp, Vec<u8>)>>,
) -> Result<Written> {
    let mut db = Connection::open(path)?;
    db.execute_batch(
        "CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, \
           serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL);
         CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, \
           timestamp INTEGER NOT NULL, data BLOB NOT NULL);
         CREATE INDEX timestamp_idx ON messages (timestamp ASC);",
    )?;
    let tx = db.transaction()?;
    for (id, (name, kind)) in topics.iter().enumerate() {
        tx.execute(
            "INSERT INTO topics(id, name, type, serialization_format, offered_qos_profiles) VALUES (?1, ?2, ?3, 'cdr', '')",
            rusqlite::params![id as i64 + 1, name, kind.ros2_type()],
        )?;
    }
    let mut written = Vec::new();
    {
        let mut insert = tx.prepare("INSERT INTO messages(topic_id, timestamp, data) VALUES (?1, ?2, ?3)")?;
        for message in messages {
            let (topic, stamp, payload) = message?;
            insert.execute(rusqlite::params![topic as i64 + 1, stamp.nanos, payload])?;
            written.push((topic, stamp));
        }
    }
    tx.commit()?;
    Ok(written)
}

fn write_mcap(
    path: &Path,
    topics: &[(String, WrittenKind)],
    messages: impl Iterator<Item = Result<(usize, Stamp, Vec<u8>)>>,
) -> Result<Written> {
    let file = std::io::BufWriter::new(File::create(path)?);
    let mut writer = mcap::WriteOptions::new().profile("ros2").create(file)?;
    let mut channels = Vec::new();
    for (name, kind) in topics {
        let schema = writer.add_schema(kind.ros2_type(), "ros2msg", ros2msg_definition(*kind).as_bytes())?;
        channels.push(writer.add_channel(schema, name, "cdr", &BTreeMap::new())?);
    }
    let mut written = Vec::new();
    let mut sequences = vec![0u32; topics.len()];
    for message in messages {
        let (topic, stamp, payload) = message?;
        let time = u64::try_from(stamp.nanos).with_context(|| format!("negative stamp {stamp}"))?;
        let header = mcap::records::MessageHeader {
            channel_id: channels[topic],
            sequence: sequences[topic],
            log_time: time,
            publish_time: time,
        };
        sequences[topic] += 1;
        writer.write_to_known_channel(&header, &payload)?;
        written.push((topic, stamp));
    }
    writer.finish()?;
    Ok(written)
}

/// rosbag2 `metadata.yaml` (version 5, which rosbag2 since Humble and `rosbags` read).
fn metadata_yaml(storage: &str, file_name: &str, topics: &[(String, WrittenKind)], written: &Written) -> String {
    let start = written.iter().map(|(_, s)| s.nanos).min().unwrap_or(0);
    let duration = written.iter().map(|(_, s)| s.nanos).max().unwrap_or(0) - start;
    let count = written.len();
    let mut topic_entries = String::new();
    for (index, (name, kind)) in topics.iter().enumerate() {
        let messages = written.iter().filter(|(topic, _)| *topic == index).count();
        topic_entries.push_str(&format!(
            "    - topic_metadata:
        name: {name}
        type: {ty}
        serialization_format: cdr
        offered_qos_profiles: \"\"
      message_count: {messages}
",
            ty = kind.ros2_type()
        ));
    }
    format!(
        "rosbag2_bagfile_information:
  version: 5
  storage_identifier: {storage}
  duration:
    nanoseconds: {duration}
  starting_time:
    nanoseconds_since_epoch: {start}
  message_count: {count}
  topics_with_message_count:
{topic_entries}  compression_format: \"\"
  compression_mode: \"\"
  relative_file_paths:
    - {file_name}
  files:
    - path: {file_name}
      starting_time:
        nanoseconds_since_epoch: {start}
      duration:
        nanoseconds: {duration}
      message_count: {count}
"
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::image_msg::encode_image;

    fn frames(n: usize) -> Vec<(Stamp, RgbImage)> {
        crate::io::test_frames(n, 7, 5, Stamp::from_sec_nsec(1_700_000_000, 123_456_789))
    }

    #[test]
    fn written_bags_read_back_in_both_storages() {
        let dir = tempfile::tempdir().unwrap();
        for storage in [Ros2Storage::Sqlite3, Ros2Storage::Mcap] {
            let bag = dir.path().join(format!("{storage:?}"));
            assert_eq!(write_ros2_bag(&bag, storage, "/cam", frames(4), WireEncoding::Rgba8).unwrap(), 4);
            let file = storage_file_of_bag_dir(&bag).unwrap();
            let source: Box<dyn crate::io::FrameSource> = match storage {
                Ros2Storage::Sqlite3 => crate::io::open_source(&file, None).unwrap(),
                Ros2Storage::Mcap => crate::io::open_source(&file, Some("/cam")).unwrap(),
            };
            assert_eq!(source.len_hint(), Some(4));
            assert!(source.describe().ends_with("topic /cam (4 messages)"), "{}", source.describe());
            let read: Vec<Frame> = source.map(|f| f.unwrap()).collect();
            assert_eq!(read.len(), 4);
            for (i, (frame, (stamp, image))) in read.iter().zip(frames(4)).enumerate() {
                assert_eq!((frame.index, frame.stamp), (i, stamp));
                assert_eq!(frame.image, image);
            }
            // Its messages compressed one by one, as `ros2 bag record --compression-mode message`
            // writes them: refused by name rather than read as damaged CDR.
            let metadata = std::fs::read_to_string(bag.join("metadata.yaml")).unwrap();
            let compressed = metadata
                .replace("compression_format: \"\"", "compression_format: zstd")
                .replace("compression_mode: \"\"", "compression_mode: MESSAGE");
            std::fs::write(bag.join("metadata.yaml"), compressed).unwrap();
            let err = format!("{:#}", storage_file_of_bag_dir(&bag).unwrap_err());
            assert!(err.contains("compressed one by one (zstd compression_mode MESSAGE)"), "{err}");
        }
    }

    /// A `camera_info` beside the images, in both storages: every frame reads back, with the
    /// intrinsics.
    #[test]
    fn a_calibrated_bag_carries_its_camera() {
        let dir = tempfile::tempdir().unwrap();
        let camera = Intrinsics { fx: 10.0, fy: 11.0, cx: 3.0, cy: 2.0, size: Some([7, 5]) };
        for storage in [Ros2Storage::Sqlite3, Ros2Storage::Mcap] {
            let bag = dir.path().join(format!("{storage:?}"));
            let written = write_ros2_bag_calibrated(
                &bag,
                storage,
                "/cam/image_raw",
                frames(4),
                WireEncoding::Rgb8,
                Some(&camera),
            );
            assert_eq!(written.unwrap(), 4);
            let metadata = std::fs::read_to_string(bag.join("metadata.yaml")).unwrap();
            assert!(metadata.contains("message_count: 8") && metadata.contains("name: /cam/camera_info"), "{metadata}");
            let source = crate::io::open_source(&bag, Some("/cam/image_raw")).unwrap();
            assert_eq!(source.intrinsics().map(|found| found.intrinsics), Some(camera), "{storage:?}");
            let read: Vec<Frame> = source.map(|f| f.unwrap()).collect();
            assert_eq!(read.iter().map(|f| (f.stamp, f.image.clone())).collect::<Vec<_>>(), frames(4));
        }
    }

    /// A message whose image does not decode is skipped in both storages: the messages after it are
    /// read with their own indexes.
    #[test]
    fn a_message_that_does_not_decode_is_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let written = frames(5);
        for storage in [Ros2Storage::Sqlite3, Ros2Storage::Mcap] {
            let messages = written.iter().enumerate().map(|(i, (stamp, image))| {
                let payload = encode_image(*stamp, "camera", image, WireEncoding::Rgb8)?.to_cdr()?;
                // The third message's pixels cut short.
                Ok((0, *stamp, if i == 2 { payload[..payload.len() - 10].to_vec() } else { payload }))
            });
            let topics = [("/cam".to_string(), WrittenKind::Image(ImageKind::Raw))];
            let file = dir.path().join(format!("bag.{}", if storage == Ros2Storage::Mcap { "mcap" } else { "db3" }));
            match storage {
                Ros2Storage::Sqlite3 => write_sqlite(&file, &topics, messages).unwrap(),
                Ros2Storage::Mcap => write_mcap(&file, &topics, messages).unwrap(),
            };
            let read: Vec<Result<Frame>> = crate::io::open_source(&file, None).unwrap().collect();
            let at = if storage == Ros2Storage::Mcap { "message 2 (log time" } else { "row id 3" };
            crate::io::assert_skips_unreadable(read, &written, 2, written[2].0, at);
        }
    }

    #[test]
    fn corrupted_mcap_bytes_never_panic() {
        let dir = tempfile::tempdir().unwrap();
        let bag = dir.path().join("m");
        write_ros2_bag(&bag, Ros2Storage::Mcap, "/cam", frames(2), WireEncoding::Bgr8).unwrap();
        let good = std::fs::read(storage_file_of_bag_dir(&bag).unwrap()).unwrap();
        let path = dir.path().join("fuzz.mcap");
        let mut state = 0x9E37_79B9u32;
        for round in 0..200 {
            let mut bytes = good.clone();
            for _ in 0..1 + round % 8 {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let at = (state as usize >> 4) % bytes.len();
                bytes[at] = (state >> 24) as u8;
            }
            std::fs::write(&path, &bytes).unwrap();
            if let Ok(source) = crate::io::open_source(&path, None) {
                for _ in source {}
            }
        }
    }

    #[test]
    fn damaged_ros2_files_are_errors_with_the_file_name() {
        let dir = tempfile::tempdir().unwrap();
        let bag = dir.path().join("m");
        write_ros2_bag(&bag, Ros2Storage::Mcap, "/cam", frames(3), WireEncoding::Png).unwrap();
        let file = storage_file_of_bag_dir(&bag).unwrap();
        let bytes = std::fs::read(&file).unwrap();
        let cut = dir.path().join("cut.mcap");
        // Cut inside the summary: every message is still there, then the reader reports the cut.
        for len in [bytes.len() - 30, bytes.len() / 2, 20, 3] {
            std::fs::write(&cut, &bytes[..len]).unwrap();
            match crate::io::open_source(&cut, None) {
                Ok(source) => {
                    let results: Vec<Result<Frame>> = source.collect();
                    let err = format!("{:#}", results.last().unwrap().as_ref().unwrap_err());
                    assert!(err.contains("cut.mcap") && err.contains("before the damage"), "{err}");
                }
                Err(err) => assert!(format!("{err:#}").contains("cut.mcap"), "{err:#}"),
            }
        }

        let bag = dir.path().join("s");
        write_ros2_bag(&bag, Ros2Storage::Sqlite3, "/cam", frames(2), WireEncoding::Mono8).unwrap();
        let file = storage_file_of_bag_dir(&bag).unwrap();
        let db = Connection::open(&file).unwrap();
        db.execute("UPDATE messages SET data = x'00010000ffff' WHERE id = 2", []).unwrap();
        drop(db);
        let results: Vec<Result<Frame>> = crate::io::open_source(&file, None).unwrap().collect();
        assert_eq!(results.len(), 2);
        // A garbage payload in an intact database is one unreadable frame, not damage.
        let err = format!("{:#}", results[1].as_ref().unwrap_err());
        assert!(err.contains("frame 1 (stamp") && err.contains("s_0.db3: row id 2"), "{err}");
        std::fs::write(&cut, b"not a database at all, just text that goes on for a while..............").unwrap();
        let err = format!("{:#}", crate::io::open_source(&cut, None).err().unwrap());
        assert!(err.contains("cut.mcap"), "{err}");
    }
}
