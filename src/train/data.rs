//! Training data: an image folder (one sub-folder per class) with its train/validation split,
//! the augmentations, and a loader thread that prepares batches while the network trains.
//!
//! Split: when the folder holds `TrainImages.txt` and `TestImages.txt` (indoorCVPR's lists, one
//! relative path `class/file.jpg` per line), those decide the split and the class of an image is
//! the folder its listed path names it in (`class/file.jpg`, `Images/class/file.jpg`); a listed
//! path is looked up under the folder and, as indoorCVPR ships its images, under `Images/`. Otherwise every image of every class sub-folder
//! is shuffled with the seed and `val_fraction` of each class (at least one image) is held out.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver};
use std::sync::Arc;
use std::thread::JoinHandle;

use anyhow::{bail, ensure, Context, Result};
use image::RgbImage;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};

use crate::preprocess::{read_image, Preprocessor};

/// Image files directly inside `dir` ([`crate::io::tum::image_files_in`]), sorted by name.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files = crate::io::tum::image_files_in(dir)?;
    files.sort();
    Ok(files)
}

/// A labelled image folder split into training and validation images.
#[derive(Clone, Debug)]
pub struct ImageFolder {
    /// Class names, sorted; a label is an index into this.
    pub classes: Vec<String>,
    pub train: Vec<(PathBuf, usize)>,
    pub val: Vec<(PathBuf, usize)>,
    /// How the split was made, for the run's JSON.
    pub split: String,
}

