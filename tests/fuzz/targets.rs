//! What each fuzz target does with one input, shared by the cargo-fuzz targets (`fuzz_targets/`) and
//! the regression test that replays the seed corpus and every crash input found (`tests/fuzz_regressions.rs`).
//! Each function must return (Ok or Err, never panic) on any input.
#![allow(dead_code)] // each fuzz target uses one of these

use ecm_lcd::io::image_msg::{decode_compressed_image, decode_image, ImageKind, ImageMessage};
use ecm_lcd::io::msgs::{CompressedImage, Image};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Every target, by the name of its corpus folder.
pub const TARGETS: [(&str, fn(&[u8])); 9] = [
    ("image_msg", image_msg),
    ("compressed_image", compressed_image),
    ("ros1_bag", ros1_bag),
    ("ros2_sqlite", ros2_sqlite),
    ("mcap", mcap),
    ("tum", tum),
    ("tflite", tflite),
    ("safetensors", safetensors),
    ("params_yaml", params_yaml),
];

const ENCODINGS: [&str; 8] = ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16", "16UC1", ""];
const FORMATS: [&str; 5] = ["jpeg", "png", "rgb8; jpeg compressed bgr8", "16UC1; compressedDepth png", "bmp"];

/// sensor_msgs/Image. First byte % 3: 0 ROS 1 message, 1 CDR message (then its pixels decoded), 2 a
/// message built field by field (width u16, height u16, step u16, encoding index, big-endian flag,
/// then the pixel bytes) whose pixels are decoded.
pub fn image_msg(data: &[u8]) {
    let Some((&selector, rest)) = data.split_first() else { return };
    match selector % 3 {
        0 => {
            if let Ok(msg) = ImageMessage::from_ros1(ImageKind::Raw, rest) {
                let _ = msg.to_rgb();
            }
        }
        1 => {
            if let Ok(msg) = ImageMessage::from_cdr(ImageKind::Raw, rest) {
                let _ = msg.to_rgb();
            }
        }
        _ => {
            if rest.len() < 8 {
                return;
            }
            let u16_at = |i: usize| u16::from_le_bytes([rest[i], rest[i + 1]]) as u32;
            let msg = Image {
                width: u16_at(0),
                height: u16_at(2),
                step: u16_at(4),
                encoding: ENCODINGS[rest[6] as usize % ENCODINGS.len()].to_string(),
                is_bigendian: rest[7] & 1,
                data: rest[8..].to_vec(),
                ..Image::default()
            };
            let _ = decode_image(&msg);
        }
    }
}

/// sensor_msgs/CompressedImage. First byte % 3: 0 ROS 1 message, 1 CDR message (then the payload
/// decoded), 2 the rest as a payload under the format string picked by first byte / 3.
pub fn compressed_image(data: &[u8]) {
    let Some((&selector, rest)) = data.split_first() else { return };
    match selector % 3 {
        0 => {
            if let Ok(msg) = ImageMessage::from_ros1(ImageKind::Compressed, rest) {
                let _ = msg.to_rgb();
            }
        }
        1 => {
            if let Ok(msg) = ImageMessage::from_cdr(ImageKind::Compressed, rest) {
                let _ = msg.to_rgb();
            }
        }
        _ => {
            let format = FORMATS[(selector / 3) as usize % FORMATS.len()].to_string();
            let _ = decode_compressed_image(&CompressedImage { format, data: rest.to_vec(), ..Default::default() });
        }
    }
}

/// A scratch directory that lives as long as the process (files are rewritten for each input).
fn scratch() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| tempfile::Builder::new().prefix("ecm-lcd-fuzz").tempdir().expect("scratch dir")).path()
}

/// Writes `bytes` to `name` in the scratch directory (removing what SQLite may have left beside it).
fn write(name: &str, bytes: &[u8]) -> PathBuf {
    for suffix in ["-wal", "-shm", "-journal"] {
        let _ = std::fs::remove_file(scratch().join(format!("{name}{suffix}")));
    }
    let path = scratch().join(name);
    std::fs::write(&path, bytes).expect("writing the scratch file");
    path
}

/// Reads the first frames of a source (each one decoded), as a replay would, up to the first error.
fn drain<S: Iterator<Item = anyhow::Result<ecm_lcd::types::Frame>>>(source: anyhow::Result<S>) {
    if let Ok(source) = source {
        for frame in source.take(8) {
            if frame.is_err() {
                break;
            }
        }
    }
}

/// The bytes as a ROS 1 bag file, read with its only image topic.
pub fn ros1_bag(data: &[u8]) {
    let path = write("input.bag", data);
    drain(ecm_lcd::io::open_source(&path, None));
}

/// The bytes as a ROS 2 sqlite3 bag file (`.db3`).
pub fn ros2_sqlite(data: &[u8]) {
    let path = write("input.db3", data);
    drain(ecm_lcd::io::open_source(&path, None));
}

/// The bytes as an MCAP file.
pub fn mcap(data: &[u8]) {
    let path = write("input.mcap", data);
    drain(ecm_lcd::io::open_source(&path, None));
}

/// A TUM folder: the bytes up to the first NUL are `rgb.txt`, the rest `groundtruth.txt`; one real
/// image `a.png` lies in the folder for `rgb.txt` to name.
pub fn tum(data: &[u8]) {
    static IMAGE: std::sync::Once = std::sync::Once::new();
    IMAGE.call_once(|| {
        image::RgbImage::from_pixel(4, 3, image::Rgb([10, 20, 30])).save(scratch().join("a.png")).expect("a.png");
    });
    let (rgb, truth) = match data.iter().position(|&b| b == 0) {
        Some(at) => (&data[..at], &data[at + 1..]),
        None => (data, &[][..]),
    };
    write("rgb.txt", rgb);
    let truth_path = write("groundtruth.txt", truth);
    drain(ecm_lcd::io::tum::ImageFilesSource::open_tum(scratch()));
    let _ = ecm_lcd::io::tum::read_groundtruth(&truth_path);
}

/// A TFLite flatbuffer: parsed, then imported as MobileNetV2 weights.
pub fn tflite(data: &[u8]) {
    if ecm_lcd::model::weights::tflite::TfModel::parse(data).is_ok() {
        let _ = ecm_lcd::model::weights::import::import_tflite_bytes(data);
    }
}

/// A safetensors weights file: loaded, then built into the network.
pub fn safetensors(data: &[u8]) {
    if let Ok(weights) = ecm_lcd::model::weights::Weights::from_bytes(data) {
        let _ = weights.network(false);
    }
}

/// A ROS 2 params YAML file (`--params-file`) for the node `/ecm_lcd`.
pub fn params_yaml(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = ecm_lcd::config::Params::from_yaml_str(text, "/ecm_lcd");
    }
}
