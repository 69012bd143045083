//! The table of malformed inputs: every decoder (raw and compressed images, ROS 1 and CDR messages,
//! ROS 1 bags, ROS 2 sqlite3 and MCAP bags, TUM folders, TFLite and safetensors weights, params YAML)
//! is given broken input of each kind below and must return an error, not panic, whose text carries
//! the context a user needs (file, offset or message index, field). The table of kind -> error is
//! printed (`--nocapture`) and written to `target/malformed_inputs.md` for the README.
//!
//! A kind is one way an input can be broken; replayed sources (bags, TUM folders) are read to the end,
//! so damage found while iterating counts as the error as well as damage found when opening.

mod support;

use anyhow::{Context as _, Result};
use ecm_lcd::config::Params;
use ecm_lcd::io::image_msg::{
    decode_compressed_image, decode_image, encode_jpeg, ImageKind, ImageMessage, WireEncoding,
};
use ecm_lcd::io::msgs::{CompressedImage, Image};
use ecm_lcd::io::open_source;
use ecm_lcd::io::ros1bag::{write_ros1_bag, Ros1Compression};
use ecm_lcd::io::ros2bag::{write_ros2_bag, Ros2Storage};
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::model::weights::{import::import_tflite, Weights};
use ecm_lcd::types::Stamp;
use image::RgbImage;
use std::fs;
use std::path::{Path, PathBuf};

/// One malformed input: where, what is broken, how to provoke it (in a fresh temporary folder), and the
/// pieces of text the error must contain.
struct Case {
    area: &'static str,
    kind: &'static str,
    provoke: fn(&Path) -> Result<()>,
    expect: &'static [&'static str],
}

fn frames(n: usize, size: u32) -> Vec<(Stamp, RgbImage)> {
    (0..n)
        .map(|i| {
            let image = RgbImage::from_fn(size, size, |x, y| image::Rgb([(x * 7 + i as u32) as u8, (y * 5) as u8, 90]));
            (Stamp::from_sec_nsec(100 + i as i64, 0), image)
        })
        .collect()
}

/// Opens a source and reads all of it; the first error, if any.
fn replay(path: &Path) -> Result<()> {
    for frame in open_source(path, None)? {
        frame?;
    }
    Ok(())
}

/// Replays up to the first error and checks that the frames before the damage came out; the error.
fn replay_expecting_frames_before_damage(path: &Path, at_least: usize) -> Result<()> {
    let mut good = 0;
    for frame in open_source(path, None)? {
        frame?;
        good += 1;
    }
    anyhow::ensure!(good >= at_least, "TEST: only {good} frames before the damage, expected at least {at_least}");
    Ok(())
}

fn raw(width: u32, height: u32, encoding: &str, step: u32, len: usize) -> Image {
    Image { width, height, encoding: encoding.into(), step, data: vec![7; len], ..Image::default() }
}

fn compressed(format: &str, data: Vec<u8>) -> CompressedImage {
    CompressedImage { format: format.into(), data, ..CompressedImage::default() }
}

fn jpeg() -> Vec<u8> {
    encode_jpeg(&frames(1, 32)[0].1, 90).unwrap()
}

fn png() -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    image::DynamicImage::ImageRgb8(frames(1, 32).remove(0).1).write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// A ROS 1 rgb8 Image message of 4x3 pixels.
fn ros1_message() -> Vec<u8> {
    let image = frames(1, 4).remove(0).1;
    ecm_lcd::io::image_msg::encode_image(Stamp::from_sec_nsec(5, 0), "cam", &image, WireEncoding::Rgb8)
        .unwrap()
        .to_ros1(0)
}

fn cdr_message() -> Vec<u8> {
    let image = frames(1, 4).remove(0).1;
    ecm_lcd::io::image_msg::encode_image(Stamp::from_sec_nsec(5, 0), "cam", &image, WireEncoding::Rgb8)
        .unwrap()
        .to_cdr()
        .unwrap()
}

fn ros1_bag(dir: &Path, compression: Ros1Compression, n: usize, size: u32) -> PathBuf {
    let bag = dir.join("in.bag");
    write_ros1_bag(&bag, "/cam", frames(n, size), WireEncoding::Rgb8, compression).unwrap();
    bag
}

/// Replaces the first occurrence of `from` in the file by `to` (same length).
fn patch(path: &Path, from: &[u8], to: &[u8]) {
    let mut bytes = fs::read(path).unwrap();
    let at = bytes
        .windows(from.len())
        .position(|w| w == from)
        .unwrap_or_else(|| panic!("{from:?} not in {}", path.display()));
    bytes[at..at + to.len()].copy_from_slice(to);
    fs::write(path, bytes).unwrap();
}

