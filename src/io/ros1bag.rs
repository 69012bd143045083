//! ROS 1 bags (format 2.0): a reader that replays one image topic in time order, as
//! `rosbag play` does, and a writer for fixtures and synthetic sequences.
//!
//! The record layer is hand-written instead of using the `rosbag` crate because that crate
//! panics on a truncated bag (it slices its memory map with the header's `index_pos`, which lies
//! past the end of a cut file) and its errors carry no file offsets; here damage is reported with
//! its byte offset and the messages before it still replay. Chunks may be uncompressed, `bz2` or
//! `lz4` (LZ4 frame format, as roslz4 writes it).
//!
//! Reading: the chunk section is scanned once for chunk records and the index-data records that
//! follow each chunk; the index section supplies the connections. A chunk with no index data, or
//! a bag with no readable index section (an unfinished recording), is walked record by record
//! instead. Messages are then sorted by receive time (stable, so ties keep file order) and
//! decoded one chunk at a time. The frame stamp is the message header stamp.

use anyhow::{anyhow, bail, ensure, Context, Result};
use image::RgbImage;
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::depth::{depth_message, describe_topics, unreadable_depth, BagMessage, MessageSource};
use super::image_msg::{
    camera_info_from_ros1, written_messages, written_topics, ImageKind, ImageMessage, WireEncoding, WrittenKind,
};
use super::{
    camera_info_topic, choose_topics, intrinsics_from_camera_info, unreadable_frame, SourceIntrinsics, TopicInfo,
    Topics, UnreadableFrame,
};
use crate::types::{Frame, Stamp};
use crate::verification::Intrinsics;

const MAGIC: &[u8] = b"#ROSBAG V2.0\n";
const OP_MESSAGE: u8 = 0x02;
const OP_BAG_HEADER: u8 = 0x03;
const OP_INDEX_DATA: u8 = 0x04;
const OP_CHUNK: u8 = 0x05;
const OP_CHUNK_INFO: u8 = 0x06;
const OP_CONNECTION: u8 = 0x07;
/// Longest record header we accept; real ones are well under 1 KiB (connection headers live in
/// the record data), so anything bigger is garbage.
const MAX_HEADER_LEN: u32 = 1 << 20;

/// Chunk compression of a ROS 1 bag.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ros1Compression {
    None,
    Bz2,
    Lz4,
}

impl Ros1Compression {
    fn name(self) -> &'static str {
        match self {
            Ros1Compression::None => "none",
            Ros1Compression::Bz2 => "bz2",
            Ros1Compression::Lz4 => "lz4",
        }
    }

    fn from_name(name: &[u8]) -> Option<Self> {
        match name {
            b"none" => Some(Ros1Compression::None),
            b"bz2" => Some(Ros1Compression::Bz2),
            b"lz4" => Some(Ros1Compression::Lz4),
            _ => None,
        }
    }
}

/// The `name=value` fields of a record header.
struct Fields<'a>(Vec<(&'a str, &'a [u8])>);

impl<'a> Fields<'a> {
    fn parse(mut bytes: &'a [u8]) -> Result<Fields<'a>> {
        let mut fields = Vec::new();
        while !bytes.is_empty() {
            ensure!(bytes.len() >= 4, "header field length cut short");
            let len = u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as usize;
            ensure!(len <= bytes.len() - 4, "header field of {len} bytes overruns the header");
            let field = &bytes[4..4 + len];
            let eq = field.iter().position(|&b| b == b'=').context("header field without '='")?;
            let name = std::str::from_utf8(&field[..eq]).context("header field name is not UTF-8")?;
            fields.push((name, &field[eq + 1..]));
            bytes = &bytes[4 + len..];
        }
        Ok(Fields(fields))
    }

    fn get(&self, name: &str) -> Result<&'a [u8]> {
        self.0
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, v)| *v)
            .with_context(|| format!("record header lacks field {name:?}"))
    }

    fn op(&self) -> Result<u8> {
        match self.get("op")? {
            [op] => Ok(*op),
            other => bail!("op field has {} bytes, expected 1", other.len()),
        }
    }

    fn u32(&self, name: &str) -> Result<u32> {
        let v = self.get(name)?;
        let bytes: [u8; 4] = v.try_into().map_err(|_| anyhow!("field {name:?} has {} bytes, expected 4", v.len()))?;
        Ok(u32::from_le_bytes(bytes))
    }

    fn u64(&self, name: &str) -> Result<u64> {
        let v = self.get(name)?;
        let bytes: [u8; 8] = v.try_into().map_err(|_| anyhow!("field {name:?} has {} bytes, expected 8", v.len()))?;
        Ok(u64::from_le_bytes(bytes))
    }

    fn time(&self, name: &str) -> Result<Stamp> {
        time_from_bytes(self.get(name)?).with_context(|| format!("field {name:?} is not an 8-byte time"))
    }

    fn string(&self, name: &str) -> Result<String> {
        String::from_utf8(self.get(name)?.to_vec()).with_context(|| format!("field {name:?} is not UTF-8"))
    }
}

fn time_from_bytes(bytes: &[u8]) -> Option<Stamp> {
    let bytes: [u8; 8] = bytes.try_into().ok()?;
    let sec = u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
    let nsec = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
    Some(Stamp::from_sec_nsec(sec as i64, nsec))
}

