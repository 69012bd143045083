//! The `ecm_lcd_msgs` interface package (`msg/` in the repository) on the Rust side: serde structs whose
//! field names, types and order equal the `.msg` files (a test parses the files and checks), the
//! `geometry_msgs` pieces they use, and the ros2-client [`Message`] impls for every type the node sends
//! or receives. CDR follows the declaration order, so never reorder fields here without the `.msg`.

use ros2_client::{Message, MessageTypeName};
use serde::{Deserialize, Serialize};

use crate::io::msgs::{CameraInfo, CompressedImage, Header, Image, Time};
use crate::types::{self, Stamp};

/// The ROS package name of ecm-lcd's own messages.
pub const PACKAGE: &str = "ecm_lcd_msgs";

/// `msg/Keyframe.msg` and `msg/LoopCandidate.msg`, as shipped, for tools and the agreement test.
pub const KEYFRAME_MSG: &str = include_str!("../../msg/msg/Keyframe.msg");
pub const LOOP_CANDIDATE_MSG: &str = include_str!("../../msg/msg/LoopCandidate.msg");

/// `geometry_msgs/Point`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/Quaternion`. Note the ROS default is the identity (w = 1), unlike `Default` here,
/// which is only used when `has_pose` is false.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

/// `geometry_msgs/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

impl Pose {
    pub fn from_isometry(pose: &nalgebra::Isometry3<f64>) -> Pose {
        let (t, q) = (pose.translation.vector, pose.rotation);
        Pose { position: Point { x: t.x, y: t.y, z: t.z }, orientation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w } }
    }

    /// As an isometry; a zero quaternion (an unset orientation) is the identity.
    pub fn to_isometry(&self) -> nalgebra::Isometry3<f64> {
        let q = self.orientation;
        let quaternion = nalgebra::Quaternion::new(q.w, q.x, q.y, q.z);
        let rotation = if quaternion.norm() > 1e-12 {
            nalgebra::UnitQuaternion::from_quaternion(quaternion)
        } else {
            nalgebra::UnitQuaternion::identity()
        };
        let p = self.position;
        nalgebra::Isometry3::from_parts(nalgebra::Translation3::new(p.x, p.y, p.z), rotation)
    }
}

/// `diagnostic_msgs/KeyValue`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

/// `diagnostic_msgs/DiagnosticStatus`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// `OK` 0, `WARN` 1, `ERROR` 2, `STALE` 3 (a `byte` on the wire).
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    pub const OK: u8 = 0;
    pub const WARN: u8 = 1;
}

/// `diagnostic_msgs/DiagnosticArray`: what `/diagnostics` carries (rqt_runtime_monitor, the diagnostic
/// aggregator).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

/// `geometry_msgs/Vector3`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `std_msgs/ColorRGBA`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRgba {
    pub r: f32,
    pub g: f32,
    pub b: f32,
    pub a: f32,
}

/// `builtin_interfaces/Duration`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}

/// `visualization_msgs/UVCoordinate`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UvCoordinate {
    pub u: f32,
    pub v: f32,
}

/// `visualization_msgs/MeshFile`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MeshFile {
    pub filename: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `visualization_msgs/Marker` in the layout of ROS 2 Humble and later (with the texture and mesh
/// file fields); ecm-lcd fills only what a line list needs.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    pub header: Header,
    pub ns: String,
    pub id: i32,
    #[serde(rename = "type")]
    pub marker_type: i32,
    pub action: i32,
    pub pose: Pose,
    pub scale: Vector3,
    pub color: ColorRgba,
    pub lifetime: Duration,
    pub frame_locked: bool,
    pub points: Vec<Point>,
    pub colors: Vec<ColorRgba>,
    pub texture_resource: String,
    pub texture: CompressedImage,
    pub uv_coordinates: Vec<UvCoordinate>,
    pub text: String,
    pub mesh_resource: String,
    pub mesh_file: MeshFile,
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    /// `LINE_LIST`: each pair of points is one segment.
    pub const LINE_LIST: i32 = 5;
    pub const ADD: i32 = 0;
}

/// `visualization_msgs/MarkerArray`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    pub markers: Vec<Marker>,
}

