//! Global descriptors from the network's feature map, their distance and the score derived from it.
//!
//! Every mode turns a [`FeatureMap`] (`[C, H, W]`, the last 1x1 conv before global pooling) into one
//! `Vec<f32>`; two descriptors are compared by the plain Euclidean [`distance`]. Each mode also maps a
//! distance to a similarity score in `[0, 1]` (1 = identical, monotone decreasing in the distance), so a
//! user may threshold on either; [`Descriptor::distance_for_score`] is the exact inverse.
//!
//! Modes:
//! - [`DescriptorMode::Paper`] reproduces Section 3.3 of Zhou et al., "A Lightweight Neural Network for
//!   Loop Closure Detection in Indoor Visual SLAM":
//!   1. `v` = global average pool of the feature map (1280 values for ECMobileNet);
//!   2. Eq. 7, min-max normalisation `v_i' = (v_i - min v) / (max v - min v)`; when `max v == min v`
//!      (e.g. a black image, every channel clipped to the same value) the ratio is undefined and we use 0
//!      for every value;
//!   3. Eq. 8, groups of ten consecutive values are summed and weighted into one value (1280 -> 128).
//!      The printed weight σ is garbled; our interpretation is the fixed weight 1/10, i.e. each group's
//!      **mean** (a channel count that is not a multiple of ten leaves a shorter last group, averaged
//!      over its own length), so every value stays in `[0, 1]`;
//!   4. Eq. 9, the distance: printed without the square root of the sum of squares; we use the true
//!      Euclidean distance (the ranking is the same, thresholds are on the usual scale).
//!
//!   Every value lies in `[0, 1]`, so a distance is at most `sqrt(dim)`; the score is the linear map
//!   `score = 1 - d / sqrt(dim)` (1 - the root-mean-square difference per value).
//! - [`DescriptorMode::L2`]: the pooled `C`-d vector, L2-normalised. Unit vectors are at most 2 apart and
//!   `score = 1 - d²/4 = (1 + cos θ)/2`. Because the features are ReLU6 outputs (non-negative) the cosine is
//!   non-negative and real scores lie in `[0.5, 1]`.
//! - [`DescriptorMode::Power`]: the pooled `C`-d vector with signed-square-root (power) normalisation,
//!   then L2-normalised; the score is that of `l2`. Power normalisation damps the few channels that
//!   fire strongly on objects (bursty), so place-wide texture and layout weigh more. Meant to be used
//!   with the detector's centring on the history ([`crate::detector`]), which removes what every
//!   image of an environment shares.
//! - [`DescriptorMode::Spatial`]: keeps coarse layout. Five blocks of `C` values are concatenated: the global
//!   average pool, then max pooling (MAC) over each cell of a 2x2 grid (cells overlap by the middle row or
//!   column when the size is odd, e.g. rows 0..4 and 3..7 of a 7x7 map). Each block gets signed-square-root
//!   (power) normalisation, which damps bursty channels, and is L2-normalised, then the whole vector is
//!   scaled by `1/sqrt(5)` so it is a unit vector: the score is `1 - d²/4` as for `l2`.
//!
//! - [`DescriptorMode::Regional`]: regional pooling over a `grid` x `grid` grid of cells (the cells of
//!   `spatial`), each cell pooled per channel by [`Pooling`] (MAC by default), power- and L2-normalised,
//!   and the cells concatenated and scaled by `1/grid` so the whole is a unit vector (`l2`'s score).
//!   Meant for mid-level maps (by default the last bottleneck's output, before the 1x1 head that was
//!   trained to name objects): the grid keeps where things are, which tells two similar rooms apart,
//!   and the bottleneck's features carry texture and parts rather than classes. Bottleneck outputs
//!   are linear (they may be negative): MAC and the signed square root take them as they are; GeM
//!   clamps at zero.
//!
//! Every mode reads one map; which one (the head or a bottleneck's output) is the pipeline's tap
//! ([`crate::model::Tap`], `descriptor.tap`); `channels` is that map's channel count.
//!
//! A zero block (all features zero) stays zero rather than dividing by zero.

pub mod projection;

pub use projection::Projection;

use crate::types::FeatureMap;
use std::fmt;
use std::str::FromStr;

/// The channel count of ECMobileNet's (and MobileNetV2's) last feature map.
pub const DEFAULT_CHANNELS: usize = 1280;