fn patch_all(path: &Path, from: &[u8], to: &[u8]) {
    let mut bytes = fs::read(path).unwrap();
    let mut found = 0;
    while let Some(at) = bytes.windows(from.len()).position(|w| w == from) {
        bytes[at..at + to.len()].copy_from_slice(to);
        found += 1;
    }
    assert!(found > 0, "{from:?} not in {}", path.display());
    fs::write(path, bytes).unwrap();
}

fn truncate(path: &Path, keep_fraction: f64) {
    let bytes = fs::read(path).unwrap();
    fs::write(path, &bytes[..(bytes.len() as f64 * keep_fraction) as usize]).unwrap();
}

/// The storage file of a fresh one-topic ROS 2 bag.
fn ros2_bag(dir: &Path, storage: Ros2Storage, encoding: WireEncoding, n: usize, size: u32) -> PathBuf {
    let bag = dir.join("bag");
    write_ros2_bag(&bag, storage, "/cam", frames(n, size), encoding).unwrap();
    let extension = if storage == Ros2Storage::Mcap { "mcap" } else { "db3" };
    bag.join(format!("bag_0.{extension}"))
}

/// Relabels the JPEG payloads of a sqlite3 bag as PNG: the CDR stays valid, the pixels do not decode.
fn relabel_jpeg_as_png(db3: &Path) {
    let db = rusqlite::Connection::open(db3).unwrap();
    let mut payloads: Vec<(i64, Vec<u8>)> = db
        .prepare("SELECT id, data FROM messages")
        .unwrap()
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
        .unwrap()
        .map(|r| r.unwrap())
        .collect();
    for (id, data) in &mut payloads {
        let at = data.windows(4).position(|w| w == b"jpeg").unwrap();
        data[at..at + 4].copy_from_slice(b"png\0");
        db.execute("UPDATE messages SET data = ?1 WHERE id = ?2", rusqlite::params![&*data, *id]).unwrap();
    }
}

/// An MCAP file with one message on `/cam`, of schema `schema` in `encoding` (the payload is a valid
/// CDR Image).
fn mcap_file(dir: &Path, schema: &str, encoding: &str) -> PathBuf {
    let path = dir.join("m.mcap");
    let mut writer = mcap::WriteOptions::new()
        .profile("ros2")
        .create(std::io::BufWriter::new(fs::File::create(&path).unwrap()))
        .unwrap();
    let schema = writer.add_schema(schema, "ros2msg", b"").unwrap();
    let channel = writer.add_channel(schema, "/cam", encoding, &Default::default()).unwrap();
    let header = mcap::records::MessageHeader { channel_id: channel, sequence: 0, log_time: 1, publish_time: 1 };
    writer.write_to_known_channel(&header, &cdr_message()).unwrap();
    writer.finish().unwrap();
    path
}

fn sqlite(path: &Path, sql: &str) {
    rusqlite::Connection::open(path).unwrap().execute_batch(sql).unwrap();
}

/// A TUM folder with two real images; `rgb_txt` replaces its list.
fn tum(dir: &Path, rgb_txt: &str) -> PathBuf {
    let seq = dir.join("seq");
    fs::create_dir_all(seq.join("rgb")).unwrap();
    for (i, (_, image)) in frames(2, 16).into_iter().enumerate() {
        image.save(seq.join(format!("rgb/{i}.png"))).unwrap();
    }
    fs::write(seq.join("rgb.txt"), rgb_txt).unwrap();
    seq
}

fn groundtruth(dir: &Path, text: &str) -> Result<()> {
    let path = dir.join("groundtruth.txt");
    fs::write(&path, text).unwrap();
    read_groundtruth(&path).map(|_| ())
}

fn weights_file(dir: &Path, name: &str, bytes: &[u8]) -> Result<()> {
    let path = dir.join(name);
    fs::write(&path, bytes).unwrap();
    Weights::load(&path).map(|_| ())
}