/// The loop edges of `candidates` whose keyframes both have positions in the tracker's map frame
/// (`position_of`), as one RViz line-list marker per candidate in frame `frame_id`, stamped `stamp`.
/// Marker ids are the query id and rank folded into an `i32`, so a re-sent candidate replaces its line.
pub fn loop_edge_markers(
    candidates: &[types::LoopCandidate],
    position_of: impl Fn(u64) -> Option<Point>,
    frame_id: &str,
    stamp: Time,
) -> MarkerArray {
    let markers = candidates
        .iter()
        .filter_map(|c| {
            let (query, matched) = (position_of(c.query_id)?, position_of(c.match_id)?);
            // Verified loops green, appearance-only ones orange.
            let color = if c.verified.is_some() {
                ColorRgba { r: 0.1, g: 0.8, b: 0.2, a: 1.0 }
            } else {
                ColorRgba { r: 1.0, g: 0.6, b: 0.0, a: 1.0 }
            };
            Some(Marker {
                header: Header { stamp, frame_id: frame_id.to_string() },
                ns: "loop_edges".into(),
                id: ((c.query_id.wrapping_mul(16).wrapping_add(c.rank as u64)) & 0x7FFF_FFFF) as i32,
                marker_type: Marker::LINE_LIST,
                action: Marker::ADD,
                pose: Pose { orientation: Quaternion { w: 1.0, ..Default::default() }, ..Default::default() },
                scale: Vector3 { x: 0.02, ..Default::default() },
                color,
                points: vec![matched, query],
                ..Default::default()
            })
        })
        .collect();
    MarkerArray { markers }
}

/// `ecm_lcd_msgs/Keyframe`: a tracker's keyframe (see `msg/Keyframe.msg`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    pub header: Header,
    pub id: u64,
    pub image: Image,
    pub has_pose: bool,
    pub pose: Pose,
}

/// `ecm_lcd_msgs/LoopCandidate`: one candidate as published (see `msg/LoopCandidate.msg`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LoopCandidate {
    pub header: Header,
    pub query_id: u64,
    pub match_id: u64,
    pub match_stamp: Time,
    pub match_frame_id: String,
    pub distance: f32,
    pub score: f32,
    pub rank: u32,
    pub num_candidates: u32,
    #[serde(rename = "type")]
    pub loop_type: u8,
    pub descriptor_mode: String,
    pub inliers: u32,
    pub relative_pose: Pose,
    pub covariance: Covariance,
}

/// `float64[36]`: a 6x6 row-major covariance (CDR: 36 values, no length).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl From<nalgebra::Matrix6<f64>> for Covariance {
    /// Row-major, as ROS stores covariances.
    fn from(matrix: nalgebra::Matrix6<f64>) -> Self {
        Covariance(std::array::from_fn(|i| matrix[(i / 6, i % 6)]))
    }
}

impl Covariance {
    /// The matrix, unless this is [`Covariance::UNKNOWN`] (element 0 negative).
    pub fn estimate(&self) -> Option<nalgebra::Matrix6<f64>> {
        (self.0[0] >= 0.0).then(|| nalgebra::Matrix6::from_fn(|r, c| self.0[r * 6 + c]))
    }

    /// The ROS convention for "no estimate": element 0 is -1.
    pub const UNKNOWN: Covariance = {
        let mut values = [0.0; 36];
        values[0] = -1.0;
        Covariance(values)
    };
}

impl Default for Covariance {
    fn default() -> Self {
        Covariance([0.0; 36])
    }
}

impl Serialize for Covariance {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeTuple;
        let mut tuple = serializer.serialize_tuple(36)?;
        for value in &self.0 {
            tuple.serialize_element(value)?;
        }
        tuple.end()
    }
}

impl<'de> Deserialize<'de> for Covariance {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Values;
        impl<'de> serde::de::Visitor<'de> for Values {
            type Value = Covariance;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("36 float64 values")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Covariance, A::Error> {
                let mut values = [0.0; 36];
                for (i, value) in values.iter_mut().enumerate() {
                    *value = seq.next_element()?.ok_or_else(|| serde::de::Error::invalid_length(i, &self))?;
                }
                Ok(Covariance(values))
            }
        }
        deserializer.deserialize_tuple(36, Values)
    }
}

