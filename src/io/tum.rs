//! TUM RGB-D folder format: reading (`rgb.txt` + images, `groundtruth.txt`), writing (for
//! synthetic sequences), and plain image folders.
//!
//! `rgb.txt` lines are `timestamp path` with `path` relative to the folder; `#` starts a
//! comment line and blank lines are skipped. `groundtruth.txt` lines are
//! `timestamp tx ty tz qx qy qz qw`. An optional `depth.txt` (same form as `rgb.txt`) lists 16-bit
//! depth PNGs (5000 units per metre); each colour image takes the depth image nearest in time, within
//! [`DEPTH_ASSOCIATION`] (the benchmark's `associate.py` rule). A plain image folder (no `rgb.txt`) replays its
//! `png`/`jpg`/`jpeg`/`bmp` files in name order ([`image_files_in_name_order`]) with stamp = index
//! seconds.

use anyhow::{bail, ensure, Context, Result};
use image::RgbImage;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

use super::{FrameSource, SourceIntrinsics};
use crate::types::{DepthImage, Frame, Stamp};

/// Largest stamp difference between a colour image and the depth image paired with it (TUM's
/// `associate.py` default).
pub const DEPTH_ASSOCIATION: Stamp = Stamp::from_nanos(20_000_000);

/// Why a stamp that does not parse is bad, when it looks like a number: it is out of range.
fn stamp_problem(text: &str) -> &'static str {
    let digits = text.trim().trim_start_matches('-');
    if !digits.is_empty()
        && digits.bytes().all(|b| b.is_ascii_digit() || b == b'.')
        && digits.bytes().filter(|&b| b == b'.').count() <= 1
    {
        " (out of range: stamps are whole nanoseconds in a signed 64-bit integer, at most about 9.2e9 s)"
    } else {
        ""
    }
}

/// Reads the non-comment, non-blank lines of a TUM text file with their 1-based line numbers (a
/// byte-order mark at the start is skipped).
fn data_lines(path: &Path) -> Result<Vec<(usize, String)>> {
    let text = super::read_capped_text(path, super::limits::TEXT_LIST, "list")?;
    Ok(text
        .lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim().to_string()))
        .filter(|(_, line)| !line.is_empty() && !line.starts_with('#'))
        .collect())
}

/// Why `path` cannot be read as a file: it does not exist, is a directory, a FIFO or device, or a
/// symlink that leads nowhere (a loop or a missing target).
fn not_a_file_reason(path: &Path) -> String {
    match (fs::symlink_metadata(path), fs::metadata(path)) {
        (Err(_), _) => "does not exist".into(),
        (Ok(link), Err(e)) if link.file_type().is_symlink() => format!("is a symlink that cannot be followed ({e})"),
        (_, Ok(m)) if m.is_dir() => "is a directory".into(),
        (_, Ok(_)) => "is not a regular file (a FIFO, socket or device)".into(),
        (Ok(_), Err(e)) => format!("cannot be read ({e})"),
    }
}

/// One image to load: where it came from (for errors), its stamp and file.
#[derive(Clone, Debug)]
struct ImageEntry {
    origin: String,
    stamp: Stamp,
    path: PathBuf,
    /// The depth image paired with it.
    depth: Option<PathBuf>,
}

/// Frames from image files listed up front (TUM folder or plain image folder).
pub struct ImageFilesSource {
    description: String,
    entries: Vec<ImageEntry>,
    next: usize,
    intrinsics: Option<SourceIntrinsics>,
    unreadable_depths: super::depth::UnreadableDepths,
}

/// The calibration of the TUM camera a TUM folder's name gives: the benchmark names its sequences
/// `rgbd_dataset_freiburgN_...` after the Kinect that recorded them (fr1, fr2, fr3), whose published
/// intrinsics are the `camera.preset` values `tum_frN`.
pub fn intrinsics_from_folder_name(dir: &Path) -> Option<SourceIntrinsics> {
    let absolute = dir.canonicalize().ok()?;
    let name = absolute.file_name()?.to_str()?;
    let camera = name.strip_prefix("rgbd_dataset_freiburg")?.split('_').next()?;
    let preset = format!("tum_fr{camera}");
    let intrinsics = crate::verification::Intrinsics::preset(&preset)?;
    Some(SourceIntrinsics { intrinsics, origin: format!("the TUM folder name {name} (camera.preset {preset})") })
}