/// One record read from memory: its header bytes and data bytes.
struct RawRecord<'a> {
    header: &'a [u8],
    data: &'a [u8],
    /// Bytes the record occupies.
    len: usize,
}

/// Splits the record at the start of `bytes`.
fn record_in(bytes: &[u8]) -> Result<RawRecord<'_>> {
    let read_len = |at: usize| -> Result<usize> {
        let b = bytes.get(at..at + 4).context("record cut short")?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    let header_len = read_len(0)?;
    let header = bytes.get(4..4 + header_len).context("record header cut short")?;
    let data_len = read_len(4 + header_len)?;
    let data_start = 8 + header_len;
    let data = bytes.get(data_start..data_start + data_len).context("record data cut short")?;
    Ok(RawRecord { header, data, len: data_start + data_len })
}

#[derive(Clone, Debug)]
struct Connection {
    topic: String,
    type_name: String,
}

/// A chunk record's place in the file.
#[derive(Clone, Debug)]
struct ChunkRef {
    /// Byte offset of the chunk record (for error messages).
    record_pos: u64,
    data_pos: u64,
    data_len: u32,
    compression: Ros1Compression,
    size: u32,
    /// `(connection, receive time, offset in the uncompressed chunk)` from index-data records.
    index: Vec<(u32, Stamp, u32)>,
}

/// Where one message lives.
#[derive(Clone, Copy, Debug)]
struct MessageRef {
    time: Stamp,
    chunk: usize,
    offset: u32,
}

/// Reads the record at `pos` in `file` (header in full, data length only).
struct FileRecord {
    header: Vec<u8>,
    data_pos: u64,
    data_len: u32,
}

fn read_record_head(file: &mut File, pos: u64, end: u64) -> Result<FileRecord> {
    ensure!(pos + 4 <= end, "record header length cut short by the end of the file");
    file.seek(SeekFrom::Start(pos))?;
    let mut len = [0u8; 4];
    file.read_exact(&mut len)?;
    let header_len = u32::from_le_bytes(len);
    ensure!(header_len <= MAX_HEADER_LEN, "implausible record header length {header_len}");
    ensure!(pos + 8 + header_len as u64 <= end, "record header of {header_len} bytes cut short by the end of the file");
    let mut header = vec![0u8; header_len as usize];
    file.read_exact(&mut header)?;
    file.read_exact(&mut len)?;
    let data_len = u32::from_le_bytes(len);
    let data_pos = pos + 8 + header_len as u64;
    ensure!(
        data_pos + data_len as u64 <= end,
        "record data of {data_len} bytes cut short by the end of the file ({} bytes left)",
        end.saturating_sub(data_pos)
    );
    Ok(FileRecord { header, data_pos, data_len })
}

fn read_bytes(file: &mut File, pos: u64, len: u32) -> Result<Vec<u8>> {
    file.seek(SeekFrom::Start(pos))?;
    let mut data = vec![0u8; len as usize];
    file.read_exact(&mut data)?;
    Ok(data)
}

fn parse_connection(header: &Fields<'_>, data: &[u8]) -> Result<(u32, Connection)> {
    let id = header.u32("conn")?;
    let fields = Fields::parse(data).context("connection header")?;
    let topic = fields.string("topic").or_else(|_| header.string("topic"))?;
    Ok((id, Connection { topic, type_name: fields.string("type")? }))
}

/// Everything learnt from scanning a bag.
struct BagScan {
    connections: HashMap<u32, Connection>,
    chunks: Vec<ChunkRef>,
    /// Where the scan stopped on damage, as an error message without the file name.
    damage: Option<String>,
}

