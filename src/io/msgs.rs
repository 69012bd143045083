//! ROS message types that ecm-lcd reads and writes, defined with serde because ros2-client
//! ships no generated `std_msgs`/`sensor_msgs`. Field order is the wire order (CDR and
//! ROS 1 serialisation both follow the `.msg` definition), so do not reorder fields.

use serde::{Deserialize, Serialize};

use crate::types::Stamp;

/// `builtin_interfaces/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl From<Stamp> for Time {
    fn from(s: Stamp) -> Self {
        Time { sec: s.sec() as i32, nanosec: s.nsec() }
    }
}

impl From<Time> for Stamp {
    fn from(t: Time) -> Self {
        Stamp::from_sec_nsec(t.sec as i64, t.nanosec)
    }
}

/// `std_msgs/Header` (ROS 2 layout: no `seq`).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/Image`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/CompressedImage`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/RegionOfInterest`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

/// `sensor_msgs/CameraInfo`: a camera driver's calibration, published beside its images.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    /// Row-major 3x3 intrinsic matrix of the raw (distorted) images.
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

impl CameraInfo {
    /// The pinhole intrinsics of the images published beside this message, or `None` for an
    /// uncalibrated camera (driver convention: `k` all zero) or values that are not a usable
    /// calibration. `k` is the full sensor's; as ROS defines the message (and image_geometry reads
    /// it), the images are its region of interest (`roi`, offsets in full-sensor pixels; all zero: the
    /// whole sensor) binned by `binning_x`, `binning_y` (0 or 1: none), so the principal point moves by
    /// the offsets and every value is divided by the binning. Distortion is not modelled: geometric
    /// verification's pixel tolerance absorbs the mild distortion of common RGB-D cameras.
    pub fn intrinsics(&self) -> Option<crate::verification::Intrinsics> {
        let [fx, _, cx, _, fy, cy, _, _, _] = self.k;
        let usable = [fx, fy, cx, cy].iter().all(|v| v.is_finite()) && fx > 0.0 && fy > 0.0;
        let (bx, by) = (self.binning_x.max(1) as f64, self.binning_y.max(1) as f64);
        let (x0, y0) = (self.roi.x_offset as f64, self.roi.y_offset as f64);
        usable.then_some(crate::verification::Intrinsics {
            fx: fx / bx,
            fy: fy / by,
            cx: (cx - x0) / bx,
            cy: (cy - y0) / by,
            size: self.image_size(),
        })
    }

    /// The size of the images published beside this message (their region of interest, binned), or
    /// `None` where the message gives none.
    pub fn image_size(&self) -> Option<[u32; 2]> {
        let roi = |side: u32, full: u32| if side > 0 { side } else { full };
        let (width, height) = (roi(self.roi.width, self.width), roi(self.roi.height, self.height));
        let binned = [width / self.binning_x.max(1), height / self.binning_y.max(1)];
        (binned[0] > 0 && binned[1] > 0).then_some(binned)
    }
}
