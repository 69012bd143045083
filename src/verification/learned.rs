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
use crate::model::kernels::matmul::{matmul, View};
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

/// ... and never taller than this: a thin image scaled to the minimum width would otherwise ask for
/// gigabytes (a 1x10000 image, 320 wide, would be 3.2 million rows).
pub const MAX_INPUT_HEIGHT: u32 = 4 * MAX_INPUT_WIDTH;

/// The network's input size for an image of `size` (width, height): scaled to at most
/// [`MAX_INPUT_WIDTH`] and at least [`MIN_INPUT_WIDTH`] wide, but at most [`MAX_INPUT_HEIGHT`] tall,
/// each side cut down to a multiple of 32.
pub fn input_size(size: [u32; 2]) -> [u32; 2] {
    if size[0] == 0 || size[1] == 0 {
        return [0, 0];
    }
    let scale = (MAX_INPUT_WIDTH as f64 / size[0] as f64)
        .min(1.0)
        .max(MIN_INPUT_WIDTH as f64 / size[0] as f64)
        .min(MAX_INPUT_HEIGHT as f64 / size[1] as f64);
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

/// Index pairs (query, match) of mutual most-similar features above [`MIN_COSINE`]; of equally
/// similar features, the first.
pub fn mutual_nearest(query: &[[i8; FEATURE_DIM]], matched: &[[i8; FEATURE_DIM]]) -> Vec<(usize, usize)> {
    if query.is_empty() || matched.is_empty() {
        return Vec::new();
    }
    // Every pair's dot product as one matrix product, a block of query rows at a time. `f32` holds
    // them exactly: integers of at most 64 * 127² < 2^24.
    const ROWS_PER_BLOCK: usize = 256;
    let as_f32 =
        |features: &[[i8; FEATURE_DIM]]| -> Vec<f32> { features.iter().flatten().map(|&v| v as f32).collect() };
    let (query_values, matched_values) = (as_f32(query), as_f32(matched));
    let columns = matched.len();
    let mut dots = vec![0f32; ROWS_PER_BLOCK.min(query.len()) * columns];
    let mut best_of_query = Vec::with_capacity(query.len());
    let (mut best_of_match, mut match_argmax) = (vec![f32::NEG_INFINITY; columns], vec![0u32; columns]);
    for (block, rows) in query_values.chunks(ROWS_PER_BLOCK * FEATURE_DIM).enumerate() {
        let count = rows.len() / FEATURE_DIM;
        matmul(
            count,
            columns,
            FEATURE_DIM,
            &mut dots,
            false,
            View::rows(rows, FEATURE_DIM),
            View::transposed(&matched_values, FEATURE_DIM),
        );
        for (r, row) in dots.chunks(columns).take(count).enumerate() {
            let i = block * ROWS_PER_BLOCK + r;
            let mut first_best = (f32::NEG_INFINITY, 0);
            for (j, &d) in row.iter().enumerate() {
                if d > first_best.0 {
                    first_best = (d, j);
                }
            }
            best_of_query.push(first_best);
            for ((best, argmax), &d) in best_of_match.iter_mut().zip(&mut match_argmax).zip(row) {
                if d > *best {
                    *best = d;
                    *argmax = i as u32;
                }
            }
        }
    }
    let min_dot = (MIN_COSINE * SCALE * SCALE).trunc();
    best_of_query
        .iter()
        .enumerate()
        .filter(|&(i, &(d, j))| d > min_dot && match_argmax[j] as usize == i)
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

    /// The plain definition: every pair's integer dot product, the first best of each side.
    fn mutual_nearest_reference(query: &[[i8; FEATURE_DIM]], matched: &[[i8; FEATURE_DIM]]) -> Vec<(usize, usize)> {
        let dot = |a: &[i8; FEATURE_DIM], b: &[i8; FEATURE_DIM]| -> i32 {
            a.iter().zip(b).map(|(&x, &y)| x as i32 * y as i32).sum()
        };
        let first_best = |scores: Vec<i32>| {
            scores.iter().enumerate().fold((i32::MIN, 0), |best, (j, &d)| if d > best.0 { (d, j) } else { best })
        };
        let min_dot = (MIN_COSINE * SCALE * SCALE) as i32;
        (0..query.len())
            .filter_map(|i| {
                let (d, j) = first_best(matched.iter().map(|m| dot(&query[i], m)).collect());
                let (_, back) = first_best(query.iter().map(|q| dot(q, &matched[j])).collect());
                (d > min_dot && back == i).then_some((i, j))
            })
            .collect()
    }

    #[test]
    fn mutual_nearest_equals_the_plain_definition_with_ties_and_many_blocks() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut random = |range: i64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % (2 * range as u64 + 1)) as i64 - range
        };
        // Coarse values make equal dot products common; features near a few centres make mutual pairs.
        let centres: Vec<[i8; FEATURE_DIM]> =
            (0..40).map(|_| std::array::from_fn(|_| (random(3) * 30) as i8)).collect();
        let mut features = |n: usize, spread: i64| -> Vec<[i8; FEATURE_DIM]> {
            (0..n)
                .map(|k| {
                    let centre = centres[k % centres.len()];
                    std::array::from_fn(|d| (centre[d] as i64 + random(spread)).clamp(-127, 127) as i8)
                })
                .collect()
        };
        let (query, matched) = (features(600, 2), features(333, 2));
        let pairs = mutual_nearest(&query, &matched);
        assert!(pairs.len() >= 20, "{}", pairs.len());
        assert_eq!(pairs, mutual_nearest_reference(&query, &matched));
        let (query, matched) = (features(7, 40), features(5, 40));
        assert_eq!(mutual_nearest(&query, &matched), mutual_nearest_reference(&query, &matched));
    }

    #[test]
    fn input_sizes_are_multiples_of_32_from_320_to_640_wide() {
        assert_eq!(input_size([960, 540]), [640, 352]);
        assert_eq!(input_size([640, 480]), [640, 480]);
        assert_eq!(input_size([320, 240]), [320, 224]);
        assert_eq!(input_size([64, 48]), [320, 224]);
        assert_eq!(input_size([160, 120]), [320, 224]);
        // Thin or tall images stay within the height bound (too thin for any cell: no input).
        assert_eq!(input_size([1, 10_000]), [0, 2560]);
        assert_eq!(input_size([640, 100_000]), [0, 2560]);
        assert_eq!(input_size([100, 10_000]), [0, 2560]);
        assert_eq!(input_size([480, 800]), [480, 800]);
        assert_eq!(input_size([0, 20]), [0, 0]);
        assert!((input_scale([960, 540]) - 540.0 / 352.0).abs() < 1e-9);
        assert_eq!(input_scale([640, 480]), 1.0);
        assert!((input_scale([64, 48]) - 48.0 / 224.0).abs() < 1e-9);
    }
}