fn scan(file: &mut File, file_len: u64) -> Result<BagScan> {
    let mut magic = [0u8; MAGIC.len()];
    file.read_exact(&mut magic).context("too short for a ROS 1 bag")?;
    ensure!(magic == MAGIC, "not a ROS 1 bag v2.0 (no #ROSBAG V2.0 line)");
    let head = read_record_head(file, MAGIC.len() as u64, file_len).context("bag header record at byte offset 13")?;
    let fields = Fields::parse(&head.header).context("bag header record at byte offset 13")?;
    ensure!(fields.op()? == OP_BAG_HEADER, "first record is not a bag header");
    let index_pos = fields.u64("index_pos")?;
    let chunk_start = head.data_pos + head.data_len as u64;

    let mut scan = BagScan { connections: HashMap::new(), chunks: Vec::new(), damage: None };
    // The index section exists only if the recording finished; otherwise scan to the end.
    let index_ok = index_pos >= chunk_start && index_pos <= file_len;
    let chunk_end = if index_ok && index_pos > chunk_start { index_pos } else { file_len };
    if index_ok && index_pos > chunk_start {
        let mut pos = index_pos;
        while pos < file_len {
            let step = (|| -> Result<u64> {
                let rec = read_record_head(file, pos, file_len)?;
                let fields = Fields::parse(&rec.header)?;
                if fields.op()? == OP_CONNECTION {
                    let data = read_bytes(file, rec.data_pos, rec.data_len)?;
                    let (id, conn) = parse_connection(&fields, &data)?;
                    scan.connections.insert(id, conn);
                }
                Ok(rec.data_pos + rec.data_len as u64)
            })();
            match step {
                Ok(next) => pos = next,
                Err(err) => {
                    log::warn!("index section damaged at byte offset {pos} ({err:#}); walking the chunks instead");
                    break;
                }
            }
        }
    }

    let mut pos = chunk_start;
    while pos < chunk_end {
        let step = (|| -> Result<u64> {
            let rec = read_record_head(file, pos, chunk_end)?;
            let fields = Fields::parse(&rec.header)?;
            match fields.op()? {
                OP_CHUNK => {
                    let compression_name = fields.get("compression")?;
                    let compression = Ros1Compression::from_name(compression_name).with_context(|| {
                        format!("unsupported chunk compression {:?}", String::from_utf8_lossy(compression_name))
                    })?;
                    scan.chunks.push(ChunkRef {
                        record_pos: pos,
                        data_pos: rec.data_pos,
                        data_len: rec.data_len,
                        compression,
                        size: fields.u32("size")?,
                        index: Vec::new(),
                    });
                }
                OP_INDEX_DATA => {
                    let conn = fields.u32("conn")?;
                    let count = fields.u32("count")?;
                    ensure!(fields.u32("ver")? == 1, "index data version {} (expected 1)", fields.u32("ver")?);
                    ensure!(
                        rec.data_len as u64 == count as u64 * 12,
                        "index data of {} bytes for {count} entries",
                        rec.data_len
                    );
                    let data = read_bytes(file, rec.data_pos, rec.data_len)?;
                    let chunk = scan.chunks.last_mut().context("index data before any chunk")?;
                    for entry in data.chunks_exact(12) {
                        let time = time_from_bytes(&entry[..8]).context("index entry time")?;
                        let offset = u32::from_le_bytes([entry[8], entry[9], entry[10], entry[11]]);
                        chunk.index.push((conn, time, offset));
                    }
                }
                OP_CONNECTION => {
                    let data = read_bytes(file, rec.data_pos, rec.data_len)?;
                    let (id, conn) = parse_connection(&fields, &data)?;
                    scan.connections.insert(id, conn);
                }
                // An unfinished recording may have been cut right where the index section
                // would start.
                OP_CHUNK_INFO => {}
                op => bail!("unexpected record op {op:#04x} in the chunk section"),
            }
            Ok(rec.data_pos + rec.data_len as u64)
        })();
        match step {
            Ok(next) => pos = next,
            Err(err) => {
                scan.damage = Some(format!("damaged record at byte offset {pos}: {err:#}"));
                break;
            }
        }
    }
    Ok(scan)
}

/// Decompresses a chunk's data, checking the announced size.
fn decompress(chunk: &ChunkRef, data: Vec<u8>) -> Result<Vec<u8>> {
    let size = chunk.size as usize;
    let out = match chunk.compression {
        Ros1Compression::None => data,
        Ros1Compression::Bz2 => {
            let mut out = Vec::with_capacity(size.min(1 << 28));
            bzip2::read::BzDecoder::new(data.as_slice())
                .take(size as u64 + 1)
                .read_to_end(&mut out)
                .context("bz2 decompression failed")?;
            out
        }
        Ros1Compression::Lz4 => {
            let mut out = Vec::with_capacity(size.min(1 << 28));
            lz4::Decoder::new(data.as_slice())
                .context("lz4 decompression failed")?
                .take(size as u64 + 1)
                .read_to_end(&mut out)
                .context("lz4 decompression failed")?;
            out
        }
    };
    ensure!(out.len() == size, "chunk decompresses to {} bytes, header says {size}", out.len());
    Ok(out)
}

fn load_chunk(file: &mut File, chunk: &ChunkRef) -> Result<Vec<u8>> {
    let data = read_bytes(file, chunk.data_pos, chunk.data_len)?;
    decompress(chunk, data)
}

/// Walks the records of an uncompressed chunk: connections and message positions.
fn walk_chunk(data: &[u8], connections: &mut HashMap<u32, Connection>) -> Result<Vec<(u32, Stamp, u32)>> {
    let mut messages = Vec::new();
    let mut offset = 0usize;
    while offset < data.len() {
        let rec = record_in(&data[offset..]).with_context(|| format!("record at chunk offset {offset}"))?;
        let fields = Fields::parse(rec.header).with_context(|| format!("record at chunk offset {offset}"))?;
        match fields.op()? {
            OP_MESSAGE => messages.push((fields.u32("conn")?, fields.time("time")?, offset as u32)),
            OP_CONNECTION => {
                let (id, conn) = parse_connection(&fields, rec.data)?;
                connections.insert(id, conn);
            }
            op => bail!("unexpected record op {op:#04x} at chunk offset {offset}"),
        }
        offset += rec.len;
    }
    Ok(messages)
}

/// Replays one image topic of a ROS 1 bag, and optionally a depth topic beside it.
pub struct Ros1BagSource {
    path: PathBuf,
    file: File,
    description: String,
    kind: ImageKind,
    chunks: Vec<ChunkRef>,
    /// The replayed messages in record order, each marked whether it is a depth message.
    messages: Vec<(bool, MessageRef)>,
    colour_count: usize,
    intrinsics: Option<SourceIntrinsics>,
    next: usize,
    /// Colour frames read so far (the next frame's index).
    colour_read: usize,
    /// The last decompressed chunk, by index into `chunks`.
    cached: Option<(usize, Vec<u8>)>,
    damage: Option<String>,
    done: bool,
}

