//! Geometric verification of loop candidates: do the two keyframes see one rigid scene?
//!
//! An appearance match alone can name a place that only looks alike (a repeated door, the same
//! furniture). Following ORB-SLAM and RTAB-Map, a candidate is checked on local features before it is
//! reported:
//! 1. ORB features on each keyframe's grayscale image (kornia-imgproc, ORB-SLAM3's extractor), kept
//!    per keyframe within a budget ([`VerificationParams::keyframes`]);
//! 2. mutual nearest neighbours by Hamming distance with a ratio test;
//! 3. RANSAC (kornia-3d) on the matched pixel positions: the 8-point fundamental matrix and a
//!    homography (a planar scene or a pure rotation, where the epipolar model is degenerate). The
//!    model with more inliers counts.
//! 4. With camera intrinsics, the relative pose: the essential matrix `E = Kᵀ F K` of the winning
//!    fundamental matrix (the 8-point-then-lift route kornia's own two-view estimator takes; the
//!    5-point solver is several times slower when the pair does not match, which is most pairs),
//!    or the homography's decomposition, whichever won; of the candidate motions, the one that puts
//!    the most inliers in front of both cameras, refined. Two views fix the translation's direction,
//!    not its length. With intrinsics a candidate is verified only if at least
//!    [`VerificationParams::min_inliers`] of the inliers, and most of them, also fit that calibrated
//!    motion within the pixel threshold (their Sampson distance to the epipolar geometry
//!    `K⁻ᵀ [t]ₓ R K⁻¹`): a fundamental matrix has two more degrees of freedom than a camera motion,
//!    and a few dozen matches can fit one that no motion explains, whose pose would then be wrong.
//! 5. With a depth image of the match keyframe, a metric pose: the inliers whose match keypoint has a
//!    depth are lifted to 3-D points in the match camera, and AP3P inside RANSAC (kornia-3d) finds the
//!    query camera that sees them where its keypoints are, refined to the least-squares pose on the
//!    points that agree with it. The metric pose replaces step 4's when enough of those points agree
//!    ([`MIN_METRIC_INLIERS`]).
//!
//! A candidate is verified when the inliers reach [`VerificationParams::min_inliers`] (and
//! [`VerificationParams::min_inlier_ratio`] of the matches). An 8-point
//! fit to a dozen random matches always finds about eight "inliers", so the minimum must sit well
//! above that. A candidate whose match keyframe has no features kept (older than the budget, or
//! stored before the process started) cannot be checked and is rejected.
//!
//! Where keyframes carry tracker poses, a verified candidate must also be consistent with the
//! tracker's trajectory ([`odometry`]): look-alike rooms pass any two-view check.

mod hamming;
pub mod learned;
pub mod odometry;

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{ensure, Result};
use image::RgbImage;
use kornia_3d::pnp::{
    refine_pose_lm as refine_pnp_lm, solve_pnp_ransac, LMRefineParams, PnPMethod, RansacParams as PnPRansacParams,
};
use kornia_3d::pose::{
    decompose_essential, decompose_homography, enforce_essential_constraints, essential_from_fundamental,
    ransac_fundamental, ransac_homography, refine_pose_lm, sampson_distance, triangulate_midpoint_known_pose,
    LmPoseConfig, RansacParams,
};
use kornia_algebra::{Mat3AF32, Mat3F64, Vec2F32, Vec2F64, Vec3AF32, Vec3F64};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

use crate::types::DepthImage;
pub use crate::types::RelativePose;
pub use learned::XFeatExtractor;
pub use odometry::{DriftBound, OdometryTrack, Tracked};

/// PnP inliers a metric pose needs (below that, the pose stays up to scale).
pub const MIN_METRIC_INLIERS: usize = 10;
use kornia_image::{Image, ImageSize};
use kornia_imgproc::features::OrbDetector;

/// Pinhole camera intrinsics in pixels, for images of `size` (or of the size the keyframes arrive
/// in, where `size` is not known).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// The width and height of the images these values describe, where known (a calibration's own,
    /// `camera_info`'s): frames of another size get them scaled ([`Intrinsics::for_image`]).
    pub size: Option<[u32; 2]>,
}

impl Intrinsics {
    /// The published calibrations of the TUM RGB-D cameras (640x480): `tum_fr1`, `tum_fr2`, `tum_fr3`.
    pub fn preset(name: &str) -> Option<Intrinsics> {
        let (fx, fy, cx, cy) = match name {
            "tum_fr1" => (517.3, 516.5, 318.6, 255.3),
            "tum_fr2" => (520.9, 521.0, 325.1, 249.7),
            "tum_fr3" => (535.4, 539.2, 320.1, 247.6),
            _ => return None,
        };
        Some(Intrinsics { fx, fy, cx, cy, size: Some([640, 480]) })
    }

    /// These intrinsics for a frame of `size` pixels: as they are where the size is theirs or not
    /// known; scaled where the frame is the calibrated image resized (a tracker that publishes its
    /// keyframes at half size, a bag recorded downscaled), its sides within a pixel of one common
    /// factor; `None` for a frame of another shape (cropped, or another camera's), which no scaling
    /// of these values describes. Resizing maps pixel centres, `x' + 0.5 = s (x + 0.5)`.
    pub fn for_image(&self, size: [u32; 2]) -> Option<Intrinsics> {
        let Some(calibrated) = self.size.filter(|&calibrated| calibrated != size) else { return Some(*self) };
        let [(w, h), (cw, ch)] = [size, calibrated].map(|[w, h]| (w as f64, h as f64));
        if w == 0.0 || h == 0.0 || cw == 0.0 || ch == 0.0 {
            return None;
        }
        let (sx, sy) = (w / cw, h / ch);
        if (cw * sy - w).abs() > 1.0 || (ch * sx - h).abs() > 1.0 {
            return None;
        }
        Some(Intrinsics {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
            size: Some(size),
        })
    }

    fn matrix(&self) -> Mat3F64 {
        // Column-major.
        Mat3F64::from_cols_array(&[self.fx, 0.0, 0.0, 0.0, self.fy, 0.0, self.cx, self.cy, 1.0])
    }
}

/// The verification policy.
#[derive(Clone, Debug, PartialEq)]
pub struct VerificationParams {
    /// Matches verified per keyframe, the nearest: those verified are reported most inliers first
    /// ([`best_supported`], `verification.candidates`).
    pub candidates: usize,
    /// Local features extracted per keyframe (at most); 0: by the frame's size
    /// ([`VerificationParams::features_for`]).
    pub max_features: usize,
    /// A match's Hamming distance must be below this fraction of the second best's.
    pub ratio: f32,
    /// RANSAC inlier threshold in pixels.
    pub pixel_threshold: f64,
    /// A candidate is verified with at least this many RANSAC inliers.
    pub min_inliers: usize,
    /// ... and at least this fraction of its feature matches as inliers (0 = any).
    pub min_inlier_ratio: f64,
    /// Local features are kept for the newest this-many keyframes (0 = all).
    pub keyframes: usize,
    /// Equalise the grey-level histogram before ORB (dim and night images keep their corners).
    pub equalise: bool,
    pub intrinsics: Option<Intrinsics>,
    /// Odometry consistency of keyframes with tracker poses (`None`: not checked).
    pub drift: Option<DriftBound>,
    /// Which local features: ORB, or XFeat (learned; matches across day and night).
    pub local_features: LocalFeatureKind,
    /// The authors' `xfeat.pt`, for [`LocalFeatureKind::XFeat`].
    pub xfeat_weights: Option<std::path::PathBuf>,
}

/// The local features verification extracts and matches.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LocalFeatureKind {
    /// ORB (FAST corners, rBRIEF), matched by Hamming distance with a ratio test.
    #[default]
    Orb,
    /// XFeat's dense features ([`learned`]), matched by cosine.
    XFeat,
}

impl Default for VerificationParams {
    fn default() -> Self {
        VerificationParams {
            candidates: 2,
            max_features: 0,
            ratio: 0.8,
            pixel_threshold: 2.0,
            min_inliers: 15,
            min_inlier_ratio: 0.0,
            keyframes: 5000,
            equalise: false,
            intrinsics: None,
            drift: None,
            local_features: LocalFeatureKind::Orb,
            xfeat_weights: None,
        }
    }
}

