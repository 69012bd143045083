//! Small value types shared by every stage: time stamps, frames and loop candidates, and the count
//! of a recurring warning.

use serde::{Deserialize, Serialize};
use std::fmt;

/// A time stamp in nanoseconds since the Unix epoch (ROS time). Integer so that stamps
/// read from bags and messages round-trip exactly.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct Stamp {
    pub nanos: i64,
}

impl Stamp {
    pub const fn from_nanos(nanos: i64) -> Self {
        Stamp { nanos }
    }

    /// From ROS `sec`/`nanosec` fields.
    pub fn from_sec_nsec(sec: i64, nsec: u32) -> Self {
        Stamp { nanos: sec * 1_000_000_000 + nsec as i64 }
    }

    /// From floating-point seconds (TUM text files); rounded to the nearest nanosecond.
    pub fn from_secs_f64(secs: f64) -> Self {
        Stamp { nanos: (secs * 1e9).round() as i64 }
    }

    /// Parses a decimal seconds string such as `1341847980.722988` exactly (no float rounding).
    pub fn parse_secs(text: &str) -> Option<Self> {
        let text = text.trim();
        let (negative, digits) = match text.strip_prefix('-') {
            Some(rest) => (true, rest),
            None => (false, text),
        };
        let (whole, frac) = digits.split_once('.').unwrap_or((digits, ""));
        if whole.is_empty() && frac.is_empty() {
            return None;
        }
        if !whole.bytes().all(|b| b.is_ascii_digit()) || !frac.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        let sec: i64 = if whole.is_empty() { 0 } else { whole.parse().ok()? };
        let mut nanos: i64 = 0;
        for (i, b) in frac.bytes().take(9).enumerate() {
            nanos += (b - b'0') as i64 * 10i64.pow(8 - i as u32);
        }
        let total = sec.checked_mul(1_000_000_000)?.checked_add(nanos)?;
        Some(Stamp { nanos: if negative { -total } else { total } })
    }

    /// The system clock now (wall time, as ROS stamps diagnostics).
    pub fn now() -> Self {
        let since_epoch = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        Stamp { nanos: since_epoch.as_nanos().min(i64::MAX as u128) as i64 }
    }

    pub fn as_secs_f64(self) -> f64 {
        self.nanos as f64 * 1e-9
    }

    /// Whole seconds (ROS `sec`).
    pub fn sec(self) -> i64 {
        self.nanos.div_euclid(1_000_000_000)
    }

    /// Nanoseconds within the second (ROS `nanosec`).
    pub fn nsec(self) -> u32 {
        self.nanos.rem_euclid(1_000_000_000) as u32
    }
}

/// The position in `sorted` (stamps in increasing order) of the stamp nearest to `stamp`, if it is at
/// most `max_offset` away; ties go to the earlier one.
pub fn nearest_stamp(sorted: &[Stamp], stamp: Stamp, max_offset: Stamp) -> Option<usize> {
    let at = sorted.partition_point(|s| *s < stamp);
    let gap = |i: usize| sorted[i].nanos.abs_diff(stamp.nanos);
    [at.checked_sub(1), (at < sorted.len()).then_some(at)]
        .into_iter()
        .flatten()
        .min_by_key(|&i| gap(i))
        .filter(|&i| gap(i) <= max_offset.nanos.unsigned_abs())
}

impl Stamp {
    /// Seconds as decimal text with `places` decimals (at most 9; further digits are cut, toward
    /// zero), as [`Stamp::parse_secs`] reads it back: a stamp before the epoch is signed as a whole,
    /// `-0.750000`, not split like ROS's `sec` and `nanosec` (`-1` and `250000000`).
    pub fn to_decimal(self, places: usize) -> String {
        let places = places.min(9);
        let magnitude = self.nanos.unsigned_abs();
        let (whole, fraction) = (magnitude / 1_000_000_000, magnitude % 1_000_000_000);
        let fraction = fraction / 10u64.pow(9 - places as u32);
        // No sign on digits that are all zero: a stamp a nanosecond before the epoch is `0.000000`.
        let sign = if self.nanos < 0 && (whole > 0 || fraction > 0) { "-" } else { "" };
        if places == 0 {
            return format!("{sign}{whole}");
        }
        format!("{sign}{whole}.{fraction:0places$}")
    }
}