impl ImageFolder {
    pub fn open(dir: &Path, seed: u64, val_fraction: f64) -> Result<Self> {
        ensure!(dir.is_dir(), "{} is not a directory", dir.display());
        let (train_list, test_list) = (dir.join("TrainImages.txt"), dir.join("TestImages.txt"));
        match (train_list.is_file(), test_list.is_file()) {
            (true, true) => return Self::from_lists(dir, &train_list, &test_list),
            (false, false) => {}
            // One list alone would be left unread while every image in the folders is trained on.
            (has_train, _) => {
                let (present, missing) = if has_train { (&train_list, &test_list) } else { (&test_list, &train_list) };
                bail!(
                    "{} is there but {} is not: a split by lists needs both (or remove it to split at random)",
                    present.display(),
                    missing.display()
                );
            }
        }
        ensure!((0.0..1.0).contains(&val_fraction), "--val-fraction {val_fraction} is not in [0, 1)");
        let mut class_dirs: Vec<PathBuf> = std::fs::read_dir(dir)
            .with_context(|| format!("cannot list {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_dir())
            .collect();
        class_dirs.sort();
        let mut classes = Vec::new();
        let (mut train, mut val) = (Vec::new(), Vec::new());
        let mut rng = StdRng::seed_from_u64(seed);
        for class_dir in class_dirs {
            let mut files = image_files(&class_dir)?;
            if files.is_empty() {
                continue;
            }
            let label = classes.len();
            classes.push(class_dir.file_name().unwrap_or_default().to_string_lossy().into_owned());
            files.shuffle(&mut rng);
            ensure!(
                val_fraction == 0.0 || files.len() >= 2,
                "class folder {} has {} image, too few to split into training and validation (add images, or \
                 --val-fraction 0)",
                class_dir.display(),
                files.len()
            );
            let held_out = if val_fraction > 0.0 {
                ((files.len() as f64 * val_fraction).round() as usize).clamp(1, files.len() - 1)
            } else {
                0
            };
            for (i, f) in files.into_iter().enumerate() {
                if i < held_out {
                    val.push((f, label))
                } else {
                    train.push((f, label))
                }
            }
        }
        ensure!(
            classes.len() >= 2,
            "{} has {} class sub-folders with images; training needs at least 2",
            dir.display(),
            classes.len()
        );
        Ok(ImageFolder {
            classes,
            train,
            val,
            split: format!("random, seed {seed}, validation fraction {val_fraction}"),
        })
    }

    fn from_lists(dir: &Path, train_list: &Path, test_list: &Path) -> Result<Self> {
        let read_list = |list: &Path| -> Result<Vec<(String, PathBuf)>> {
            let text = crate::io::read_capped_text(list, crate::io::limits::TEXT_LIST, "image list")?;
            let mut out = Vec::new();
            for (line_no, line) in text.lines().enumerate() {
                let rel = line.trim();
                if rel.is_empty() || rel.starts_with('#') {
                    continue;
                }
                // The image's folder: `./a/x.png` and `Images/a/x.png` both name class `a`.
                let names: Vec<_> =
                    Path::new(rel).components().filter(|c| matches!(c, std::path::Component::Normal(_))).collect();
                let class = names.len().checked_sub(2).map(|i| &names[i]);
                let class = class
                    .with_context(|| format!("{} line {}: '{rel}' is not class/file", list.display(), line_no + 1))?;
                let path = [dir.join(rel), dir.join("Images").join(rel)].into_iter().find(|p| p.is_file());
                let path = path.with_context(|| {
                    format!("{} line {}: no file {rel} under {}", list.display(), line_no + 1, dir.display())
                })?;
                out.push((class.as_os_str().to_string_lossy().into_owned(), path));
            }
            Ok(out)
        };
        let (train, val) = (read_list(train_list)?, read_list(test_list)?);
        let mut classes: Vec<String> = train.iter().map(|(c, _)| c.clone()).collect();
        classes.sort();
        classes.dedup();
        ensure!(
            classes.len() >= 2,
            "{} lists {} classes; training needs at least 2",
            train_list.display(),
            classes.len()
        );
        let label = |c: &str| classes.binary_search_by(|x| x.as_str().cmp(c)).ok();
        let train = train.iter().map(|(c, p)| (p.clone(), label(c).expect("listed class"))).collect();
        let mut labelled_val = Vec::new();
        for (c, p) in &val {
            let l = label(c).with_context(|| {
                format!("{}: class {c} of {} has no training images", test_list.display(), p.display())
            })?;
            labelled_val.push((p.clone(), l));
        }
        Ok(ImageFolder { classes, train, val: labelled_val, split: "TrainImages.txt / TestImages.txt".into() })
    }
}

/// Augmentation strength.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Augment {
    /// Smallest area fraction of a random resized crop (largest is 1).
    pub min_crop_area: f64,
    pub flip: bool,
    /// Brightness, contrast and saturation factors are drawn from [1 - j, 1 + j].
    pub colour_jitter: f64,
}

impl Augment {
    pub const NONE: Augment = Augment { min_crop_area: 1.0, flip: false, colour_jitter: 0.0 };
}

/// Random resized crop (area fraction and aspect ratio 3/4..4/3, as Inception training does),
/// then the project's preprocessing at `size`, a random horizontal flip and colour jitter.
/// Output: `[3, size, size]` values in [-1, 1], channel-major.
pub fn augmented_chw(
    image: &RgbImage,
    augment: &Augment,
    pre: &mut Preprocessor,
    rng: &mut StdRng,
) -> Result<Vec<f32>> {
    let (w, h) = (image.width() as f64, image.height() as f64);
    let cropped;
    let image = if augment.min_crop_area < 1.0 {
        let area = rng.random_range(augment.min_crop_area..=1.0) * w * h;
        let ratio = (rng.random_range((0.75f64).ln()..=(4.0f64 / 3.0).ln())).exp();
        let cw = ((area * ratio).sqrt().round()).clamp(1.0, w) as u32;
        let ch = ((area / ratio).sqrt().round()).clamp(1.0, h) as u32;
        let x = rng.random_range(0..=image.width() - cw);
        let y = rng.random_range(0..=image.height() - ch);
        cropped = image::imageops::crop_imm(image, x, y, cw, ch).to_image();
        &cropped
    } else {
        image
    };
    let mut chw = pre.chw(image)?;
    let size = pre.size();
    let plane = size * size;
    if augment.flip && rng.random_bool(0.5) {
        for row in chw.chunks_exact_mut(size) {
            row.reverse();
        }
    }
    let j = augment.colour_jitter;
    if j > 0.0 {
        let mut factor = || rng.random_range(1.0 - j..=1.0 + j) as f32;
        let (brightness, contrast, saturation) = (factor(), factor(), factor());
        // In [0, 1] units: brightness scales, contrast blends with the image's mean grey,
        // saturation blends each pixel with its own grey.
        let to01 = |v: f32| (v + 1.0) * 0.5;
        let grey: Vec<f32> = (0..plane)
            .map(|i| 0.299 * to01(chw[i]) + 0.587 * to01(chw[plane + i]) + 0.114 * to01(chw[2 * plane + i]))
            .collect();
        let mean_grey = grey.iter().sum::<f32>() / plane as f32 * brightness;
        for c in 0..3 {
            for i in 0..plane {
                let mut v = to01(chw[c * plane + i]) * brightness;
                v = (v - mean_grey) * contrast + mean_grey;
                let g = grey[i] * brightness;
                v = (v - g) * saturation + g;
                chw[c * plane + i] = v.clamp(0.0, 1.0) * 2.0 - 1.0;
            }
        }
    }
    Ok(chw)
}

/// Where a loader gets image `i` and its label from.
pub trait ImageSet: Send + Sync {
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    fn image(&self, index: usize) -> Result<RgbImage>;
    fn label(&self, index: usize) -> usize;
}

/// Labelled image files, read from disk when needed.
pub struct FileSet(pub Vec<(PathBuf, usize)>);

impl ImageSet for FileSet {
    fn len(&self) -> usize {
        self.0.len()
    }
    fn image(&self, index: usize) -> Result<RgbImage> {
        read_image(&self.0[index].0)
    }
    fn label(&self, index: usize) -> usize {
        self.0[index].1
    }
}

/// Images held in memory (unlabelled: every label is 0).
pub struct MemorySet(pub Vec<RgbImage>);

impl ImageSet for MemorySet {
    fn len(&self) -> usize {
        self.0.len()
    }
    fn image(&self, index: usize) -> Result<RgbImage> {
        Ok(self.0[index].clone())
    }
    fn label(&self, _: usize) -> usize {
        0
    }
}

/// A batch: `data` is `[n, 3, size, size]` flattened.
pub struct Batch {
    pub data: Vec<f32>,
    pub labels: Vec<u32>,
}

impl Batch {
    pub fn len(&self) -> usize {
        self.labels.len()
    }
    pub fn is_empty(&self) -> bool {
        self.labels.is_empty()
    }
    pub fn tensor(&self, size: usize) -> Result<candle_core::Tensor> {
        Ok(candle_core::Tensor::from_slice(&self.data, (self.len(), 3, size, size), &candle_core::Device::Cpu)?)
    }
}

/// One epoch of batches, prepared on a separate thread (a bounded channel keeps it at most a few
/// batches ahead). The order is a shuffle seeded by `seed`; a last batch of one image is dropped
/// (BatchNorm needs two). The thread stops early when the receiver is dropped.
pub struct Loader {
    pub batches: Receiver<Result<Batch>>,
    thread: Option<JoinHandle<()>>,
}

impl Loader {
    pub fn spawn(
        set: Arc<dyn ImageSet>,
        batch: usize,
        size: usize,
        augment: Augment,
        shuffle: bool,
        seed: u64,
    ) -> Loader {
        let (tx, rx) = sync_channel(3);
        let thread = std::thread::spawn(move || {
            // A panic here would only close the channel, and the epoch would end as if done.
            let on_panic = tx.clone();
            let loaded = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                let mut rng = StdRng::seed_from_u64(seed);
                let mut order: Vec<usize> = (0..set.len()).collect();
                if shuffle {
                    order.shuffle(&mut rng);
                }
                let mut pre = Preprocessor::new(size);
                for chunk in order.chunks(batch.max(1)) {
                    if chunk.len() < 2 && shuffle {
                        break;
                    }
                    let mut out = Batch {
                        data: Vec::with_capacity(chunk.len() * 3 * size * size),
                        labels: Vec::with_capacity(chunk.len()),
                    };
                    let result = chunk.iter().try_for_each(|&i| {
                        let image = set.image(i)?;
                        out.data.extend(augmented_chw(&image, &augment, &mut pre, &mut rng)?);
                        out.labels.push(set.label(i) as u32);
                        Ok(())
                    });
                    let failed = result.is_err();
                    if tx.send(result.map(|_| out)).is_err() || failed {
                        return;
                    }
                }
            }));
            if let Err(panic) = loaded {
                let why = panic
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| panic.downcast_ref::<String>().cloned());
                let _ = on_panic.send(Err(anyhow::anyhow!("the batch loader failed: {}", why.unwrap_or_default())));
            }
        });
        Loader { batches: rx, thread: Some(thread) }
    }
}