/// Features per keyframe by frame size ([`VerificationParams::features_for`]): ORB-SLAM's setting
/// for TUM RGB-D's 640x480 frames, its floor and its ceiling.
const FEATURES_AT_640X480: f64 = 1000.0;
const FEWEST_FEATURES: usize = 500;
const MOST_FEATURES: usize = 2000;

impl VerificationParams {
    /// The features a `width` x `height` keyframe gets: `max_features`, or where that is 0, 1000 at
    /// 640x480 (ORB-SLAM's setting for TUM RGB-D) in proportion to the pixel count, from 500 to 2000.
    /// Why by size: a small frame has fewer distinct corners, so more features only add weak ones
    /// (1000 ORB features on 160x120 frames verified fewer loops than 500), while at 640x480 500 are
    /// too few for some real revisits that 1000 verify.
    pub fn features_for(&self, width: u32, height: u32) -> usize {
        if self.max_features > 0 {
            return self.max_features;
        }
        let pixels = width as f64 * height as f64;
        ((FEATURES_AT_640X480 * pixels / (640.0 * 480.0)).round() as usize).clamp(FEWEST_FEATURES, MOST_FEATURES)
    }
}

/// Which geometric model explained the most matches.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GeometricModel {
    /// Fundamental matrix: a rigid motion of the camera (lifted to the essential matrix with intrinsics).
    Fundamental,
    /// Homography: a planar scene or a pure rotation.
    Homography,
}

/// Descriptors of a keyframe's local features, by extractor.
#[derive(Clone, Debug, PartialEq)]
pub enum Descriptors {
    /// 256-bit rBRIEF (ORB).
    Orb(Vec<[u8; 32]>),
    /// XFeat features, unit length, each value times 127 rounded to `i8`.
    XFeat(Vec<[i8; learned::FEATURE_DIM]>),
}

impl Default for Descriptors {
    fn default() -> Self {
        Descriptors::Orb(Vec::new())
    }
}

impl Descriptors {
    /// The extractor that made them.
    pub fn kind(&self) -> LocalFeatureKind {
        match self {
            Descriptors::Orb(_) => LocalFeatureKind::Orb,
            Descriptors::XFeat(_) => LocalFeatureKind::XFeat,
        }
    }

    /// Bytes per descriptor.
    fn size(&self) -> usize {
        match self {
            Descriptors::Orb(_) => 32,
            Descriptors::XFeat(_) => learned::FEATURE_DIM,
        }
    }

    /// The store's version of the features (1: ORB, 2: XFeat).
    fn version(&self) -> u8 {
        match self {
            Descriptors::Orb(_) => 1,
            Descriptors::XFeat(_) => 2,
        }
    }

    fn bytes(&self) -> Vec<u8> {
        match self {
            Descriptors::Orb(d) => d.iter().flatten().copied().collect(),
            Descriptors::XFeat(d) => d.iter().flatten().map(|&v| v as u8).collect(),
        }
    }
}

/// Local keypoints and descriptors of one keyframe.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LocalFeatures {
    /// Pixel positions (x, y).
    pub keypoints: Vec<[f32; 2]>,
    pub descriptors: Descriptors,
    /// Depth in metres of each keypoint (0: unknown), or empty when the keyframe has no depth image.
    pub depths: Vec<f32>,
    /// Width and height of the image the keypoints were found in.
    pub image_size: [u32; 2],
}

impl LocalFeatures {
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }

    /// Reads each keypoint's depth from `depth`, which must have the image's size; a keypoint on an
    /// occlusion edge gets none ([`DepthImage::at_continuous`]).
    pub fn set_depth(&mut self, depth: &DepthImage) -> Result<()> {
        let [width, height] = self.image_size;
        ensure!(
            (depth.width, depth.height) == (width, height),
            "depth image is {}x{}, its colour image {width}x{height}",
            depth.width,
            depth.height,
        );
        self.depths = self.keypoints.iter().map(|&[x, y]| depth.at_continuous(x, y).unwrap_or(0.0)).collect();
        Ok(())
    }

    /// The features as bytes (for the keyframe store): version (1: ORB, 2: XFeat), image width and
    /// height and the keypoint count (`u32`), whether depths follow (`u8`), then keypoints as `f32`
    /// pairs, the descriptors (32 bytes for ORB, 64 for XFeat) and the depths, all little-endian.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(14 + self.bytes());
        out.push(self.descriptors.version());
        for v in [self.image_size[0], self.image_size[1], self.keypoints.len() as u32] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.push(u8::from(!self.depths.is_empty()));
        out.extend(self.keypoints.iter().flatten().flat_map(|v| v.to_le_bytes()));
        out.extend(self.descriptors.bytes());
        out.extend(self.depths.iter().flat_map(|v| v.to_le_bytes()));
        out
    }

    /// Features written by [`LocalFeatures::to_bytes`]; an error says what does not fit.
    pub fn from_bytes(bytes: &[u8]) -> Result<LocalFeatures> {
        ensure!(
            bytes.len() >= 14 && (bytes[0] == 1 || bytes[0] == 2),
            "not local features of version 1 or 2 ({} bytes)",
            bytes.len()
        );
        let word = |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
        let (width, height, n) = (word(1), word(5), word(9) as usize);
        let with_depth = bytes[13] == 1;
        let size = if bytes[0] == 1 { 32 } else { learned::FEATURE_DIM };
        let expected = 14 + n * (8 + size + if with_depth { 4 } else { 0 });
        ensure!(bytes.len() == expected, "local features of {n} keypoints take {expected} bytes, not {}", bytes.len());
        let floats = |from: usize, count: usize| -> Vec<f32> {
            bytes[from..from + 4 * count]
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        };
        let keypoints = floats(14, 2 * n).chunks_exact(2).map(|p| [p[0], p[1]]).collect();
        let start = 14 + 8 * n;
        let packed = &bytes[start..start + size * n];
        let descriptors = if bytes[0] == 1 {
            Descriptors::Orb(packed.chunks_exact(32).map(|d| <[u8; 32]>::try_from(d).expect("32 bytes")).collect())
        } else {
            Descriptors::XFeat(packed.chunks_exact(size).map(|d| std::array::from_fn(|k| d[k] as i8)).collect())
        };
        let depths = if with_depth { floats(start + size * n, n) } else { Vec::new() };
        Ok(LocalFeatures { keypoints, descriptors, depths, image_size: [width, height] })
    }

    /// Memory the features take.
    pub fn bytes(&self) -> usize {
        self.len() * (std::mem::size_of::<[f32; 2]>() + self.descriptors.size())
            + self.depths.len() * std::mem::size_of::<f32>()
    }
}

/// The outcome of checking one pair.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Verification {
    /// Descriptor matches that passed the mutual and ratio tests.
    pub matches: usize,
    /// RANSAC inliers of the winning model (0 when no model could be fitted).
    pub inliers: usize,
    pub model: Option<GeometricModel>,
    /// Whether the inliers reach the minimum.
    pub accepted: bool,
    /// The query camera's pose in the match camera's frame, translation a unit direction; only with
    /// intrinsics, for an accepted pair.
    pub pose: Option<RelativePose>,
}

impl Verification {
    /// How strongly the pair is verified, for choosing among the matches tried: its inliers where
    /// accepted, `None` (below any) where not.
    pub fn support(&self) -> Option<usize> {
        self.accepted.then_some(self.inliers)
    }
}

/// Which of the matches tried for a keyframe, best ranked first, to report (`verifications`, one
/// each; `None` where a match could not be checked): the accepted one with the most inliers, the
/// better ranked on a tie; `None` when none is accepted. Retrieval's order is by appearance alone, and
/// a look-alike can outrank the place itself; where both pass, the place the images agree on in
/// more points is the better loop (spatial re-ranking of the nearest matches).
pub fn best_supported(verifications: impl IntoIterator<Item = Option<Verification>>) -> Option<usize> {
    verifications
        .into_iter()
        .enumerate()
        .filter_map(|(i, v)| Some((i, v?.support()?)))
        .min_by_key(|&(i, inliers)| (std::cmp::Reverse(inliers), i))
        .map(|(i, _)| i)
}

