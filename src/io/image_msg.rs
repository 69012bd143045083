//! ROS image messages (`sensor_msgs/Image`, `sensor_msgs/CompressedImage`) to and from
//! [`image::RgbImage`], the calibration beside them (`sensor_msgs/CameraInfo`), and their two wire formats: ROS 1 serialisation (little-endian, no
//! alignment, u32-length-prefixed strings and arrays, `uint32 seq` first in the header) and
//! ROS 2 CDR (4-byte encapsulation header, then aligned little- or big-endian data).
//!
//! Interpretations written down once:
//! - `mono16` becomes 8-bit grey by `round(v * 255 / 65535)`, then replicated to R, G and B;
//!   `mono8` is replicated as is.
//! - Alpha of `rgba8`/`bgra8` is dropped (not blended).
//! - A `CompressedImage` `format` names its codec anywhere in the string, as
//!   compressed_image_transport writes it (`"jpeg"`, `"png"`, `"rgb8; jpeg compressed bgr8"`);
//!   the decoded JPEG/PNG is already in true colour order, so no channel swap follows.
//!   `compressedDepth` payloads are depth maps, not camera images, and are refused.
//! - ROS 1 `time` seconds are unsigned; they are kept bit for bit in the `i32` of
//!   `builtin_interfaces/Time`, so ROS 1 stamps after 2038-01-19 would read as negative.

use anyhow::{bail, ensure, Context, Result};
use byteorder::{BigEndian, LittleEndian};
use image::RgbImage;

use super::msgs::{CameraInfo, CompressedImage, Header, Image, RegionOfInterest};
use crate::types::Stamp;
use crate::verification::Intrinsics;

/// The two image message types a source can carry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageKind {
    Raw,
    Compressed,
}

impl ImageKind {
    /// Recognises ROS 1 (`sensor_msgs/Image`) and ROS 2 (`sensor_msgs/msg/Image`) type names.
    pub fn from_type_name(type_name: &str) -> Option<ImageKind> {
        match type_name {
            "sensor_msgs/Image" | "sensor_msgs/msg/Image" => Some(ImageKind::Raw),
            "sensor_msgs/CompressedImage" | "sensor_msgs/msg/CompressedImage" => Some(ImageKind::Compressed),
            _ => None,
        }
    }

    pub fn ros1_type(self) -> &'static str {
        match self {
            ImageKind::Raw => "sensor_msgs/Image",
            ImageKind::Compressed => "sensor_msgs/CompressedImage",
        }
    }

    pub fn ros2_type(self) -> &'static str {
        match self {
            ImageKind::Raw => "sensor_msgs/msg/Image",
            ImageKind::Compressed => "sensor_msgs/msg/CompressedImage",
        }
    }
}

/// `sensor_msgs/RegionOfInterest`'s definition, the same in ROS 1 and ROS 2 (bags carry it).
pub const REGION_OF_INTEREST_DEFINITION: &str =
    "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n";

/// What a topic of a bag this crate writes carries: images, or the calibration beside them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WrittenKind {
    Image(ImageKind),
    CameraInfo,
}

impl WrittenKind {
    pub fn ros1_type(self) -> &'static str {
        match self {
            WrittenKind::Image(kind) => kind.ros1_type(),
            WrittenKind::CameraInfo => "sensor_msgs/CameraInfo",
        }
    }

    pub fn ros2_type(self) -> &'static str {
        match self {
            WrittenKind::Image(kind) => kind.ros2_type(),
            WrittenKind::CameraInfo => "sensor_msgs/msg/CameraInfo",
        }
    }
}

/// The topics of a bag of `frames` on `image_topic` and, where `camera` is given, a `CameraInfo`
/// beside each frame on its `camera_info` topic (image_transport's naming, as the readers look for
/// it: [`crate::io::camera_info_topic`]).
pub fn written_topics(
    image_topic: &str,
    encoding: WireEncoding,
    camera: Option<&Intrinsics>,
) -> Vec<(String, WrittenKind)> {
    let mut topics = vec![(image_topic.to_string(), WrittenKind::Image(encoding.kind()))];
    if camera.is_some() {
        topics.push((super::camera_info_topic_name(image_topic), WrittenKind::CameraInfo));
    }
    topics
}

/// One message of a bag this crate writes, of either kind.
pub enum WrittenMessage {
    Image(ImageMessage),
    CameraInfo(Box<CameraInfo>),
}

impl WrittenMessage {
    pub fn to_ros1(&self, seq: u32) -> Vec<u8> {
        match self {
            WrittenMessage::Image(image) => image.to_ros1(seq),
            WrittenMessage::CameraInfo(info) => info.to_ros1(seq),
        }
    }

