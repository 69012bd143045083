//! MobileNetV2 weights from a TFLite model (e.g. the quantisation-aware-trained
//! `mobilenet_v2_1.0_224_quant.tflite`): de-quantised convolution weights with BatchNorm already
//! folded in (conv weight + int32 bias), mapped to [`super`]'s names by their order in the graph,
//! since some TFLite tensor names join several layer names with ';'.
//!
//! TFLite layouts: convolution weights OHWI, depthwise weights `[1, H, W, C]`; both become OIHW.
//! TFLite's "SAME" padding (extra pixel bottom/right at stride 2) is what our convolutions do.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{ensure, Context, Result};
use candle_core::{Device, Tensor};

use super::tflite::{Activation, Padding, TfModel};
use super::Weights;
use crate::model::mobilenetv2::MOBILENET_V2;
use crate::model::Arch;

/// Reads `path` and imports it; see [`import_tflite_bytes`].
pub fn import_tflite(path: &Path) -> Result<Weights> {
    let bytes = crate::io::read_capped(path, crate::io::limits::WEIGHTS_FILE, "TFLite model")?;
    import_tflite_file(path, &bytes)
}

/// Imports `bytes`, read from `path`, and says where they came from. Every way of importing a file
/// (`import-weights`, `--weights x.tflite`, the cache) goes through here, so the same file gives the
/// same weights, byte for byte once saved, and so the same keyframe database identity: the public
/// file is named as published whatever the copy is called, another file by its name and hash.
pub fn import_tflite_file(path: &Path, bytes: &[u8]) -> Result<Weights> {
    let mut weights = import_tflite_bytes(bytes).with_context(|| format!("cannot import {}", path.display()))?;
    weights.check_finite().with_context(|| format!("cannot import {}", path.display()))?;
    let sha256 = super::fetch::sha256_hex(bytes);
    weights.source = if sha256 == super::resolve::UPSTREAM_SHA256 {
        format!("{} (TFLite)", super::resolve::UPSTREAM_FILE)
    } else {
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        format!("{name} (TFLite, sha256 {sha256})")
    };
    Ok(weights)
}

/// Imports a MobileNetV2 (width 1.0) TFLite model with its classifier.
pub fn import_tflite_bytes(bytes: &[u8]) -> Result<Weights> {
    let model = TfModel::parse(bytes)?;
    let convs: Vec<_> = model.convolutions().collect();

    // The expected convolutions in graph order: (name, depthwise, OIHW shape, activation).
    let mut expected = vec![("stem".to_string(), false, [MOBILENET_V2.stem_channels, 3, 3, 3], Activation::Relu6)];
    for (i, b) in MOBILENET_V2.blocks().iter().enumerate() {
        if b.has_expansion() {
            expected.push((format!("blocks.{i}.expand"), false, [b.hidden, b.input, 1, 1], Activation::Relu6));
        }
        expected.push((format!("blocks.{i}.depthwise"), true, [b.hidden, 1, 3, 3], Activation::Relu6));
        expected.push((format!("blocks.{i}.project"), false, [b.output, b.hidden, 1, 1], Activation::None));
    }
    expected.push(("head".to_string(), false, [MOBILENET_V2.head_channels, 320, 1, 1], Activation::Relu6));
    ensure!(
        convs.len() == expected.len() + 1,
        "expected {} convolutions (MobileNetV2 1.0 with classifier), found {}",
        expected.len() + 1,
        convs.len()
    );

    let mut tensors = HashMap::new();
    for ((name, depthwise, shape, activation), conv) in expected.iter().zip(&convs) {
        let what = format!("convolution for {name}");
        ensure!(conv.depthwise == *depthwise, "{what}: depthwise is {}, expected {depthwise}", conv.depthwise);
        ensure!(conv.padding == Padding::Same, "{what}: padding is not SAME");
        ensure!(
            conv.activation == *activation,
            "{what}: fused activation {:?}, expected {activation:?}",
            conv.activation
        );
        let weight = model.tensors[conv.weight].clone();
        let values = weight.to_f32().with_context(|| what.clone())?;
        // OHWI -> OIHW; depthwise [1, H, W, C] -> [C, 1, H, W].
        let dims: [usize; 4] =
            weight.shape.clone().try_into().map_err(|_| anyhow::anyhow!("{what}: weight is not 4-D"))?;
        let t = Tensor::from_vec(values, dims.to_vec(), &Device::Cpu)?;
        let t = if *depthwise { t.permute((3, 0, 1, 2))? } else { t.permute((0, 3, 1, 2))? }.contiguous()?;
        ensure!(t.dims() == shape, "{what}: weight shape {:?} (OIHW), expected {shape:?}", t.dims());
        tensors.insert(format!("{name}.weight"), t);
        tensors.insert(format!("{name}.bias"), bias_tensor(&model, conv.bias, shape[0], &what)?);
    }

    let classifier = convs.last().expect("count checked above");
    let weight = &model.tensors[classifier.weight];
    ensure!(!classifier.depthwise && weight.shape.len() == 4, "classifier is not a 1x1 convolution");
    let classes = weight.shape[0];
    ensure!(weight.shape[1..] == [1, 1, MOBILENET_V2.head_channels], "classifier weight shape {:?}", weight.shape);
    let w = Tensor::from_vec(
        weight.to_f32().context("classifier weight")?,
        (classes, MOBILENET_V2.head_channels),
        &Device::Cpu,
    )?;
    tensors.insert("classifier.weight".to_string(), w);
    tensors.insert("classifier.bias".to_string(), bias_tensor(&model, classifier.bias, classes, "classifier")?);
    Ok(Weights { arch: Arch::MobileNetV2, classes: Some(classes), source: "TFLite".to_string(), tensors })
}

fn bias_tensor(model: &TfModel, index: Option<usize>, channels: usize, what: &str) -> Result<Tensor> {
    let index = index.with_context(|| format!("{what}: no bias"))?;
    let values = model.tensors[index].to_f32().with_context(|| format!("{what}: bias"))?;
    ensure!(values.len() == channels, "{what}: {} biases for {channels} channels", values.len());
    Ok(Tensor::from_vec(values, channels, &Device::Cpu)?)
}
