//! Writes a synthetic sequence as a TUM RGB-D folder: `rgb/<stamp>.png`, `rgb.txt`
//! (`timestamp rgb/<stamp>.png`) and `groundtruth.txt` (`timestamp tx ty tz qx qy qz qw`, the
//! camera-to-world pose at exactly the image stamps, printed with full f64 precision), the drifted
//! `odometry.txt` beside it, and with [`super::SynthConfig::depth`] `depth/<stamp>.png` (16-bit, TUM
//! scale) listed in `depth.txt`.

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
    let depth_paths: Vec<_> = if scene.config().depth {
        (0..scene.len()).map(|index| writer.add_depth(scene.stamp(index)).map(Some)).collect::<Result<_>>()?
    } else {
        vec![None; scene.len()]
    };
    paths.par_iter().zip(&depth_paths).enumerate().try_for_each(|(index, (path, depth_path))| -> Result<()> {
        scene
            .render(index)
            .save_with_format(path, image::ImageFormat::Png)
            .with_context(|| format!("writing frame {index} to {}", path.display()))?;
        if let Some(depth_path) = depth_path {
            scene
                .depth(index)
                .to_tum()
                .save_with_format(depth_path, image::ImageFormat::Png)
                .with_context(|| format!("writing depth {index} to {}", depth_path.display()))?;
        }
        Ok(())
    })?;
    for (index, odometry) in scene.odometry().iter().enumerate() {
        writer.write_pose(scene.stamp(index), &scene.pose(index))?;
        writer.write_odometry(scene.stamp(index), odometry);
    }
    writer.finish()
}