impl ImageFilesSource {
    /// A TUM folder: `dir/rgb.txt` lists the images. Every listed file must exist (checked up
    /// front so that a broken sequence fails before any work is done).
    pub fn open_tum(dir: &Path) -> Result<ImageFilesSource> {
        let list = dir.join("rgb.txt");
        let mut entries: Vec<ImageEntry> = read_list(dir, &list, "image file")?
            .into_iter()
            .map(|(origin, stamp, path)| ImageEntry { origin, stamp, path, depth: None })
            .collect();
        ensure!(!entries.is_empty(), "{} lists no images", list.display());
        let depth_list = dir.join("depth.txt");
        if depth_list.exists() {
            let depths = read_list(dir, &depth_list, "depth image")?;
            let paired = associate_depth(&mut entries, depths);
            log::info!("{}: {paired} of {} images have a depth image", depth_list.display(), entries.len());
        }
        // Frames replay in file order; stamps that repeat or go back are kept but said.
        let repeated = entries.windows(2).filter(|w| w[1].stamp == w[0].stamp).count();
        let backwards = entries.windows(2).filter(|w| w[1].stamp < w[0].stamp).count();
        if repeated + backwards > 0 {
            log::warn!(
                "{}: {repeated} stamp(s) repeat the previous line's and {backwards} go back in time; frames are replayed in file order",
                list.display()
            );
        }
        let description = format!("TUM folder {} ({} images)", dir.display(), entries.len());
        let intrinsics = intrinsics_from_folder_name(dir);
        Ok(ImageFilesSource { description, entries, next: 0, intrinsics, unreadable_depths: Default::default() })
    }

    /// A folder of image files in name order; stamps are the index in seconds.
    pub fn open_image_folder(dir: &Path) -> Result<ImageFilesSource> {
        let paths = image_files_in_name_order(dir)?;
        ensure!(!paths.is_empty(), "{} has no rgb.txt and no png/jpg/jpeg/bmp images", dir.display());
        let entries: Vec<ImageEntry> = paths
            .into_iter()
            .enumerate()
            .map(|(i, path)| ImageEntry {
                origin: format!("image {i}"),
                stamp: Stamp::from_sec_nsec(i as i64, 0),
                path,
                depth: None,
            })
            .collect();
        let description = format!("image folder {} ({} images)", dir.display(), entries.len());
        Ok(ImageFilesSource { description, entries, next: 0, intrinsics: None, unreadable_depths: Default::default() })
    }
}

/// The `timestamp path` lines of `rgb.txt` or `depth.txt` with their origin (`file:line`), every
/// listed file checked up front so that a broken sequence fails before any work is done.
fn read_list(dir: &Path, list: &Path, what: &str) -> Result<Vec<(String, Stamp, PathBuf)>> {
    let mut entries = Vec::new();
    for (line_no, line) in data_lines(list)? {
        let origin = format!("{}:{line_no}", list.display());
        let mut fields = line.split_whitespace();
        let (Some(stamp_text), Some(rel), None) = (fields.next(), fields.next(), fields.next()) else {
            bail!("{origin}: expected `timestamp path`, found {}", super::excerpt(&line, 80));
        };
        let stamp = Stamp::parse_secs(stamp_text).with_context(|| {
            format!("{origin}: bad timestamp {}{}", super::excerpt(stamp_text, 40), stamp_problem(stamp_text))
        })?;
        let path = dir.join(rel);
        if !path.is_file() {
            let shown = if rel.len() <= 200 { path.display().to_string() } else { super::excerpt(rel, 120) };
            bail!("{origin}: {what} {shown} {}", not_a_file_reason(&path));
        }
        entries.push((origin, stamp, path));
    }
    Ok(entries)
}

/// Pairs each image with the depth image nearest in time, within [`DEPTH_ASSOCIATION`]; returns how
/// many were paired.
fn associate_depth(entries: &mut [ImageEntry], depths: Vec<(String, Stamp, PathBuf)>) -> usize {
    let mut depths: Vec<(Stamp, PathBuf)> = depths.into_iter().map(|(_, stamp, path)| (stamp, path)).collect();
    depths.sort_by_key(|(stamp, _)| *stamp);
    let stamps: Vec<Stamp> = depths.iter().map(|(stamp, _)| *stamp).collect();
    let mut paired = 0;
    for entry in entries.iter_mut() {
        if let Some(i) = crate::types::nearest_stamp(&stamps, entry.stamp, DEPTH_ASSOCIATION) {
            entry.depth = Some(depths[i].1.clone());
            paired += 1;
        }
    }
    paired
}