impl Ros1BagSource {
    /// Opens `path` and selects the image topic (see [`super::open_source`]).
    pub fn open(path: &Path, wanted: &Topics) -> Result<Ros1BagSource> {
        let name = format!("ROS 1 bag {}", path.display());
        let mut file = File::open(path).with_context(|| format!("cannot open {name}"))?;
        let file_len = file.metadata().with_context(|| format!("cannot stat {name}"))?.len();
        let BagScan { mut connections, mut chunks, mut damage } =
            scan(&mut file, file_len).with_context(|| name.to_string())?;

        // Message positions per chunk, from the index data or by walking the chunk.
        let mut per_conn: Vec<(u32, MessageRef)> = Vec::new();
        for (chunk_no, chunk) in chunks.iter().enumerate() {
            let indexed = !chunk.index.is_empty() && chunk.index.iter().all(|(c, ..)| connections.contains_key(c));
            let entries = if indexed {
                chunk.index.clone()
            } else {
                match load_chunk(&mut file, chunk).and_then(|data| walk_chunk(&data, &mut connections)) {
                    Ok(entries) => entries,
                    Err(err) => {
                        damage = Some(format!("damaged chunk at byte offset {}: {err:#}", chunk.record_pos));
                        chunks.truncate(chunk_no);
                        break;
                    }
                }
            };
            per_conn.extend(
                entries.into_iter().map(|(conn, time, offset)| (conn, MessageRef { time, chunk: chunk_no, offset })),
            );
        }

        // By topic and type: a ROS 1 topic may carry connections of several types (a recording of
        // two publishers that disagreed), and only the image type's messages are frames.
        let mut topics: BTreeMap<(&str, &str), TopicInfo> = BTreeMap::new();
        for conn in connections.values() {
            topics.entry((&conn.topic, &conn.type_name)).or_insert_with(|| TopicInfo {
                name: conn.topic.clone(),
                type_name: conn.type_name.clone(),
                count: 0,
            });
        }
        for (conn, _) in &per_conn {
            if let Some(info) =
                connections.get(conn).and_then(|c| topics.get_mut(&(c.topic.as_str(), c.type_name.as_str())))
            {
                info.count += 1;
            }
        }
        let topics: Vec<TopicInfo> = topics.into_values().collect();
        let with_damage = |err: anyhow::Error| match &damage {
            Some(d) => err.context(format!("{name}: {d}")),
            None => err,
        };
        let (chosen, kind, depth) = choose_topics(&name, &topics, wanted).map_err(with_damage)?;
        let is = |conn: &Connection, topic: &TopicInfo| conn.topic == topic.name && conn.type_name == topic.type_name;
        let intrinsics = camera_info_topic(&topics, &chosen.name).and_then(|info_topic| {
            let first = per_conn
                .iter()
                .filter(|(conn, _)| connections.get(conn).is_some_and(|c| is(c, info_topic)))
                .min_by_key(|(_, m)| m.time)?;
            let chunk = &chunks[first.1.chunk];
            let decoded = load_chunk(&mut file, chunk)
                .and_then(|data| camera_info_from_ros1(message_data(&data, &first.1, chunk)?));
            intrinsics_from_camera_info(&name, &info_topic.name, decoded)
        });
        for other in topics.iter().filter(|t| t.name == chosen.name && t.type_name != chosen.type_name) {
            log::warn!(
                "{name}: topic {} also carries {} messages of type {}, left out (its frames are the {})",
                other.name,
                other.count,
                other.type_name,
                chosen.type_name
            );
        }
        let mut messages: Vec<(bool, MessageRef)> = per_conn
            .into_iter()
            .filter_map(|(conn, m)| {
                let conn = connections.get(&conn)?;
                let is_depth = depth.as_ref().is_some_and(|d| is(conn, d));
                (is_depth || is(conn, &chosen)).then_some((is_depth, m))
            })
            .collect();
        messages.sort_by_key(|(_, m)| m.time);
        let colour_count = messages.iter().filter(|(is_depth, _)| !is_depth).count();
        let description = describe_topics(&name, &chosen.name, colour_count, depth.as_ref());
        Ok(Ros1BagSource {
            path: path.to_path_buf(),
            file,
            description,
            kind,
            chunks,
            messages,
            colour_count,
            intrinsics,
            next: 0,
            colour_read: 0,
            cached: None,
            damage,
            done: false,
        })
    }

    /// The message at `position` of `messages`; a colour frame gets index `colour_index`.
    fn read_message(&mut self, position: usize, colour_index: usize) -> Result<BagMessage> {
        let (is_depth, message) = self.messages[position];
        let chunk = &self.chunks[message.chunk];
        if self.cached.as_ref().map(|(i, _)| *i) != Some(message.chunk) {
            let data = load_chunk(&mut self.file, chunk)
                .with_context(|| format!("damaged chunk at byte offset {}", chunk.record_pos))?;
            self.cached = Some((message.chunk, data));
        }
        let data = &self.cached.as_ref().context("chunk cached above")?.1;
        let at = || record_at(&message, chunk);
        let bytes = message_data(data, &message, chunk)?;
        if is_depth {
            let depth = ImageMessage::from_ros1(ImageKind::Raw, bytes)
                .and_then(|msg| depth_message(&msg))
                .with_context(|| format!("ROS 1 bag {}: {} (depth, sensor_msgs/Image)", self.path.display(), at()));
            return depth.or_else(unreadable_depth);
        }
        // The record was read: only this image is unreadable, and the messages after it are read.
        let decoded = ImageMessage::from_ros1(self.kind, bytes);
        // Its header's stamp where the header reads, else the time the bag recorded it.
        let stamp = decoded.as_ref().map_or(message.time, |msg| msg.stamp());
        let image = decoded
            .and_then(|msg| msg.to_rgb())
            .with_context(|| format!("ROS 1 bag {}: {} ({})", self.path.display(), at(), self.kind.ros1_type()))
            .map_err(|err| UnreadableFrame::error(colour_index, stamp, &err))?;
        Ok(BagMessage::Colour(Frame { index: colour_index, stamp, image, depth: None }))
    }
}

