//! TUM RGB-D folder format: reading (`rgb.txt` + images, `groundtruth.txt`), writing (for
//! synthetic sequences), and plain image folders.
//!
//! `rgb.txt` lines are `timestamp path` with `path` relative to the folder; `#` starts a
//! comment line and blank lines are skipped. `groundtruth.txt` lines are
//! `timestamp tx ty tz qx qy qz qw`. A plain image folder (no `rgb.txt`) replays its
//! `png`/`jpg`/`jpeg`/`bmp` files in file-name order with stamp = index seconds.

use anyhow::{bail, ensure, Context, Result};
use image::RgbImage;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

use super::FrameSource;
use crate::types::{Frame, Stamp};

/// Why a stamp that does not parse is bad, when it looks like a number: it is out of range.
fn stamp_problem(text: &str) -> &'static str {
    let digits = text.trim().trim_start_matches('-');
    if !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit() || b == b'.') && digits.bytes().filter(|&b| b == b'.').count() <= 1 {
        " (out of range: stamps are whole nanoseconds in a signed 64-bit integer, at most about 9.2e9 s)"
    } else {
        ""
    }
}

/// Reads the non-comment, non-blank lines of a TUM text file with their 1-based line numbers (a
/// byte-order mark at the start is skipped).
fn data_lines(path: &Path) -> Result<Vec<(usize, String)>> {
    let text = super::read_capped_text(path, super::limits::TEXT_LIST, "list")?;
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
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
}

/// Frames from image files listed up front (TUM folder or plain image folder).
pub struct ImageFilesSource {
    description: String,
    entries: Vec<ImageEntry>,
    next: usize,
}

impl ImageFilesSource {
    /// A TUM folder: `dir/rgb.txt` lists the images. Every listed file must exist (checked up
    /// front so that a broken sequence fails before any work is done).
    pub fn open_tum(dir: &Path) -> Result<ImageFilesSource> {
        let list = dir.join("rgb.txt");
        let mut entries = Vec::new();
        for (line_no, line) in data_lines(&list)? {
            let origin = format!("{}:{line_no}", list.display());
            let mut fields = line.split_whitespace();
            let (Some(stamp_text), Some(rel), None) = (fields.next(), fields.next(), fields.next()) else {
                bail!("{origin}: expected `timestamp path`, found {}", super::excerpt(&line, 80));
            };
            let stamp = Stamp::parse_secs(stamp_text)
                .with_context(|| format!("{origin}: bad timestamp {}{}", super::excerpt(stamp_text, 40), stamp_problem(stamp_text)))?;
            let path = dir.join(rel);
            if !path.is_file() {
                let shown = if rel.len() <= 200 { path.display().to_string() } else { super::excerpt(rel, 120) };
                bail!("{origin}: image file {shown} {}", not_a_file_reason(&path));
            }
            entries.push(ImageEntry { origin, stamp, path });
        }
        ensure!(!entries.is_empty(), "{} lists no images", list.display());
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
        Ok(ImageFilesSource { description, entries, next: 0 })
    }

    /// A folder of image files in file-name order; stamps are the index in seconds.
    pub fn open_image_folder(dir: &Path) -> Result<ImageFilesSource> {
        let mut paths = image_files_in(dir)?;
        ensure!(!paths.is_empty(), "{} has no rgb.txt and no png/jpg/jpeg/bmp images", dir.display());
        paths.sort();
        let entries: Vec<ImageEntry> = paths
            .into_iter()
            .enumerate()
            .map(|(i, path)| ImageEntry {
                origin: format!("image {i}"),
                stamp: Stamp::from_sec_nsec(i as i64, 0),
                path,
            })
            .collect();
        let description = format!("image folder {} ({} images)", dir.display(), entries.len());
        Ok(ImageFilesSource { description, entries, next: 0 })
    }
}