/// A safetensors file: an 8-byte header length, the JSON header, the data.
fn safetensors_bytes(header: &str, data: &[u8]) -> Vec<u8> {
    let mut out = (header.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

fn tflite_file(dir: &Path, bytes: &[u8]) -> Result<()> {
    let path = dir.join("model.tflite");
    fs::write(&path, bytes).unwrap();
    import_tflite(&path).map(|_| ())
}

fn shared_tflite() -> Vec<u8> {
    let path = support::shared_dir().join("models/mobilenet_v2_1.0_224_quant.tflite");
    fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn params_file(dir: &Path, text: &str) -> Result<()> {
    let path = dir.join("params.yaml");
    fs::write(&path, text).unwrap();
    Params::load(&path, "/ecm_lcd").map(|_| ())
}

const CASES: &[Case] = &[
    // Raw images: every encoding with a wrong step or data size, and what is not an image at all.
    Case {
        area: "image",
        kind: "rgb8, step smaller than width*3",
        provoke: |_| decode_image(&raw(4, 3, "rgb8", 11, 33)).map(|_| ()),
        expect: &["rgb8 image 4x3", "step 11 is smaller than width*3 = 12"],
    },
    Case {
        area: "image",
        kind: "bgr8, data shorter than step*height",
        provoke: |_| decode_image(&raw(4, 3, "bgr8", 12, 35)).map(|_| ()),
        expect: &["bgr8 image 4x3", "data has 35 bytes but step*height = 12*3 = 36"],
    },
    Case {
        area: "image",
        kind: "rgba8, data longer than step*height",
        provoke: |_| decode_image(&raw(4, 3, "rgba8", 16, 49)).map(|_| ()),
        expect: &["rgba8 image 4x3", "data has 49 bytes", "16*3 = 48"],
    },
    Case {
        area: "image",
        kind: "bgra8, padded step but data without the padding",
        provoke: |_| decode_image(&raw(4, 3, "bgra8", 20, 48)).map(|_| ()),
        expect: &["bgra8 image 4x3", "data has 48 bytes but step*height = 20*3 = 60"],
    },
    Case {
        area: "image",
        kind: "mono8, zero width",
        provoke: |_| decode_image(&raw(0, 3, "mono8", 0, 0)).map(|_| ()),
        expect: &["empty mono8 image (0x3)"],
    },
    Case {
        area: "image",
        kind: "mono16, step of one byte per pixel",
        provoke: |_| decode_image(&raw(4, 3, "mono16", 4, 12)).map(|_| ()),
        expect: &["mono16 image 4x3", "step 4 is smaller than width*2 = 8"],
    },
    Case {
        area: "image",
        kind: "unknown encoding",
        provoke: |_| decode_image(&raw(4, 3, "yuv422", 8, 24)).map(|_| ()),
        expect: &["unsupported image encoding \"yuv422\"", "supported: rgb8"],
    },
    Case {
        area: "image",
        kind: "size overflowing memory (65535x65535 rgba8, 16 bytes of data)",
        provoke: |_| decode_image(&raw(65535, 65535, "rgba8", 262140, 16)).map(|_| ()),
        expect: &["rgba8 image 65535x65535", "data has 16 bytes"],
    },
    Case {
        area: "image",
        kind: "CompressedImage, truncated JPEG",
        provoke: |_| {
            let j = jpeg();
            decode_compressed_image(&compressed("jpeg", j[..j.len() / 2].to_vec())).map(|_| ())
        },
        expect: &["CompressedImage format \"jpeg\"", "do not decode as Jpeg"],
    },
    Case {
        area: "image",
        kind: "CompressedImage, truncated PNG",
        provoke: |_| {
            let p = png();
            decode_compressed_image(&compressed("png", p[..p.len() / 2].to_vec())).map(|_| ())
        },
        expect: &["CompressedImage format \"png\"", "do not decode as Png"],
    },
    Case {
        area: "image",
        kind: "CompressedImage, JPEG bytes labelled PNG",
        provoke: |_| decode_compressed_image(&compressed("rgb8; png compressed bgr8", jpeg())).map(|_| ()),
        expect: &["format \"rgb8; png compressed bgr8\"", "do not decode as Png"],
    },
    Case {
        area: "image",
        kind: "CompressedImage, unknown format",
        provoke: |_| decode_compressed_image(&compressed("webp", jpeg())).map(|_| ()),
        expect: &["unsupported CompressedImage format \"webp\" (supported: jpeg, png)"],
    },
    Case {
        area: "image",
        kind: "CompressedImage, compressedDepth (a depth map)",
        provoke: |_| decode_compressed_image(&compressed("16UC1; compressedDepth png", png())).map(|_| ()),
        expect: &["compressed depth map, not a camera image"],
    },
    Case {
        area: "image",
        kind: "CompressedImage, empty payload",
        provoke: |_| decode_compressed_image(&compressed("jpeg", Vec::new())).map(|_| ()),
        expect: &["0 bytes do not decode as Jpeg"],
    },
    // Serialised messages.
    Case {
        area: "message",
        kind: "ROS 1 Image, cut inside the pixel data",
        provoke: |_| {
            let m = ros1_message();
            ImageMessage::from_ros1(ImageKind::Raw, &m[..m.len() - 5]).map(|_| ())
        },
        expect: &["message truncated: uint8[] data needs 48 bytes", "only 43 left"],
    },
    Case {
        area: "message",
        kind: "ROS 1 Image, bytes left over",
        provoke: |_| {
            let mut m = ros1_message();
            m.extend_from_slice(b"xyz");
            ImageMessage::from_ros1(ImageKind::Raw, &m).map(|_| ())
        },
        expect: &["3 bytes left over after the sensor_msgs/Image message"],
    },
    Case {
        area: "message",
        kind: "ROS 1 Image, string length past the end",
        provoke: |_| {
            let mut m = ros1_message();
            m[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
            ImageMessage::from_ros1(ImageKind::Raw, &m).map(|_| ())
        },
        expect: &["message truncated: string needs 4294967295 bytes at offset 16"],
    },
    Case {
        area: "message",
        kind: "ROS 1 CompressedImage, format not UTF-8",
        provoke: |_| {
            let mut m = ImageMessage::Compressed(compressed("jpeg", jpeg())).to_ros1(0);
            m[20] = 0xff;
            ImageMessage::from_ros1(ImageKind::Compressed, &m).map(|_| ())
        },
        expect: &["string at offset 20 is not UTF-8"],
    },
    Case {
        area: "message",
        kind: "CDR, shorter than the encapsulation header",
        provoke: |_| ImageMessage::from_cdr(ImageKind::Raw, &[0, 1]).map(|_| ()),
        expect: &["CDR payload of 2 bytes is shorter than its 4-byte header"],
    },
    Case {
        area: "message",
        kind: "CDR, unknown encapsulation (XCDR2)",
        provoke: |_| {
            let mut m = cdr_message();
            m[1] = 0x07;
            ImageMessage::from_cdr(ImageKind::Raw, &m).map(|_| ())
        },
        expect: &["unsupported CDR encapsulation 0x00 0x07"],
    },
    Case {
        area: "message",
        kind: "CDR Image, cut short",
        provoke: |_| {
            let m = cdr_message();
            ImageMessage::from_cdr(ImageKind::Raw, &m[..m.len() - 10]).map(|_| ())
        },
        expect: &["sensor_msgs/msg/Image CDR message of 86 bytes", "unexpected end of input"],
    },
    // ROS 1 bags.
    Case {
        area: "ROS 1 bag",
        kind: "missing file",
        provoke: |d| replay(&d.join("nothing.bag")),
        expect: &["nothing.bag does not exist"],
    },
    Case {
        area: "ROS 1 bag",
        kind: "not a bag (wrong magic line)",
        provoke: |d| {
            let p = d.join("x.bag");
            fs::write(&p, b"#ROSBAG V1.2\nhello").unwrap();
            replay(&p)
        },
        expect: &["x.bag", "not a ROS 1 bag v2.0"],
    },
    Case {
        area: "ROS 1 bag",
        kind: "bad bag header record",
        provoke: |d| {
            let p = d.join("g.bag");
            fs::write(&p, b"#ROSBAG V2.0\n\xff\xff\xff\xff").unwrap();
            replay(&p)
        },
        expect: &["g.bag", "bag header record at byte offset 13"],
    },
    Case {
        area: "ROS 1 bag",
        kind: "truncated (lz4 chunks): frames before the damage, then the error",
        provoke: |d| {
            let b = ros1_bag(d, Ros1Compression::Lz4, 6, 300);
            truncate(&b, 0.75);
            replay_expecting_frames_before_damage(&b, 1)
        },
        expect: &["in.bag", "byte offset", "messages before the damage"],
    },
    Case {
        area: "ROS 1 bag",
        kind: "unknown chunk compression",
        provoke: |d| {
            let b = ros1_bag(d, Ros1Compression::Lz4, 2, 8);
            patch(&b, b"compression=lz4", b"compression=zst");
            replay(&b)
        },
        expect: &["in.bag", "unsupported chunk compression \"zst\""],
    },
    Case {
        area: "ROS 1 bag",
        kind: "corrupt bz2 chunk",
        provoke: |d| {
            let b = ros1_bag(d, Ros1Compression::Bz2, 2, 8);
            let mut bytes = fs::read(&b).unwrap();
            let at = bytes.windows(3).position(|w| w == b"BZh").unwrap();
            bytes[at + 3] = b'0';
            fs::write(&b, bytes).unwrap();
            replay(&b)
        },
        expect: &["in.bag", "damaged chunk at byte offset", "bz2 decompression failed"],
    },
    Case {
        area: "ROS 1 bag",
        kind: "chunk size field disagreeing with the data",
        provoke: |d| {
            let b = ros1_bag(d, Ros1Compression::None, 2, 8);
            let mut bytes = fs::read(&b).unwrap();
            let at = bytes.windows(5).position(|w| w == b"size=").unwrap() + 5;
            bytes[at..at + 4].copy_from_slice(&7u32.to_le_bytes());
            fs::write(&b, bytes).unwrap();
            replay(&b)
        },
        expect: &["in.bag", "chunk decompresses to", "header says 7"],
    },
    Case {
        area: "ROS 1 bag",
        kind: "message with an unknown pixel encoding",
        provoke: |d| {
            let b = ros1_bag(d, Ros1Compression::None, 2, 8);
            patch_all(&b, b"\x04\0\0\0rgb8", b"\x04\0\0\0rgbX");
            replay(&b)
        },
        expect: &["frame 0 (stamp", "in.bag", "unsupported image encoding \"rgbX\""],
    },
    Case {
        area: "ROS 1 bag",
        kind: "no image topic asked for exists",
        provoke: |d| {
            let b = ros1_bag(d, Ros1Compression::None, 2, 8);
            open_source(&b, Some("/depth")).map(|_| ())
        },
        expect: &["in.bag has no topic /depth; image topics: /cam (sensor_msgs/Image, 2 messages)"],
    },
    // ROS 2 bags.
    Case {
        area: "ROS 2 sqlite3 bag",
        kind: "no image topic asked for exists",
        provoke: |d| {
            let b = ros2_bag(d, Ros2Storage::Sqlite3, WireEncoding::Png, 3, 4);
            open_source(b.parent().unwrap(), Some("/nope")).map(|_| ())
        },
        expect: &["bag_0.db3 has no topic /nope; image topics: /cam (sensor_msgs/msg/CompressedImage, 3 messages)"],
    },
    Case {
        area: "MCAP",
        kind: "no image topic asked for exists",
        provoke: |d| {
            let b = ros2_bag(d, Ros2Storage::Mcap, WireEncoding::Png, 3, 4);
            open_source(b.parent().unwrap(), Some("/nope")).map(|_| ())
        },
        expect: &["bag_0.mcap has no topic /nope; image topics: /cam (sensor_msgs/msg/CompressedImage, 3 messages)"],
    },
    Case {
        area: "ROS 2 sqlite3 bag",
        kind: "garbage file",
        provoke: |d| {
            let p = d.join("g.db3");
            fs::write(&p, vec![0x5a; 4096]).unwrap();
            replay(&p)
        },
        expect: &["g.db3", "cannot read the topics and messages tables", "not a database"],
    },
    Case {
        area: "ROS 2 sqlite3 bag",
        kind: "SQLite database with another schema",
        provoke: |d| {
            let p = d.join("other.db3");
            sqlite(&p, "CREATE TABLE notes (id INTEGER, text TEXT);");
            replay(&p)
        },
        expect: &["other.db3", "cannot read the topics and messages tables", "no such table: messages"],
    },
    Case {
        area: "ROS 2 sqlite3 bag",
        kind: "serialization format other than cdr",
        provoke: |d| {
            let b = ros2_bag(d, Ros2Storage::Sqlite3, WireEncoding::Rgb8, 2, 16);
            sqlite(&b, "UPDATE topics SET serialization_format = 'json';");
            replay(&b)
        },
        expect: &["bag_0.db3", "topic /cam is serialised as \"json\", only cdr is supported"],
    },
    Case {
        area: "ROS 2 sqlite3 bag",
        kind: "JPEG payloads relabelled PNG",
        provoke: |d| {
            let b = ros2_bag(d, Ros2Storage::Sqlite3, WireEncoding::Jpeg { quality: 80 }, 2, 16);
            relabel_jpeg_as_png(&b);
            replay(&b)
        },
        expect: &["frame 0 (stamp", "bag_0.db3", "row id 1", "do not decode as Png"],
    },
    Case {
        area: "ROS 2 sqlite3 bag",
        kind: "message cut short (an unreadable frame: the frames after it are read)",
        provoke: |d| {
            let b = ros2_bag(d, Ros2Storage::Sqlite3, WireEncoding::Rgb8, 3, 16);
            sqlite(&b, "UPDATE messages SET data = substr(data, 1, 30) WHERE id = (SELECT MAX(id) FROM messages);");
            replay_expecting_frames_before_damage(&b, 2)
        },
        expect: &["frame 2 (stamp 102.000000000) cannot be read", "bag_0.db3", "row id 3", "unexpected end of input"],
    },
    Case {
        area: "ROS 2 bag folder",
        kind: "metadata.yaml without a storage file",
        provoke: |d| {
            let b = d.join("bagdir");
            fs::create_dir(&b).unwrap();
            fs::write(b.join("metadata.yaml"), "x: 1").unwrap();
            replay(&b)
        },
        expect: &["bagdir", "has metadata.yaml but no .db3 or .mcap file"],
    },
    Case {
        area: "MCAP",
        kind: "bad magic",
        provoke: |d| {
            let p = d.join("g.mcap");
            fs::write(&p, b"garbage, not an MCAP file at all").unwrap();
            replay(&p)
        },
        expect: &["g.mcap", "magic"],
    },
    Case {
        area: "MCAP",
        kind: "truncated: frames before the damage, then the error",
        provoke: |d| {
            let b = ros2_bag(d, Ros2Storage::Mcap, WireEncoding::Rgb8, 6, 300);
            truncate(&b, 0.75);
            replay_expecting_frames_before_damage(&b, 0)
        },
        expect: &["bag_0.mcap", "messages of /cam before the damage"],
    },
    Case {
        area: "MCAP",
        kind: "message encoding other than cdr",
        provoke: |d| replay(&mcap_file(d, "sensor_msgs/msg/Image", "json")),
        expect: &["m.mcap", "topic /cam has message encoding \"json\", only cdr is supported"],
    },
    Case {
        area: "MCAP",
        kind: "no image topic at all",
        provoke: |d| replay(&mcap_file(d, "sensor_msgs/msg/Imu", "cdr")),
        expect: &[
            "m.mcap has no sensor_msgs Image or CompressedImage topic; topics: /cam (sensor_msgs/msg/Imu, 1 messages)",
        ],
    },
    // TUM folders and trajectories.
    Case {
        area: "TUM",
        kind: "rgb.txt names a missing image",
        provoke: |d| replay(&tum(d, "1.0 rgb/0.png\n2.0 rgb/9.png\n")),
        expect: &["rgb.txt:2: image file", "rgb/9.png does not exist"],
    },
    Case {
        area: "TUM",
        kind: "rgb.txt bad timestamp",
        provoke: |d| replay(&tum(d, "# comment\n1.0 rgb/0.png\nabc rgb/1.png\n")),
        expect: &["rgb.txt:3: bad timestamp \"abc\""],
    },
    Case {
        area: "TUM",
        kind: "rgb.txt line with three fields",
        provoke: |d| replay(&tum(d, "1.0 rgb/0.png extra\n")),
        expect: &["rgb.txt:1: expected `timestamp path`"],
    },
    Case {
        area: "TUM",
        kind: "rgb.txt lists nothing",
        provoke: |d| replay(&tum(d, "# only comments\n\n")),
        expect: &["rgb.txt lists no images"],
    },
    Case {
        area: "TUM",
        kind: "listed image is not an image",
        provoke: |d| {
            let s = tum(d, "1.0 rgb/0.png\n2.0 rgb/1.png\n");
            fs::write(s.join("rgb/1.png"), b"this is not a png").unwrap();
            replay(&s)
        },
        expect: &["rgb.txt:2: cannot decode image", "rgb/1.png"],
    },
    Case {
        area: "TUM",
        kind: "folder with neither rgb.txt nor images",
        provoke: |d| replay(d),
        expect: &["has no rgb.txt and no png/jpg/jpeg/bmp images"],
    },
    Case {
        area: "TUM",
        kind: "unsupported source file",
        provoke: |d| {
            let p = d.join("x.txt");
            fs::write(&p, "hello").unwrap();
            replay(&p)
        },
        expect: &["x.txt: unsupported source"],
    },
    Case {
        area: "TUM",
        kind: "groundtruth line with 7 fields",
        provoke: |d| groundtruth(d, "# gt\n1.0 0 0 0 0 0 1\n"),
        expect: &["groundtruth.txt:2: expected 8 fields", "found 7"],
    },
    Case {
        area: "TUM",
        kind: "groundtruth bad number",
        provoke: |d| groundtruth(d, "1.0 0 0 0 0 0 0 1\n2.0 0 x 0 0 0 0 1\n"),
        expect: &["groundtruth.txt:2: bad number \"x\""],
    },
    Case {
        area: "TUM",
        kind: "groundtruth non-finite number",
        provoke: |d| groundtruth(d, "1.0 0 0 inf 0 0 0 1\n"),
        expect: &["groundtruth.txt:1: non-finite number \"inf\""],
    },
    Case {
        area: "TUM",
        kind: "groundtruth zero quaternion",
        provoke: |d| groundtruth(d, "1.0 0 0 0 0 0 0 0\n"),
        expect: &["groundtruth.txt:1: zero quaternion"],
    },
    // Weights.
    Case {
        area: "weights",
        kind: "safetensors, missing file",
        provoke: |d| Weights::load(&d.join("missing.safetensors")).map(|_| ()),
        expect: &["cannot read weights file", "missing.safetensors"],
    },
    Case {
        area: "weights",
        kind: "safetensors, header not JSON",
        provoke: |d| weights_file(d, "c.safetensors", &safetensors_bytes("{not json}......", b"")),
        expect: &["c.safetensors is not a valid ecm-lcd weights file", "safetensors header"],
    },
    Case {
        area: "weights",
        kind: "safetensors, header length past the end",
        provoke: |d| weights_file(d, "l.safetensors", &u64::MAX.to_le_bytes()),
        expect: &["l.safetensors is not a valid ecm-lcd weights file", "safetensors header"],
    },
    Case {
        area: "weights",
        kind: "safetensors, no arch in the metadata",
        provoke: |d| {
            weights_file(
                d,
                "n.safetensors",
                &safetensors_bytes(r#"{"__metadata__":{"format":"ecm-lcd-weights/1"}}"#, b""),
            )
        },
        expect: &["n.safetensors", "no 'arch' in the safetensors metadata"],
    },
    Case {
        area: "weights",
        kind: "safetensors, tensor data offsets past the data",
        provoke: |d| {
            weights_file(
                d,
                "o.safetensors",
                &safetensors_bytes(
                    r#"{"__metadata__":{"arch":"ecmobilenet"},"stem.weight":{"dtype":"F32","shape":[2,2],"data_offsets":[0,16]}}"#,
                    &[0; 8],
                ),
            )
        },
        expect: &["o.safetensors is not a valid ecm-lcd weights file"],
    },
    Case {
        area: "weights",
        kind: "safetensors, tensors that do not fit the network",
        provoke: |d| {
            let p = d.join("s.safetensors");
            fs::write(&p, safetensors_bytes(r#"{"__metadata__":{"arch":"ecmobilenet"},"stem.weight":{"dtype":"F32","shape":[2,1],"data_offsets":[0,8]}}"#, &[0; 8])).unwrap();
            Weights::load(&p)?.network(false).map(|_| ())
        },
        expect: &["weights do not fit ecmobilenet"],
    },
    Case {
        area: "weights",
        kind: "TFLite, wrong file identifier",
        provoke: |d| tflite_file(d, b"\x10\0\0\0TFL2\0\0\0\0\0\0\0\0"),
        expect: &["model.tflite", "not a TFLite model (file identifier is not 'TFL3')"],
    },
    Case {
        area: "weights",
        kind: "TFLite, too short",
        provoke: |d| tflite_file(d, b"TFL3"),
        expect: &["model.tflite", "file is 4 bytes, too short"],
    },
    Case {
        area: "weights",
        kind: "TFLite, real model cut to a third",
        provoke: |d| {
            let b = shared_tflite();
            tflite_file(d, &b[..b.len() / 3])
        },
        expect: &["cannot import", "model.tflite", "past the end"],
    },
    Case {
        area: "weights",
        kind: "TFLite, root table offset past the end",
        provoke: |d| {
            let mut b = shared_tflite();
            b[..4].copy_from_slice(&u32::MAX.to_le_bytes());
            tflite_file(d, &b)
        },
        expect: &["cannot import", "model table", "past the end"],
    },
    // Configuration.
    Case {
        area: "config",
        kind: "params file not YAML",
        provoke: |d| params_file(d, "/ecm_lcd: [unclosed"),
        expect: &["in params file", "params.yaml", "not valid YAML"],
    },
    Case {
        area: "config",
        kind: "params file top level a list",
        provoke: |d| params_file(d, "- a\n- b\n"),
        expect: &["params.yaml", "the top level must map node names to `ros__parameters`"],
    },
    Case {
        area: "config",
        kind: "params file, no section for the node",
        provoke: |d| params_file(d, "/other_node:\n  ros__parameters:\n    detector.top_k: 2\n"),
        expect: &["params.yaml", "no section applies to node \"/ecm_lcd\"", "/other_node"],
    },
    Case {
        area: "config",
        kind: "params file, section without ros__parameters",
        provoke: |d| params_file(d, "/ecm_lcd:\n  detector.top_k: 2\n"),
        expect: &["params.yaml", "node section \"/ecm_lcd\" has no `ros__parameters`"],
    },
    Case {
        area: "config",
        kind: "params file, wrong type",
        provoke: |d| params_file(d, "/ecm_lcd:\n  ros__parameters:\n    detector:\n      min_score: high\n"),
        expect: &["params.yaml", "detector.min_score", "\"/ecm_lcd\""],
    },
    Case {
        area: "config",
        kind: "params file, unknown key",
        provoke: |d| params_file(d, "/**:\n  ros__parameters:\n    detector.nope: 1\n"),
        expect: &["params.yaml", "detector.nope", "\"/**\""],
    },
    Case {
        area: "config",
        kind: "params file, out of range",
        provoke: |d| params_file(d, "/ecm_lcd:\n  ros__parameters:\n    detector.top_k: 1000\n"),
        expect: &["params.yaml", "detector.top_k", "1000"],
    },
    Case {
        area: "config",
        kind: "params file, unknown descriptor mode",
        provoke: |d| params_file(d, "/ecm_lcd:\n  ros__parameters:\n    descriptor.mode: fancy\n"),
        expect: &["params.yaml", "descriptor.mode", "fancy"],
    },
    Case {
        area: "config",
        kind: "--param value not valid YAML",
        provoke: |_| ecm_lcd::ros::args::parse_param_value("[1, 2").map(|_| ()),
        expect: &["parameter value \"[1, 2\" is not valid YAML"],
    },
];

#[test]
fn every_malformed_input_gives_an_error_with_context() {
    let mut table = String::from("| input | malformed kind | error |\n|---|---|---|\n");
    let mut failures = Vec::new();
    for case in CASES {
        let dir = tempfile::tempdir().unwrap();
        let outcome = std::panic::catch_unwind(|| (case.provoke)(dir.path()));
        // Paths differ per run: show the error relative to the temporary folder.
        let shown = |text: String| {
            text.replace(&format!("{}/", dir.path().display()), "").replace(&dir.path().display().to_string(), ".")
        };
        let error = match outcome {
            Err(panic) => {
                let message = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()));
                failures.push(format!("{} / {}: PANICKED: {message:?}", case.area, case.kind));
                continue;
            }
            Ok(Ok(())) => {
                failures.push(format!("{} / {}: no error", case.area, case.kind));
                continue;
            }
            // candle appends a backtrace to its errors when RUST_BACKTRACE is set: not part of the message.
            Ok(Err(e)) => format!("{e:#}")
                .lines()
                .take_while(|l| !l.trim_start().starts_with("0: "))
                .collect::<Vec<_>>()
                .join("\n")
                .trim_end()
                .to_string(),
        };
        let missing: Vec<&&str> = case.expect.iter().filter(|needle| !error.contains(**needle)).collect();
        if !missing.is_empty() || error.contains("TEST:") {
            failures.push(format!("{} / {}: error lacks {missing:?}:\n    {error}", case.area, case.kind));
        }
        table.push_str(&format!(
            "| {} | {} | `{}` |\n",
            case.area,
            case.kind,
            shown(error).replace('|', "\\|").replace('\n', " ")
        ));
    }
    println!("{table}");
    let out = Path::new(env!("CARGO_TARGET_TMPDIR")).parent().unwrap().join("malformed_inputs.md");
    fs::write(&out, &table).with_context(|| format!("writing {}", out.display())).unwrap();
    println!("{} kinds of malformed input; table written to {}", CASES.len(), out.display());
    assert!(CASES.len() >= 25);
    assert!(failures.is_empty(), "{} of {} cases failed:\n{}", failures.len(), CASES.len(), failures.join("\n"));
}