    pub fn to_cdr(&self) -> Result<Vec<u8>> {
        match self {
            WrittenMessage::Image(image) => image.to_cdr(),
            WrittenMessage::CameraInfo(info) => {
                with_encapsulation(cdr_encoding::to_vec::<_, LittleEndian>(info.as_ref()))
            }
        }
    }
}

/// The messages of `frames` for the topics [`written_topics`] gives: each frame's image, then its
/// calibration where `camera` is given, with the topic's index.
pub fn written_messages<'a>(
    frames: impl IntoIterator<Item = (Stamp, RgbImage)> + 'a,
    encoding: WireEncoding,
    camera: Option<&'a Intrinsics>,
) -> impl Iterator<Item = Result<(usize, Stamp, WrittenMessage)>> + 'a {
    frames.into_iter().flat_map(move |(stamp, image)| {
        let info = camera.map(|camera| camera_info_message(stamp, "camera", [image.width(), image.height()], camera));
        let image = encode_image(stamp, "camera", &image, encoding).map(|m| (0, stamp, WrittenMessage::Image(m)));
        std::iter::once(image).chain(info.map(|info| Ok((1, stamp, WrittenMessage::CameraInfo(Box::new(info))))))
    })
}

/// The `sensor_msgs/CameraInfo` of a pinhole camera without distortion whose images are `size`
/// (`intrinsics` scaled to it where they describe another size), stamped like its image.
pub fn camera_info_message(stamp: Stamp, frame_id: &str, size: [u32; 2], intrinsics: &Intrinsics) -> CameraInfo {
    let at = intrinsics.for_image(size).unwrap_or(*intrinsics);
    let (fx, fy, cx, cy) = (at.fx, at.fy, at.cx, at.cy);
    CameraInfo {
        header: Header { stamp: stamp.into(), frame_id: frame_id.into() },
        width: size[0],
        height: size[1],
        distortion_model: "plumb_bob".into(),
        d: vec![0.0; 5],
        k: [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        binning_x: 0,
        binning_y: 0,
        roi: RegionOfInterest::default(),
    }
}

impl CameraInfo {
    /// Serialises to ROS 1 bytes; `seq` goes into the ROS 1 header.
    pub fn to_ros1(&self, seq: u32) -> Vec<u8> {
        let mut out = Vec::new();
        put_ros1_header(&mut out, &self.header, seq);
        out.extend_from_slice(&self.height.to_le_bytes());
        out.extend_from_slice(&self.width.to_le_bytes());
        put_ros1_bytes(&mut out, self.distortion_model.as_bytes());
        out.extend_from_slice(&(self.d.len() as u32).to_le_bytes());
        for v in self.d.iter().chain(&self.k).chain(&self.r).chain(&self.p) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let roi = &self.roi;
        for v in [self.binning_x, self.binning_y, roi.x_offset, roi.y_offset, roi.height, roi.width] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.push(roi.do_rectify as u8);
        out
    }
}

/// A decoded-from-the-wire image message of either kind.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ImageMessage {
    Raw(Image),
    Compressed(CompressedImage),
}

impl ImageMessage {
    pub fn kind(&self) -> ImageKind {
        match self {
            ImageMessage::Raw(_) => ImageKind::Raw,
            ImageMessage::Compressed(_) => ImageKind::Compressed,
        }
    }

    pub fn header(&self) -> &Header {
        match self {
            ImageMessage::Raw(m) => &m.header,
            ImageMessage::Compressed(m) => &m.header,
        }
    }

    /// The header stamp.
    pub fn stamp(&self) -> Stamp {
        self.header().stamp.into()
    }

    /// Decodes the pixels to 8-bit RGB.
    pub fn to_rgb(&self) -> Result<RgbImage> {
        match self {
            ImageMessage::Raw(m) => decode_image(m),
            ImageMessage::Compressed(m) => decode_compressed_image(m),
        }
    }

    /// Parses ROS 1 serialised bytes of the given kind.
    pub fn from_ros1(kind: ImageKind, bytes: &[u8]) -> Result<ImageMessage> {
        let mut reader = Ros1Reader { bytes, pos: 0 };
        let header = reader.header()?;
        let message = match kind {
            ImageKind::Raw => ImageMessage::Raw(Image {
                header,
                height: reader.u32()?,
                width: reader.u32()?,
                encoding: reader.string()?,
                is_bigendian: reader.u8()?,
                step: reader.u32()?,
                data: reader.byte_array()?,
            }),
            ImageKind::Compressed => ImageMessage::Compressed(CompressedImage {
                header,
                format: reader.string()?,
                data: reader.byte_array()?,
            }),
        };
        ensure!(
            reader.pos == bytes.len(),
            "{} bytes left over after the {} message ({} bytes)",
            bytes.len() - reader.pos,
            kind.ros1_type(),
            bytes.len()
        );
        Ok(message)
    }