/// Reads a TUM 16-bit depth PNG; it must have the colour image's size.
/// The depth image `path` of a `width` x `height` colour image: `None` (counted in `unreadable`) where
/// the file does not decode, an error where it cannot be read or is no TUM depth image of that size
/// (a `depth.txt` naming other images: every frame would go on without depth).
fn load_depth(
    path: &Path,
    width: u32,
    height: u32,
    unreadable: &mut super::depth::UnreadableDepths,
) -> Result<Option<DepthImage>> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read depth image {}", path.display()))?;
    let image = match crate::preprocess::decode_image_file(path, &bytes) {
        Ok(image) => image,
        Err(err) => {
            unreadable.skip(&err.context(format!("cannot decode depth image {}", path.display())));
            return Ok(None);
        }
    };
    let image::DynamicImage::ImageLuma16(depth) = image else {
        bail!("depth image {} is not a 16-bit grayscale PNG (TUM depth: 5000 units per metre)", path.display());
    };
    ensure!(
        depth.width() == width && depth.height() == height,
        "depth image {} is {}x{}, its colour image {width}x{height}",
        path.display(),
        depth.width(),
        depth.height()
    );
    Ok(Some(DepthImage::from_tum(&depth)))
}

/// Whether `path`'s name ends in an image folder's extension: png, jpg, jpeg or bmp, in any case.
pub fn has_image_extension(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["png", "jpg", "jpeg", "bmp"].iter().any(|known| e.eq_ignore_ascii_case(known)))
}

/// Extensions of image formats this build does not read: such a file in an image folder is a
/// frame the user expects and does not get.
const UNREAD_IMAGE_EXTENSIONS: [&str; 9] = ["tif", "tiff", "webp", "gif", "pgm", "ppm", "pnm", "jxl", "heic"];

/// The image files (png, jpg, jpeg, bmp; any case) directly inside `dir`, in no order. Hidden
/// files are left out: a name starting with a dot is no frame (macOS writes `._name.png` beside
/// every image it copies to a foreign disk). Images this build does not read (TIFF, WebP, ...) and
/// links to nothing are named in a warning: they are frames the user meant, and a loops file that
/// counts them is off by one for each; other files (lists, notes) are left out quietly.
pub fn image_files_in(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut paths = Vec::new();
    let (mut hidden, mut missed) = (0, Vec::new());
    for entry in fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))? {
        let path = entry.with_context(|| format!("cannot list {}", dir.display()))?.path();
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let extension = path.extension().and_then(|e| e.to_str()).unwrap_or_default().to_ascii_lowercase();
        let dangling = !path.exists() && path.is_symlink();
        if name.starts_with('.') {
            hidden += 1;
        } else if path.is_file() && has_image_extension(&path) {
            paths.push(path);
        } else if dangling || UNREAD_IMAGE_EXTENSIONS.contains(&extension.as_str()) {
            missed.push(name);
        }
    }
    if hidden > 0 {
        log::info!("{}: {hidden} hidden files (names starting with a dot) left out", dir.display());
    }
    if !missed.is_empty() {
        missed.sort();
        let shown = missed.iter().take(5).cloned().collect::<Vec<_>>().join(", ");
        log::warn!(
            "{}: {} images left out, in a format not read here (png, jpg, jpeg, bmp are) or links to nothing: {shown}{}",
            dir.display(),
            missed.len(),
            if missed.len() > 5 { ", ..." } else { "" }
        );
    }
    Ok(paths)
}

/// The image files of [`image_files_in`] in name order with numbers compared by value (`frame2`
/// before `frame10`), as cameras and tools that number their frames without leading zeros mean
/// them; zero-padded names keep their plain order. Where every name is a decimal number (stamps
/// such as `1341847981.1.png` and `1341847981.033333.png`), they are ordered by value.
pub(crate) fn image_files_in_name_order(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut paths = image_files_in(dir)?;
    let value = |path: &PathBuf| -> Option<f64> {
        let stem = path.file_stem()?.to_str()?;
        stem.parse::<f64>().ok().filter(|v| v.is_finite() && stem.bytes().all(|b| b.is_ascii_digit() || b == b'.'))
    };
    let values: Option<Vec<f64>> = paths.iter().map(value).collect();
    match values {
        Some(_) if !paths.is_empty() => {
            paths.sort_by(|a, b| {
                let (x, y) = (value(a).expect("checked above"), value(b).expect("checked above"));
                x.total_cmp(&y).then_with(|| alphanumeric_sort::compare_path(a, b))
            });
        }
        _ => alphanumeric_sort::sort_path_slice(&mut paths),
    }
    Ok(paths)
}

impl Iterator for ImageFilesSource {
    type Item = Result<Frame>;

