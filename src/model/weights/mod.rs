//! Weights: the TFLite importer, safetensors load/save with a stable naming scheme, and where to find them.

pub mod tflite;
