//! MobileNetV2, width 1.0 (Sandler et al., Table 2): the reference network and the target of the
//! TFLite import.

use super::{row, Arch, NetworkSpec};

/// Table 2 of the MobileNetV2 paper: 17 bottlenecks.
pub const MOBILENET_V2: NetworkSpec = NetworkSpec {
    arch: Arch::MobileNetV2,
    stem_channels: 32,
    rows: &[
        row(1, 16, 1, 1),
        row(6, 24, 2, 2),
        row(6, 32, 3, 2),
        row(6, 64, 4, 2),
        row(6, 96, 3, 1),
        row(6, 160, 3, 2),
        row(6, 320, 1, 1),
    ],
    head_channels: 1280,
    eca_kernel: None,
};