/// The image files (by extension, case-insensitive) directly inside `dir`.
pub(crate) fn image_files_in(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut paths = Vec::new();
    for entry in fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))? {
        let path = entry.with_context(|| format!("cannot list {}", dir.display()))?.path();
        let ext = path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase());
        if path.is_file() && matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg" | "bmp")) {
            paths.push(path);
        }
    }
    Ok(paths)
}

impl Iterator for ImageFilesSource {
    type Item = Result<Frame>;

    fn next(&mut self) -> Option<Result<Frame>> {
        let entry = self.entries.get(self.next)?;
        let index = self.next;
        self.next += 1;
        let loaded = image::open(&entry.path)
            .map_err(crate::io::image_msg::image_error)
            .with_context(|| format!("{}: cannot decode image {}", entry.origin, entry.path.display()));
        Some(loaded.map(|img| Frame { index, stamp: entry.stamp, image: img.into_rgb8() }))
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
}

/// Reads a TUM trajectory (`timestamp tx ty tz qx qy qz qw` per line, `#` comments). The
/// quaternion is normalised; a zero quaternion is an error.
pub fn read_groundtruth(path: &Path) -> Result<Vec<(Stamp, Isometry3<f64>)>> {
    let mut poses = Vec::new();
    for (line_no, line) in data_lines(path)? {
        let origin = || format!("{}:{line_no}", path.display());
        let fields: Vec<&str> = line.split_whitespace().collect();
        ensure!(fields.len() == 8, "{}: expected 8 fields `timestamp tx ty tz qx qy qz qw`, found {}", origin(), fields.len());
        let stamp = Stamp::parse_secs(fields[0])
            .with_context(|| format!("{}: bad timestamp {}{}", origin(), super::excerpt(fields[0], 40), stamp_problem(fields[0])))?;
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

/// Writes a TUM folder: `rgb/<stamp>.png`, `rgb.txt` and `groundtruth.txt`.
/// Text files are written by [`TumWriter::finish`]; images as they come.
pub struct TumWriter {
    dir: PathBuf,
    rgb_lines: String,
    pose_lines: String,
}

impl TumWriter {
    /// Creates `dir` and `dir/rgb` (existing files with the same names are overwritten).
    pub fn create(dir: &Path) -> Result<TumWriter> {
        fs::create_dir_all(dir.join("rgb")).with_context(|| format!("cannot create {}/rgb", dir.display()))?;
        Ok(TumWriter {
            dir: dir.to_path_buf(),
            rgb_lines: "# color images\n# timestamp filename\n".to_string(),
            pose_lines: "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n".to_string(),
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

    pub fn write_pose(&mut self, stamp: Stamp, pose: &Isometry3<f64>) -> Result<()> {
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion();
        let _ = writeln!(
            self.pose_lines,
            // Shortest text that reads back to the same f64: ground truth round-trips exactly.
            "{} {} {} {} {} {} {} {}",
            tum_stamp(stamp), t.x, t.y, t.z, q.i, q.j, q.k, q.w
        );
        Ok(())
    }

    /// Writes `rgb.txt` and `groundtruth.txt`.
    pub fn finish(self) -> Result<()> {
        for (name, text) in [("rgb.txt", &self.rgb_lines), ("groundtruth.txt", &self.pose_lines)] {
            let path = self.dir.join(name);
            fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
        }
        Ok(())
    }
}

/// `sec.micros`, as TUM files print stamps.
fn tum_stamp(stamp: Stamp) -> String {
    format!("{}.{:06}", stamp.sec(), stamp.nsec() / 1000)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writer_output_reads_back_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let seq = dir.path().join("seq");
        let mut writer = TumWriter::create(&seq).unwrap();
        let stamps = [Stamp::from_sec_nsec(100, 0), Stamp::from_sec_nsec(100, 500_000_000), Stamp::from_sec_nsec(101, 123_456_000)];
        let pose = Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 0.5),
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
        );
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
            img.save_with_format(dir.path().join(name), image::ImageFormat::from_path(name.to_lowercase()).unwrap()).unwrap();
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
}
