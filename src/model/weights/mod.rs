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

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use anyhow::{bail, Context, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use super::{Arch, Network};

pub const FORMAT: &str = "ecm-lcd-weights/1";

/// The safetensors metadata entry under which [`Weights::save`] writes its fields.
const METADATA_KEY: &str = "ecm-lcd";

/// A set of named weights with what they are.
#[derive(Clone, Debug)]
pub struct Weights {
    pub arch: Arch,
    pub classes: Option<usize>,
    pub source: String,
    pub tensors: HashMap<String, Tensor>,
}

impl Weights {
    /// Saves as safetensors with the metadata in the header ([`Weights::to_bytes`]).
    pub fn save(&self, path: &Path) -> Result<()> {
        let bytes = self.to_bytes()?;
        crate::io::output::create_folder_of(path)?;
        // A regular file is replaced by rename (a crash never leaves half a weights file); a device,
        // FIFO or symlink is written in place, never replaced.
        crate::io::output::write_replacing(path, &bytes)?;
        Ok(())
    }

    /// The safetensors file [`Weights::save`] writes: the same weights always give the same bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let mut fields = BTreeMap::new();
        fields.insert("format", FORMAT.to_string());
        fields.insert("arch", self.arch.name().to_string());
        fields.insert("source", self.source.clone());
        if let Some(k) = self.classes {
            fields.insert("classes", k.to_string());
        }
        // One metadata entry holding the fields as sorted JSON: safetensors writes its metadata map in
        // hash order, which differs from process to process, and the file's SHA-256 is the weights'
        // identity in keyframe databases, so the same weights must always give the same bytes.
        let metadata = HashMap::from([(METADATA_KEY.to_string(), serde_json::to_string(&fields)?)]);
        let mut names: Vec<&String> = self.tensors.keys().collect();
        names.sort();
        let data: Vec<(&str, &Tensor)> = names.iter().map(|n| (n.as_str(), &self.tensors[*n])).collect();
        safetensors::serialize(data, Some(metadata)).context("serialising the weights")
    }

    /// Loads a safetensors file written by [`Weights::save`] (or any file using the naming scheme
    /// with an `arch` in its metadata).
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = crate::io::read_capped(path, crate::io::limits::WEIGHTS_FILE, "weights file")?;
        Self::from_bytes(&bytes).with_context(|| format!("{} is not a valid ecm-lcd weights file", path.display()))
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        let (_, header) =
            safetensors::SafeTensors::read_metadata(bytes).map_err(|e| anyhow::anyhow!("safetensors header: {e}"))?;
        let mut metadata = header.metadata().clone().unwrap_or_default();
        // Files from [`Weights::save`] hold their fields as JSON under one key; older ones (and
        // other writers) as separate entries.
        if let Some(json) = metadata.remove(METADATA_KEY) {
            let fields: BTreeMap<String, String> = serde_json::from_str(&json)
                .with_context(|| format!("bad '{METADATA_KEY}' entry in the safetensors metadata"))?;
            metadata.extend(fields);
        }
        let arch: Arch = metadata.get("arch").context("no 'arch' in the safetensors metadata")?.parse()?;
        let classes =
            metadata.get("classes").map(|k| k.parse::<usize>()).transpose().context("bad 'classes' in metadata")?;
        let source = metadata.get("source").cloned().unwrap_or_default();
        let tensors = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)?;
        let tensors = tensors
            .into_iter()
            .map(|(name, t)| Ok((name, t.to_dtype(DType::F32)?)))
            .collect::<Result<HashMap<_, _>>>()?;
        let weights = Weights { arch, classes, source, tensors };
        weights.check_finite()?;
        Ok(weights)
    }

    /// Refuses weights with a NaN or infinite value (a diverged training run): every descriptor
    /// would be garbage and every image would match every other.
    pub fn check_finite(&self) -> Result<()> {
        let mut names: Vec<&String> = self.tensors.keys().collect();
        names.sort();
        for name in names {
            let values = self.tensors[name].flatten_all()?.to_vec1::<f32>()?;
            if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
                anyhow::bail!(
                    "tensor {name} holds a non-finite value ({} at index {bad}); the weights are unusable",
                    values[bad]
                );
            }
        }
        Ok(())
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
        let classes =
            if with_classifier { Some(self.classes.context("these weights have no classifier")?) } else { None };
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

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> Weights {
        let tensors = HashMap::from([
            ("a.weight".to_string(), Tensor::new(&[1f32, 2.0, 3.0], &Device::Cpu).unwrap()),
            ("b.bias".to_string(), Tensor::new(&[4f32], &Device::Cpu).unwrap()),
        ]);
        Weights { arch: Arch::EcMobileNet, classes: Some(4), source: "test".into(), tensors }
    }

    /// The file is the weights' identity (its SHA-256 names them in keyframe databases), so the same
    /// weights always give the same bytes, and the fields round-trip.
    #[test]
    fn saving_the_same_weights_gives_the_same_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let weights = tiny();
        let files: Vec<Vec<u8>> = (0..8)
            .map(|i| {
                let path = dir.path().join(format!("w{i}.safetensors"));
                weights.save(&path).unwrap();
                std::fs::read(&path).unwrap()
            })
            .collect();
        assert!(files.iter().all(|f| f == &files[0]), "two saves of the same weights differ");
        let back = Weights::from_bytes(&files[0]).unwrap();
        assert_eq!((back.arch, back.classes, back.source.as_str()), (Arch::EcMobileNet, Some(4), "test"));
        assert_eq!(back.tensors["a.weight"].to_vec1::<f32>().unwrap(), [1.0, 2.0, 3.0]);
    }

    /// Files written before the fields moved under one key still load.
    #[test]
    fn files_with_separate_metadata_entries_still_load() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("old.safetensors");
        let weights = tiny();
        let metadata = HashMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("arch".to_string(), "mobilenetv2".to_string()),
            ("source".to_string(), "old".to_string()),
        ]);
        let data: Vec<(&str, &Tensor)> = weights.tensors.iter().map(|(n, t)| (n.as_str(), t)).collect();
        safetensors::serialize_to_file(data, Some(metadata), &path).unwrap();
        let back = Weights::load(&path).unwrap();
        assert_eq!((back.arch, back.classes, back.source.as_str()), (Arch::MobileNetV2, None, "old"));
    }

    #[test]
    fn non_finite_weights_are_refused_naming_the_tensor() {
        let mut weights = tiny();
        weights.tensors.insert("c.weight".into(), Tensor::new(&[0f32, f32::NAN], &Device::Cpu).unwrap());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nan.safetensors");
        weights.save(&path).unwrap();
        let err = format!("{:#}", Weights::load(&path).unwrap_err());
        assert!(err.contains("c.weight") && err.contains("non-finite") && err.contains("nan.safetensors"), "{err}");
    }
}