/// Size of the groups that the paper's Eq. 8 sums into one value.
const PAPER_GROUP: usize = 10;

/// Grid of the spatial mode's regional max pooling (per side).
const SPATIAL_GRID: usize = 2;

/// Which descriptor is computed from the feature map; the names are those of config files and the CLI.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum DescriptorMode {
    /// `paper`: the paper's 128-d min-max normalised, group-averaged descriptor.
    Paper,
    /// `l2`: the L2-normalised global average pool.
    L2,
    /// `spatial`: global average + 2x2 regional max pooling, power- and L2-normalised.
    Spatial,
    /// `power`: the global average pool, power- and L2-normalised; best with the detector's centring
    /// on the history.
    Power,
    /// `regional`: a grid of regionally pooled cells, each power- and L2-normalised. The default: on
    /// MobileNetV2's last bottleneck it measured best on the development sets
    /// (`examples/accuracy_table.rs`, `examples/descriptor_study.rs`).
    #[default]
    Regional,
}

/// How the regional mode pools one channel over one cell.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Pooling {
    /// `gap`: the mean.
    Gap,
    /// `gem`: generalised mean with exponent 3 of the values clamped at zero (between mean and max).
    Gem,
    /// `mac`: the maximum.
    #[default]
    Mac,
}

/// GeM's exponent: 3 is the usual choice (Radenović et al.) between the mean (1) and the max (inf).
const GEM_EXPONENT: i32 = 3;

impl Pooling {
    pub const ALL: [Pooling; 3] = [Pooling::Gap, Pooling::Gem, Pooling::Mac];
    pub const NAMES: [&'static str; 3] = ["gap", "gem", "mac"];

    pub fn name(self) -> &'static str {
        Self::NAMES[self as usize]
    }

    fn pool(self, values: impl Iterator<Item = f32>) -> f32 {
        match self {
            Pooling::Gap => {
                let (sum, n) = values.fold((0.0f32, 0usize), |(s, n), x| (s + x, n + 1));
                sum / n.max(1) as f32
            }
            Pooling::Gem => {
                let (sum, n) = values.fold((0.0f32, 0usize), |(s, n), x| (s + x.max(0.0).powi(GEM_EXPONENT), n + 1));
                (sum / n.max(1) as f32).powf(1.0 / GEM_EXPONENT as f32)
            }
            Pooling::Mac => values.fold(f32::NEG_INFINITY, f32::max),
        }
    }
}

impl DescriptorMode {
    /// Every mode, in the order of the names of [`DescriptorMode::NAMES`].
    pub const ALL: [DescriptorMode; 5] = [
        DescriptorMode::Paper,
        DescriptorMode::L2,
        DescriptorMode::Spatial,
        DescriptorMode::Power,
        DescriptorMode::Regional,
    ];
    /// The names accepted by [`FromStr`], as used in config files.
    pub const NAMES: [&'static str; 5] = ["paper", "l2", "spatial", "power", "regional"];

    pub fn name(self) -> &'static str {
        match self {
            DescriptorMode::Paper => "paper",
            DescriptorMode::L2 => "l2",
            DescriptorMode::Spatial => "spatial",
            DescriptorMode::Power => "power",
            DescriptorMode::Regional => "regional",
        }
    }

    /// Whether the mode's descriptors are unit vectors compared by their cosine (all but `paper`).
    pub fn is_unit_vector(self) -> bool {
        self != DescriptorMode::Paper
    }
}

/// `Display` as the name and `FromStr` from it, for an enum with `ALL`, `NAMES` and `name()`.
macro_rules! named_choice {
    ($type:ty, $what:literal) => {
        impl fmt::Display for $type {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(self.name())
            }
        }

        impl FromStr for $type {
            type Err = String;

            fn from_str(text: &str) -> Result<Self, Self::Err> {
                Self::ALL.into_iter().find(|choice| choice.name() == text).ok_or_else(|| {
                    format!(concat!("unknown ", $what, " {:?} (expected one of {})"), text, Self::NAMES.join(", "))
                })
            }
        }
    };
}

named_choice!(DescriptorMode, "descriptor mode");
named_choice!(Pooling, "pooling");

/// Euclidean distance between two descriptors of the same length (extra values of the longer are ignored;
/// callers check lengths, see [`crate::detector::KeyframeDb`]).
pub fn distance(a: &[f32], b: &[f32]) -> f32 {
    squared_distance(a, b).sqrt()
}