impl fmt::Display for Stamp {
    /// Seconds with nine decimals, e.g. `1341847980.722988000`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_decimal(9))
    }
}

/// One decoded camera image from any source, in source order.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Position in the source's replay order, from 0.
    pub index: usize,
    pub stamp: Stamp,
    pub image: image::RgbImage,
    /// The depth image registered to `image`, where the source has one (TUM `depth.txt`).
    pub depth: Option<DepthImage>,
}

/// Depth along the optical axis, in metres, of every pixel of a colour image (0: unknown).
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    /// Row-major, `width * height` values.
    pub metres: Vec<f32>,
}

impl DepthImage {
    /// TUM RGB-D's 16-bit depth PNGs store 5000 units per metre.
    pub const TUM_UNITS_PER_METRE: f32 = 5000.0;

    /// From a TUM 16-bit depth image.
    pub fn from_tum(image: &image::ImageBuffer<image::Luma<u16>, Vec<u16>>) -> DepthImage {
        let metres = image.as_raw().iter().map(|&d| d as f32 / Self::TUM_UNITS_PER_METRE).collect();
        DepthImage { width: image.width(), height: image.height(), metres }
    }

    /// As a TUM 16-bit depth image (depths beyond 13.1 m are written as 0, unknown).
    pub fn to_tum(&self) -> image::ImageBuffer<image::Luma<u16>, Vec<u16>> {
        let units = |m: f32| {
            let u = (m * Self::TUM_UNITS_PER_METRE).round();
            if u.is_finite() && u > 0.0 && u <= u16::MAX as f32 {
                u as u16
            } else {
                0
            }
        };
        let raw = self.metres.iter().map(|&m| units(m)).collect();
        image::ImageBuffer::from_raw(self.width, self.height, raw).expect("width * height values")
    }

    /// The depth at pixel position (x, y) (nearest pixel; pixel centres at whole numbers); `None`
    /// outside the image or unknown.
    pub fn at(&self, x: f32, y: f32) -> Option<f32> {
        self.at_pixel(x.round(), y.round())
    }

    /// The depth at pixel position (x, y) where the surface around it is continuous, `None` where it
    /// is not known to be: at an occlusion edge the nearest pixel may lie on either side of it (and a
    /// depth camera's pixels there often on neither), so a corner found on a silhouette gets a depth
    /// that is not its own. Continuous means: the 3x3 pixels around the nearest one are all known,
    /// and along each of the four lines through it the inverse depth's second difference is at most
    /// [`Self::EDGE_TOLERANCE`] of its value. Inverse depth is affine in the pixel position on a plane,
    /// so a plane passes at any slant, and a crease (a corner of a room) passes too.
    pub fn at_continuous(&self, x: f32, y: f32) -> Option<f32> {
        let (col, row) = (x.round(), y.round());
        let depth = self.at_pixel(col, row)?;
        let centre = 1.0 / depth;
        let inverse = |dx: f32, dy: f32| self.at_pixel(col + dx, row + dy).map(|d| 1.0 / d);
        for (dx, dy) in [(1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (1.0, -1.0)] {
            let second_difference = inverse(dx, dy)? + inverse(-dx, -dy)? - 2.0 * centre;
            if second_difference.abs() > Self::EDGE_TOLERANCE * centre {
                return None;
            }
        }
        Some(depth)
    }

    /// The largest second difference of inverse depth, as a fraction of it, that
    /// [`Self::at_continuous`] takes for a continuous surface: above the steps of a Kinect's
    /// disparity (about 1% at 3 m), well below an occlusion edge's jump.
    pub const EDGE_TOLERANCE: f32 = 0.05;

    fn at_pixel(&self, col: f32, row: f32) -> Option<f32> {
        if !(col >= 0.0 && row >= 0.0 && col < self.width as f32 && row < self.height as f32) {
            return None;
        }
        let d = self.metres[row as usize * self.width as usize + col as usize];
        (d.is_finite() && d > 0.0).then_some(d)
    }
}

/// A loop candidate: the query keyframe probably revisits the place of the matched one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoopCandidate {
    pub query_id: u64,
    pub query_stamp: Stamp,
    pub match_id: u64,
    pub match_stamp: Stamp,
    /// Euclidean distance between the two descriptors.
    pub distance: f32,
    /// Similarity in [0, 1] derived from the distance (see [`crate::descriptor`]).
    pub score: f32,
    /// 0 for the best match of this query, 1 for the next, ...
    pub rank: u32,
    /// What geometric verification found; `None`: appearance only, not verified.
    pub verified: Option<Verified>,
}