    /// Serialises to ROS 1 bytes; `seq` goes into the ROS 1 header.
    pub fn to_ros1(&self, seq: u32) -> Vec<u8> {
        let mut out = Vec::new();
        put_ros1_header(&mut out, self.header(), seq);
        match self {
            ImageMessage::Raw(m) => {
                out.extend_from_slice(&m.height.to_le_bytes());
                out.extend_from_slice(&m.width.to_le_bytes());
                put_ros1_bytes(&mut out, m.encoding.as_bytes());
                out.push(m.is_bigendian);
                out.extend_from_slice(&m.step.to_le_bytes());
                put_ros1_bytes(&mut out, &m.data);
            }
            ImageMessage::Compressed(m) => {
                put_ros1_bytes(&mut out, m.format.as_bytes());
                put_ros1_bytes(&mut out, &m.data);
            }
        }
        out
    }

    /// Parses a CDR payload (with its 4-byte encapsulation header) of the given kind.
    pub fn from_cdr(kind: ImageKind, bytes: &[u8]) -> Result<ImageMessage> {
        let message = match kind {
            ImageKind::Raw => parse_cdr(bytes).map(ImageMessage::Raw),
            ImageKind::Compressed => parse_cdr(bytes).map(ImageMessage::Compressed),
        };
        message.with_context(|| format!("{} CDR message of {} bytes", kind.ros2_type(), bytes.len()))
    }

    /// Serialises to little-endian CDR with the encapsulation header, as rosbag2 stores it.
    pub fn to_cdr(&self) -> Result<Vec<u8>> {
        with_encapsulation(match self {
            ImageMessage::Raw(m) => cdr_encoding::to_vec::<_, LittleEndian>(m),
            ImageMessage::Compressed(m) => cdr_encoding::to_vec::<_, LittleEndian>(m),
        })
    }
}

/// A little-endian CDR body behind its 4-byte encapsulation header, as rosbag2 stores messages.
fn with_encapsulation<E: std::fmt::Display>(body: std::result::Result<Vec<u8>, E>) -> Result<Vec<u8>> {
    let body = body.map_err(|e| anyhow::anyhow!("CDR serialisation failed: {e}"))?;
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&[0, 1, 0, 0]);
    out.extend_from_slice(&body);
    Ok(out)
}

/// A ROS 1 `std_msgs/Header`: `seq`, the stamp (seconds as `uint32`), the frame id.
fn put_ros1_header(out: &mut Vec<u8>, header: &Header, seq: u32) {
    out.extend_from_slice(&seq.to_le_bytes());
    out.extend_from_slice(&(header.stamp.sec as u32).to_le_bytes());
    out.extend_from_slice(&header.stamp.nanosec.to_le_bytes());
    put_ros1_bytes(out, header.frame_id.as_bytes());
}

/// Parses a CDR payload: its 4-byte encapsulation header, then the message.
fn parse_cdr<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T> {
    ensure!(bytes.len() >= 4, "CDR payload of {} bytes is shorter than its 4-byte header", bytes.len());
    let body = &bytes[4..];
    let parsed = match bytes[..2] {
        [0, 0] => cdr_encoding::from_bytes::<T, BigEndian>(body),
        [0, 1] => cdr_encoding::from_bytes::<T, LittleEndian>(body),
        [a, b] => bail!("unsupported CDR encapsulation {a:#04x} {b:#04x} (expected plain CDR, 00 00 or 00 01)"),
        _ => unreachable!("slice of two"),
    };
    Ok(parsed.map_err(|e| anyhow::anyhow!("{e}"))?.0)
}