/// Squared Euclidean distance; the database ranks by it to skip the square root per stored keyframe.
/// Inlined so that the database's scan compiles it for the widest SIMD the CPU has ([`crate::detector::index`]).
#[inline(always)]
pub fn squared_distance(a: &[f32], b: &[f32]) -> f32 {
    // Eight independent partial sums let the compiler vectorise (a single running f32 sum cannot be
    // reordered, so it would stay scalar).
    const LANES: usize = 8;
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut lanes = [0.0f32; LANES];
    let (a_chunks, b_chunks) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let tail: f32 = a_chunks.remainder().iter().zip(b_chunks.remainder()).map(|(x, y)| (x - y) * (x - y)).sum();
    for (ca, cb) in a_chunks.zip(b_chunks) {
        for lane in 0..LANES {
            let d = ca[lane] - cb[lane];
            lanes[lane] += d * d;
        }
    }
    lanes.iter().sum::<f32>() + tail
}

/// The regional mode's default grid side: 3x3 cells measured best on the development sets
/// (`examples/descriptor_study.rs`).
pub const DEFAULT_GRID: usize = 3;

/// A descriptor mode bound to the tapped map's channel count (the paper mode's score depends on the
/// length), with the regional mode's grid and pooling (ignored by the other modes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Descriptor {
    pub mode: DescriptorMode,
    pub channels: usize,
    /// Cells per side of the regional grid, at least 1.
    pub grid: usize,
    pub pooling: Pooling,
    /// Length after a learned projection ([`Projection`], applied by the pipeline), where one is set.
    pub projected_dim: Option<usize>,
}

impl Default for Descriptor {
    fn default() -> Self {
        Descriptor::new(DescriptorMode::default(), DEFAULT_CHANNELS)
    }
}

impl Descriptor {
    pub fn new(mode: DescriptorMode, channels: usize) -> Self {
        Descriptor { mode, channels, grid: DEFAULT_GRID, pooling: Pooling::default(), projected_dim: None }
    }

    /// The regional mode on a `channels`-channel map, `grid` x `grid` cells (at least 1) pooled by `pooling`.
    pub fn regional(channels: usize, grid: usize, pooling: Pooling) -> Self {
        Descriptor { mode: DescriptorMode::Regional, channels, grid: grid.max(1), pooling, projected_dim: None }
    }

    /// What the descriptor's values depend on besides the network, as one name: the mode's name,
    /// with the regional grid and pooling (`regional-3x3-mac`).
    pub fn name(&self) -> String {
        match self.mode {
            DescriptorMode::Regional => format!("regional-{0}x{0}-{1}", self.grid, self.pooling),
            mode => mode.name().to_string(),
        }
    }

    /// Length of the descriptor stored and compared: the projected length where a projection is set.
    pub fn dim(&self) -> usize {
        self.projected_dim.unwrap_or_else(|| self.computed_dim())
    }

    /// Length of the descriptor this mode computes from a `channels`-channel feature map.
    pub fn computed_dim(&self) -> usize {
        match self.mode {
            DescriptorMode::Paper => self.channels.div_ceil(PAPER_GROUP),
            DescriptorMode::L2 | DescriptorMode::Power => self.channels,
            DescriptorMode::Spatial => self.channels * (1 + SPATIAL_GRID * SPATIAL_GRID),
            DescriptorMode::Regional => self.channels * self.grid * self.grid,
        }
    }

    /// Computes the descriptor of one feature map. Errors when the map's channel count differs from
    /// [`Descriptor::channels`] or its data length does not match its shape.
    pub fn compute(&self, fm: &FeatureMap) -> anyhow::Result<Vec<f32>> {
        let expected_len = fm.channels.checked_mul(fm.height).and_then(|n| n.checked_mul(fm.width));
        if expected_len != Some(fm.data.len()) || fm.height == 0 || fm.width == 0 {
            anyhow::bail!(
                "feature map of shape [{}, {}, {}] holds {} values; expected a non-empty map with C*H*W values",
                fm.channels,
                fm.height,
                fm.width,
                fm.data.len()
            );
        }
        if fm.channels != self.channels {
            anyhow::bail!(
                "feature map has {} channels but the {} descriptor was set up for {}",
                fm.channels,
                self.mode,
                self.channels
            );
        }
        Ok(match self.mode {
            DescriptorMode::Paper => paper_descriptor(&fm.global_average()),
            DescriptorMode::L2 => {
                let mut v = fm.global_average();
                l2_normalise(&mut v);
                v
            }
            DescriptorMode::Spatial => spatial_descriptor(fm),
            DescriptorMode::Power => {
                let mut v = fm.global_average();
                power_normalise(&mut v);
                l2_normalise(&mut v);
                v
            }
            DescriptorMode::Regional => regional_descriptor(fm, self.grid, self.pooling),
        })
    }