/// [`best_supported`] among the matches that pass the detector's threshold (`passes`, one each)
/// where one of them is verified, else among all: a verified match above the threshold is never
/// passed over for a better-supported one below it, which would not be reported as a loop.
pub fn best_supported_passing(verifications: &[Option<Verification>], passes: &[bool]) -> Option<usize> {
    let passing = verifications.iter().zip(passes).map(|(v, &passes)| v.filter(|_| passes));
    best_supported(passing).or_else(|| best_supported(verifications.iter().copied()))
}

/// ORB features of `image` (converted to grayscale), at most `max_features`.
pub fn extract(image: &RgbImage, max_features: usize) -> Result<LocalFeatures> {
    extract_gray(image::imageops::grayscale(image), max_features)
}

/// ORB's pyramid and patches need a frame at least this many pixels on its shorter side; a smaller
/// one has no ORB features.
const ORB_MIN_SIDE: u32 = 64;

/// ORB features of a grayscale image, at most `max_features`.
fn extract_gray(gray: image::GrayImage, max_features: usize) -> Result<LocalFeatures> {
    let size = ImageSize { width: gray.width() as usize, height: gray.height() as usize };
    let orb = OrbDetector { n_keypoints: max_features, ..OrbDetector::default() };
    let image_size = [gray.width(), gray.height()];
    // The extractor needs room for its pyramid and patch; a tiny image simply has no features.
    if gray.width().min(gray.height()) < ORB_MIN_SIDE {
        return Ok(LocalFeatures { image_size, ..LocalFeatures::default() });
    }
    let image =
        Image::<u8, 1>::new(size, gray.into_raw()).map_err(|e| anyhow::anyhow!("grayscale image for ORB: {e}"))?;
    let features = orb.detect_and_extract_u8(&image).map_err(|e| anyhow::anyhow!("ORB extraction: {e}"))?;
    Ok(LocalFeatures {
        keypoints: features.keypoints_xy,
        descriptors: Descriptors::Orb(features.descriptors),
        depths: Vec::new(),
        image_size,
    })
}

/// Spreads the grey levels over the full range by their cumulative histogram.
fn equalise_histogram(gray: &mut image::GrayImage) {
    let mut histogram = [0u64; 256];
    gray.pixels().for_each(|p| histogram[p[0] as usize] += 1);
    let total = gray.pixels().len() as u64;
    let lowest = histogram.iter().copied().find(|&h| h > 0).unwrap_or(0);
    let mut cumulative = 0u64;
    let mut map = [0u8; 256];
    for (level, count) in histogram.iter().enumerate() {
        cumulative += count;
        map[level] = ((cumulative.saturating_sub(lowest)) * 255 / total.saturating_sub(lowest).max(1)) as u8;
    }
    gray.pixels_mut().for_each(|p| p[0] = map[p[0] as usize]);
}

/// Checks whether `query` and `matched` see one rigid scene (module doc).
pub fn verify(query: &LocalFeatures, matched: &LocalFeatures, params: &VerificationParams) -> Verification {
    // Each view's camera: the intrinsics scaled to its image. An image of a shape they do not
    // describe leaves the pair verified as without intrinsics (no pose), the pipeline having said why.
    let cameras = params.intrinsics.and_then(|k| {
        Some(Cameras { query: k.for_image(query.image_size)?, matched: k.for_image(matched.image_size)? })
    });
    let (pairs, threshold) = match (&query.descriptors, &matched.descriptors) {
        (Descriptors::Orb(q), Descriptors::Orb(m)) => {
            (hamming::mutual_matches(q, m, params.ratio), params.pixel_threshold)
        }
        (Descriptors::XFeat(q), Descriptors::XFeat(m)) => {
            // The threshold holds in the network's input pixels.
            let scale = learned::input_scale(query.image_size).max(learned::input_scale(matched.image_size));
            (learned::mutual_nearest(q, m), params.pixel_threshold * scale)
        }
        // Features of another extractor (a store made with the other setting) cannot be compared.
        _ => (Vec::new(), params.pixel_threshold),
    };
    let point = |p: [f32; 2]| Vec2F64::new(p[0] as f64, p[1] as f64);
    let x1: Vec<Vec2F64> = pairs.iter().map(|&(i, _)| point(query.keypoints[i])).collect();
    let x2: Vec<Vec2F64> = pairs.iter().map(|&(_, j)| point(matched.keypoints[j])).collect();
    let (mut verification, inliers) = fit(&x1, &x2, params, threshold, cameras.as_ref());
    if let (true, Some(cameras), false) = (verification.accepted, &cameras, matched.depths.is_empty()) {
        // Step 5: the inliers whose match keypoint has a depth.
        let points: Vec<(Vec2F64, Vec2F64, f32)> = pairs
            .iter()
            .zip(&inliers)
            .filter(|&(&(_, j), &inlier)| inlier && matched.depths[j] > 0.0)
            .map(|(&(i, j), _)| (point(query.keypoints[i]), point(matched.keypoints[j]), matched.depths[j]))
            .collect();
        if let Some(pose) = metric_pose(&points, cameras, threshold) {
            verification.pose = Some(pose);
        }
    }
    verification
}

/// Step 5 of the module doc: from (query pixel, match pixel, match depth) triples, the query camera's
/// metric pose in the match camera's frame; `None` when too few agree.
fn metric_pose(points: &[(Vec2F64, Vec2F64, f32)], cameras: &Cameras, pixel_threshold: f64) -> Option<RelativePose> {
    if points.len() < MIN_METRIC_INLIERS {
        return None;
    }
    let lifted = cameras.matched;
    let world: Vec<Vec3AF32> = points
        .iter()
        .map(|&(_, m, d)| {
            let (x, y) = ((m.x - lifted.cx) / lifted.fx, (m.y - lifted.cy) / lifted.fy);
            Vec3AF32::new(x as f32 * d, y as f32 * d, d)
        })
        .collect();
    let intrinsics = &cameras.query;
    let Intrinsics { fx, fy, cx, cy, .. } = *intrinsics;
    let image: Vec<Vec2F32> = points.iter().map(|&(q, _, _)| Vec2F32::new(q.x as f32, q.y as f32)).collect();
    let k = Mat3AF32::from_cols(
        Vec3AF32::new(fx as f32, 0.0, 0.0),
        Vec3AF32::new(0.0, fy as f32, 0.0),
        Vec3AF32::new(cx as f32, cy as f32, 1.0),
    );
    let ransac = PnPRansacParams {
        reproj_threshold_px: pixel_threshold as f32,
        random_seed: Some(0),
        ..PnPRansacParams::default()
    };
    let found = solve_pnp_ransac(&world, &image, &k, None, PnPMethod::AP3PDefault, &ransac).ok()?;
    if found.inliers.len() < MIN_METRIC_INLIERS {
        return None;
    }
    // The minimal solver's pose fits a few points; a Levenberg-Marquardt pass on the inliers'
    // reprojection errors (kornia's PnP refinement) brings it near the least-squares pose.
    let (inlier_world, inlier_image): (Vec<Vec3AF32>, Vec<Vec2F32>) =
        found.inliers.iter().map(|&i| (world[i], image[i])).unzip();
    let pose = refine_pnp_lm(
        &inlier_world,
        &inlier_image,
        &k,
        &found.pose.rotation,
        &found.pose.translation,
        None,
        &LMRefineParams::default(),
    )
    .unwrap_or(found.pose);
    // PnP gives the match frame's points in the query camera: p_query = R p_match + t.
    let r = &pose.rotation;
    let columns = [r.x_axis, r.y_axis, r.z_axis].map(|c| Vector3::new(c.x as f64, c.y as f64, c.z as f64));
    let rotation = Matrix3::from_columns(&columns);
    let t = pose.translation;
    let t = Vector3::new(t.x as f64, t.y as f64, t.z as f64);
    let inverse = rotation.transpose();
    let mut rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&inverse));
    let mut translation = -(inverse * t);
    // Its inliers are those of the best minimal sample's pose: a biased subset (about 85 where 98
    // agree with the refined pose), which left the errors' spread over twice what the covariance
    // says. So: Gauss-Newton in f64 (which also gives the covariance at the optimum) on the inliers
    // of the current pose, until they stop changing. Gauss-Newton on RANSAC's inliers alone changed
    // nothing: kornia's f32 pass ends within a millimetre and a milliradian of it.
    let all: Vec<(Vector3<f64>, [f64; 2])> = world
        .iter()
        .zip(&image)
        .map(|(p, q)| (Vector3::new(p.x as f64, p.y as f64, p.z as f64), [q.x as f64, q.y as f64]))
        .collect();
    let mut inliers = found.inliers;
    let mut covariance = None;
    for _ in 0..MAX_INLIER_ROUNDS {
        let subset: Vec<_> = inliers.iter().map(|&i| all[i]).collect();
        let Some(fitted) = least_squares_pose(rotation, translation, &subset, intrinsics, pixel_threshold) else {
            break;
        };
        (rotation, translation, covariance) = (fitted.0, fitted.1, Some(fitted.2));
        let agreeing: Vec<usize> = (0..all.len())
            .filter(|&i| {
                let [u, v] = project_into_query(&rotation, &translation, &all[i].0, intrinsics);
                (u - all[i].1[0]).hypot(v - all[i].1[1]) < pixel_threshold
            })
            .collect();
        if agreeing == inliers || agreeing.len() < MIN_METRIC_INLIERS {
            break;
        }
        inliers = agreeing;
    }
    Some(RelativePose { rotation, translation, metric: true, covariance })
}