/// `sensor_msgs/CameraInfo` from ROS 1 serialised bytes (the ROS 2 layout, with `uint32 seq` in the
/// header).
pub fn camera_info_from_ros1(bytes: &[u8]) -> Result<CameraInfo> {
    let mut reader = Ros1Reader { bytes, pos: 0 };
    let header = reader.header()?;
    let (height, width, distortion_model) = (reader.u32()?, reader.u32()?, reader.string()?);
    let d_len = reader.u32()? as usize;
    let d = (0..d_len).map(|_| reader.f64()).collect::<Result<Vec<f64>>>()?;
    let k = reader.f64_array::<9>()?;
    let r = reader.f64_array::<9>()?;
    let p = reader.f64_array::<12>()?;
    let (binning_x, binning_y) = (reader.u32()?, reader.u32()?);
    let roi = RegionOfInterest {
        x_offset: reader.u32()?,
        y_offset: reader.u32()?,
        height: reader.u32()?,
        width: reader.u32()?,
        do_rectify: reader.u8()? != 0,
    };
    ensure!(
        reader.pos == bytes.len(),
        "{} bytes left over after the sensor_msgs/CameraInfo message",
        bytes.len() - reader.pos
    );
    Ok(CameraInfo { header, height, width, distortion_model, d, k, r, p, binning_x, binning_y, roi })
}

/// `sensor_msgs/CameraInfo` from a CDR payload.
pub fn camera_info_from_cdr(bytes: &[u8]) -> Result<CameraInfo> {
    parse_cdr(bytes).with_context(|| format!("sensor_msgs/msg/CameraInfo CDR message of {} bytes", bytes.len()))
}

fn put_ros1_bytes(out: &mut Vec<u8>, bytes: &[u8]) {
    out.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(bytes);
}

