//! Writes a synthetic sequence as a TUM RGB-D folder: `rgb/<stamp>.png`, `rgb.txt`
//! (`timestamp rgb/<stamp>.png`) and `groundtruth.txt` (`timestamp tx ty tz qx qy qz qw`, the
//! camera-to-world pose at exactly the image stamps, printed with full f64 precision).
//! Kept minimal on purpose; the general TUM reader and writer live in `io`.

use super::Scene;
use crate::types::Stamp;
use anyhow::{Context, Result};
use rayon::prelude::*;
use std::fmt::Write as _;
use std::path::Path;

/// `seconds.micros`, the TUM file-name form; stamps of a [`Scene`] are whole microseconds.
fn tum_stamp(stamp: Stamp) -> String {
    format!("{}.{:06}", stamp.sec(), stamp.nsec() / 1000)
}

/// Renders every frame of `scene` (frames in parallel) and writes the TUM folder into `dir`,
/// which is created if missing. Existing files of the same names are overwritten.
pub fn write_tum_folder(scene: &Scene, dir: &Path) -> Result<()> {
    let rgb_dir = dir.join("rgb");
    std::fs::create_dir_all(&rgb_dir).with_context(|| format!("creating {}", rgb_dir.display()))?;
    (0..scene.len()).into_par_iter().try_for_each(|index| -> Result<()> {
        let path = rgb_dir.join(format!("{}.png", tum_stamp(scene.stamp(index))));
        scene
            .render(index)
            .save_with_format(&path, image::ImageFormat::Png)
            .with_context(|| format!("writing frame {index} to {}", path.display()))
    })?;
    let mut rgb = String::from("# color images\n# timestamp filename\n");
    let mut truth = String::from("# ground truth trajectory (ecm-lcd synth, camera-to-world)\n# timestamp tx ty tz qx qy qz qw\n");
    for index in 0..scene.len() {
        let stamp = tum_stamp(scene.stamp(index));
        let pose = scene.pose(index);
        let (t, q) = (pose.translation.vector, pose.rotation.quaternion());
        writeln!(rgb, "{stamp} rgb/{stamp}.png")?;
        writeln!(truth, "{stamp} {} {} {} {} {} {} {}", t.x, t.y, t.z, q.i, q.j, q.k, q.w)?;
    }
    for (name, text) in [("rgb.txt", rgb), ("groundtruth.txt", truth)] {
        let path = dir.join(name);
        std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