    fn next(&mut self) -> Option<Result<Frame>> {
        let entry = self.entries.get(self.next)?;
        let index = self.next;
        self.next += 1;
        // A file that cannot be read (a disk gone) ends the source; one that does not decode is an
        // unreadable frame, and the frames after it are still read (module doc of `io`).
        let bytes = match std::fs::read(&entry.path) {
            Ok(bytes) => bytes,
            Err(err) => {
                let err = anyhow::Error::new(err);
                return Some(Err(err.context(format!("{}: cannot read image {}", entry.origin, entry.path.display()))));
            }
        };
        let loaded = crate::preprocess::decode_image_file(&entry.path, &bytes)
            .with_context(|| format!("{}: cannot decode image {}", entry.origin, entry.path.display()))
            .map_err(|err| super::UnreadableFrame::error(index, entry.stamp, &err));
        let frame = loaded.and_then(|img| {
            let image = img.into_rgb8();
            let depth = match &entry.depth {
                Some(path) => load_depth(path, image.width(), image.height(), &mut self.unreadable_depths)
                    .with_context(|| entry.origin.clone())?,
                None => None,
            };
            Ok(Frame { index, stamp: entry.stamp, image, depth })
        });
        if self.next == self.entries.len() {
            self.unreadable_depths.report_end();
        }
        Some(frame)
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.entries.len() - self.next;
        (left, Some(left))
    }
}

impl FrameSource for ImageFilesSource {
    fn describe(&self) -> String {
        self.description.clone()
    }

    fn len_hint(&self) -> Option<usize> {
        Some(self.entries.len())
    }

    fn intrinsics(&self) -> Option<SourceIntrinsics> {
        self.intrinsics.clone()
    }
}

/// Reads a TUM trajectory (`timestamp tx ty tz qx qy qz qw` per line, `#` comments). The
/// quaternion is normalised; a zero quaternion is an error.
pub fn read_groundtruth(path: &Path) -> Result<Vec<(Stamp, Isometry3<f64>)>> {
    let mut poses = Vec::new();
    for (line_no, line) in data_lines(path)? {
        let origin = || format!("{}:{line_no}", path.display());
        let fields: Vec<&str> = line.split_whitespace().collect();
        ensure!(
            fields.len() == 8,
            "{}: expected 8 fields `timestamp tx ty tz qx qy qz qw`, found {}",
            origin(),
            fields.len()
        );
        let stamp = Stamp::parse_secs(fields[0]).with_context(|| {
            format!("{}: bad timestamp {}{}", origin(), super::excerpt(fields[0], 40), stamp_problem(fields[0]))
        })?;
        let mut values = [0f64; 7];
        for (value, text) in values.iter_mut().zip(&fields[1..]) {
            *value = text.parse().with_context(|| format!("{}: bad number {text:?}", origin()))?;
            ensure!(value.is_finite(), "{}: non-finite number {text:?}", origin());
        }
        let [tx, ty, tz, qx, qy, qz, qw] = values;
        let quaternion = Quaternion::new(qw, qx, qy, qz);
        ensure!(quaternion.norm() > 1e-9, "{}: zero quaternion", origin());
        let rotation = UnitQuaternion::from_quaternion(quaternion);
        poses.push((stamp, Isometry3::from_parts(Translation3::new(tx, ty, tz), rotation)));
    }
    Ok(poses)
}

/// Writes a TUM folder: `rgb/<stamp>.png`, `rgb.txt` and `groundtruth.txt`, and where given
/// `depth/<stamp>.png` with `depth.txt`, and an odometry trajectory `odometry.txt` (TUM trajectory
/// format, as `groundtruth.txt`). Text files are written by [`TumWriter::finish`]; images as they come.
pub struct TumWriter {
    dir: PathBuf,
    rgb_lines: String,
    depth_lines: String,
    pose_lines: String,
    odometry_lines: String,
}

impl TumWriter {
    /// Creates `dir` and `dir/rgb` (existing files with the same names are overwritten).
    pub fn create(dir: &Path) -> Result<TumWriter> {
        fs::create_dir_all(dir.join("rgb")).with_context(|| format!("cannot create {}/rgb", dir.display()))?;
        Ok(TumWriter {
            dir: dir.to_path_buf(),
            rgb_lines: "# color images\n# timestamp filename\n".to_string(),
            depth_lines: String::new(),
            pose_lines: "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n".to_string(),
            odometry_lines: String::new(),
        })
    }

    /// Stamps are written with 6 decimals (the TUM convention), so use microsecond stamps for
    /// exact round trips.
    pub fn write_frame(&mut self, stamp: Stamp, image: &RgbImage) -> Result<()> {
        let path = self.add_frame(stamp);
        image.save(&path).with_context(|| format!("cannot write {}", path.display()))
    }

    /// Lists a frame in `rgb.txt` and returns the path its PNG must be written to, for callers
    /// that encode many images in parallel.
    pub fn add_frame(&mut self, stamp: Stamp) -> PathBuf {
        let name = tum_stamp(stamp);
        let rel = format!("rgb/{name}.png");
        let _ = writeln!(self.rgb_lines, "{name} {rel}");
        self.dir.join(rel)
    }