/// Cursor over ROS 1 serialised bytes; every read checks the remaining length.
struct Ros1Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Ros1Reader<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&end| end <= self.bytes.len()).with_context(|| {
            format!(
                "message truncated: {what} needs {n} bytes at offset {}, only {} left",
                self.pos,
                self.bytes.len() - self.pos
            )
        })?;
        let slice = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(slice)
    }

    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1, "uint8")?[0])
    }

    fn u32(&mut self) -> Result<u32> {
        let b = self.take(4, "uint32")?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn f64(&mut self) -> Result<f64> {
        let b = self.take(8, "float64")?;
        Ok(f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
    }

    fn f64_array<const N: usize>(&mut self) -> Result<[f64; N]> {
        let mut values = [0.0; N];
        for v in &mut values {
            *v = self.f64()?;
        }
        Ok(values)
    }

    fn byte_array(&mut self) -> Result<Vec<u8>> {
        let len = self.u32()? as usize;
        Ok(self.take(len, "uint8[] data")?.to_vec())
    }

    fn string(&mut self) -> Result<String> {
        let len = self.u32()? as usize;
        let at = self.pos;
        let bytes = self.take(len, "string")?;
        String::from_utf8(bytes.to_vec()).with_context(|| format!("string at offset {at} is not UTF-8"))
    }

    fn header(&mut self) -> Result<Header> {
        let _seq = self.u32()?;
        let sec = self.u32()?;
        let nanosec = self.u32()?;
        let frame_id = self.string()?;
        // ROS 1 time is unsigned; keep it in the i32 of builtin_interfaces/Time bit for bit.
        Ok(Header { stamp: super::msgs::Time { sec: sec as i32, nanosec }, frame_id })
    }
}

/// Bytes per pixel of the raw encodings we decode.
fn bytes_per_pixel(encoding: &str) -> Option<usize> {
    match encoding {
        "rgb8" | "bgr8" => Some(3),
        "rgba8" | "bgra8" => Some(4),
        "mono8" => Some(1),
        "mono16" => Some(2),
        _ => None,
    }
}

/// Decodes a raw `sensor_msgs/Image` to RGB (see the module doc for the conversions).
pub fn decode_image(msg: &Image) -> Result<RgbImage> {
    let encoding = msg.encoding.as_str();
    let bpp = bytes_per_pixel(encoding).with_context(|| match encoding {
        // A depth topic taken for the colour one (the ROS depth encodings, REP 118).
        "16UC1" | "32FC1" => format!(
            "image encoding {encoding:?} is a depth image's: this topic carries depth, not the colour images \
             to describe (give it as the depth topic: --depth-topic, or the node's `depth`)"
        ),
        _ => format!("unsupported image encoding {encoding:?} (supported: rgb8, bgr8, rgba8, bgra8, mono8, mono16)"),
    })?;
    let (row_bytes, step) = checked_layout(msg, bpp, &format!("{encoding} image"))?;
    let (width, height) = (msg.width as usize, msg.height as usize);
    let big_endian = msg.is_bigendian != 0;
    let mut out = Vec::with_capacity(width * height * 3);
    for row in msg.data.chunks_exact(step) {
        let pixels = &row[..row_bytes];
        match encoding {
            "rgb8" => out.extend_from_slice(pixels),
            "bgr8" => pixels.chunks_exact(3).for_each(|p| out.extend_from_slice(&[p[2], p[1], p[0]])),
            "rgba8" => pixels.chunks_exact(4).for_each(|p| out.extend_from_slice(&p[..3])),
            "bgra8" => pixels.chunks_exact(4).for_each(|p| out.extend_from_slice(&[p[2], p[1], p[0]])),
            "mono8" => pixels.iter().for_each(|&v| out.extend_from_slice(&[v, v, v])),
            "mono16" => pixels.chunks_exact(2).for_each(|p| {
                let v = if big_endian { u16::from_be_bytes([p[0], p[1]]) } else { u16::from_le_bytes([p[0], p[1]]) };
                let g = mono16_to_8(v);
                out.extend_from_slice(&[g, g, g]);
            }),
            _ => unreachable!("checked by bytes_per_pixel"),
        }
    }
    RgbImage::from_raw(msg.width, msg.height, out).context("pixel buffer size (internal)")
}

/// The bytes of one row of `msg`'s pixels and its step, checked against the size and the data
/// (`what` names the image in errors, e.g. "rgb8 image").
pub(crate) fn checked_layout(msg: &Image, bytes_per_pixel: usize, what: &str) -> Result<(usize, usize)> {
    let (width, height) = (msg.width as usize, msg.height as usize);
    ensure!(width > 0 && height > 0, "empty {what} ({width}x{height})");
    let row_bytes = width.checked_mul(bytes_per_pixel).context("image width overflows")?;
    let step = msg.step as usize;
    ensure!(
        step >= row_bytes,
        "{what} {width}x{height}: step {step} is smaller than width*{bytes_per_pixel} = {row_bytes}"
    );
    let expected = step.checked_mul(height).context("image size overflows")?;
    ensure!(
        msg.data.len() == expected,
        "{what} {width}x{height}: data has {} bytes but step*height = {step}*{height} = {expected}",
        msg.data.len()
    );
    Ok((row_bytes, step))
}

/// `round(v * 255 / 65535)`.
pub fn mono16_to_8(v: u16) -> u8 {
    ((v as u32 * 255 + 32767) / 65535) as u8
}

/// The codec named by a `CompressedImage.format` string.
fn compressed_codec(format: &str) -> Result<image::ImageFormat> {
    let lower = format.to_ascii_lowercase();
    if lower.contains("compresseddepth") {
        bail!("CompressedImage format {format:?} is a compressed depth map, not a camera image");
    }
    if lower.contains("jpeg") || lower.contains("jpg") {
        Ok(image::ImageFormat::Jpeg)
    } else if lower.contains("png") {
        Ok(image::ImageFormat::Png)
    } else {
        bail!("unsupported CompressedImage format {format:?} (supported: jpeg, png)")
    }
}

/// An `image` crate error as one message. Its decoding errors display their cause and also
/// return it as their source, so an error chain would say the cause twice ("Invalid PNG
/// signature.: Invalid PNG signature."); the source is kept only where the message lacks it.
pub fn image_error(error: image::ImageError) -> anyhow::Error {
    use std::error::Error as _;
    let message = error.to_string();
    match error.source().map(|s| s.to_string()) {
        Some(source) if !message.contains(&source) => anyhow::anyhow!("{message}: {source}"),
        _ => anyhow::anyhow!(message),
    }
}

/// Decodes a `sensor_msgs/CompressedImage` (JPEG or PNG) to RGB.
pub fn decode_compressed_image(msg: &CompressedImage) -> Result<RgbImage> {
    let codec = compressed_codec(&msg.format)?;
    let decoded = image::load_from_memory_with_format(&msg.data, codec).map_err(image_error).with_context(|| {
        format!("CompressedImage format {:?}: {} bytes do not decode as {codec:?}", msg.format, msg.data.len())
    })?;
    // `into_rgb8` hands over an rgb8 decode without copying it (JPEG colour images are rgb8).
    Ok(decoded.into_rgb8())
}

/// The pixel encodings our writers can produce (the inverse of the decoders above).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WireEncoding {
    Rgb8,
    Bgr8,
    Rgba8,
    Bgra8,
    /// Luma (ITU-R BT.601, as `image` computes it).
    Mono8,
    /// Luma scaled to 16 bits (`v * 257`).
    Mono16 {
        big_endian: bool,
    },
    /// `CompressedImage` with format "jpeg" at the given quality.
    Jpeg {
        quality: u8,
    },
    /// `CompressedImage` with format "png".
    Png,
}

impl WireEncoding {
    pub fn kind(self) -> ImageKind {
        match self {
            WireEncoding::Jpeg { .. } | WireEncoding::Png => ImageKind::Compressed,
            _ => ImageKind::Raw,
        }
    }
}