/// Rounds of [`metric_pose`]'s refit on the inliers of its latest pose; they settle in two or three.
const MAX_INLIER_ROUNDS: usize = 5;

/// The per-axis variance of isotropic 2-D Gaussian pixel errors whose vectors were kept only under
/// `cut` pixels long (the inlier threshold), from the variance `observed` in those kept: the cut
/// drops the tails, so the kept ones understate the spread. Where the kept errors fill the cut so
/// evenly that the Gaussian would need more than twice their variance, they are not Gaussian tails
/// to restore, and the correction stops at twice.
fn untruncated_variance(observed: f64, cut: f64) -> f64 {
    // A kept error's squared length over 2 sigma² is exponential with rate 1 cut at a = cut² / 2
    // sigma²: its mean is 1 - a e^-a / (1 - e^-a). Fixed-point iteration on sigma².
    let mut variance = observed;
    for _ in 0..50 {
        let a = cut * cut / (2.0 * variance);
        let kept = 1.0 - a * (-a).exp() / (1.0 - (-a).exp());
        variance = (observed / kept).min(2.0 * observed);
    }
    variance
}

/// Pixel position in the query image of `point` (in the match camera's frame), with the query
/// camera at (`rotation`, `translation`) in the match camera's frame.
fn project_into_query(
    rotation: &UnitQuaternion<f64>,
    translation: &Vector3<f64>,
    point: &Vector3<f64>,
    intrinsics: &Intrinsics,
) -> [f64; 2] {
    // p_match = r p_query + t, so p_query = rᵀ (p_match - t).
    let c = rotation.inverse() * (point - translation);
    [intrinsics.fx * c.x / c.z + intrinsics.cx, intrinsics.fy * c.y / c.z + intrinsics.cy]
}

/// Gauss-Newton from a metric relative pose near the optimum to the least-squares one over its PnP
/// inliers (3-D points in the match camera, pixels in the query image), with its covariance
/// `s² (JᵀJ)⁻¹`: `J` the reprojection errors' Jacobian (central differences) and `s²` their variance
/// per degree of freedom, restored for the tails that `inlier_threshold` (pixels) cut off
/// ([`untruncated_variance`]). The six parameters follow ROS's `PoseWithCovariance`: translation x, y, z
/// in the match camera's frame, then rotations about its x, y and z axes (applied on the left of the
/// rotation). `None` where the inliers do not fix the pose.
fn least_squares_pose(
    mut rotation: UnitQuaternion<f64>,
    mut translation: Vector3<f64>,
    inliers: &[(Vector3<f64>, [f64; 2])],
    intrinsics: &Intrinsics,
    inlier_threshold: f64,
) -> Option<(UnitQuaternion<f64>, Vector3<f64>, nalgebra::Matrix6<f64>)> {
    if inliers.len() < 4 {
        return None;
    }
    // The steps shrink quadratically from a pose this close; a few always suffice.
    const MAX_STEPS: usize = 10;
    let mut steps = 0;
    loop {
        let residuals = |delta: &nalgebra::Vector6<f64>| -> nalgebra::DVector<f64> {
            let r = UnitQuaternion::from_scaled_axis(Vector3::new(delta[3], delta[4], delta[5])) * rotation;
            let t = translation + Vector3::new(delta[0], delta[1], delta[2]);
            let errors = inliers.iter().flat_map(|(p, q)| {
                let [u, v] = project_into_query(&r, &t, p, intrinsics);
                [u - q[0], v - q[1]]
            });
            nalgebra::DVector::from_iterator(2 * inliers.len(), errors)
        };
        let at = residuals(&nalgebra::Vector6::zeros());
        let mut jacobian = nalgebra::DMatrix::<f64>::zeros(at.len(), 6);
        for k in 0..6 {
            let mut step = nalgebra::Vector6::zeros();
            step[k] = 1e-6;
            jacobian.set_column(k, &((residuals(&step) - residuals(&-step)) / 2e-6));
        }
        let information: nalgebra::Matrix6<f64> = (jacobian.transpose() * &jacobian).fixed_view::<6, 6>(0, 0).into();
        let inverse = information.try_inverse()?;
        let gradient: nalgebra::Vector6<f64> = (jacobian.transpose() * &at).fixed_view::<6, 1>(0, 0).into();
        let step = -(inverse * gradient);
        // Converged (a step under a micrometre and a microradian) or out of steps: the covariance
        // of the pose the Jacobian was taken at.
        if step.amax() < 1e-6 || steps == MAX_STEPS {
            let variance = untruncated_variance(at.norm_squared() / (at.len() - 6) as f64, inlier_threshold);
            let covariance = inverse * variance;
            return covariance.iter().all(|v| v.is_finite()).then_some((rotation, translation, covariance));
        }
        rotation = UnitQuaternion::from_scaled_axis(Vector3::new(step[3], step[4], step[5])) * rotation;
        translation += Vector3::new(step[0], step[1], step[2]);
        steps += 1;
    }
}

/// Steps 3 and 4 of the module doc on matched pixel positions (`x1[i]` in the query, `x2[i]` in the
/// match).
pub fn fit_geometry(x1: &[Vec2F64], x2: &[Vec2F64], params: &VerificationParams) -> Verification {
    let cameras = params.intrinsics.map(|k| Cameras { query: k, matched: k });
    fit(x1, x2, params, params.pixel_threshold, cameras.as_ref()).0
}

/// The intrinsics of the two views of a pair, each scaled to its own image.
#[derive(Clone, Copy, Debug)]
struct Cameras {
    query: Intrinsics,
    matched: Intrinsics,
}