    /// Similarity in `[0, 1]` for a distance between two descriptors of this mode (see the module doc).
    /// Non-finite or negative distances are clamped into range (NaN gives 0).
    pub fn score(&self, distance: f32) -> f32 {
        if distance.is_nan() {
            return 0.0;
        }
        let distance = distance.max(0.0);
        let score = match self.mode {
            DescriptorMode::Paper => 1.0 - distance / (self.dim() as f32).sqrt(),
            _ => 1.0 - distance * distance / 4.0,
        };
        // An infinite distance gives -inf here (and inf * inf stays inf), so clamping is enough.
        score.clamp(0.0, 1.0)
    }

    /// The distance whose score is `score` (the inverse of [`Descriptor::score`]); `score` is clamped to `[0, 1]`.
    pub fn distance_for_score(&self, score: f32) -> f32 {
        let score = if score.is_nan() { 0.0 } else { score.clamp(0.0, 1.0) };
        match self.mode {
            DescriptorMode::Paper => (1.0 - score) * (self.dim() as f32).sqrt(),
            _ => (4.0 * (1.0 - score)).sqrt(),
        }
    }
}

/// Eq. 7 (min-max) then Eq. 8 (group means of ten), see the module doc.
fn paper_descriptor(pooled: &[f32]) -> Vec<f32> {
    let (min, max) = pooled.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &x| (lo.min(x), hi.max(x)));
    let range = max - min;
    let normalise = |x: f32| if range > 0.0 { (x - min) / range } else { 0.0 };
    pooled
        .chunks(PAPER_GROUP)
        .map(|group| group.iter().map(|&x| normalise(x)).sum::<f32>() / group.len() as f32)
        .collect()
}

/// Scales `v` to unit length; a zero vector stays zero.
pub fn l2_normalise(v: &mut [f32]) {
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if norm > 0.0 {
        v.iter_mut().for_each(|x| *x /= norm);
    }
}

/// Signed square root of every value (power normalisation with exponent 1/2).
pub fn power_normalise(v: &mut [f32]) {
    v.iter_mut().for_each(|x| *x = x.signum() * x.abs().sqrt());
}

/// Half-open cell `index` of `cells` cells covering `0..size`; cells overlap when `size` is not a multiple.
pub fn grid_cell(size: usize, cells: usize, index: usize) -> std::ops::Range<usize> {
    (index * size / cells)..((index + 1) * size).div_ceil(cells)
}

fn spatial_descriptor(fm: &FeatureMap) -> Vec<f32> {
    let plane = fm.height * fm.width;
    let mut out = fm.global_average();
    out.reserve(fm.channels * SPATIAL_GRID * SPATIAL_GRID);
    for cell_row in 0..SPATIAL_GRID {
        let rows = grid_cell(fm.height, SPATIAL_GRID, cell_row);
        for cell_col in 0..SPATIAL_GRID {
            let cols = grid_cell(fm.width, SPATIAL_GRID, cell_col);
            for channel in fm.data.chunks_exact(plane) {
                let max = rows
                    .clone()
                    .flat_map(|r| channel[r * fm.width + cols.start..r * fm.width + cols.end].iter())
                    .fold(f32::NEG_INFINITY, |m, &x| m.max(x));
                out.push(max);
            }
        }
    }
    let block_weight = 1.0 / ((1 + SPATIAL_GRID * SPATIAL_GRID) as f32).sqrt();
    for block in out.chunks_exact_mut(fm.channels) {
        power_normalise(block);
        l2_normalise(block);
        block.iter_mut().for_each(|x| *x *= block_weight);
    }
    out
}

