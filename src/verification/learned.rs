//! Learned local features for verification: XFeat's dense features ([`crate::model::xfeat`]), which
//! match where ORB does not (a place by day and by night).
//!
//! Each keyframe keeps the `verification.features` best cells of the 1/8 map (reliability times
//! keypoint probability, XFeat's score): the keypoint at the cell's most probable pixel and the
//! cell's unit feature, quantised to `i8`. Two keyframes' features match when each is the other's
//! most similar (cosine) and the similarity exceeds [`MIN_COSINE`], XFeat's own matching rule.
//! RANSAC's pixel threshold applies in the network's input pixels, so it scales with the image.

use std::path::Path;
use std::sync::Arc;

use anyhow::Result;
use image::GrayImage;

use super::{Descriptors, LocalFeatures};
use crate::model::xfeat::{XFeat, CELL, SIDE_MULTIPLE};

pub use crate::model::xfeat::FEATURE_DIM;

/// Images are scaled down to at most this width for the network (its published setting, VGA).
pub const MAX_INPUT_WIDTH: u32 = 640;
/// ... and up to at least this width: a low-resolution camera's image has too few of XFeat's 8-pixel
/// cells to match (64x48 would have 8x4), while its upscaled copy keeps matching.
pub const MIN_INPUT_WIDTH: u32 = 320;
/// Cosine similarity a match must exceed (XFeat's `match` default).
pub const MIN_COSINE: f32 = 0.82;
/// Quantisation of unit features to `i8`.
const SCALE: f32 = 127.0;

/// The network's input size for an image of `size` (width, height): scaled to at most
/// [`MAX_INPUT_WIDTH`] and at least [`MIN_INPUT_WIDTH`] wide, each side cut down to a multiple of 32.
pub fn input_size(size: [u32; 2]) -> [u32; 2] {
    if size[0] == 0 || size[1] == 0 {
        return [0, 0];
    }
    let scale = (MAX_INPUT_WIDTH as f64 / size[0] as f64).min(1.0).max(MIN_INPUT_WIDTH as f64 / size[0] as f64);
    let cut = |side: u32| ((side as f64 * scale) as u32) / SIDE_MULTIPLE as u32 * SIDE_MULTIPLE as u32;
    [cut(size[0]), cut(size[1])]
}

/// Image pixels per network input pixel for an image of `size` (the larger of its two scales).
pub fn input_scale(size: [u32; 2]) -> f64 {
    let input = input_size(size);
    if input[0] == 0 || input[1] == 0 {
        return 1.0;
    }
    (size[0] as f64 / input[0] as f64).max(size[1] as f64 / input[1] as f64)
}

/// XFeat, loaded once and shared by the verifier's clones.
#[derive(Clone)]
pub struct XFeatExtractor(Arc<XFeat>);

impl std::fmt::Debug for XFeatExtractor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("XFeatExtractor")
    }
}

impl XFeatExtractor {
    pub fn load(path: &Path) -> Result<Self> {
        Ok(XFeatExtractor(Arc::new(XFeat::load(path)?)))
    }

