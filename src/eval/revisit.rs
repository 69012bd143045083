//! A revisit sequence made from a short real TUM recording that has no loop of its own: the odd
//! frames forward, then the even frames backward. The second pass sees each place again from a
//! neighbouring pose, so every query of the second pass has real, pose-verified loops.
//!
//! Frames are re-stamped at a fixed period in the new order (replay time must increase for the
//! detector's recency rules); each keeps the ground-truth pose of its original stamp, so the
//! loop truth comes from the real poses. A frame with no ground-truth pose within
//! `max_offset_s` gets none (its truth is unknown).

use std::path::Path;

use anyhow::{ensure, Result};

use crate::eval::poses_at_stamps;
use crate::io::open_source;
use crate::io::tum::{read_groundtruth, TumWriter};
use crate::types::Stamp;

/// Replay order of `n` frames: 1, 3, 5, ... then the even indexes backwards.
pub fn two_pass_order(n: usize) -> Vec<usize> {
    let forward = (1..n).step_by(2);
    let backward = (0..n).step_by(2).rev();
    forward.chain(backward).collect()
}

/// Writes the two-pass sequence of the TUM folder `source` (with `groundtruth.txt`) into `out`,
/// one frame every `period_s` seconds from the source's first stamp. Returns the frame count.
pub fn write_two_pass(source: &Path, out: &Path, period_s: f64, max_offset_s: f64) -> Result<usize> {
    let frames: Vec<_> = crate::io::skip_unreadable(open_source(source, None)?, source).collect::<Result<_>>()?;
    ensure!(
        frames.len() >= 3,
        "{} has {} frames; a two-pass sequence needs at least 3",
        source.display(),
        frames.len()
    );
    let groundtruth = read_groundtruth(&source.join("groundtruth.txt"))?;
    let stamps: Vec<Stamp> = frames.iter().map(|f| f.stamp).collect();
    let poses = poses_at_stamps(&stamps, &groundtruth, max_offset_s);
    let start = stamps[0];
    let mut writer = TumWriter::create(out)?;
    for (k, &i) in two_pass_order(frames.len()).iter().enumerate() {
        // Whole microseconds, as TUM files print them.
        let stamp = Stamp::from_nanos(start.nanos + ((k as f64 * period_s * 1e6).round() as i64) * 1000);
        writer.write_frame(stamp, &frames[i].image)?;
        if let Some(pose) = &poses[i] {
            writer.write_pose(stamp, pose)?;
        }
    }
    writer.finish()?;
    Ok(frames.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn odd_forward_then_even_backward() {
        assert_eq!(two_pass_order(7), [1, 3, 5, 6, 4, 2, 0]);
        assert_eq!(two_pass_order(6), [1, 3, 5, 4, 2, 0]);
    }
}