    /// Lists a depth image in `depth.txt` (creating `depth/`) and returns the path its 16-bit PNG
    /// must be written to.
    pub fn add_depth(&mut self, stamp: Stamp) -> Result<PathBuf> {
        if self.depth_lines.is_empty() {
            fs::create_dir_all(self.dir.join("depth"))
                .with_context(|| format!("cannot create {}/depth", self.dir.display()))?;
            self.depth_lines = "# depth maps\n# timestamp filename\n".to_string();
        }
        let name = tum_stamp(stamp);
        let rel = format!("depth/{name}.png");
        let _ = writeln!(self.depth_lines, "{name} {rel}");
        Ok(self.dir.join(rel))
    }

    pub fn write_pose(&mut self, stamp: Stamp, pose: &Isometry3<f64>) -> Result<()> {
        write_trajectory_line(&mut self.pose_lines, stamp, pose);
        Ok(())
    }

    /// One pose of the odometry trajectory (`odometry.txt`).
    pub fn write_odometry(&mut self, stamp: Stamp, pose: &Isometry3<f64>) {
        if self.odometry_lines.is_empty() {
            self.odometry_lines = "# odometry trajectory (drifts)\n# timestamp tx ty tz qx qy qz qw\n".to_string();
        }
        write_trajectory_line(&mut self.odometry_lines, stamp, pose);
    }

    /// Writes `rgb.txt`, `groundtruth.txt`, and `depth.txt` and `odometry.txt` where given.
    pub fn finish(self) -> Result<()> {
        let lists = [
            ("rgb.txt", &self.rgb_lines),
            ("groundtruth.txt", &self.pose_lines),
            ("depth.txt", &self.depth_lines),
            ("odometry.txt", &self.odometry_lines),
        ];
        for (name, text) in lists {
            if text.is_empty() {
                continue;
            }
            let path = self.dir.join(name);
            fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
        }
        Ok(())
    }
}

/// Writes a TUM trajectory (`timestamp tx ty tz qx qy qz qw` per line) to `path`.
pub fn write_trajectory(path: &Path, poses: &[(Stamp, Isometry3<f64>)]) -> Result<()> {
    let mut text = "# timestamp tx ty tz qx qy qz qw\n".to_string();
    for (stamp, pose) in poses {
        write_trajectory_line(&mut text, *stamp, pose);
    }
    crate::io::output::write_replacing(path, text.as_bytes())
}

fn write_trajectory_line(text: &mut String, stamp: Stamp, pose: &Isometry3<f64>) {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    // Shortest text that reads back to the same f64: trajectories round-trip exactly.
    let _ = writeln!(text, "{} {} {} {} {} {} {} {}", tum_stamp(stamp), t.x, t.y, t.z, q.i, q.j, q.k, q.w);
}

/// `sec.micros`, as TUM files print stamps; `sec.nanos` for a stamp that is not whole microseconds
/// (a ROS header's), so that it joins its frame's exactly.
fn tum_stamp(stamp: Stamp) -> String {
    stamp.to_decimal(if stamp.nanos % 1000 == 0 { 6 } else { 9 })
}

/// A tracker's trajectory (TUM format, camera-to-world) looked up by frame stamp: each frame takes
/// the pose at the nearest stamp within [`super::TRACKER_POSE_MAX_OFFSET`] (`replay --poses`,
/// `play-keyframes --poses`).
pub struct TrackerPoses {
    path: String,
    stamps: Vec<Stamp>,
    poses: Vec<Isometry3<f64>>,
    /// Frames that found a pose.
    found: usize,
}

impl TrackerPoses {
    pub fn read(path: &Path) -> Result<TrackerPoses> {
        let mut trajectory = read_groundtruth(path)?;
        ensure!(!trajectory.is_empty(), "{}: no poses in the file", path.display());
        trajectory.sort_by_key(|(stamp, _)| *stamp);
        let (stamps, poses) = trajectory.into_iter().unzip();
        Ok(TrackerPoses { path: path.display().to_string(), stamps, poses, found: 0 })
    }

    /// The pose of the frame stamped `stamp`, if one lies near enough.
    pub fn at(&mut self, stamp: Stamp) -> Option<Isometry3<f64>> {
        let index = crate::types::nearest_stamp(&self.stamps, stamp, super::TRACKER_POSE_MAX_OFFSET)?;
        self.found += 1;
        Some(self.poses[index])
    }