/// [`fit_geometry`] with the winning model's inlier mask.
fn fit(
    x1: &[Vec2F64],
    x2: &[Vec2F64],
    params: &VerificationParams,
    threshold: f64,
    cameras: Option<&Cameras>,
) -> (Verification, Vec<bool>) {
    // A fixed seed: the same pair is always judged the same way.
    let ransac = RansacParams { max_iterations: 500, threshold, min_inliers: 0, random_seed: Some(0), refit: false };
    let fits = [
        (GeometricModel::Fundamental, ransac_fundamental(x1, x2, &ransac).ok()),
        (GeometricModel::Homography, ransac_homography(x1, x2, &ransac).ok()),
    ];
    // Ties go to the fundamental matrix, the general model.
    let best = fits
        .iter()
        .filter_map(|(model, fit)| fit.as_ref().map(|fit| (*model, fit)))
        .max_by_key(|(model, fit)| (fit.inlier_count, *model == GeometricModel::Fundamental));
    let inliers = best.map_or(0, |(_, fit)| fit.inlier_count);
    let accepted = inliers >= params.min_inliers && inliers as f64 >= params.min_inlier_ratio * x1.len() as f64;
    let pose = match (best, cameras) {
        (Some((model, fit)), Some(cameras)) if accepted => {
            let pairs: Vec<(Vec2F64, Vec2F64)> =
                (0..x1.len()).filter(|&i| fit.inliers[i]).map(|i| (x1[i], x2[i])).collect();
            relative_pose(model, &fit.model, cameras, &pairs, threshold, params.min_inliers)
        }
        _ => None,
    };
    // With intrinsics, a camera motion must explain the matches, not only a fundamental matrix.
    let accepted = accepted && (cameras.is_none() || pose.is_some());
    let mask = best.map_or_else(|| vec![false; x1.len()], |(_, fit)| fit.inliers.clone());
    (Verification { matches: x1.len(), inliers, model: best.map(|(model, _)| model), accepted, pose }, mask)
}

/// Step 4 of the module doc: the motion, among those `model` allows, that puts the most of
/// `inliers` in front of both cameras; `None` unless `min_support` of them, and most, fit it
/// within `threshold` pixels.
fn relative_pose(
    model: GeometricModel,
    fit: &Mat3F64,
    cameras: &Cameras,
    inliers: &[(Vec2F64, Vec2F64)],
    threshold: f64,
    min_support: usize,
) -> Option<RelativePose> {
    let (k1, k2) = (cameras.query.matrix(), cameras.matched.matrix());
    let motions: Vec<(Mat3F64, Vec3F64)> = match model {
        GeometricModel::Fundamental => {
            let e = enforce_essential_constraints(&essential_from_fundamental(fit, &k1, &k2))?;
            decompose_essential(&e)?.to_vec()
        }
        GeometricModel::Homography => decompose_homography(fit, &k1, &k2),
    };
    let (k1_inv, k2_inv) = (k1.inverse(), k2.inverse());
    let ray = |k_inv: &Mat3F64, p: &Vec2F64| *k_inv * Vec3F64::new(p.x, p.y, 1.0);
    let in_front = |(r, t): &(Mat3F64, Vec3F64)| {
        inliers
            .iter()
            .filter(|(a, b)| triangulate_midpoint_known_pose(&ray(&k1_inv, a), &ray(&k2_inv, b), r, t).is_some())
            .count()
    };
    let (mut r, mut t) = *motions.iter().max_by_key(|motion| in_front(motion))?;
    if model == GeometricModel::Fundamental {
        // The lift from F loses accuracy; a Levenberg-Marquardt pass on the inliers' Sampson errors
        // (kornia's two-view refinement) recovers it.
        let (y1, y2): (Vec<Vec2F64>, Vec<Vec2F64>) = inliers.iter().copied().unzip();
        (r, t) = refine_pose_lm(r, t, &y1, &y2, &k1, &k2, &LmPoseConfig::default());
    }
    let cross =
        Mat3F64::from_cols(Vec3F64::new(0.0, t.z, -t.y), Vec3F64::new(-t.z, 0.0, t.x), Vec3F64::new(t.y, -t.x, 0.0));
    let epipolar = k2_inv.transpose() * cross * r * k1_inv;
    let support = inliers.iter().filter(|(a, b)| sampson_distance(&epipolar, a, b) < threshold * threshold).count();
    if support < min_support || 2 * support < inliers.len() {
        return None;
    }
    let columns: [f64; 9] = r.into();
    let rotation = Matrix3::from_column_slice(&columns);
    let translation = Vector3::new(t.x, t.y, t.z);
    let norm = translation.norm();
    Some(RelativePose {
        rotation: UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&rotation)),
        translation: if norm > 1e-12 { translation / norm } else { Vector3::zeros() },
        metric: false,
        covariance: None,
    })
}

/// The verification stage of a pipeline: the local features of recent keyframes and the policy.
#[derive(Debug)]
pub struct Verifier {
    params: VerificationParams,
    features: HashMap<u64, LocalFeatures>,
    /// Keyframe ids in the order their features were kept (the budget drops the oldest).
    order: VecDeque<u64>,
    /// The XFeat network, with [`LocalFeatureKind::XFeat`].
    xfeat: Option<XFeatExtractor>,
    /// Whether the user was told that the frames are too small for ORB (once a run).
    told_frames_too_small: AtomicBool,
}

impl Verifier {
    pub fn new(params: VerificationParams) -> Result<Self> {
        ensure!(
            params.ratio > 0.0 && params.ratio <= 1.0,
            "the ratio test's ratio must be in (0, 1], got {}",
            params.ratio
        );
        let xfeat = match params.local_features {
            LocalFeatureKind::Orb => None,
            LocalFeatureKind::XFeat => {
                Some(XFeatExtractor::load(&crate::model::xfeat::resolve_weights(params.xfeat_weights.as_deref())?)?)
            }
        };
        Ok(Verifier {
            params,
            features: HashMap::new(),
            order: VecDeque::new(),
            xfeat,
            told_frames_too_small: AtomicBool::new(false),
        })
    }

    pub fn params(&self) -> &VerificationParams {
        &self.params
    }

    /// Changes the policy at run time (kept features stay; the budget applies at the next keyframe).
    pub fn set_params(&mut self, params: VerificationParams) {
        self.params = params;
    }

    /// Features of an image (and keypoint depths, from `depth` where given) under this verifier's
    /// settings.
    pub fn extract(&self, image: &RgbImage, depth: Option<&DepthImage>) -> Result<LocalFeatures> {
        let mut gray = image::imageops::grayscale(image);
        if self.params.equalise {
            equalise_histogram(&mut gray);
        }
        let features = self.params.features_for(gray.width(), gray.height());
        let mut features = match &self.xfeat {
            Some(xfeat) => xfeat.extract(&gray, features)?,
            None => {
                let (width, height) = gray.dimensions();
                if width.min(height) < ORB_MIN_SIDE && !self.told_frames_too_small.swap(true, Ordering::Relaxed) {
                    log::warn!(
                        "keyframes of {width}x{height} pixels are under ORB's {ORB_MIN_SIDE} on a side: they have no \
                         features, so geometric verification rejects every candidate; set \
                         verification.local_features xfeat (which works on small frames) or verification.mode off"
                    );
                }
                extract_gray(gray, features)?
            }
        };
        if let Some(depth) = depth {
            features.set_depth(depth)?;
        }
        Ok(features)
    }

    /// Keeps `features` as keyframe `id`'s, dropping the oldest beyond the budget.
    pub fn remember(&mut self, id: u64, features: LocalFeatures) {
        if self.features.insert(id, features).is_none() {
            self.order.push_back(id);
        }
        let budget = self.params.keyframes;
        while budget > 0 && self.order.len() > budget {
            if let Some(oldest) = self.order.pop_front() {
                self.features.remove(&oldest);
            }
        }
    }

    /// Gives keyframe `id`'s kept features their depths from `depth` (a depth image that arrived after
    /// its keyframe); returns whether they were kept and had none yet.
    pub fn attach_depth(&mut self, id: u64, depth: &DepthImage) -> Result<bool> {
        match self.features.get_mut(&id) {
            Some(features) if features.depths.is_empty() => features.set_depth(depth).map(|()| true),
            _ => Ok(false),
        }
    }

    /// The features kept for keyframe `id`.
    pub fn features(&self, id: u64) -> Option<&LocalFeatures> {
        self.features.get(&id)
    }

    /// Number of keyframes whose features are kept.
    pub fn kept(&self) -> usize {
        self.order.len()
    }