/// Where `message` lies, for error messages.
fn record_at(message: &MessageRef, chunk: &ChunkRef) -> String {
    format!("message record at offset {} of the chunk at byte offset {}", message.offset, chunk.record_pos)
}

/// The serialised message of the message record `message` in `data`, its decompressed `chunk`.
fn message_data<'a>(data: &'a [u8], message: &MessageRef, chunk: &ChunkRef) -> Result<&'a [u8]> {
    let at = || record_at(message, chunk);
    let rest = data.get(message.offset as usize..).with_context(|| format!("{} lies outside the chunk", at()))?;
    let record = record_in(rest).with_context(at)?;
    let fields = Fields::parse(record.header).with_context(at)?;
    ensure!(fields.op().with_context(at)? == OP_MESSAGE, "{} is not a message record", at());
    Ok(record.data)
}

impl Iterator for Ros1BagSource {
    type Item = Result<BagMessage>;

    fn next(&mut self) -> Option<Result<BagMessage>> {
        if self.done {
            return None;
        }
        let (position, index) = (self.next, self.colour_read);
        if position >= self.messages.len() {
            self.done = true;
            let damage = self.damage.take()?;
            return Some(Err(anyhow!(
                "ROS 1 bag {}: {damage}; read {index} messages before the damage",
                self.path.display()
            )));
        }
        self.next += 1;
        let message = self.read_message(position, index);
        match &message {
            Ok(BagMessage::Colour(_)) => self.colour_read += 1,
            Ok(BagMessage::Depth(..) | BagMessage::UnreadableDepth(_)) => {}
            Err(err) if unreadable_frame(err).is_some() => {
                self.colour_read += 1;
                return Some(message);
            }
            Err(_) => self.done = true,
        }
        Some(message.map_err(|err| {
            err.context(format!(
                "ROS 1 bag {}: message {index}; read {index} messages before the damage",
                self.path.display()
            ))
        }))
    }
}

impl MessageSource for Ros1BagSource {
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

// ---------------------------------------------------------------------------------------------
// Writer

const IMAGE_MD5: &str = "060021388200f6f0f447d0fcd9c64743";
const COMPRESSED_IMAGE_MD5: &str = "8f7a12909da2c9d3332d540a0977563f";
const HEADER_DEFINITION: &str = "uint32 seq\ntime stamp\nstring frame_id\n";
const IMAGE_DEFINITION: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n";
const COMPRESSED_IMAGE_DEFINITION: &str = "std_msgs/Header header\nstring format\nuint8[] data\n";
const CAMERA_INFO_MD5: &str = "c9a58c1b0b154e0e6da7578cb991d214";
const CAMERA_INFO_DEFINITION: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] D\nfloat64[9] K\nfloat64[9] R\nfloat64[12] P\nuint32 binning_x\nuint32 binning_y\nRegionOfInterest roi\n";
/// Uncompressed bytes after which a chunk is closed (rosbag's default chunk threshold).
const CHUNK_THRESHOLD: usize = 768 * 1024;

fn message_definition(kind: WrittenKind) -> String {
    let line = "=".repeat(80);
    let body = match kind {
        WrittenKind::Image(ImageKind::Raw) => IMAGE_DEFINITION,
        WrittenKind::Image(ImageKind::Compressed) => COMPRESSED_IMAGE_DEFINITION,
        WrittenKind::CameraInfo => {
            return format!(
                "{CAMERA_INFO_DEFINITION}\n{line}\nMSG: std_msgs/Header\n{HEADER_DEFINITION}\n{line}\nMSG: sensor_msgs/RegionOfInterest\n{}",
                super::image_msg::REGION_OF_INTEREST_DEFINITION
            )
        }
    };
    format!("{body}\n{line}\nMSG: std_msgs/Header\n{HEADER_DEFINITION}")
}

fn put_field(out: &mut Vec<u8>, name: &str, value: &[u8]) {
    out.extend_from_slice(&((name.len() + 1 + value.len()) as u32).to_le_bytes());
    out.extend_from_slice(name.as_bytes());
    out.push(b'=');
    out.extend_from_slice(value);
}

fn time_bytes(stamp: Stamp) -> Result<[u8; 8]> {
    let sec = u32::try_from(stamp.sec()).with_context(|| format!("stamp {stamp} does not fit ROS 1 time"))?;
    let mut out = [0u8; 8];
    out[..4].copy_from_slice(&sec.to_le_bytes());
    out[4..].copy_from_slice(&stamp.nsec().to_le_bytes());
    Ok(out)
}

fn put_record(out: &mut Vec<u8>, header: &[u8], data: &[u8]) {
    out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    out.extend_from_slice(header);
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    out.extend_from_slice(data);
}