impl Drop for Loader {
    fn drop(&mut self) {
        // Unblock the thread (its send fails once the receiver is gone), then wait for it.
        let (_, dummy) = sync_channel(0);
        drop(std::mem::replace(&mut self.batches, dummy));
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// `image` scaled so its short side is `keep_side` (unchanged when already no longer than that).
pub fn shrink_to_short_side(image: RgbImage, keep_side: u32) -> RgbImage {
    let short = image.width().min(image.height());
    if short <= keep_side {
        return image;
    }
    let scale = |side: u32| ((side as u64 * keep_side as u64 / short as u64) as u32).max(1);
    image::imageops::resize(&image, scale(image.width()), scale(image.height()), image::imageops::FilterType::Triangle)
}

/// Every image of `source` (an image folder with sub-folders, or anything [`crate::io::open_source`]
/// replays), each scaled so its shorter side is `keep_side` (memory stays small), at most
/// `max_images` evenly spread over the source. A sub-folder is read as what it is: a folder of
/// images, or a replay source (a TUM folder, a ROS 2 bag folder).
pub fn load_unlabelled(source: &Path, keep_side: u32, max_images: usize) -> Result<Vec<RgbImage>> {
    let subfolders: Vec<PathBuf> = if crate::io::is_image_folder(source) && image_files(source)?.is_empty() {
        let mut dirs: Vec<PathBuf> = std::fs::read_dir(source)
            .with_context(|| format!("cannot list {}", source.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_dir())
            .collect();
        dirs.sort();
        dirs
    } else {
        Vec::new()
    };
    // Only the images chosen are kept: image files are read once chosen, and a replay source is
    // played twice, to count its frames and then to keep the chosen ones.
    enum Item {
        File(PathBuf),
        Frame { source: usize, index: usize },
    }
    let mut items = Vec::new();
    let mut replayed: Vec<PathBuf> = Vec::new();
    let mut add_source = |path: &Path, items: &mut Vec<Item>| -> Result<()> {
        let frames = crate::io::open_source(path, None)?;
        let count = match frames.len_hint() {
            Some(count) => count,
            None => frames.count(),
        };
        items.extend((0..count).map(|index| Item::Frame { source: replayed.len(), index }));
        replayed.push(path.to_path_buf());
        Ok(())
    };
    if subfolders.is_empty() {
        add_source(source, &mut items)?;
    }
    for folder in &subfolders {
        if crate::io::is_image_folder(folder) {
            items.extend(image_files(folder)?.into_iter().map(Item::File));
        } else {
            add_source(folder, &mut items)?;
        }
    }
    let chosen = spread(&items, max_images);
    let mut kept: std::collections::HashMap<(usize, usize), RgbImage> = std::collections::HashMap::new();
    for (number, path) in replayed.iter().enumerate() {
        let wanted: std::collections::HashSet<usize> = chosen
            .iter()
            .filter_map(|item| match item {
                Item::Frame { source, index } if *source == number => Some(*index),
                _ => None,
            })
            .collect();
        for frame in crate::io::skip_unreadable(crate::io::open_source(path, None)?, path) {
            let frame = frame.with_context(|| format!("cannot read the frames of {}", path.display()))?;
            if wanted.contains(&frame.index) {
                kept.insert((number, frame.index), shrink_to_short_side(frame.image, keep_side));
            }
        }
    }
    let mut images = Vec::new();
    for item in chosen {
        match item {
            Item::File(path) => images.push(shrink_to_short_side(read_image(path)?, keep_side)),
            // An unreadable frame (passed over with a warning) is missing.
            Item::Frame { source, index } => images.extend(kept.remove(&(*source, *index))),
        }
    }
    if images.len() < 4 {
        bail!("{} has {} images; distillation needs at least 4", source.display(), images.len());
    }
    Ok(images)
}

/// At most `n` items of `items`, evenly spread.
fn spread<T>(items: &[T], n: usize) -> Vec<&T> {
    if items.len() <= n {
        return items.iter().collect();
    }
    (0..n).map(|i| &items[i * items.len() / n]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A folder with a class sub-folder per `(name, images)`, the images empty files (listing only).
    fn folder(classes: &[(&str, usize)]) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        for (name, images) in classes {
            std::fs::create_dir(dir.path().join(name)).unwrap();
            for i in 0..*images {
                std::fs::write(dir.path().join(name).join(format!("{i}.png")), b"").unwrap();
            }
        }
        dir
    }

    #[test]
    fn a_split_that_cannot_be_made_is_refused_with_a_reason() {
        let dir = folder(&[("a", 1), ("b", 3)]);
        let err = ImageFolder::open(dir.path(), 1, 0.2).unwrap_err().to_string();
        assert!(err.contains("has 1 image, too few to split") && err.contains("--val-fraction 0"), "{err}");
        let all = ImageFolder::open(dir.path(), 1, 0.0).unwrap();
        assert_eq!((all.train.len(), all.val.len()), (4, 0));
        let split = ImageFolder::open(folder(&[("a", 2), ("b", 3)]).path(), 1, 0.2).unwrap();
        assert_eq!((split.train.len(), split.val.len()), (3, 2));
        // One list without the other is not silently ignored.
        std::fs::write(dir.path().join("TrainImages.txt"), "a/0.png\n./b/0.png\n").unwrap();
        let err = ImageFolder::open(dir.path(), 1, 0.0).unwrap_err().to_string();
        assert!(err.contains("TrainImages.txt is there but") && err.contains("TestImages.txt is not"), "{err}");
        // With both lists; `./b/0.png` and `Images/b/9.png` are class b.
        std::fs::create_dir_all(dir.path().join("Images/b")).unwrap();
        std::fs::copy(dir.path().join("b/1.png"), dir.path().join("Images/b/9.png")).unwrap();
        std::fs::write(dir.path().join("TestImages.txt"), "b/1.png\nImages/b/9.png\n").unwrap();
        let listed = ImageFolder::open(dir.path(), 1, 0.0).unwrap();
        assert_eq!(
            (listed.classes.clone(), listed.train.len(), listed.val.len()),
            (vec!["a".into(), "b".into()], 2, 2)
        );
    }

    /// Sub-folders are read as what they are: a folder of images, or a TUM folder whose images are
    /// listed in `rgb.txt` under `rgb/`.
    #[test]
    fn unlabelled_sub_folders_may_be_replay_sources() {
        let dir = tempfile::tempdir().unwrap();
        let frames = crate::io::test_frames(6, 16, 12, crate::types::Stamp::from_nanos(0));
        let plain = dir.path().join("a_images");
        let tum = dir.path().join("b_tum");
        std::fs::create_dir_all(&plain).unwrap();
        std::fs::create_dir_all(tum.join("rgb")).unwrap();
        let mut list = String::new();
        for (i, (_, image)) in frames.iter().enumerate() {
            if i < 2 {
                image.save(plain.join(format!("{i}.png"))).unwrap();
            } else {
                image.save(tum.join(format!("rgb/{i}.png"))).unwrap();
                list.push_str(&format!("{i}.0 rgb/{i}.png\n"));
            }
        }
        std::fs::write(tum.join("rgb.txt"), list).unwrap();
        let images = load_unlabelled(dir.path(), 64, 100).unwrap();
        assert_eq!(images.len(), 6);
        let blue: Vec<u8> = images.iter().map(|image| image.get_pixel(0, 0)[2]).collect();
        assert_eq!(blue, vec![0, 20, 40, 60, 80, 100]);
        // At most `max_images`, spread over both.
        let blue: Vec<u8> = load_unlabelled(dir.path(), 64, 4).unwrap().iter().map(|i| i.get_pixel(0, 0)[2]).collect();
        assert_eq!(blue, vec![0, 20, 60, 80]);
    }
}