/// The messages for one keyframe's `candidates`, in order. `frame_of` gives a keyframe's frame id
/// (`current_frame` where unknown): a loop that temporal consistency reported late carries its own,
/// earlier keyframe's. `num_candidates` counts each query's ranks published so far.
pub fn candidate_messages<'a>(
    candidates: &[types::LoopCandidate],
    frame_of: impl Fn(u64) -> Option<&'a str>,
    current_frame: &'a str,
    descriptor_mode: &str,
) -> Vec<LoopCandidate> {
    candidates
        .iter()
        .map(|candidate| {
            let of_query = candidates.iter().filter(|c| c.query_id == candidate.query_id);
            let total = of_query.map(|c| c.rank + 1).max().unwrap_or(1);
            let query_frame = frame_of(candidate.query_id).unwrap_or(current_frame);
            let match_frame = frame_of(candidate.match_id).unwrap_or(current_frame);
            LoopCandidate::from_candidate(candidate, query_frame, match_frame, total, descriptor_mode)
        })
        .collect()
}

impl LoopCandidate {
    /// `TYPE_APPEARANCE`: appearance-only, not geometrically verified.
    pub const TYPE_APPEARANCE: u8 = 0;
    /// `TYPE_VERIFIED`: verified on local features, no relative pose (intrinsics unknown).
    pub const TYPE_VERIFIED: u8 = 1;
    /// `TYPE_VERIFIED_UP_TO_SCALE`: verified, with a relative pose whose translation is a unit direction.
    pub const TYPE_VERIFIED_UP_TO_SCALE: u8 = 2;
    /// `TYPE_VERIFIED_METRIC`: verified, with a metric relative pose (from depth).
    pub const TYPE_VERIFIED_METRIC: u8 = 3;

    /// The message for `candidate`, one of `num_candidates` found for its query.
    pub fn from_candidate(
        candidate: &types::LoopCandidate,
        query_frame_id: &str,
        match_frame_id: &str,
        num_candidates: u32,
        descriptor_mode: &str,
    ) -> Self {
        LoopCandidate {
            header: Header { stamp: candidate.query_stamp.into(), frame_id: query_frame_id.to_string() },
            query_id: candidate.query_id,
            match_id: candidate.match_id,
            match_stamp: candidate.match_stamp.into(),
            match_frame_id: match_frame_id.to_string(),
            distance: candidate.distance,
            score: candidate.score,
            rank: candidate.rank,
            num_candidates,
            loop_type: match candidate.verified {
                None => Self::TYPE_APPEARANCE,
                Some(types::Verified { pose: None, .. }) => Self::TYPE_VERIFIED,
                Some(types::Verified { pose: Some(pose), .. }) if pose.metric => Self::TYPE_VERIFIED_METRIC,
                Some(types::Verified { pose: Some(_), .. }) => Self::TYPE_VERIFIED_UP_TO_SCALE,
            },
            descriptor_mode: descriptor_mode.to_string(),
            inliers: candidate.verified.map_or(0, |v| v.inliers),
            relative_pose: candidate.verified.and_then(|v| v.pose).map_or(Pose::IDENTITY, |pose| pose.into()),
            covariance: candidate
                .verified
                .and_then(|v| v.pose)
                .and_then(|p| p.covariance)
                .map_or(Covariance::UNKNOWN, Covariance::from),
        }
    }

    /// Back to the library's candidate (drops the ROS-only fields).
    pub fn to_candidate(&self) -> types::LoopCandidate {
        types::LoopCandidate {
            query_id: self.query_id,
            query_stamp: Stamp::from(self.header.stamp),
            match_id: self.match_id,
            match_stamp: Stamp::from(self.match_stamp),
            distance: self.distance,
            score: self.score,
            rank: self.rank,
            verified: (self.loop_type != Self::TYPE_APPEARANCE).then(|| types::Verified {
                inliers: self.inliers,
                pose: (self.loop_type != Self::TYPE_VERIFIED).then(|| types::RelativePose {
                    metric: self.loop_type == Self::TYPE_VERIFIED_METRIC,
                    covariance: self.covariance.estimate(),
                    ..self.relative_pose.into()
                }),
            }),
        }
    }
}