/// Builds the message that carries `image` in `encoding`, stamped `stamp`.
pub fn encode_image(stamp: Stamp, frame_id: &str, image: &RgbImage, encoding: WireEncoding) -> Result<ImageMessage> {
    let header = Header { stamp: stamp.into(), frame_id: frame_id.to_string() };
    let (width, height) = image.dimensions();
    let raw = |name: &str, bpp: u32, data: Vec<u8>, is_bigendian: u8| {
        ImageMessage::Raw(Image {
            header: header.clone(),
            height,
            width,
            encoding: name.to_string(),
            is_bigendian,
            step: width * bpp,
            data,
        })
    };
    let pixels = image.pixels();
    let luma = || image::DynamicImage::ImageRgb8(image.clone()).to_luma8().into_raw();
    Ok(match encoding {
        WireEncoding::Rgb8 => raw("rgb8", 3, image.as_raw().clone(), 0),
        WireEncoding::Bgr8 => raw("bgr8", 3, pixels.flat_map(|p| [p[2], p[1], p[0]]).collect(), 0),
        WireEncoding::Rgba8 => raw("rgba8", 4, pixels.flat_map(|p| [p[0], p[1], p[2], 255]).collect(), 0),
        WireEncoding::Bgra8 => raw("bgra8", 4, pixels.flat_map(|p| [p[2], p[1], p[0], 255]).collect(), 0),
        WireEncoding::Mono8 => raw("mono8", 1, luma(), 0),
        WireEncoding::Mono16 { big_endian } => {
            let data = luma()
                .into_iter()
                .flat_map(|v| {
                    let wide = v as u16 * 257;
                    if big_endian {
                        wide.to_be_bytes()
                    } else {
                        wide.to_le_bytes()
                    }
                })
                .collect();
            raw("mono16", 2, data, big_endian as u8)
        }
        WireEncoding::Jpeg { quality } => ImageMessage::Compressed(CompressedImage {
            header,
            format: "jpeg".to_string(),
            data: encode_jpeg(image, quality)?,
        }),
        WireEncoding::Png => {
            let mut data = Vec::new();
            image
                .write_to(&mut std::io::Cursor::new(&mut data), image::ImageFormat::Png)
                .context("PNG encoding failed")?;
            ImageMessage::Compressed(CompressedImage { header, format: "png".to_string(), data })
        }
    })
}

/// JPEG bytes of `image` at `quality` (1-100).
pub fn encode_jpeg(image: &RgbImage, quality: u8) -> Result<Vec<u8>> {
    let mut data = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut data, quality.clamp(1, 100))
        .encode_image(image)
        .context("JPEG encoding failed")?;
    Ok(data)
}

/// `sensor_msgs/Image` with encoding rgb8 (what the ROS 2 publisher sends).
pub fn rgb8_message(stamp: Stamp, frame_id: &str, image: &RgbImage) -> Image {
    Image {
        header: Header { stamp: stamp.into(), frame_id: frame_id.to_string() },
        height: image.height(),
        width: image.width(),
        encoding: "rgb8".to_string(),
        is_bigendian: 0,
        step: image.width() * 3,
        data: image.as_raw().clone(),
    }
}