/// The regional mode (module doc): cells in row-major order, each a block of `channels` values.
fn regional_descriptor(fm: &FeatureMap, grid: usize, pooling: Pooling) -> Vec<f32> {
    let plane = fm.height * fm.width;
    let mut out = Vec::with_capacity(fm.channels * grid * grid);
    for cell_row in 0..grid {
        let rows = grid_cell(fm.height, grid, cell_row);
        for cell_col in 0..grid {
            let cols = grid_cell(fm.width, grid, cell_col);
            let start = out.len();
            for channel in fm.data.chunks_exact(plane) {
                let values = rows
                    .clone()
                    .flat_map(|r| channel[r * fm.width + cols.start..r * fm.width + cols.end].iter().copied());
                out.push(pooling.pool(values));
            }
            let cell = &mut out[start..];
            power_normalise(cell);
            l2_normalise(cell);
            cell.iter_mut().for_each(|x| *x /= grid as f32);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(channels: usize, height: usize, width: usize, f: impl Fn(usize, usize, usize) -> f32) -> FeatureMap {
        let mut data = Vec::with_capacity(channels * height * width);
        for c in 0..channels {
            for y in 0..height {
                for x in 0..width {
                    data.push(f(c, y, x));
                }
            }
        }
        FeatureMap { channels, height, width, data }
    }

    fn assert_close(a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!((x - y).abs() < 1e-5, "value {i}: {x} vs {y}");
        }
    }

    #[test]
    fn names_round_trip_and_unknown_is_refused() {
        for mode in DescriptorMode::ALL {
            assert_eq!(mode.to_string().parse::<DescriptorMode>().unwrap(), mode);
        }
        let err = "cosine".parse::<DescriptorMode>().unwrap_err();
        assert!(err.contains("cosine") && err.contains("paper"), "{err}");
    }

    #[test]
    fn paper_mode_hand_computed() {
        // 20 channels on a 1x2 map: channel c has pixels (c, c+2) -> pooled mean c + 1, i.e. 1..=20.
        // Min-max: (c+1 - 1)/19 = c/19. Groups of ten: mean(0..10)/19 = 4.5/19, mean(10..20)/19 = 14.5/19.
        let fm = map(20, 1, 2, |c, _, x| c as f32 + 2.0 * x as f32);
        let d = Descriptor::new(DescriptorMode::Paper, 20);
        assert_eq!(d.dim(), 2);
        assert_close(&d.compute(&fm).unwrap(), &[4.5 / 19.0, 14.5 / 19.0]);
        // A last short group (25 channels -> 3 groups, the last of 5) is averaged over its own length.
        let fm = map(25, 1, 1, |c, _, _| c as f32);
        let d = Descriptor::new(DescriptorMode::Paper, 25);
        assert_eq!(d.dim(), 3);
        assert_close(&d.compute(&fm).unwrap(), &[4.5 / 24.0, 14.5 / 24.0, 22.0 / 24.0]);
        // Constant input: the undefined ratio gives zeros, not NaN.
        let fm = map(20, 2, 2, |_, _, _| 6.0);
        assert_close(&Descriptor::new(DescriptorMode::Paper, 20).compute(&fm).unwrap(), &[0.0, 0.0]);
        // Full-size map gives 128 values in [0, 1].
        let fm = map(1280, 7, 7, |c, y, x| ((c * 7 + y * 3 + x) % 13) as f32 * 0.4);
        let v = Descriptor::new(DescriptorMode::Paper, 1280).compute(&fm).unwrap();
        assert_eq!(v.len(), 128);
        assert!(v.iter().all(|x| (0.0..=1.0).contains(x)));
    }

    #[test]
    fn paper_score_is_linear_in_rms_difference() {
        let d = Descriptor::new(DescriptorMode::Paper, 1280);
        // Opposite corners of the unit cube are sqrt(128) apart: score 0.
        assert_eq!(d.score(0.0), 1.0);
        assert!((d.score(128f32.sqrt())).abs() < 1e-6);
        assert!((d.score(128f32.sqrt() / 4.0) - 0.75).abs() < 1e-6);
    }

    #[test]
    fn l2_mode_hand_computed() {
        // Pooled (3, 4) -> (0.6, 0.8).
        let fm = map(2, 1, 2, |c, _, x| if c == 0 { 2.0 + 2.0 * x as f32 } else { 4.0 });
        let d = Descriptor::new(DescriptorMode::L2, 2);
        assert_close(&d.compute(&fm).unwrap(), &[0.6, 0.8]);
        // Orthogonal unit vectors: d = sqrt(2), score = (1 + 0)/2.
        assert!((d.score(2f32.sqrt()) - 0.5).abs() < 1e-6);
        // A zero map stays zero instead of NaN.
        assert_close(&d.compute(&map(2, 1, 1, |_, _, _| 0.0)).unwrap(), &[0.0, 0.0]);
    }

    #[test]
    fn power_mode_hand_computed() {
        // Pooled (9, 16) -> sqrt (3, 4) -> (0.6, 0.8); a zero map stays zero.
        let fm = map(2, 1, 2, |c, _, x| if c == 0 { 9.0 } else { 12.0 + 8.0 * x as f32 });
        let d = Descriptor::new(DescriptorMode::Power, 2);
        assert_eq!(d.dim(), 2);
        assert_close(&d.compute(&fm).unwrap(), &[0.6, 0.8]);
        assert_close(&d.compute(&map(2, 1, 1, |_, _, _| 0.0)).unwrap(), &[0.0, 0.0]);
    }

    #[test]
    fn spatial_mode_hand_computed() {
        // One channel on a 3x3 map with values 0..9 (row-major). Global mean 4; cells overlap on the
        // middle row/column: maxima top-left 4, top-right 5, bottom-left 7, bottom-right 8. Each 1-value
        // block after sqrt and L2 normalisation is 1, scaled by 1/sqrt(5).
        let fm = map(1, 3, 3, |_, y, x| (y * 3 + x) as f32);
        let d = Descriptor::new(DescriptorMode::Spatial, 1);
        assert_eq!(d.dim(), 5);
        let w = 1.0 / 5f32.sqrt();
        assert_close(&d.compute(&fm).unwrap(), &[w; 5]);
        // Two channels: global means (1, 4) -> sqrt -> (1, 2)/sqrt(5); the top-left cell of a 2x2 map is
        // one pixel: (0, 9) -> (0, 3) -> (0, 1).
        let fm = FeatureMap { channels: 2, height: 2, width: 2, data: vec![0.0, 1.0, 1.0, 2.0, 9.0, 1.0, 1.0, 5.0] };
        let v = Descriptor::new(DescriptorMode::Spatial, 2).compute(&fm).unwrap();
        assert_eq!(v.len(), 10);
        let s5 = 5f32.sqrt();
        assert_close(&v[0..4], &[w / s5, 2.0 * w / s5, 0.0, w]);
        let norm: f32 = v.iter().map(|x| x * x).sum();
        assert!((norm - 1.0).abs() < 1e-5);
    }

    /// The regional mode written out plainly: index arithmetic per pixel, f64 sums.
    fn regional_reference(fm: &FeatureMap, grid: usize, pooling: Pooling) -> Vec<f32> {
        let at = |c: usize, y: usize, x: usize| fm.data[(c * fm.height + y) * fm.width + x] as f64;
        let mut out = Vec::new();
        for gy in 0..grid {
            for gx in 0..grid {
                let (y0, y1) = (gy * fm.height / grid, ((gy + 1) * fm.height).div_ceil(grid));
                let (x0, x1) = (gx * fm.width / grid, ((gx + 1) * fm.width).div_ceil(grid));
                let mut cell = Vec::new();
                for c in 0..fm.channels {
                    let pixels: Vec<f64> =
                        (y0..y1).flat_map(|y| (x0..x1).map(move |x| (y, x))).map(|(y, x)| at(c, y, x)).collect();
                    let n = pixels.len() as f64;
                    let pooled = match pooling {
                        Pooling::Gap => pixels.iter().sum::<f64>() / n,
                        Pooling::Gem => (pixels.iter().map(|v| v.max(0.0).powi(3)).sum::<f64>() / n).cbrt(),
                        Pooling::Mac => pixels.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
                    };
                    cell.push(pooled.signum() * pooled.abs().sqrt());
                }
                let norm = cell.iter().map(|v| v * v).sum::<f64>().sqrt();
                out.extend(cell.iter().map(|v| if norm > 0.0 { (v / norm / grid as f64) as f32 } else { 0.0 }));
            }
        }
        out
    }

    #[test]
    fn regional_mode_matches_the_plain_reference() {
        // Signed values (a bottleneck's output is linear), odd sizes (overlapping cells), every pooling.
        let fm = map(5, 7, 6, |c, y, x| ((c * 31 + y * 7 + x * 3) % 11) as f32 - 4.5 + 0.1 * c as f32);
        for pooling in Pooling::ALL {
            for grid in 1..=4 {
                let d = Descriptor::regional(5, grid, pooling);
                let v = d.compute(&fm).unwrap();
                assert_eq!(v.len(), d.dim());
                assert_close(&v, &regional_reference(&fm, grid, pooling));
                let norm: f32 = v.iter().map(|x| x * x).sum();
                assert!((norm - 1.0).abs() < 1e-5, "{pooling} {grid}: |v|² = {norm}");
            }
        }
        assert_eq!(Descriptor::regional(320, 3, Pooling::Mac).name(), "regional-3x3-mac");
        assert_eq!("gem".parse::<Pooling>().unwrap(), Pooling::Gem);
        assert!("max".parse::<Pooling>().unwrap_err().contains("mac"));
    }

    #[test]
    fn regional_mode_hand_computed() {
        // One channel, a 2x2 map, 2x2 cells: every cell is one pixel; sqrt then L2 of a 1-value
        // block is its sign; scaled by 1/2.
        let fm = map(1, 2, 2, |_, y, x| [4.0, -9.0, 0.0, 1.0][y * 2 + x]);
        let v = Descriptor::regional(1, 2, Pooling::Mac).compute(&fm).unwrap();
        assert_close(&v, &[0.5, -0.5, 0.0, 0.5]);
        // Two channels, one cell: MAC (9, 16) -> sqrt (3, 4) -> (0.6, 0.8); GAP (4.5, 8) -> ...
        let fm = map(2, 1, 2, |c, _, x| if c == 0 { 9.0 * x as f32 } else { 16.0 * x as f32 });
        assert_close(&Descriptor::regional(2, 1, Pooling::Mac).compute(&fm).unwrap(), &[0.6, 0.8]);
        assert_close(&Descriptor::regional(2, 1, Pooling::Gap).compute(&fm).unwrap(), &[0.6, 0.8]);
    }

    #[test]
    fn grid_cells_cover_with_overlap() {
        assert_eq!(grid_cell(7, 2, 0), 0..4);
        assert_eq!(grid_cell(7, 2, 1), 3..7);
        assert_eq!(grid_cell(4, 2, 1), 2..4);
        assert_eq!(grid_cell(1, 2, 0), 0..1);
        assert_eq!(grid_cell(1, 2, 1), 0..1);
    }

    #[test]
    fn scores_are_in_range_monotone_and_invertible() {
        for mode in DescriptorMode::ALL {
            let d = Descriptor::new(mode, DEFAULT_CHANNELS);
            let mut last = f32::INFINITY;
            for step in 0..=100 {
                let dist = step as f32 * 0.25;
                let s = d.score(dist);
                assert!((0.0..=1.0).contains(&s), "{mode} score {s} at {dist}");
                assert!(s <= last, "{mode} not monotone at {dist}");
                last = s;
            }
            for step in 0..=20 {
                let s = step as f32 / 20.0;
                assert!((d.score(d.distance_for_score(s)) - s).abs() < 1e-5, "{mode} inverse at {s}");
            }
            assert_eq!(d.score(f32::NAN), 0.0);
            assert_eq!(d.score(-1.0), 1.0);
            assert_eq!(d.score(f32::INFINITY), 0.0);
        }
    }

    #[test]
    fn distance_is_euclidean() {
        assert_eq!(distance(&[0.0, 0.0], &[3.0, 4.0]), 5.0);
        assert_eq!(squared_distance(&[1.0, 1.0], &[2.0, 3.0]), 5.0);
        // Longer than one vector block, with a tail: 19 differences of 1 and one of 2.
        let a = vec![0.0f32; 20];
        let mut b = vec![1.0f32; 20];
        b[17] = 2.0;
        assert_eq!(squared_distance(&a, &b), 23.0);
    }

    #[test]
    fn bad_feature_maps_are_refused() {
        let d = Descriptor::new(DescriptorMode::L2, 4);
        let wrong_len = FeatureMap { channels: 4, height: 2, width: 2, data: vec![0.0; 15] };
        assert!(d.compute(&wrong_len).unwrap_err().to_string().contains("15 values"));
        let wrong_channels = FeatureMap { channels: 2, height: 1, width: 1, data: vec![0.0; 2] };
        assert!(d.compute(&wrong_channels).unwrap_err().to_string().contains("2 channels"));
        let empty = FeatureMap { channels: 4, height: 0, width: 1, data: vec![] };
        assert!(d.compute(&empty).is_err());
    }
}
