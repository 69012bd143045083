//! The networks: MobileNetV2 (reference and import target) and ECMobileNet (the paper's variant),
//! their building blocks, the fast depthwise kernel, and weights import/load/save.

pub mod weights;
