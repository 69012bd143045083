//! Writes a synthetic sequence as a TUM RGB-D folder: `rgb/<stamp>.png`, `rgb.txt`
//! (`timestamp rgb/<stamp>.png`) and `groundtruth.txt` (`timestamp tx ty tz qx qy qz qw`, the
//! camera-to-world pose at exactly the image stamps, printed with full f64 precision).

use super::Scene;
use crate::io::tum::TumWriter;
use anyhow::{Context, Result};
use rayon::prelude::*;
use std::path::Path;

/// Renders every frame of `scene` (frames rendered and encoded in parallel) and writes the TUM
/// folder into `dir`, which is created if missing.
pub fn write_tum_folder(scene: &Scene, dir: &Path) -> Result<()> {
    let mut writer = TumWriter::create(dir)?;
    let paths: Vec<_> = (0..scene.len()).map(|index| writer.add_frame(scene.stamp(index))).collect();
    paths.par_iter().enumerate().try_for_each(|(index, path)| -> Result<()> {
        scene
            .render(index)
            .save_with_format(path, image::ImageFormat::Png)
            .with_context(|| format!("writing frame {index} to {}", path.display()))
    })?;
    for index in 0..scene.len() {
        writer.write_pose(scene.stamp(index), &scene.pose(index))?;
    }
    writer.finish()
}