    /// Checks `query` against keyframe `id`; `None` when that keyframe's features are not kept.
    pub fn verify(&self, query: &LocalFeatures, id: u64) -> Option<Verification> {
        self.features.get(&id).map(|matched| verify(query, matched, &self.params))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgb;

    /// A textured test image: random blocks (many corners), the same for the same seed.
    fn blocks(seed: u64, width: u32, height: u32) -> RgbImage {
        let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let mut next = move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 33) as u32
        };
        let cells: Vec<u8> = (0..(width / 8) * (height / 8)).map(|_| (next() % 256) as u8).collect();
        RgbImage::from_fn(width, height, |x, y| {
            let v = cells[((y / 8) * (width / 8) + x / 8) as usize];
            Rgb([v, v, v])
        })
    }

    /// `image` shifted right by `dx` pixels (a camera panning: a homography), edges filled by clamping.
    fn shifted(image: &RgbImage, dx: u32) -> RgbImage {
        RgbImage::from_fn(image.width(), image.height(), |x, y| *image.get_pixel(x.saturating_sub(dx), y))
    }

    #[test]
    fn the_verified_match_with_the_most_inliers_is_chosen_the_better_ranked_on_a_tie() {
        let verdict = |inliers: usize, accepted: bool| {
            Some(Verification { matches: 40, inliers, model: None, accepted, pose: None })
        };
        assert_eq!(best_supported([verdict(15, true), verdict(30, true)]), Some(1));
        assert_eq!(best_supported([verdict(30, true), verdict(30, true), verdict(20, true)]), Some(0));
        // A rejected pair does not count, whatever its inliers; nor one that could not be checked.
        assert_eq!(best_supported([verdict(40, false), None, verdict(16, true)]), Some(2));
        assert_eq!(best_supported([verdict(40, false), None]), None);
        assert_eq!(best_supported(std::iter::empty()), None);
        // Among the verified matches that pass the threshold first, then among all.
        let tried = [verdict(40, true), verdict(20, true), verdict(30, true)];
        assert_eq!(best_supported_passing(&tried, &[false, true, true]), Some(2));
        assert_eq!(best_supported_passing(&tried, &[false, false, false]), Some(0));
        assert_eq!(best_supported_passing(&[verdict(40, true), verdict(20, false)], &[false, true]), Some(0));
    }

    #[test]
    fn the_same_scene_is_verified_and_another_is_not() {
        let params = VerificationParams::default();
        let scene = blocks(1, 320, 240);
        let a = extract(&scene, 500).unwrap();
        assert!(a.len() > 100, "{} features", a.len());
        let same = verify(&a, &extract(&shifted(&scene, 12), 500).unwrap(), &params);
        assert!(same.accepted, "{same:?}");
        assert!(same.inliers >= 50, "{same:?}");
        let other = verify(&a, &extract(&blocks(2, 320, 240), 500).unwrap(), &params);
        assert!(!other.accepted, "{other:?}");
        assert!(other.inliers < params.min_inliers, "{other:?}");
    }

    #[test]
    fn with_intrinsics_a_shifted_view_is_verified() {
        let params = VerificationParams { intrinsics: Intrinsics::preset("tum_fr3"), ..VerificationParams::default() };
        let scene = blocks(3, 320, 240);
        let a = extract(&scene, 500).unwrap();
        let result = verify(&a, &extract(&shifted(&scene, 8), 500).unwrap(), &params);
        assert!(result.accepted, "{result:?}");
        assert!(Intrinsics::preset("tum_fr4").is_none());
    }

    /// Projections of random points seen by two cameras `p2 = r p1 + t` (non-planar), plus outliers.
    fn two_views(
        r: &Rotation3<f64>,
        t: &Vector3<f64>,
        k: &Intrinsics,
        points: usize,
        outliers: usize,
    ) -> (Vec<Vec2F64>, Vec<Vec2F64>) {
        let mut state = 7u64;
        let mut uniform = move |lo: f64, hi: f64| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            lo + (hi - lo) * ((state >> 11) as f64 / (1u64 << 53) as f64)
        };
        let project = |p: Vector3<f64>| Vec2F64::new(k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
        let (mut x1, mut x2) = (Vec::new(), Vec::new());
        for _ in 0..points {
            let p1 = Vector3::new(uniform(-2.0, 2.0), uniform(-1.5, 1.5), uniform(3.0, 8.0));
            x1.push(project(p1));
            x2.push(project(r * p1 + t));
        }
        for _ in 0..outliers {
            x1.push(Vec2F64::new(uniform(0.0, 640.0), uniform(0.0, 480.0)));
            x2.push(Vec2F64::new(uniform(0.0, 640.0), uniform(0.0, 480.0)));
        }
        (x1, x2)
    }

    #[test]
    fn intrinsics_follow_a_resized_frame_and_not_a_cropped_one() {
        let k = Intrinsics::preset("tum_fr3").unwrap();
        assert_eq!(k.for_image([640, 480]), Some(k));
        let half = k.for_image([320, 240]).unwrap();
        let expected = [535.4 / 2.0, 539.2 / 2.0, 160.0 - 0.25 + 0.05, 123.8 - 0.25];
        for (value, expected) in [half.fx, half.fy, half.cx, half.cy].into_iter().zip(expected) {
            assert!((value - expected).abs() < 1e-9, "{half:?}");
        }
        assert_eq!(half.size, Some([320, 240]));
        // A third, rounded to whole pixels.
        assert!(k.for_image([213, 160]).is_some());
        assert_eq!(k.for_image([640, 360]), None, "a crop");
        assert_eq!(k.for_image([480, 640]), None, "turned");
        assert_eq!(k.for_image([0, 0]), None);
        assert_eq!(Intrinsics { size: Some([0, 0]), ..k }.for_image([320, 240]), None);
        let size_unknown = Intrinsics { size: None, ..k };
        assert_eq!(size_unknown.for_image([320, 240]), Some(size_unknown));
    }

    /// ORB-kind features at `points`, the i-th with the i-th of a set of distinct descriptors, so
    /// that two such sets match point for point.
    fn orb_features(points: &[Vec2F64], image_size: [u32; 2]) -> LocalFeatures {
        let descriptor = |i: u64| {
            std::array::from_fn(|byte| ((i * 32 + byte as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 56) as u8)
        };
        LocalFeatures {
            keypoints: points.iter().map(|p| [p.x as f32, p.y as f32]).collect(),
            descriptors: Descriptors::Orb((0..points.len() as u64).map(descriptor).collect()),
            depths: Vec::new(),
            image_size,
        }
    }

    #[test]
    fn a_calibration_of_the_full_frame_verifies_half_size_keyframes_with_the_right_pose() {
        let k = Intrinsics::preset("tum_fr3").unwrap();
        let half = k.for_image([320, 240]).unwrap();
        let r = Rotation3::from_euler_angles(0.04, -0.25, 0.02);
        let t = Vector3::new(0.5, 0.05, 0.1);
        let (x1, x2) = two_views(&r, &t, &half, 150, 0);
        let params = VerificationParams { intrinsics: Some(k), ..VerificationParams::default() };
        let direction_error = |v: &Verification| v.pose.map(|pose| pose.translation.angle(&t).to_degrees());
        let scaled = verify(&orb_features(&x1, [320, 240]), &orb_features(&x2, [320, 240]), &params);
        assert!(scaled.accepted, "{scaled:?}");
        let error = direction_error(&scaled).expect("a pose");
        assert!(error < 2.0, "translation direction off by {error} degrees");
        // The full frame's values taken as they are would not describe these frames.
        let unscaled = fit_geometry(&x1, &x2, &params);
        assert!(direction_error(&unscaled).is_none_or(|error| error > 5.0), "{unscaled:?}");
        // The match keyframe at full size (a map made before from the full frames): each view
        // gets its own camera.
        let full: Vec<Vec2F64> = x2.iter().map(|p| Vec2F64::new(2.0 * p.x + 0.5, 2.0 * p.y + 0.5)).collect();
        let mixed = verify(&orb_features(&x1, [320, 240]), &orb_features(&full, [640, 480]), &params);
        let error = direction_error(&mixed).expect("a pose");
        assert!(mixed.accepted && error < 2.0, "translation direction off by {error} degrees: {mixed:?}");
        // A cropped frame is verified as without intrinsics: no pose.
        let cropped = verify(&orb_features(&x1, [320, 200]), &orb_features(&x2, [320, 240]), &params);
        assert!(cropped.accepted && cropped.pose.is_none(), "{cropped:?}");
    }

    fn same_camera(intrinsics: Intrinsics) -> Cameras {
        Cameras { query: intrinsics, matched: intrinsics }
    }

    #[test]
    fn the_relative_pose_of_a_rigid_motion_is_recovered() {
        let k = Intrinsics::preset("tum_fr3").unwrap();
        let params = VerificationParams { intrinsics: Some(k), ..VerificationParams::default() };
        let r = Rotation3::from_euler_angles(0.05, -0.2, 0.03);
        let t = Vector3::new(0.4, -0.05, 0.15);
        let (x1, x2) = two_views(&r, &t, &k, 120, 40);
        let result = fit_geometry(&x1, &x2, &params);
        assert!(result.accepted, "{result:?}");
        assert_eq!(result.model, Some(GeometricModel::Fundamental));
        assert!(result.inliers >= 110, "{result:?}");
        let pose = result.pose.expect("a pose with intrinsics");
        let rotation_error = pose.rotation.angle_to(&UnitQuaternion::from_rotation_matrix(&r)).to_degrees();
        let direction_error = pose.translation.angle(&t).to_degrees();
        assert!(rotation_error < 0.5, "rotation off by {rotation_error} degrees");
        assert!(direction_error < 2.0, "translation direction off by {direction_error} degrees");
        assert!((pose.translation.norm() - 1.0).abs() < 1e-9);
        // Without intrinsics the pair still verifies, with no pose.
        let uncalibrated = fit_geometry(&x1, &x2, &VerificationParams::default());
        assert!(uncalibrated.accepted && uncalibrated.pose.is_none());
        // 120 of 160 matches fit: a minimum ratio of inliers above 3/4 refuses the pair.
        let ratio = |min_inlier_ratio| VerificationParams { min_inlier_ratio, ..params.clone() };
        assert!(fit_geometry(&x1, &x2, &ratio(0.7)).accepted);
        assert!(!fit_geometry(&x1, &x2, &ratio(0.8)).accepted);
        // A pair that only a fundamental matrix explains (the query's pixels stretched 1.6x
        // sideways and shrunk 0.7x upright, which no camera motion does) verifies without
        // intrinsics and not with them.
        let zoomed = Intrinsics { fx: 1.6 * k.fx, fy: 0.7 * k.fy, ..k };
        let (y1, y2) = two_views(&r, &t, &k, 120, 0);
        let (z1, _) = two_views(&r, &t, &zoomed, 120, 0);
        let (z1, y2): (Vec<Vec2F64>, Vec<Vec2F64>) =
            z1.into_iter().zip(y2).filter(|(p, _)| p.x.abs() < 2000.0 && p.y.abs() < 2000.0).unzip();
        assert!(y1.len() == 120 && z1.len() >= 100);
        let uncalibrated = fit_geometry(&z1, &y2, &VerificationParams::default());
        assert!(uncalibrated.accepted && uncalibrated.inliers >= 100, "{uncalibrated:?}");
        let calibrated = fit_geometry(&z1, &y2, &params);
        assert!(!calibrated.accepted && calibrated.pose.is_none(), "{calibrated:?}");
        // Outliers alone do not.
        let (_, noise) = two_views(&r, &t, &k, 0, 160);
        let shuffled: Vec<Vec2F64> = noise.iter().rev().copied().collect();
        assert!(!fit_geometry(&noise, &shuffled, &params).accepted);
    }

    #[test]
    fn the_budget_drops_the_oldest_features_and_unknown_keyframes_are_not_verified() {
        let mut verifier = Verifier::new(VerificationParams { keyframes: 2, ..VerificationParams::default() }).unwrap();
        let scene = blocks(4, 160, 120);
        let features = verifier.extract(&scene, None).unwrap();
        for id in 0..3 {
            verifier.remember(id, features.clone());
        }
        assert_eq!(verifier.kept(), 2);
        assert!(verifier.verify(&features, 0).is_none(), "keyframe 0 was dropped");
        assert!(verifier.verify(&features, 2).is_some_and(|v| v.accepted));
        assert!(verifier.verify(&features, 9).is_none());
    }

    #[test]
    fn the_feature_count_follows_the_frame_size_unless_it_is_set() {
        let by_size = VerificationParams::default();
        assert_eq!(by_size.features_for(640, 480), 1000);
        assert_eq!(by_size.features_for(752, 480), 1175);
        assert_eq!(by_size.features_for(320, 240), 500);
        assert_eq!(by_size.features_for(160, 120), 500);
        assert_eq!(by_size.features_for(1920, 1080), 2000);
        let fixed = VerificationParams { max_features: 300, ..VerificationParams::default() };
        assert_eq!(fixed.features_for(640, 480), 300);
    }

    #[test]
    fn a_tiny_or_flat_image_has_no_features_and_verifies_nothing() {
        let params = VerificationParams::default();
        let tiny = extract(&blocks(5, 32, 32), 500).unwrap();
        assert!(tiny.is_empty());
        let flat = extract(&RgbImage::from_pixel(200, 150, Rgb([90, 90, 90])), 500).unwrap();
        assert!(flat.is_empty());
        let result = verify(&tiny, &flat, &params);
        assert_eq!((result.matches, result.inliers, result.accepted), (0, 0, false));
    }

    /// `count` seeded random 3-D points 2-5 m in front of the match camera, seen from both cameras
    /// (the query camera at `truth` in the match camera's frame) with Gaussian pixel noise of
    /// `sigma` pixels in each image: (query pixel, match pixel, depth) as [`metric_pose`] takes them.
    fn noisy_correspondences(
        truth: &nalgebra::Isometry3<f64>,
        intrinsics: &Intrinsics,
        count: usize,
        sigma: f64,
        seed: u64,
    ) -> Vec<(Vec2F64, Vec2F64, f32)> {
        let mut state = seed;
        let mut uniform = move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let project = |c: Vector3<f64>| {
            Vec2F64::new(intrinsics.fx * c.x / c.z + intrinsics.cx, intrinsics.fy * c.y / c.z + intrinsics.cy)
        };
        let mut points = Vec::with_capacity(count);
        for _ in 0..count {
            let p = Vector3::new(uniform() * 4.0 - 2.0, uniform() * 3.0 - 1.5, 2.0 + uniform() * 3.0);
            let (mut q, mut m) = (project((truth.inverse() * nalgebra::Point3::from(p)).coords), project(p));
            for value in [&mut q.x, &mut q.y, &mut m.x, &mut m.y] {
                // Box-Muller.
                let (u, v) = (uniform(), uniform());
                *value += sigma * (-2.0 * u.max(1e-12).ln()).sqrt() * (std::f64::consts::TAU * v).cos();
            }
            points.push((q, m, p.z as f32));
        }
        points
    }

    #[test]
    fn a_metric_pose_from_depth_matches_the_truth_within_its_covariance() {
        let intrinsics = Intrinsics { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, size: None };
        // The query camera in the match camera's frame: 0.3 m right, 0.1 m forward, turned 5 degrees.
        let truth = nalgebra::Isometry3::new(Vector3::new(0.3, 0.0, 0.1), Vector3::new(0.0, 5f64.to_radians(), 0.0));
        let points = noisy_correspondences(&truth, &intrinsics, 150, 0.5, 7);
        let pose = metric_pose(&points, &same_camera(intrinsics), 2.0).expect("a metric pose");
        assert!(pose.metric);
        let rotation_error = pose.rotation.angle_to(&truth.rotation).to_degrees();
        let translation_error = pose.translation - truth.translation.vector;
        assert!(rotation_error < 0.2 && translation_error.norm() < 0.02, "{rotation_error} deg, {translation_error:?}");
        let covariance = pose.covariance.expect("a covariance");
        assert!(covariance.cholesky().is_some(), "positive definite: {covariance}");
        for axis in 0..3 {
            let sd = covariance[(axis, axis)].sqrt();
            assert!(sd > 1e-5 && sd < 0.05, "axis {axis}: sd {sd}");
            assert!(
                translation_error[axis].abs() < 5.0 * sd,
                "axis {axis}: error {} vs sd {sd}",
                translation_error[axis]
            );
        }
        // The match keyframe at twice the size (its camera scaled with it): the same pose.
        let doubled = Intrinsics { size: Some([320, 240]), ..intrinsics }.for_image([640, 480]).unwrap();
        let double: Vec<_> =
            points.iter().map(|&(q, m, d)| (q, Vec2F64::new(2.0 * m.x + 0.5, 2.0 * m.y + 0.5), d)).collect();
        let cameras = Cameras { query: intrinsics, matched: doubled };
        let mixed = metric_pose(&double, &cameras, 2.0).expect("a metric pose");
        assert!(mixed.rotation.angle_to(&pose.rotation) < 1e-4, "{mixed:?} against {pose:?}");
        assert!((mixed.translation - pose.translation).norm() < 1e-4, "{mixed:?} against {pose:?}");
        // Too few points: no metric pose.
        assert!(metric_pose(&points[..MIN_METRIC_INLIERS - 1], &same_camera(intrinsics), 2.0).is_none());
    }

    /// The covariance is calibrated: over many seeded pairs with independent pixel noise in both
    /// images, the squared Mahalanobis distance of the errors averages 3 (chi-square, 3 degrees of
    /// freedom) for rotation and for translation (3.5 here: the errors in the 3-D points are
    /// not in the model). A pose fitted to the best minimal sample's inliers averaged about 8.5.
    #[test]
    fn the_metric_covariance_matches_the_spread_of_the_errors() {
        // The synthetic camera at 320x240 and a revisit 13 cm apart, turned 3.5 degrees.
        let intrinsics = Intrinsics { fx: 262.4, fy: 262.4, cx: 159.5, cy: 119.5, size: None };
        let truth =
            nalgebra::Isometry3::new(Vector3::new(0.12, 0.0, 0.05), Vector3::new(0.0, 3.5f64.to_radians(), 0.0));
        let trials = 100;
        let (mut rotation, mut translation) = (0.0, 0.0);
        for seed in 0..trials {
            let points = noisy_correspondences(&truth, &intrinsics, 120, 1.0, seed);
            let pose = metric_pose(&points, &same_camera(intrinsics), 4.0).expect("a metric pose");
            let (r, t) = pose.normalised_squared_errors(&truth).expect("a covariance");
            rotation += r / trials as f64;
            translation += t / trials as f64;
        }
        // The mean of 100 chi-square(3) draws: 3 with a standard deviation of 0.245.
        for (name, mean) in [("rotation", rotation), ("translation", translation)] {
            assert!((2.4..4.0).contains(&mean), "{name}: mean normalised squared error {mean:.2}, 3 if right");
        }
    }

    #[test]
    fn depth_attached_after_the_fact_fills_the_kept_features_once() {
        let params = VerificationParams { keyframes: 2, ..VerificationParams::default() };
        let mut verifier = Verifier::new(params).unwrap();
        let features = LocalFeatures {
            keypoints: vec![[1.4, 1.4], [3.0, 2.0]],
            descriptors: Descriptors::Orb(vec![[0; 32]; 2]),
            depths: Vec::new(),
            image_size: [5, 4],
        };
        verifier.remember(7, features);
        // A wall 2 m away with one pixel unknown, beside the second keypoint.
        let mut depth = DepthImage { width: 5, height: 4, metres: vec![2.0; 20] };
        depth.metres[2 * 5 + 4] = 0.0;
        let small = DepthImage { width: 2, height: 2, metres: vec![1.0; 4] };
        let err = verifier.attach_depth(7, &small).unwrap_err().to_string();
        assert!(err.contains("depth image is 2x2, its colour image 5x4"), "{err}");
        assert!(verifier.attach_depth(7, &depth).unwrap());
        assert_eq!(verifier.features[&7].depths, vec![2.0, 0.0]);
        // Once only, and only for kept keyframes.
        assert!(!verifier.attach_depth(7, &depth).unwrap());
        assert!(!verifier.attach_depth(8, &depth).unwrap());
    }

    #[test]
    fn local_features_round_trip_through_bytes_and_refuse_damage() {
        let mut features = extract(&blocks(3, 128, 96), 200).unwrap();
        assert!(features.len() > 50, "{} features", features.len());
        assert_eq!(LocalFeatures::from_bytes(&features.to_bytes()).unwrap(), features);
        features.depths = (0..features.len()).map(|i| i as f32 * 0.25).collect();
        let bytes = features.to_bytes();
        assert_eq!(LocalFeatures::from_bytes(&bytes).unwrap(), features);
        let err = LocalFeatures::from_bytes(&bytes[..bytes.len() - 1]).unwrap_err().to_string();
        assert!(err.contains("take"), "{err}");
        assert!(LocalFeatures::from_bytes(&[2, 0, 0]).is_err());
        let empty = LocalFeatures { image_size: [10, 20], ..LocalFeatures::default() };
        assert_eq!(LocalFeatures::from_bytes(&empty.to_bytes()).unwrap(), empty);
    }

    /// XFeat-kind features: `n` keypoints with distinct unit descriptors.
    fn learned_features(n: usize) -> LocalFeatures {
        LocalFeatures {
            keypoints: (0..n).map(|i| [i as f32 * 3.5, 7.0]).collect(),
            descriptors: Descriptors::XFeat(
                (0..n)
                    .map(|i| {
                        let v: Vec<f32> = (0..64u64)
                            .map(|k| {
                                let h = (i as u64 * 64 + k + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                                ((h ^ (h >> 29)) % 2001) as f32 - 1000.0
                            })
                            .collect();
                        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                        std::array::from_fn(|k| (v[k] / norm * 127.0).round() as i8)
                    })
                    .collect(),
            ),
            depths: Vec::new(),
            image_size: [640, 480],
        }
    }

    #[test]
    fn learned_features_round_trip_as_version_2() {
        let mut features = learned_features(5);
        let bytes = features.to_bytes();
        assert_eq!(bytes[0], 2);
        assert_eq!(bytes.len(), 14 + 5 * (8 + 64));
        assert_eq!(LocalFeatures::from_bytes(&bytes).unwrap(), features);
        features.depths = vec![1.0, 0.0, 2.5, 3.0, 0.5];
        assert_eq!(LocalFeatures::from_bytes(&features.to_bytes()).unwrap(), features);
        assert!(LocalFeatures::from_bytes(&[3; 20]).is_err());
    }

    #[test]
    fn features_of_different_extractors_do_not_match() {
        let orb = extract(&blocks(3, 128, 96), 200).unwrap();
        let learned = learned_features(40);
        let params = VerificationParams::default();
        for (a, b) in [(&orb, &learned), (&learned, &orb)] {
            let result = verify(a, b, &params);
            assert_eq!((result.matches, result.accepted), (0, false));
        }
        // The same learned features match themselves, one pair each.
        assert_eq!(verify(&learned, &learned, &params).matches, 40);
    }

    #[test]
    fn frames_too_small_for_orb_have_no_features_and_are_told_once() {
        let verifier = Verifier::new(VerificationParams::default()).unwrap();
        let big = blocks(9, 320, 240);
        assert!(!verifier.extract(&big, None).unwrap().is_empty());
        assert!(!verifier.told_frames_too_small.load(Ordering::Relaxed), "a 320x240 frame has features");
        let small = image::imageops::resize(&big, 80, 60, image::imageops::FilterType::Triangle);
        let features = verifier.extract(&small, None).unwrap();
        assert!(features.is_empty() && features.image_size == [80, 60]);
        assert!(verifier.told_frames_too_small.load(Ordering::Relaxed));
    }

    #[test]
    fn equalising_keeps_the_corners_of_a_dark_image() {
        let bright = blocks(9, 320, 240);
        let dark = RgbImage::from_fn(320, 240, |x, y| Rgb([bright.get_pixel(x, y)[0] / 40; 3]));
        let count = |equalise: bool, image: &RgbImage| {
            let verifier = Verifier::new(VerificationParams { equalise, ..VerificationParams::default() }).unwrap();
            verifier.extract(image, None).unwrap().len()
        };
        let (plain, equalised, reference) = (count(false, &dark), count(true, &dark), count(false, &bright));
        assert!(
            equalised > plain * 2 && equalised * 10 >= reference * 8,
            "{plain} plain, {equalised} equalised, {reference} bright"
        );
    }
}