    /// Logs how many of `frames` found a pose; a warning when none did (another sequence's file).
    pub fn report(&self, frames: usize) {
        if self.found == 0 && frames > 0 {
            log::warn!("no frame had a tracker pose in {} within 20 ms of its stamp: is it this source's?", self.path);
        } else {
            log::info!("{} of {frames} frames had a tracker pose in {}", self.found, self.path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tum_folder_name_gives_its_camera() {
        let dir = tempfile::tempdir().unwrap();
        let named = |name: &str| {
            let path = dir.path().join(name);
            fs::create_dir_all(&path).unwrap();
            intrinsics_from_folder_name(&path)
        };
        let fr2 = named("rgbd_dataset_freiburg2_desk").expect("fr2");
        assert_eq!(fr2.intrinsics, crate::verification::Intrinsics::preset("tum_fr2").unwrap());
        assert!(fr2.origin.contains("camera.preset tum_fr2"), "{}", fr2.origin);
        assert!(named("rgbd_dataset_freiburg3_long_office_household").is_some());
        assert_eq!(named("rgbd_dataset_freiburg4_x"), None);
        assert_eq!(named("freiburg1_desk"), None);
        assert_eq!(named("seq"), None);
    }

    #[test]
    fn writer_output_reads_back_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let seq = dir.path().join("seq");
        let mut writer = TumWriter::create(&seq).unwrap();
        let stamps = [
            Stamp::from_sec_nsec(100, 0),
            Stamp::from_sec_nsec(100, 500_000_000),
            Stamp::from_sec_nsec(101, 123_456_000),
        ];
        let pose =
            Isometry3::from_parts(Translation3::new(1.0, -2.0, 0.5), UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3));
        for (i, &stamp) in stamps.iter().enumerate() {
            let img = RgbImage::from_fn(4, 3, |x, y| image::Rgb([x as u8, y as u8, i as u8]));
            writer.write_frame(stamp, &img).unwrap();
            writer.write_pose(stamp, &pose).unwrap();
        }
        writer.finish().unwrap();

        let frames: Vec<Frame> = ImageFilesSource::open_tum(&seq).unwrap().map(|f| f.unwrap()).collect();
        assert_eq!(frames.len(), 3);
        for (i, frame) in frames.iter().enumerate() {
            assert_eq!(frame.index, i);
            assert_eq!(frame.stamp, stamps[i]);
            assert_eq!(frame.image.get_pixel(3, 2).0, [3, 2, i as u8]);
        }
        let poses = read_groundtruth(&seq.join("groundtruth.txt")).unwrap();
        assert_eq!(poses.len(), 3);
        assert_eq!(poses[2].0, stamps[2]);
        assert!((poses[2].1.translation.vector - pose.translation.vector).norm() < 1e-9);
        assert!(poses[2].1.rotation.angle_to(&pose.rotation) < 1e-8);
        assert!(frames.iter().all(|f| f.depth.is_none()), "no depth.txt, no depth");
        // A trajectory at a ROS header's nanosecond stamps keeps them, and whole microseconds keep
        // TUM's six decimals.
        let nanos = [Stamp::from_sec_nsec(1_600_000_000, 789), Stamp::from_sec_nsec(1_600_000_000, 500_000_000)];
        let path = dir.path().join("corrected.txt");
        write_trajectory(&path, &nanos.map(|stamp| (stamp, pose))).unwrap();
        let read: Vec<Stamp> = read_groundtruth(&path).unwrap().iter().map(|(stamp, _)| *stamp).collect();
        assert_eq!(read, nanos);
        assert!(std::fs::read_to_string(&path).unwrap().contains("\n1600000000.500000 "));
    }

    #[test]
    fn depth_images_pair_with_the_nearest_colour_image_within_20_ms() {
        let dir = tempfile::tempdir().unwrap();
        let seq = dir.path().join("seq");
        let mut writer = TumWriter::create(&seq).unwrap();
        let colour =
            [Stamp::from_sec_nsec(10, 0), Stamp::from_sec_nsec(10, 100_000_000), Stamp::from_sec_nsec(10, 200_000_000)];
        // Depth 15 ms after the first image, 5 ms before the second; none near the third.
        let depth_stamps = [
            Stamp::from_sec_nsec(10, 15_000_000),
            Stamp::from_sec_nsec(10, 95_000_000),
            Stamp::from_sec_nsec(10, 400_000_000),
        ];
        for &stamp in &colour {
            writer.write_frame(stamp, &RgbImage::new(4, 3)).unwrap();
        }
        for (i, &stamp) in depth_stamps.iter().enumerate() {
            let depth = DepthImage { width: 4, height: 3, metres: vec![1.0 + i as f32; 12] };
            depth.to_tum().save(writer.add_depth(stamp).unwrap()).unwrap();
        }
        writer.finish().unwrap();
        let frames: Vec<Frame> = ImageFilesSource::open_tum(&seq).unwrap().map(|f| f.unwrap()).collect();
        let depth_at = |f: &Frame| f.depth.as_ref().map(|d| d.at(1.5, 1.5).unwrap());
        // The second depth (95 ms) is nearer the second image; the first (15 ms) the first image.
        assert_eq!(frames.iter().map(depth_at).collect::<Vec<_>>(), [Some(1.0), Some(2.0), None]);
        // A depth image that does not decode is passed over (warned): its frame goes on without
        // depth, the others keep theirs.
        let kept = fs::read(seq.join("depth/10.095000.png")).unwrap();
        fs::write(seq.join("depth/10.095000.png"), b"cut").unwrap();
        let frames: Vec<Frame> = ImageFilesSource::open_tum(&seq).unwrap().map(|f| f.unwrap()).collect();
        assert_eq!(frames.iter().map(depth_at).collect::<Vec<_>>(), [Some(1.0), None, None]);
        fs::write(seq.join("depth/10.095000.png"), kept).unwrap();
        // One of another size is no depth image of this camera (depth.txt naming other images): the
        // error names it.
        let wrong = DepthImage { width: 2, height: 2, metres: vec![1.0; 4] };
        wrong.to_tum().save(seq.join("depth/10.095000.png")).unwrap();
        let err = format!("{:#}", ImageFilesSource::open_tum(&seq).unwrap().nth(1).unwrap().unwrap_err());
        assert!(err.contains("10.095000.png") && err.contains("2x2"), "{err}");
    }

    #[test]
    fn bad_rgb_txt_lines_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join("rgb.txt"), "# comment\n\n1.0 rgb/missing.png\n").unwrap();
        let err = ImageFilesSource::open_tum(dir.path()).err().unwrap().to_string();
        assert!(err.contains("rgb.txt:3") && err.contains("missing.png") && err.contains("does not exist"), "{err}");
        fs::write(dir.path().join("rgb.txt"), "abc rgb/x.png\n").unwrap();
        let err = ImageFilesSource::open_tum(dir.path()).err().unwrap().to_string();
        assert!(err.contains("rgb.txt:1: bad timestamp \"abc\""), "{err}");
        // A byte-order mark is not part of the first stamp.
        fs::write(dir.path().join("rgb.txt"), "\u{feff}abc rgb/x.png\n").unwrap();
        let err = ImageFilesSource::open_tum(dir.path()).err().unwrap().to_string();
        assert!(err.contains("rgb.txt:1: bad timestamp \"abc\""), "{err}");
        std::fs::write(dir.path().join("rgb.txt"), "99999999999999999999.0 a.png\n").unwrap();
        let err = format!("{:#}", ImageFilesSource::open_tum(dir.path()).err().unwrap());
        assert!(err.contains("rgb.txt:1") && err.contains("out of range"), "{err}");
        fs::write(dir.path().join("rgb.txt"), "1.0\n").unwrap();
        let err = ImageFilesSource::open_tum(dir.path()).err().unwrap().to_string();
        assert!(err.contains("expected `timestamp path`"), "{err}");
        // A listed file that is not an image fails when it is read, naming the line.
        fs::create_dir(dir.path().join("rgb")).unwrap();
        fs::write(dir.path().join("rgb/a.png"), b"not a png").unwrap();
        fs::write(dir.path().join("rgb.txt"), "1.0 rgb/a.png\n").unwrap();
        let err = format!("{:#}", ImageFilesSource::open_tum(dir.path()).unwrap().next().unwrap().unwrap_err());
        assert!(err.contains("rgb.txt:1: cannot decode image"), "{err}");
    }

    /// An image that does not decode is skipped, in a TUM folder and in an image folder alike: the
    /// frames after it are read with their own indexes.
    #[test]
    fn an_image_that_does_not_decode_is_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let written = crate::io::test_frames(4, 8, 6, Stamp::from_sec_nsec(1_341_847_980, 0));
        fs::create_dir(dir.path().join("rgb")).unwrap();
        let mut listing = String::new();
        for (i, (stamp, image)) in written.iter().enumerate() {
            image.save(dir.path().join(format!("rgb/{i}.png"))).unwrap();
            listing.push_str(&format!("{stamp} rgb/{i}.png\n"));
        }
        fs::write(dir.path().join("rgb/1.png"), b"not a png").unwrap();
        fs::write(dir.path().join("rgb.txt"), listing).unwrap();
        let read = ImageFilesSource::open_tum(dir.path()).unwrap().collect();
        crate::io::assert_skips_unreadable(read, &written, 1, written[1].0, "rgb.txt:2: cannot decode image");
        // The image folder's stamps count seconds from 0 by name order.
        let folder: Vec<_> = written
            .iter()
            .enumerate()
            .map(|(i, (_, image))| (Stamp::from_sec_nsec(i as i64, 0), image.clone()))
            .collect();
        let read = ImageFilesSource::open_image_folder(&dir.path().join("rgb")).unwrap().collect();
        crate::io::assert_skips_unreadable(read, &folder, 1, folder[1].0, "1.png");
        // A file that cannot be read at all (an I/O error: a disk gone) is no unreadable frame: it
        // ends the source, where skipping would pass over every frame after it.
        #[cfg(target_os = "linux")]
        {
            fs::remove_file(dir.path().join("rgb/2.png")).unwrap();
            std::os::unix::fs::symlink("/proc/self/mem", dir.path().join("rgb/2.png")).unwrap();
            let read: Vec<Result<Frame>> = ImageFilesSource::open_tum(dir.path()).unwrap().collect();
            let err = read[2].as_ref().unwrap_err();
            assert!(crate::io::unreadable_frame(err).is_none(), "{err:#}");
            assert!(format!("{err:#}").contains("rgb.txt:3: cannot read image"), "{err:#}");
        }
    }

    #[test]
    fn bad_groundtruth_lines_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("groundtruth.txt");
        fs::write(&path, "# c\n1.0 0 0 0 0 0 0 1\n2.0 0 0 x 0 0 0 1\n").unwrap();
        let err = read_groundtruth(&path).unwrap_err().to_string();
        assert!(err.contains("groundtruth.txt:3: bad number \"x\""), "{err}");
        fs::write(&path, "1.0 0 0 0 0 0 0 0\n").unwrap();
        assert!(read_groundtruth(&path).unwrap_err().to_string().contains("zero quaternion"));
        fs::write(&path, "1.0 0 0 0\n").unwrap();
        assert!(read_groundtruth(&path).unwrap_err().to_string().contains("expected 8 fields"));
    }

    #[test]
    fn image_folder_replays_in_name_order_with_index_stamps() {
        let dir = tempfile::tempdir().unwrap();
        for (name, value) in [("b.png", 2u8), ("a.bmp", 1), ("c.JPG", 3)] {
            let img = RgbImage::from_pixel(2, 2, image::Rgb([value * 50; 3]));
            img.save_with_format(dir.path().join(name), image::ImageFormat::from_path(name.to_lowercase()).unwrap())
                .unwrap();
        }
        fs::write(dir.path().join("notes.txt"), "ignored").unwrap();
        let source = ImageFilesSource::open_image_folder(dir.path()).unwrap();
        assert_eq!(source.len_hint(), Some(3));
        let frames: Vec<Frame> = source.map(|f| f.unwrap()).collect();
        assert_eq!(frames.iter().map(|f| f.stamp.sec()).collect::<Vec<_>>(), vec![0, 1, 2]);
        assert_eq!(frames[0].image.get_pixel(0, 0).0, [50; 3]);
        assert_eq!(frames[1].image.get_pixel(0, 0).0, [100; 3]);
        assert!(frames[2].image.get_pixel(0, 0).0[0].abs_diff(150) < 4);
    }
    #[test]
    fn frames_numbered_without_leading_zeros_keep_their_numeric_order() {
        let dir = tempfile::tempdir().unwrap();
        let names = ["frame9.png", "frame10.png", "frame100.png", "frame2.png", "frame1.png", "frame11.png"];
        for name in names {
            fs::write(dir.path().join(name), b"x").unwrap();
        }
        let listed: Vec<_> = image_files_in_name_order(dir.path())
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_str().unwrap().to_string())
            .collect();
        assert_eq!(listed, ["frame1.png", "frame2.png", "frame9.png", "frame10.png", "frame11.png", "frame100.png"]);
        let padded = tempfile::tempdir().unwrap();
        for name in ["0000010.jpg", "0000002.jpg", "0000001.jpg"] {
            fs::write(padded.path().join(name), b"x").unwrap();
        }
        let listed: Vec<_> = image_files_in_name_order(padded.path()).unwrap();
        assert_eq!(listed, ["0000001.jpg", "0000002.jpg", "0000010.jpg"].map(|n| padded.path().join(n)));
        // Stamps as names: by value (981.1 after 981.033333), and hidden files are no frames.
        let stamps = tempfile::tempdir().unwrap();
        for name in ["1341847981.1.png", "1341847981.033333.png", "1341847980.9.png", "._1341847980.png"] {
            fs::write(stamps.path().join(name), b"x").unwrap();
        }
        let listed: Vec<_> = image_files_in_name_order(stamps.path()).unwrap();
        let expected = ["1341847980.9.png", "1341847981.033333.png", "1341847981.1.png"];
        assert_eq!(listed, expected.map(|n| stamps.path().join(n)));
    }
}