/// `sensor_msgs/CompressedImage` with format "jpeg".
pub fn jpeg_message(stamp: Stamp, frame_id: &str, image: &RgbImage, quality: u8) -> Result<CompressedImage> {
    Ok(CompressedImage {
        header: Header { stamp: stamp.into(), frame_id: frame_id.to_string() },
        format: "jpeg".to_string(),
        data: encode_jpeg(image, quality)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_info_reads_from_both_wire_formats() {
        let info = CameraInfo {
            header: Header { stamp: super::super::msgs::Time { sec: 5, nanosec: 7 }, frame_id: "rgb".into() },
            height: 480,
            width: 640,
            distortion_model: "plumb_bob".into(),
            d: vec![0.25, -0.5, 0.0, 0.0, 1.0],
            k: [525.0, 0.0, 319.5, 0.0, 526.0, 239.5, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [525.0, 0.0, 319.5, 0.0, 0.0, 526.0, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0],
            binning_x: 1,
            binning_y: 2,
            roi: RegionOfInterest { x_offset: 1, y_offset: 2, height: 3, width: 4, do_rectify: true },
        };
        let mut cdr = vec![0, 1, 0, 0];
        cdr.extend(cdr_encoding::to_vec::<_, LittleEndian>(&info).unwrap());
        assert_eq!(camera_info_from_cdr(&cdr).unwrap(), info);
        // ROS 1: `uint32 seq` first, then the same fields unaligned; `float64[]` carries a length.
        let mut ros1 = Vec::new();
        for v in [9u32, 5, 7] {
            ros1.extend(v.to_le_bytes());
        }
        put_ros1_bytes(&mut ros1, b"rgb");
        ros1.extend(480u32.to_le_bytes());
        ros1.extend(640u32.to_le_bytes());
        put_ros1_bytes(&mut ros1, b"plumb_bob");
        ros1.extend(5u32.to_le_bytes());
        for v in info.d.iter().chain(&info.k).chain(&info.r).chain(&info.p) {
            ros1.extend(v.to_le_bytes());
        }
        for v in [1u32, 2, 1, 2, 3, 4] {
            ros1.extend(v.to_le_bytes());
        }
        ros1.push(1);
        assert_eq!(camera_info_from_ros1(&ros1).unwrap(), info);
        for cut in [0, 20, ros1.len() - 1] {
            assert!(camera_info_from_ros1(&ros1[..cut]).is_err(), "cut at {cut}");
        }
        let err = camera_info_from_ros1(&[ros1.as_slice(), &[0]].concat()).unwrap_err().to_string();
        assert!(err.contains("1 bytes left over"), "{err}");
        // The images are the region of interest binned (1 by 2): the principal point moves by the
        // offsets, and the vertical values halve.
        let expected =
            crate::verification::Intrinsics { fx: 525.0, fy: 263.0, cx: 318.5, cy: 118.75, size: Some([4, 1]) };
        assert_eq!(info.intrinsics(), Some(expected));
        assert_eq!(info.image_size(), Some([4, 1]));
        let whole = CameraInfo { binning_x: 0, binning_y: 0, roi: RegionOfInterest::default(), ..info.clone() };
        let plain =
            crate::verification::Intrinsics { fx: 525.0, fy: 526.0, cx: 319.5, cy: 239.5, size: Some([640, 480]) };
        assert_eq!((whole.intrinsics(), whole.image_size()), (Some(plain), Some([640, 480])));
        assert_eq!(CameraInfo { width: 0, height: 0, ..whole }.image_size(), None);
        let uncalibrated = CameraInfo { k: [0.0; 9], ..info };
        assert_eq!(uncalibrated.intrinsics(), None);
    }

    fn test_image() -> RgbImage {
        RgbImage::from_fn(5, 3, |x, y| image::Rgb([(x * 40) as u8, (y * 70) as u8, (x * 10 + y * 5 + 3) as u8]))
    }

    fn raw(encoding: &str, width: u32, height: u32, step: u32, data: Vec<u8>, big: u8) -> Image {
        Image { header: Header::default(), height, width, encoding: encoding.into(), is_bigendian: big, step, data }
    }

    #[test]
    fn every_raw_encoding_round_trips_through_both_wire_formats() {
        let img = test_image();
        let stamp = Stamp::from_sec_nsec(1341847980, 722_988_000);
        for enc in [WireEncoding::Rgb8, WireEncoding::Bgr8, WireEncoding::Rgba8, WireEncoding::Bgra8] {
            let msg = encode_image(stamp, "cam", &img, enc).unwrap();
            let ros1 = ImageMessage::from_ros1(ImageKind::Raw, &msg.to_ros1(7)).unwrap();
            let cdr = ImageMessage::from_cdr(ImageKind::Raw, &msg.to_cdr().unwrap()).unwrap();
            assert_eq!(ros1, msg);
            assert_eq!(cdr, msg);
            assert_eq!(cdr.stamp(), stamp);
            assert_eq!(cdr.to_rgb().unwrap(), img, "{enc:?}");
        }
        let grey = image::DynamicImage::ImageRgb8(img.clone()).to_luma8();
        for enc in
            [WireEncoding::Mono8, WireEncoding::Mono16 { big_endian: false }, WireEncoding::Mono16 { big_endian: true }]
        {
            let msg = encode_image(stamp, "cam", &img, enc).unwrap();
            let back = ImageMessage::from_cdr(ImageKind::Raw, &msg.to_cdr().unwrap()).unwrap().to_rgb().unwrap();
            for (p, g) in back.pixels().zip(grey.pixels()) {
                assert_eq!(p.0, [g[0]; 3], "{enc:?}");
            }
        }
    }

    #[test]
    fn step_padding_is_skipped_and_mono16_byte_order_is_honoured() {
        // 2x2 bgr8 with two bytes of padding per row.
        let data = vec![1, 2, 3, 4, 5, 6, 0xEE, 0xEE, 7, 8, 9, 10, 11, 12, 0xEE, 0xEE];
        let img = decode_image(&raw("bgr8", 2, 2, 8, data, 0)).unwrap();
        assert_eq!(img.as_raw(), &vec![3, 2, 1, 6, 5, 4, 9, 8, 7, 12, 11, 10]);
        let big = decode_image(&raw("mono16", 1, 1, 2, vec![0xFF, 0x00], 1)).unwrap();
        let little = decode_image(&raw("mono16", 1, 1, 2, vec![0xFF, 0x00], 0)).unwrap();
        assert_eq!(big.as_raw(), &vec![254, 254, 254]); // 0xFF00 = 65280 -> 254.0
        assert_eq!(little.as_raw(), &vec![1, 1, 1]); // 0x00FF = 255 -> 0.99
    }

    #[test]
    fn inconsistent_raw_images_are_errors() {
        let err = decode_image(&raw("rgb8", 2, 2, 6, vec![0; 11], 0)).unwrap_err().to_string();
        assert!(err.contains("data has 11 bytes but step*height = 6*2 = 12"), "{err}");
        let err = decode_image(&raw("rgb8", 2, 2, 5, vec![0; 10], 0)).unwrap_err().to_string();
        assert!(err.contains("step 5 is smaller than width*3 = 6"), "{err}");
        let err = decode_image(&raw("yuv422", 2, 2, 4, vec![0; 8], 0)).unwrap_err().to_string();
        assert!(err.contains("unsupported image encoding \"yuv422\""), "{err}");
        let err = decode_image(&raw("16UC1", 2, 2, 4, vec![0; 8], 0)).unwrap_err().to_string();
        assert!(err.contains("is a depth image's") && err.contains("--depth-topic"), "{err}");
        let err = decode_image(&raw("mono8", u32::MAX, u32::MAX, u32::MAX, vec![], 0)).unwrap_err().to_string();
        assert!(err.contains("overflow") || err.contains("data has 0 bytes"), "{err}");
    }

    #[test]
    fn compressed_formats_decode_and_mismatches_are_errors() {
        let img = test_image();
        let stamp = Stamp::from_nanos(5);
        let png = encode_image(stamp, "", &img, WireEncoding::Png).unwrap();
        assert_eq!(ImageMessage::from_ros1(ImageKind::Compressed, &png.to_ros1(0)).unwrap().to_rgb().unwrap(), img);
        let jpeg = encode_image(stamp, "", &img, WireEncoding::Jpeg { quality: 95 }).unwrap();
        let ImageMessage::Compressed(mut jpeg) = jpeg else { panic!("compressed expected") };
        jpeg.format = "rgb8; jpeg compressed bgr8".into();
        let back = decode_compressed_image(&jpeg).unwrap();
        let max_diff = back.as_raw().iter().zip(img.as_raw()).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        assert!(max_diff < 30, "jpeg differs by {max_diff}");
        jpeg.format = "png".into();
        let err = format!("{:#}", decode_compressed_image(&jpeg).unwrap_err());
        assert!(err.contains("do not decode as Png"), "{err}");
        assert_eq!(err.matches("Invalid PNG signature").count(), 1, "the cause once: {err}");
        jpeg.format = "tiff".into();
        assert!(decode_compressed_image(&jpeg)
            .unwrap_err()
            .to_string()
            .contains("unsupported CompressedImage format \"tiff\""));
    }

    #[test]
    fn truncated_or_garbage_bytes_are_errors_not_panics() {
        let msg = encode_image(Stamp::from_nanos(1), "frame", &test_image(), WireEncoding::Rgb8).unwrap();
        let ros1 = msg.to_ros1(0);
        let cdr = msg.to_cdr().unwrap();
        for cut in 0..ros1.len() {
            assert!(ImageMessage::from_ros1(ImageKind::Raw, &ros1[..cut]).is_err());
        }
        for cut in 0..cdr.len() {
            assert!(ImageMessage::from_cdr(ImageKind::Raw, &cdr[..cut]).is_err());
        }
        let err = ImageMessage::from_ros1(ImageKind::Raw, &[0xFF; 64]).unwrap_err().to_string();
        assert!(err.contains("truncated"), "{err}");
        let err = format!("{:#}", ImageMessage::from_cdr(ImageKind::Raw, &[0, 7, 0, 0, 1]).unwrap_err());
        assert!(
            err.contains("sensor_msgs/msg/Image CDR message") && err.contains("unsupported CDR encapsulation"),
            "{err}"
        );
    }
}