impl Pose {
    /// No motion (what `relative_pose` holds when there is none).
    pub const IDENTITY: Pose =
        Pose { position: Point { x: 0.0, y: 0.0, z: 0.0 }, orientation: Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 } };
}

impl From<types::RelativePose> for Pose {
    fn from(pose: types::RelativePose) -> Self {
        let (t, q) = (pose.translation, pose.rotation);
        Pose { position: Point { x: t.x, y: t.y, z: t.z }, orientation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w } }
    }
}

impl From<Pose> for types::RelativePose {
    fn from(pose: Pose) -> Self {
        let (p, q) = (pose.position, pose.orientation);
        types::RelativePose {
            rotation: nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z)),
            translation: nalgebra::Vector3::new(p.x, p.y, p.z),
            metric: false,
            covariance: None,
        }
    }
}

impl Message for Keyframe {}
impl Message for LoopCandidate {}
impl Message for Image {}
impl Message for CompressedImage {}
impl Message for CameraInfo {}
impl Message for DiagnosticArray {}
impl Message for MarkerArray {}

/// ROS type names of the messages on ecm-lcd's topics.
pub fn keyframe_type() -> MessageTypeName {
    MessageTypeName::new(PACKAGE, "Keyframe")
}
pub fn loop_candidate_type() -> MessageTypeName {
    MessageTypeName::new(PACKAGE, "LoopCandidate")
}
pub fn image_type() -> MessageTypeName {
    MessageTypeName::new("sensor_msgs", "Image")
}
pub fn marker_array_type() -> MessageTypeName {
    MessageTypeName::new("visualization_msgs", "MarkerArray")
}
pub fn diagnostic_array_type() -> MessageTypeName {
    MessageTypeName::new("diagnostic_msgs", "DiagnosticArray")
}
pub fn camera_info_type() -> MessageTypeName {
    MessageTypeName::new("sensor_msgs", "CameraInfo")
}
pub fn compressed_image_type() -> MessageTypeName {
    MessageTypeName::new("sensor_msgs", "CompressedImage")
}

#[cfg(test)]
mod tests {
    //! The `.msg` files and the Rust structs must agree field by field. The `.msg` side is parsed here
    //! (nested types expanded from the official definitions of the standard messages we use); the Rust
    //! side is traced from the serde derive with serde-reflection, so the check sees exactly what the
    //! CDR serialiser sees.
    use super::*;
    use serde_reflection::{ContainerFormat, Format, Named, Registry, Tracer, TracerConfig};

    /// Official definitions of the standard messages the ecm_lcd_msgs use (constants and comments omitted).
    const STANDARD: &[(&str, &str)] = &[
        ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec"),
        ("std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id"),
        (
            "sensor_msgs/Image",
            "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data",
        ),
        ("sensor_msgs/CompressedImage", "std_msgs/Header header\nstring format\nuint8[] data"),
        (
            "sensor_msgs/CameraInfo",
            "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nRegionOfInterest roi",
        ),
        ("sensor_msgs/RegionOfInterest", "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify"),
        ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z"),
        ("geometry_msgs/Quaternion", "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1"),
        ("geometry_msgs/Pose", "Point position\nQuaternion orientation"),
    ];

    /// `(type, name)` of each field of a `.msg` text; constants (`TYPE NAME=VALUE`), comments and default
    /// values are not fields.
    fn msg_fields(text: &str) -> Vec<(String, String)> {
        text.lines()
            .map(|line| line.split('#').next().unwrap().trim())
            .filter(|line| !line.is_empty())
            .filter_map(|line| {
                let mut parts = line.split_whitespace();
                let ty = parts.next()?;
                let name = parts.next()?;
                (!name.contains('=')).then(|| (ty.to_string(), name.to_string()))
            })
            .collect()
    }

