//! Image -> feature map: the preprocessor and a network in inference mode, one image at a time.

use anyhow::Result;
use image::RgbImage;

use super::layers::Mode;
use super::weights::resolve::{self, Resolved};
use super::{Arch, Network, Tap};
use crate::preprocess::Preprocessor;
use crate::types::FeatureMap;

/// Turns images into the network's last feature map (the input of every descriptor).
pub struct Embedder {
    pub network: Network,
    preprocessor: Preprocessor,
    mode: Mode,
    /// The map [`Embedder::feature_map`] returns.
    tap: Tap,
}

impl Embedder {
    /// Resolves `weights` ([`super::weights::resolve`]), picks the network (`arch`, else that of
    /// ECMobileNet weights, which serve no other, else `default_arch`), logs which weights run, and
    /// builds the embedder at `input_size`, with the classifier where asked.
    pub fn from_weights(
        weights: Option<&std::path::Path>,
        arch: Option<Arch>,
        default_arch: Arch,
        input_size: usize,
        with_classifier: bool,
    ) -> Result<(Self, Resolved)> {
        let resolved = resolve::resolve(weights)?;
        let own = resolved.weights.arch;
        let arch = arch.unwrap_or(if own == Arch::EcMobileNet { own } else { default_arch });
        let network = resolved.weights.for_arch(arch)?.network(with_classifier)?;
        log::info!("weights: {} -> {arch}", resolved.describe());
        Ok((Embedder::new(network, input_size)?, resolved))
    }

    /// `input_size`: a multiple of 32 (224 is what the weights were trained at).
    pub fn new(network: Network, input_size: usize) -> Result<Self> {
        super::check_input_size(input_size)?;
        Ok(Embedder { network, preprocessor: Preprocessor::new(input_size), mode: Mode::Inference, tap: Tap::Head })
    }

    /// Which map [`Embedder::feature_map`] returns (the head by default). Errors when the network
    /// has no such block.
    pub fn set_tap(&mut self, tap: Tap) -> Result<()> {
        if let Tap::Block(i) = tap {
            let blocks = self.network.blocks.len();
            anyhow::ensure!(i < blocks, "tap {tap} is past the last of {blocks} bottlenecks");
        }
        self.tap = tap;
        Ok(())
    }

    pub fn tap(&self) -> Tap {
        self.tap
    }

    /// Use stock candle ops instead of the fast kernels (for verification).
    pub fn set_reference(&mut self, reference: bool) {
        self.mode = if reference { Mode::Reference } else { Mode::Inference };
    }

    pub fn input_size(&self) -> usize {
        self.preprocessor.size()
    }

    /// The feature map of `image` at the tap ([`Embedder::set_tap`]), computed on a rayon worker
    /// ([`crate::runtime::on_worker`]).
    pub fn feature_map(&mut self, image: &RgbImage) -> Result<FeatureMap> {
        let tap = self.tap;
        Ok(self.tapped_maps(image, &[tap])?.pop().expect("one map per tap"))
    }

    /// The maps at `taps` of `image` (see [`super::Network::tapped_features`]), computed on a rayon worker.
    pub fn tapped_maps(&mut self, image: &RgbImage, taps: &[Tap]) -> Result<Vec<FeatureMap>> {
        crate::runtime::on_worker(|| {
            let x = self.preprocessor.tensor(image)?;
            let maps = self.network.tapped_features(&x, self.mode, taps)?;
            maps.iter()
                .map(|y| {
                    let (_, channels, height, width) = y.dims4()?;
                    Ok(FeatureMap { channels, height, width, data: y.flatten_all()?.to_vec1::<f32>()? })
                })
                .collect()
        })
    }

    /// Class probabilities (softmax of the classifier's logits), computed on a rayon worker.
    pub fn probabilities(&mut self, image: &RgbImage) -> Result<Vec<f32>> {
        crate::runtime::on_worker(|| {
            let x = self.preprocessor.tensor(image)?;
            let logits = self.network.logits(&x, self.mode)?;
            Ok(candle_nn::ops::softmax_last_dim(&logits)?.flatten_all()?.to_vec1::<f32>()?)
        })
    }
}