    /// The features of the `max_features` best cells of `gray` (module doc); none for an image under
    /// 32 pixels a side once scaled.
    pub fn extract(&self, gray: &GrayImage, max_features: usize) -> Result<LocalFeatures> {
        let image_size = [gray.width(), gray.height()];
        let [width, height] = input_size(image_size);
        if width == 0 || height == 0 {
            return Ok(LocalFeatures { image_size, descriptors: Descriptors::XFeat(Vec::new()), ..Default::default() });
        }
        let resized = image::imageops::resize(gray, width, height, image::imageops::FilterType::Triangle);
        let pixels: Vec<f32> = resized.as_raw().iter().map(|&v| v as f32 / 255.0).collect();
        let dense = crate::runtime::on_worker(|| self.0.dense(&pixels, height as usize, width as usize))?;
        let (sx, sy) = (image_size[0] as f32 / width as f32, image_size[1] as f32 / height as f32);
        let cells = dense.best_cells(max_features);
        // Pixel-index coordinates: input pixel x covers the image's pixels from x * s to (x + 1) * s.
        let at = |input: usize, scale: f32| (input as f32 + 0.5) * scale - 0.5;
        let keypoints = cells
            .iter()
            .map(|&c| {
                let [dx, dy] = dense.keypoints[c].0;
                [at((c % dense.width) * CELL + dx as usize, sx), at((c / dense.width) * CELL + dy as usize, sy)]
            })
            .collect();
        let descriptors = cells
            .iter()
            .map(|&c| {
                let feature = dense.feature(c);
                std::array::from_fn(|k| (feature[k] * SCALE).round().clamp(-SCALE, SCALE) as i8)
            })
            .collect();
        Ok(LocalFeatures { keypoints, descriptors: Descriptors::XFeat(descriptors), depths: Vec::new(), image_size })
    }
}

/// Index pairs (query, match) of mutual most-similar features above [`MIN_COSINE`].
pub fn mutual_nearest(query: &[[i8; FEATURE_DIM]], matched: &[[i8; FEATURE_DIM]]) -> Vec<(usize, usize)> {
    if query.is_empty() || matched.is_empty() {
        return Vec::new();
    }
    let dot = |a: &[i8; FEATURE_DIM], b: &[i8; FEATURE_DIM]| -> i32 {
        a.iter().zip(b).map(|(&x, &y)| x as i32 * y as i32).sum()
    };
    let mut best_of_query = vec![(i32::MIN, 0usize); query.len()];
    let mut best_of_match = vec![(i32::MIN, 0usize); matched.len()];
    for (i, q) in query.iter().enumerate() {
        for (j, m) in matched.iter().enumerate() {
            let d = dot(q, m);
            if d > best_of_query[i].0 {
                best_of_query[i] = (d, j);
            }
            if d > best_of_match[j].0 {
                best_of_match[j] = (d, i);
            }
        }
    }
    let min_dot = (MIN_COSINE * SCALE * SCALE) as i32;
    best_of_query
        .iter()
        .enumerate()
        .filter(|&(i, &(d, j))| d > min_dot && best_of_match[j].1 == i)
        .map(|(i, &(_, j))| (i, j))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(seed: usize) -> [i8; FEATURE_DIM] {
        let v: Vec<f32> = (0..FEATURE_DIM).map(|k| ((seed * 131 + k * 17) % 23) as f32 - 11.0).collect();
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        std::array::from_fn(|k| (v[k] / norm * SCALE).round() as i8)
    }

    #[test]
    fn mutual_nearest_pairs_equal_features_and_drops_dissimilar_ones() {
        let query = [unit(1), unit(2), unit(3)];
        let matched = [unit(3), unit(1), unit(9)];
        let pairs = mutual_nearest(&query, &matched);
        assert!(pairs.contains(&(0, 1)) && pairs.contains(&(2, 0)), "{pairs:?}");
        // unit(2) has no equal: its nearest is below the cosine threshold (or not mutual).
        assert!(!pairs.iter().any(|&(i, _)| i == 1), "{pairs:?}");
        assert!(mutual_nearest(&[], &matched).is_empty());
    }

    #[test]
    fn input_sizes_are_multiples_of_32_from_320_to_640_wide() {
        assert_eq!(input_size([960, 540]), [640, 352]);
        assert_eq!(input_size([640, 480]), [640, 480]);
        assert_eq!(input_size([320, 240]), [320, 224]);
        assert_eq!(input_size([64, 48]), [320, 224]);
        assert_eq!(input_size([160, 120]), [320, 224]);
        assert_eq!(input_size([0, 20]), [0, 0]);
        assert!((input_scale([960, 540]) - 540.0 / 352.0).abs() < 1e-9);
        assert_eq!(input_scale([640, 480]), 1.0);
        assert!((input_scale([64, 48]) - 48.0 / 224.0).abs() < 1e-9);
    }
}