    /// Expands `text` (of package `package`) to `field.path -> primitive type`, in wire order.
    fn flatten_msg(package: &str, text: &str, prefix: &str, out: &mut Vec<(String, String)>) {
        for (ty, name) in msg_fields(text) {
            let path = format!("{prefix}{name}");
            // `T[]` (a sequence) and `T[N]` (a fixed array) are fields of primitive T.
            let base = ty.split('[').next().unwrap();
            let primitive = matches!(
                base,
                "bool"
                    | "int8"
                    | "uint8"
                    | "int16"
                    | "uint16"
                    | "int32"
                    | "uint32"
                    | "int64"
                    | "uint64"
                    | "float32"
                    | "float64"
                    | "string"
            );
            if primitive {
                out.push((path, ty));
                continue;
            }
            let full = if base.contains('/') { base.to_string() } else { format!("{package}/{base}") };
            let (pkg, _) = full.split_once('/').unwrap();
            let sub = STANDARD
                .iter()
                .find(|(n, _)| *n == full)
                .unwrap_or_else(|| panic!("unknown message type {full} in the test's table"))
                .1;
            flatten_msg(pkg, sub, &format!("{path}."), out);
        }
    }

    fn ros_type_of(format: &Format) -> String {
        match format {
            Format::Bool => "bool",
            Format::I8 => "int8",
            Format::U8 => "uint8",
            Format::I16 => "int16",
            Format::U16 => "uint16",
            Format::I32 => "int32",
            Format::U32 => "uint32",
            Format::I64 => "int64",
            Format::U64 => "uint64",
            Format::F32 => "float32",
            Format::F64 => "float64",
            Format::Str => "string",
            Format::Bytes => "uint8[]",
            other => panic!("no ROS primitive for {other:?}"),
        }
        .to_string()
    }

    fn flatten_rust(registry: &Registry, container: &str, prefix: &str, out: &mut Vec<(String, String)>) {
        let ContainerFormat::Struct(fields) = &registry[container] else { panic!("{container} is not a struct") };
        for Named { name, value } in fields {
            let path = format!("{prefix}{name}");
            match value {
                Format::TypeName(sub) => flatten_rust(registry, sub, &format!("{path}."), out),
                Format::Seq(inner) => out.push((path, format!("{}[]", ros_type_of(inner)))),
                Format::TupleArray { content, size } => out.push((path, format!("{}[{size}]", ros_type_of(content)))),
                other => out.push((path, ros_type_of(other))),
            }
        }
    }

    fn rust_fields<T: for<'de> Deserialize<'de>>(name: &str) -> Vec<(String, String)> {
        let mut tracer = Tracer::new(TracerConfig::default());
        tracer.trace_simple_type::<T>().unwrap();
        let registry = tracer.registry().unwrap();
        let mut out = Vec::new();
        flatten_rust(&registry, name, "", &mut out);
        out
    }

    fn msg_side(text: &str) -> Vec<(String, String)> {
        let mut out = Vec::new();
        flatten_msg(PACKAGE, text, "", &mut out);
        out
    }

    #[test]
    fn keyframe_struct_agrees_with_msg_file() {
        let expected = msg_side(KEYFRAME_MSG);
        assert_eq!(expected.len(), 21, "{expected:?}");
        assert_eq!(rust_fields::<Keyframe>("Keyframe"), expected);
    }

    #[test]
    fn loop_candidate_struct_agrees_with_msg_file() {
        let expected = msg_side(LOOP_CANDIDATE_MSG);
        assert_eq!(expected.len(), 23, "{expected:?}");
        assert_eq!(rust_fields::<LoopCandidate>("LoopCandidate"), expected);
    }

    #[test]
    fn standard_messages_agree_with_their_definitions() {
        let image = msg_side("sensor_msgs/Image image");
        let image: Vec<_> = image.into_iter().map(|(p, t)| (p.trim_start_matches("image.").to_string(), t)).collect();
        assert_eq!(rust_fields::<Image>("Image"), image);
        let compressed = msg_side("sensor_msgs/CompressedImage c");
        let compressed: Vec<_> =
            compressed.into_iter().map(|(p, t)| (p.trim_start_matches("c.").to_string(), t)).collect();
        assert_eq!(rust_fields::<CompressedImage>("CompressedImage"), compressed);
        let info = msg_side("sensor_msgs/CameraInfo c");
        let info: Vec<_> = info.into_iter().map(|(p, t)| (p.trim_start_matches("c.").to_string(), t)).collect();
        assert_eq!(info.len(), 17, "{info:?}");
        assert_eq!(rust_fields::<CameraInfo>("CameraInfo"), info);
    }

