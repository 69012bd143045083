//! Weights: safetensors load/save with a stable naming scheme, the TFLite importer, and where
//! every command finds its weights ([`resolve`]).
//!
//! # Tensor names (stable; format `ecm-lcd-weights/1`)
//! Layout NCHW / OIHW, f32:
//! - `stem.weight` `[32, 3, 3, 3]`, `stem.bias` `[32]`
//! - `blocks.{i}.expand.weight` `[hidden, in, 1, 1]`, `.bias` (absent when the expansion is 1)
//! - `blocks.{i}.depthwise.weight` `[hidden, 1, 3, 3]`, `.bias`
//! - `blocks.{i}.eca.weight` `[1, 1, k]` (ECMobileNet only)
//! - `blocks.{i}.project.weight` `[out, hidden, 1, 1]`, `.bias`
//! - `head.weight` `[1280, 320, 1, 1]`, `head.bias`
//! - `classifier.weight` `[classes, 1280]`, `classifier.bias` `[classes]` (optional)
//!
//! `i` counts the network's own bottlenecks from 0 (17 in MobileNetV2, 13 in ECMobileNet).
//! `.bias` means BatchNorm is folded in (inference form). A training checkpoint instead stores
//! `X.bn.weight`, `X.bn.bias`, `X.bn.running_mean`, `X.bn.running_var` beside `X.weight`; loading it
//! for inference folds them. The header's metadata says `format`, `arch`, `classes` (if any) and
//! `source`.

pub mod fetch;
pub mod import;
pub mod resolve;
pub mod tflite;

use std::collections::HashMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use super::{Arch, Network};

pub const FORMAT: &str = "ecm-lcd-weights/1";

/// A set of named weights with what they are.
#[derive(Clone, Debug)]
pub struct Weights {
    pub arch: Arch,
    pub classes: Option<usize>,
    pub source: String,
    pub tensors: HashMap<String, Tensor>,
}

impl Weights {
    /// Saves as safetensors with the metadata in the header.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut metadata = HashMap::new();
        metadata.insert("format".to_string(), FORMAT.to_string());
        metadata.insert("arch".to_string(), self.arch.name().to_string());
        metadata.insert("source".to_string(), self.source.clone());
        if let Some(k) = self.classes {
            metadata.insert("classes".to_string(), k.to_string());
        }
        let mut names: Vec<&String> = self.tensors.keys().collect();
        names.sort();
        let data: Vec<(&str, &Tensor)> = names.iter().map(|n| (n.as_str(), &self.tensors[*n])).collect();
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        }
        // Write then rename, so a crash never leaves a half-written weights file behind.
        let tmp = path.with_extension("safetensors.part");
        safetensors::serialize_to_file(data, Some(metadata), &tmp).with_context(|| format!("cannot write {}", tmp.display()))?;
        std::fs::rename(&tmp, path).with_context(|| format!("cannot move {} to {}", tmp.display(), path.display()))?;
        Ok(())
    }

    /// Loads a safetensors file written by [`Weights::save`] (or any file using the naming scheme
    /// with an `arch` in its metadata).
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("cannot read weights file {}", path.display()))?;
        Self::from_bytes(&bytes).with_context(|| format!("{} is not a valid ecm-lcd weights file", path.display()))
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        let (_, header) = safetensors::SafeTensors::read_metadata(bytes).map_err(|e| anyhow::anyhow!("safetensors header: {e}"))?;
        let metadata = header.metadata().clone().unwrap_or_default();
        let arch: Arch = metadata.get("arch").context("no 'arch' in the safetensors metadata")?.parse()?;
        let classes = metadata.get("classes").map(|k| k.parse::<usize>()).transpose().context("bad 'classes' in metadata")?;
        let source = metadata.get("source").cloned().unwrap_or_default();
        let tensors = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)?;
        let tensors = tensors
            .into_iter()
            .map(|(name, t)| Ok((name, t.to_dtype(DType::F32)?)))
            .collect::<Result<HashMap<_, _>>>()?;
        Ok(Weights { arch, classes, source, tensors })
    }

    /// These weights for `arch`: as they are, or ECMobileNet made from MobileNetV2 weights.
    pub fn for_arch(&self, arch: Arch) -> Result<Weights> {
        match (self.arch, arch) {
            (a, b) if a == b => Ok(self.clone()),
            (Arch::MobileNetV2, Arch::EcMobileNet) => Ok(Weights {
                arch,
                classes: self.classes,
                source: format!("{} (ECMobileNet initialised from MobileNetV2; ECA untrained)", self.source),
                tensors: super::ecmobilenet::from_mobilenet_v2(&self.tensors)?,
            }),
            (from, to) => bail!("weights for {from} cannot be used for {to}"),
        }
    }

    /// Builds the network for inference (BatchNorm folded), with the classifier if wanted.
    pub fn network(&self, with_classifier: bool) -> Result<Network> {
        let classes = if with_classifier {
            Some(self.classes.context("these weights have no classifier")?)
        } else {
            None
        };
        let vb = VarBuilder::from_tensors(self.tensors.clone(), DType::F32, &Device::Cpu);
        Network::load(self.arch.spec(), vb, classes, false).with_context(|| format!("weights do not fit {}", self.arch))
    }
}

/// The inference-form tensors of a network (BatchNorm folded), named as above.
pub fn inference_tensors(network: &Network) -> Result<HashMap<String, Tensor>> {
    let mut out = HashMap::new();
    network.visit_units(&mut |name, weight, bias| {
        out.insert(format!("{name}.weight"), weight.clone());
        if let Some(b) = bias {
            out.insert(format!("{name}.bias"), b.clone());
        }
    })?;
    Ok(out)
}