fn bag_header_record(index_pos: u64, conn_count: u32, chunk_count: u32) -> Vec<u8> {
    let mut header = Vec::new();
    put_field(&mut header, "op", &[OP_BAG_HEADER]);
    put_field(&mut header, "index_pos", &index_pos.to_le_bytes());
    put_field(&mut header, "conn_count", &conn_count.to_le_bytes());
    put_field(&mut header, "chunk_count", &chunk_count.to_le_bytes());
    // The bag header record is padded with spaces to 4096 bytes so it can be rewritten in place.
    let padding = vec![b' '; 4096 - 8 - header.len()];
    let mut out = Vec::new();
    put_record(&mut out, &header, &padding);
    out
}

/// Writes an uncompressed-or-compressed ROS 1 bag v2.0 with one connection (id 0) on `topic`,
/// carrying `frames` in `encoding`, with index-data records after each chunk and connection
/// and chunk-info records in the index section (what `rosbag` and `rosbags` need). The record
/// time of each message is its stamp. Returns the number of frames written.
pub fn write_ros1_bag(
    path: &Path,
    topic: &str,
    frames: impl IntoIterator<Item = (Stamp, RgbImage)>,
    encoding: WireEncoding,
    compression: Ros1Compression,
) -> Result<usize> {
    write_ros1_bag_calibrated(path, topic, frames, encoding, compression, None)
}

/// [`write_ros1_bag`], with a `sensor_msgs/CameraInfo` of `camera` beside each frame on the image
/// topic's `camera_info` (connection 1, [`written_topics`]) where it is given.
pub fn write_ros1_bag_calibrated(
    path: &Path,
    topic: &str,
    frames: impl IntoIterator<Item = (Stamp, RgbImage)>,
    encoding: WireEncoding,
    compression: Ros1Compression,
    camera: Option<&Intrinsics>,
) -> Result<usize> {
    // Written beside it and renamed into place when complete (its header names the index, written
    // last): a writer killed half-way leaves no bag under the final name.
    let writing = crate::io::output::unused_name_beside(path, "writing")?;
    let write = || -> Result<usize> {
        let mut file = std::io::BufWriter::new(File::options().write(true).create_new(true).open(&writing)?);
        file.write_all(MAGIC)?;
        file.write_all(&bag_header_record(0, 0, 0))?;
        let mut pos = (MAGIC.len() + 4096) as u64;

        let topics = written_topics(topic, encoding, camera);
        let connections: Vec<(Vec<u8>, Vec<u8>)> =
            topics.iter().enumerate().map(|(conn, (name, kind))| connection_record(conn as u32, name, *kind)).collect();
        // Per chunk: its position, first and last stamp, and messages per connection.
        let mut chunk_infos: Vec<(u64, Stamp, Stamp, Vec<u32>)> = Vec::new();
        let mut chunk = Vec::new();
        // Per connection: (stamp, offset in the chunk) of its messages in the open chunk.
        let mut chunk_entries: Vec<Vec<(Stamp, u32)>> = vec![Vec::new(); topics.len()];
        let (mut count, mut frames_written) = (0usize, 0usize);
        let mut flush = |file: &mut std::io::BufWriter<File>,
                         chunk: &mut Vec<u8>,
                         entries: &mut Vec<Vec<(Stamp, u32)>>,
                         pos: &mut u64|
         -> Result<()> {
            if entries.iter().all(Vec::is_empty) {
                return Ok(());
            }
            let compressed = compress(chunk, compression)?;
            let mut header = Vec::new();
            put_field(&mut header, "op", &[OP_CHUNK]);
            put_field(&mut header, "compression", compression.name().as_bytes());
            put_field(&mut header, "size", &(chunk.len() as u32).to_le_bytes());
            let mut out = Vec::new();
            put_record(&mut out, &header, &compressed);
            for (conn, entries) in entries.iter().enumerate().filter(|(_, e)| !e.is_empty()) {
                let mut index_header = Vec::new();
                put_field(&mut index_header, "op", &[OP_INDEX_DATA]);
                put_field(&mut index_header, "ver", &1u32.to_le_bytes());
                put_field(&mut index_header, "conn", &(conn as u32).to_le_bytes());
                put_field(&mut index_header, "count", &(entries.len() as u32).to_le_bytes());
                let mut index_data = Vec::new();
                for (stamp, offset) in entries {
                    index_data.extend_from_slice(&time_bytes(*stamp)?);
                    index_data.extend_from_slice(&offset.to_le_bytes());
                }
                put_record(&mut out, &index_header, &index_data);
            }
            let stamps = entries.iter().flatten().map(|e| e.0);
            let start = stamps.clone().min().context("non-empty")?;
            let end = stamps.max().context("non-empty")?;
            chunk_infos.push((*pos, start, end, entries.iter().map(|e| e.len() as u32).collect()));
            file.write_all(&out)?;
            *pos += out.len() as u64;
            chunk.clear();
            entries.iter_mut().for_each(Vec::clear);
            Ok(())
        };
        let mut seqs = vec![0u32; topics.len()];
        for message in written_messages(frames, encoding, camera) {
            let (conn, stamp, message) = message?;
            if count == 0 {
                for (header, data) in &connections {
                    put_record(&mut chunk, header, data);
                }
            }
            let payload = message.to_ros1(seqs[conn]);
            seqs[conn] += 1;
            let mut header = Vec::new();
            put_field(&mut header, "op", &[OP_MESSAGE]);
            put_field(&mut header, "conn", &(conn as u32).to_le_bytes());
            put_field(&mut header, "time", &time_bytes(stamp)?);
            chunk_entries[conn].push((stamp, chunk.len() as u32));
            put_record(&mut chunk, &header, &payload);
            count += 1;
            frames_written += usize::from(conn == 0);
            if chunk.len() >= CHUNK_THRESHOLD {
                flush(&mut file, &mut chunk, &mut chunk_entries, &mut pos)?;
            }
        }
        flush(&mut file, &mut chunk, &mut chunk_entries, &mut pos)?;

        let index_pos = pos;
        let mut index = Vec::new();
        let conn_count = if count > 0 { connections.len() as u32 } else { 0 };
        if count > 0 {
            for (header, data) in &connections {
                put_record(&mut index, header, data);
            }
        }
        for (chunk_pos, start, end, counts) in &chunk_infos {
            let mut header = Vec::new();
            put_field(&mut header, "op", &[OP_CHUNK_INFO]);
            put_field(&mut header, "ver", &1u32.to_le_bytes());
            put_field(&mut header, "chunk_pos", &chunk_pos.to_le_bytes());
            put_field(&mut header, "start_time", &time_bytes(*start)?);
            put_field(&mut header, "end_time", &time_bytes(*end)?);
            let present: Vec<(u32, u32)> =
                counts.iter().enumerate().filter(|(_, n)| **n > 0).map(|(conn, n)| (conn as u32, *n)).collect();
            put_field(&mut header, "count", &(present.len() as u32).to_le_bytes());
            let mut data = Vec::new();
            for (conn, n) in present {
                data.extend_from_slice(&conn.to_le_bytes());
                data.extend_from_slice(&n.to_le_bytes());
            }
            put_record(&mut index, &header, &data);
        }
        file.write_all(&index)?;
        let mut file = file.into_inner().map_err(|e| e.into_error())?;
        file.seek(SeekFrom::Start(MAGIC.len() as u64))?;
        file.write_all(&bag_header_record(index_pos, conn_count, chunk_infos.len() as u32))?;
        file.sync_all()?;
        std::fs::rename(&writing, path).with_context(|| format!("renaming {} into place", writing.display()))?;
        Ok(frames_written)
    };
    let written = write();
    if written.is_err() {
        let _ = std::fs::remove_file(&writing);
    }
    written.with_context(|| format!("cannot write ROS 1 bag {}", path.display()))
}