    #[test]
    fn camera_info_round_trips_and_gives_its_intrinsics() {
        let mut info = CameraInfo {
            width: 640,
            height: 480,
            distortion_model: "plumb_bob".into(),
            d: vec![0.1, -0.2, 0.0, 0.0, 0.0],
            ..Default::default()
        };
        assert_eq!(info.intrinsics(), None, "an uncalibrated camera publishes a zero K");
        info.k = [535.4, 0.0, 320.1, 0.0, 539.2, 247.6, 0.0, 0.0, 1.0];
        let bytes = cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&info).unwrap();
        let back: CameraInfo = cdr_encoding::from_bytes::<_, byteorder::LittleEndian>(&bytes).unwrap().0;
        assert_eq!(back, info);
        assert_eq!(back.intrinsics(), crate::verification::Intrinsics::preset("tum_fr3"));
        info.k[0] = f64::NAN;
        assert_eq!(info.intrinsics(), None);
    }

    #[test]
    fn the_check_notices_a_disagreement() {
        // A .msg with two fields swapped must not pass as the struct's definition.
        let swapped = LOOP_CANDIDATE_MSG.replace("float32 distance\nfloat32 score", "float32 score\nfloat32 distance");
        assert_ne!(swapped, LOOP_CANDIDATE_MSG);
        assert_ne!(rust_fields::<LoopCandidate>("LoopCandidate"), msg_side(&swapped));
    }

    #[test]
    fn a_verified_candidate_round_trips_with_its_pose() {
        let pose = types::RelativePose {
            rotation: nalgebra::UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
            translation: nalgebra::Vector3::new(0.6, 0.0, 0.8),
            metric: false,
            covariance: None,
        };
        let covariance =
            nalgebra::Matrix6::from_fn(|r, c| if r == c { 0.01 * (r + 1) as f64 } else { 0.001 * (r + 2 * c) as f64 });
        let metric = types::RelativePose {
            metric: true,
            translation: nalgebra::Vector3::new(1.2, 0.0, 1.6),
            covariance: Some(covariance),
            ..pose
        };
        for verified in [
            types::Verified { inliers: 40, pose: Some(pose) },
            types::Verified { inliers: 17, pose: None },
            types::Verified { inliers: 33, pose: Some(metric) },
        ] {
            let candidate = types::LoopCandidate {
                query_id: 9,
                query_stamp: Stamp::from_nanos(9_000_000_000),
                match_id: 0,
                match_stamp: Stamp::from_nanos(0),
                distance: 0.5,
                score: 0.8,
                rank: 0,
                verified: Some(verified),
            };
            let msg = LoopCandidate::from_candidate(&candidate, "cam", "cam", 1, "power");
            let expected_type = match verified.pose {
                Some(p) if p.metric => LoopCandidate::TYPE_VERIFIED_METRIC,
                Some(_) => LoopCandidate::TYPE_VERIFIED_UP_TO_SCALE,
                None => LoopCandidate::TYPE_VERIFIED,
            };
            assert_eq!(msg.loop_type, expected_type);
            match verified.pose.and_then(|p| p.covariance) {
                Some(c) => assert_eq!(msg.covariance.0[1], c[(0, 1)], "row-major"),
                None => assert_eq!(msg.covariance, Covariance::UNKNOWN),
            }
            let bytes = cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&msg).unwrap();
            let back: LoopCandidate = cdr_encoding::from_bytes::<_, byteorder::LittleEndian>(&bytes).unwrap().0;
            assert_eq!(back, msg);
            let again = back.to_candidate();
            assert_eq!(again.verified.map(|v| v.inliers), Some(verified.inliers));
            match (again.verified.and_then(|v| v.pose), verified.pose) {
                (Some(a), Some(b)) => {
                    assert_eq!((a.metric, a.covariance), (b.metric, b.covariance));
                    assert!(a.rotation.angle_to(&b.rotation) < 1e-12);
                    assert!((a.translation - b.translation).norm() < 1e-12);
                }
                (None, None) => {}
                other => panic!("pose lost or invented: {other:?}"),
            }
        }
    }

    #[test]
    fn candidate_round_trips_through_cdr() {
        let candidate = types::LoopCandidate {
            query_id: 42,
            query_stamp: Stamp::from_nanos(1_341_847_980_722_988_000),
            match_id: 7,
            match_stamp: Stamp::from_nanos(1_341_847_900_000_000_001),
            distance: 0.25,
            score: 0.9,
            rank: 1,
            verified: None,
        };
        let msg = LoopCandidate::from_candidate(&candidate, "cam", "cam_old", 3, "paper");
        let bytes = cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&msg).unwrap();
        let back: LoopCandidate = cdr_encoding::from_bytes::<_, byteorder::LittleEndian>(&bytes).unwrap().0;
        assert_eq!(back, msg);
        assert_eq!(back.to_candidate(), candidate);
        assert_eq!(back.num_candidates, 3);
        assert_eq!(back.loop_type, LoopCandidate::TYPE_APPEARANCE);
    }

    #[test]
    fn a_late_loop_carries_its_own_keyframe_s_frame_and_ranks() {
        let candidate =
            |query: u64, matched: u64, rank: u32| types::LoopCandidate { rank, ..edge(query, matched, false) };
        // Keyframe 12 confirms 11's held-back loop (11 had already reported one, rank 0).
        let candidates = [candidate(11, 4, 1), candidate(12, 5, 0), candidate(12, 6, 1)];
        let frames = |id: u64| match id {
            11 => Some("cam_left"),
            4 => Some("cam_old"),
            _ => None,
        };
        let msgs = candidate_messages(&candidates, frames, "cam_right", "l2");
        let got: Vec<(u64, &str, &str, u32, u32)> = msgs
            .iter()
            .map(|m| (m.query_id, &*m.header.frame_id, &*m.match_frame_id, m.rank, m.num_candidates))
            .collect();
        assert_eq!(
            got,
            [
                (11, "cam_left", "cam_old", 1, 2),
                (12, "cam_right", "cam_right", 0, 2),
                (12, "cam_right", "cam_right", 1, 2)
            ]
        );
        assert_eq!(msgs[0].header.stamp, Stamp::from_nanos(11).into());
    }

    /// A rank-0 candidate from keyframe `query` to `matched`, stamped with their ids in nanoseconds.
    fn edge(query: u64, matched: u64, verified: bool) -> types::LoopCandidate {
        types::LoopCandidate {
            query_id: query,
            query_stamp: Stamp::from_nanos(query as i64),
            match_id: matched,
            match_stamp: Stamp::from_nanos(matched as i64),
            distance: 0.5,
            score: 0.9,
            rank: 0,
            verified: verified.then_some(types::Verified { inliers: 30, pose: None }),
        }
    }

    #[test]
    fn loop_edges_become_line_markers_that_round_trip_through_cdr() {
        let position = |id: u64| (id != 7).then_some(Point { x: id as f64, y: 2.0 * id as f64, z: 0.5 });
        let candidates = [edge(10, 2, true), edge(11, 7, false), edge(12, 3, false)];
        let array = loop_edge_markers(&candidates, position, "map", Time::default());
        // The candidate whose match has no position draws nothing.
        assert_eq!(array.markers.len(), 2);
        let first = &array.markers[0];
        assert_eq!((first.marker_type, first.header.frame_id.as_str()), (Marker::LINE_LIST, "map"));
        assert_eq!(first.points, vec![position(2).unwrap(), position(10).unwrap()]);
        assert_ne!(first.color, array.markers[1].color, "verified and appearance-only edges differ");
        assert_ne!(first.id, array.markers[1].id);
        let bytes = cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&array).unwrap();
        let back: MarkerArray = cdr_encoding::from_bytes::<_, byteorder::LittleEndian>(&bytes).unwrap().0;
        assert_eq!(back, array);
    }
}