/// A candidate's geometric verification ([`crate::verification`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Verified {
    /// Feature matches that fit the pair's geometry (RANSAC inliers).
    pub inliers: u32,
    /// The query camera's pose in the match camera's frame, when the intrinsics are known.
    pub pose: Option<RelativePose>,
}

/// A relative camera pose from two views: `p_match = rotation * p_query + translation` for a point's
/// coordinates in each camera's frame (x right, y down, z forward). Two views fix the translation
/// only up to scale: it is a unit vector (zero for a pure rotation), unless `metric` (a depth image gave
/// the scale: metres).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RelativePose {
    pub rotation: nalgebra::UnitQuaternion<f64>,
    pub translation: nalgebra::Vector3<f64>,
    /// Whether `translation` is in metres (else a unit direction).
    #[serde(default)]
    pub metric: bool,
    /// Covariance of a metric pose (translation x, y, z in metres, then rotation about x, y, z in
    /// radians, as ROS's `PoseWithCovariance`), where it was estimated.
    #[serde(default)]
    pub covariance: Option<nalgebra::Matrix6<f64>>,
}

impl RelativePose {
    /// How far `truth` (the query camera's true pose in the match camera's frame) lies from this
    /// metric pose in units of its covariance: the squared Mahalanobis distances of the rotation
    /// error (a left perturbation) and of the translation error, each against its own 3x3 block.
    /// Chi-square distributed with 3 degrees of freedom where the covariance is right. `None`
    /// without a covariance or when a block is singular.
    pub fn normalised_squared_errors(&self, truth: &nalgebra::Isometry3<f64>) -> Option<(f64, f64)> {
        let covariance = self.covariance.filter(|_| self.metric)?;
        let rotation_error = (truth.rotation * self.rotation.inverse()).scaled_axis();
        let translation_error = truth.translation.vector - self.translation;
        let mahalanobis = |error: nalgebra::Vector3<f64>, block: nalgebra::Matrix3<f64>| {
            block.try_inverse().map(|information| (error.transpose() * information * error)[0])
        };
        Some((
            mahalanobis(rotation_error, covariance.fixed_view::<3, 3>(3, 3).into())?,
            mahalanobis(translation_error, covariance.fixed_view::<3, 3>(0, 0).into())?,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamp_parses_exactly_and_prints_ros_fields() {
        let s = Stamp::parse_secs("1341847980.722988").unwrap();
        assert_eq!(s.sec(), 1341847980);
        assert_eq!(s.nsec(), 722_988_000);
        assert_eq!(s.to_string(), "1341847980.722988000");
        assert_eq!(Stamp::from_sec_nsec(s.sec(), s.nsec()), s);
        assert_eq!(Stamp::parse_secs("-0.5").unwrap().nanos, -500_000_000);
        // Before the epoch, printed signed as a whole and read back the same.
        for text in ["-0.750000000", "-1.250000000", "-3.000000001", "0.000000000"] {
            let stamp = Stamp::parse_secs(text).unwrap();
            assert_eq!((stamp.to_string(), Stamp::parse_secs(&stamp.to_string())), (text.to_string(), Some(stamp)));
        }
        assert_eq!(Stamp::parse_secs("-0.7509").unwrap().to_decimal(6), "-0.750900");
        assert_eq!(Stamp::parse_secs("12.5").unwrap().to_decimal(0), "12");
        assert_eq!(Stamp::from_nanos(-100).to_decimal(6), "0.000000");
        assert_eq!(Stamp::from_nanos(-100).to_string(), "-0.000000100");
        assert!(Stamp::parse_secs("12a.3").is_none());
        assert!(Stamp::parse_secs("").is_none());
    }

    #[test]
    fn depth_is_read_at_the_nearest_pixel_and_not_across_occlusion_edges() {
        let image = |inverse: &dyn Fn(f32, f32) -> f32| DepthImage {
            width: 10,
            height: 8,
            metres: (0..80).map(|i| 1.0 / inverse((i % 10) as f32, (i / 10) as f32)).collect(),
        };
        // A slanted plane: inverse depth is affine in the pixel position.
        let plane = image(&|x, y| 0.2 + 0.05 * x + 0.01 * y);
        let at_4_4 = 1.0 / (0.2 + 0.05 * 4.0 + 0.01 * 4.0);
        assert_eq!(plane.at(4.4, 3.6), Some(at_4_4), "nearest pixel, not the one above and left");
        assert_eq!(plane.at_continuous(4.4, 3.6), Some(at_4_4));
        assert_eq!(plane.at_continuous(0.0, 4.0), None, "no 3x3 neighbourhood at the border");
        assert_eq!((plane.at(9.6, 2.0), plane.at(-0.6, 2.0)), (None, None), "outside");
        // A crease: two walls meeting at a room's corner.
        let corner = image(&|x, _| 0.3 * (1.0 + 0.004 * (x - 5.0).abs()));
        assert_eq!(corner.at_continuous(5.0, 3.0), corner.at(5.0, 3.0));
        // A box 1 m away in front of a wall 3 m away, from column 5 on.
        let edge = image(&|x, _| if x >= 5.0 { 1.0 } else { 1.0 / 3.0 });
        assert_eq!((edge.at(5.0, 3.0), edge.at_continuous(5.0, 3.0)), (Some(1.0), None));
        assert_eq!((edge.at(4.0, 3.0), edge.at_continuous(4.0, 3.0)), (Some(3.0), None));
        assert_eq!(edge.at_continuous(6.0, 3.0), Some(1.0));
        assert_eq!(edge.at_continuous(2.0, 3.0), Some(3.0));
        // An unknown pixel beside the keypoint.
        let mut hole = image(&|_, _| 0.5);
        hole.metres[3 * 10 + 6] = 0.0;
        assert_eq!((hole.at_continuous(5.0, 3.0), hole.at_continuous(3.0, 3.0)), (None, Some(2.0)));
    }

    #[test]
    fn errors_are_measured_in_units_of_the_covariance() {
        // Standard deviations 0.1 m and 0.01 rad on every axis.
        let covariance = nalgebra::Matrix6::from_diagonal(&nalgebra::Vector6::new(0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4));
        let pose = RelativePose {
            rotation: nalgebra::UnitQuaternion::identity(),
            translation: nalgebra::Vector3::new(1.0, 0.0, 0.0),
            metric: true,
            covariance: Some(covariance),
        };
        // Two standard deviations off in translation, three in rotation.
        let truth =
            nalgebra::Isometry3::new(nalgebra::Vector3::new(1.0, 0.2, 0.0), nalgebra::Vector3::new(0.0, 0.0, 0.03));
        let (rotation, translation) = pose.normalised_squared_errors(&truth).unwrap();
        assert!((rotation - 9.0).abs() < 1e-9 && (translation - 4.0).abs() < 1e-9, "{rotation} {translation}");
        let direction = RelativePose { metric: false, ..pose };
        assert_eq!(direction.normalised_squared_errors(&truth), None, "a unit direction has no covariance");
    }
}

/// The network's last feature map for one image, channel-major `[C, H, W]`, on the CPU.
/// Descriptors are computed from it (global pooling, spatial pooling, ...).
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureMap {
    pub channels: usize,
    pub height: usize,
    pub width: usize,
    pub data: Vec<f32>,
}

impl FeatureMap {
    /// Global average pool: one mean per channel.
    pub fn global_average(&self) -> Vec<f32> {
        let plane = self.height * self.width;
        self.data.chunks_exact(plane).map(|c| c.iter().sum::<f32>() / plane as f32).collect()
    }
}

/// How often one kind of input problem has recurred; the log names it on the first and every
/// hundredth occurrence, since a warning per frame would bury everything else at camera rates.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Recurring(u64);

impl Recurring {
    /// Counts one more occurrence; returns the count where this one is to be logged.
    pub fn occurred(&mut self) -> Option<u64> {
        self.0 += 1;
        (self.0 % 100 == 1).then_some(self.0)
    }

    /// Occurrences so far.
    pub fn count(&self) -> u64 {
        self.0
    }
}