/// A connection record's header and data for connection `conn` on `topic`.
fn connection_record(conn: u32, topic: &str, kind: WrittenKind) -> (Vec<u8>, Vec<u8>) {
    let mut header = Vec::new();
    put_field(&mut header, "op", &[OP_CONNECTION]);
    put_field(&mut header, "conn", &conn.to_le_bytes());
    put_field(&mut header, "topic", topic.as_bytes());
    let mut data = Vec::new();
    put_field(&mut data, "topic", topic.as_bytes());
    put_field(&mut data, "type", kind.ros1_type().as_bytes());
    let md5 = match kind {
        WrittenKind::Image(ImageKind::Raw) => IMAGE_MD5,
        WrittenKind::Image(ImageKind::Compressed) => COMPRESSED_IMAGE_MD5,
        WrittenKind::CameraInfo => CAMERA_INFO_MD5,
    };
    put_field(&mut data, "md5sum", md5.as_bytes());
    put_field(&mut data, "message_definition", message_definition(kind).as_bytes());
    put_field(&mut data, "callerid", b"/ecm_lcd");
    put_field(&mut data, "latching", b"0");
    (header, data)
}

fn compress(data: &[u8], compression: Ros1Compression) -> Result<Vec<u8>> {
    Ok(match compression {
        Ros1Compression::None => data.to_vec(),
        Ros1Compression::Bz2 => {
            let mut encoder = bzip2::write::BzEncoder::new(Vec::new(), bzip2::Compression::default());
            encoder.write_all(data)?;
            encoder.finish()?
        }
        Ros1Compression::Lz4 => {
            let mut encoder = lz4::EncoderBuilder::new().build(Vec::new())?;
            encoder.write_all(data)?;
            let (out, result) = encoder.finish();
            result?;
            out
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frames(n: usize) -> Vec<(Stamp, RgbImage)> {
        crate::io::test_frames(n, 8, 6, Stamp::from_sec_nsec(1_341_847_980, 722_988_000))
    }

    /// A message whose image does not decode is skipped: the messages after it are read with their
    /// own indexes.
    #[test]
    fn a_message_that_does_not_decode_is_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("seq.bag");
        let written = frames(5);
        write_ros1_bag(&path, "/cam", written.clone(), WireEncoding::Png, Ros1Compression::None).unwrap();
        // The third message's PNG signature broken, in place: the bag's records stay intact.
        let mut bytes = std::fs::read(&path).unwrap();
        let signature = b"\x89PNG";
        let third = (0..bytes.len() - 4).filter(|&at| &bytes[at..at + 4] == signature).nth(2).unwrap();
        bytes[third..third + 4].copy_from_slice(b"JUNK");
        std::fs::write(&path, bytes).unwrap();
        let read: Vec<Result<Frame>> = crate::io::open_source(&path, None).unwrap().collect();
        crate::io::assert_skips_unreadable(read, &written, 2, written[2].0, "seq.bag: message record at offset");
    }

    #[test]
    fn written_bags_read_back_for_every_compression() {
        let dir = tempfile::tempdir().unwrap();
        for compression in [Ros1Compression::None, Ros1Compression::Bz2, Ros1Compression::Lz4] {
            let path = dir.path().join(format!("{}.bag", compression.name()));
            assert_eq!(write_ros1_bag(&path, "/cam/rgb", frames(5), WireEncoding::Bgr8, compression).unwrap(), 5);
            let source = crate::io::open_source(&path, None).unwrap();
            assert_eq!(source.len_hint(), Some(5));
            assert!(source.describe().ends_with("topic /cam/rgb (5 messages)"), "{}", source.describe());
            // The name `rosbag record` gives a bag it is still writing.
            let active = dir.path().join(format!("{}.bag.active", compression.name()));
            std::fs::copy(&path, &active).unwrap();
            assert_eq!(crate::io::open_source(&active, None).unwrap().count(), 5);
            let read: Vec<Frame> = source.map(|f| f.unwrap()).collect();
            for (i, (frame, (stamp, image))) in read.iter().zip(frames(5)).enumerate() {
                assert_eq!((frame.index, frame.stamp), (i, stamp));
                assert_eq!(frame.image, image);
            }
        }
    }

    /// A `camera_info` beside the images, over several chunks: every frame reads back, with the
    /// intrinsics.
    #[test]
    fn a_calibrated_bag_carries_its_camera() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("calibrated.bag");
        let frames = crate::io::test_frames(10, 320, 240, Stamp::from_sec_nsec(1_341_847_980, 5));
        let camera = Intrinsics { fx: 300.0, fy: 301.0, cx: 159.5, cy: 119.5, size: Some([320, 240]) };
        let written = write_ros1_bag_calibrated(
            &path,
            "/cam/rgb/image_raw",
            frames.clone(),
            WireEncoding::Rgb8,
            Ros1Compression::None,
            Some(&camera),
        );
        assert_eq!(written.unwrap(), 10);
        let source = crate::io::open_source(&path, None).unwrap();
        let found = source.intrinsics().unwrap();
        assert_eq!((found.intrinsics, found.origin.as_str()), (camera, "topic /cam/rgb/camera_info"));
        let read: Vec<Frame> = source.map(|f| f.unwrap()).collect();
        assert_eq!(read.len(), 10);
        for (frame, (stamp, image)) in read.iter().zip(&frames) {
            assert_eq!((&frame.stamp, &frame.image), (stamp, image));
        }
    }

    #[test]
    fn truncated_bag_replays_what_precedes_the_damage() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("full.bag");
        // Big frames so that every message gets its own chunk.
        let big: Vec<(Stamp, RgbImage)> = (0..4)
            .map(|i| (Stamp::from_sec_nsec(10 + i, 0), RgbImage::from_pixel(640, 480, image::Rgb([i as u8; 3]))))
            .collect();
        write_ros1_bag(&path, "/cam", big, WireEncoding::Rgb8, Ros1Compression::None).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let cut = dir.path().join("cut.bag");
        std::fs::write(&cut, &bytes[..bytes.len() * 5 / 8]).unwrap();
        let results: Vec<Result<Frame>> = crate::io::open_source(&cut, None).unwrap().collect();
        assert_eq!(results.len(), 3, "two whole chunks, then the error");
        assert_eq!(results[1].as_ref().unwrap().image.get_pixel(0, 0).0, [1; 3]);
        let err = format!("{:#}", results[2].as_ref().unwrap_err());
        assert!(
            err.contains("cut.bag") && err.contains("byte offset") && err.contains("read 2 messages before the damage"),
            "{err}"
        );

        for len in [0, 10, 13, 100, 4109] {
            std::fs::write(&cut, &bytes[..len]).unwrap();
            let err = format!("{:#}", crate::io::open_source(&cut, None).err().unwrap());
            assert!(err.contains("cut.bag"), "{err}");
        }
    }

    #[test]
    fn corrupt_chunk_is_reported_with_its_offset() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bz.bag");
        write_ros1_bag(&path, "/cam", frames(3), WireEncoding::Rgb8, Ros1Compression::Bz2).unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        let chunk_data = 13 + 4096 + 80; // inside the first chunk's compressed data
        for b in &mut bytes[chunk_data..chunk_data + 40] {
            *b ^= 0x5A;
        }
        std::fs::write(&path, &bytes).unwrap();
        let results: Vec<Result<Frame>> = crate::io::open_source(&path, None).unwrap().collect();
        assert_eq!(results.len(), 1);
        let err = format!("{:#}", results[0].as_ref().unwrap_err());
        assert!(err.contains("damaged chunk at byte offset 4109") && err.contains("read 0 messages"), "{err}");
    }

    #[test]
    fn garbage_never_panics() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.bag");
        let mut state = 0x1234_5678u32;
        let mut good = Vec::new();
        for round in 0..300 {
            if round % 100 == 0 {
                let compression = [Ros1Compression::None, Ros1Compression::Bz2, Ros1Compression::Lz4][round / 100];
                write_ros1_bag(&path, "/cam", frames(2), WireEncoding::Mono8, compression).unwrap();
                good = std::fs::read(&path).unwrap();
            }
            let mut bytes = good.clone();
            for _ in 0..1 + round % 8 {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let at = 13 + (state as usize >> 4) % (bytes.len() - 13);
                bytes[at] = (state >> 24) as u8;
            }
            std::fs::write(&path, &bytes).unwrap();
            if let Ok(source) = crate::io::open_source(&path, None) {
                for _ in source {}
            }
        }
    }
}
