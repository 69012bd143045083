//! Synthetic indoor sequences with loops and exact ground truth, rendered by the project itself.
//!
//! A camera walks a smooth closed path through three connected, textured rooms ([`world`]) for
//! several laps ([`path`]); each lap is perturbed a little (position, height, heading, pitch,
//! roll) and the lighting drifts (global exposure and colour, per-lap lamp strength), so a
//! revisited place looks alike but never pixel-identical. Everything derives from the seed.
//!
//! Conventions: world z is up, the floor is z = 0; poses are camera-to-world with the TUM camera
//! axes (x right, y down, z forward, along the optical axis). Stamps start at
//! [`SynthConfig::start_stamp`] and advance by `1 / rate_hz`, rounded to whole microseconds so
//! that the six-decimal TUM text files hold them exactly.

mod path;
mod tum_out;
mod world;

pub use path::camera_rotation;
pub use tum_out::write_tum_folder;
pub use world::SplitMix64;

use crate::types::Stamp;
use anyhow::{bail, Result};
use image::RgbImage;
use nalgebra::Isometry3;

/// What to render.
#[derive(Clone, Debug, PartialEq)]
pub struct SynthConfig {
    /// Number of frames in the whole sequence.
    pub frames: usize,
    /// Number of laps of the closed path the frames are spread over.
    pub laps: usize,
    pub seed: u64,
    pub width: u32,
    pub height: u32,
    /// Frame rate of the stamps, frames per second.
    pub rate_hz: f64,
    /// Stamp of the first frame.
    pub start_stamp: Stamp,
}

impl Default for SynthConfig {
    /// 3 laps of 800 frames at 30 Hz (27 s and about 20 m per lap, 0.75 m/s), 320x240.
    fn default() -> Self {
        SynthConfig {
            frames: 2400,
            laps: 3,
            seed: 1,
            width: 320,
            height: 240,
            rate_hz: 30.0,
            start_stamp: Stamp::from_nanos(1_600_000_000_000_000_000),
        }
    }
}

/// A rendered-on-demand sequence: any frame can be rendered on its own, in any order.
pub struct Scene {
    config: SynthConfig,
    world: world::World,
    path: path::CameraPath,
}

impl Scene {
    pub fn new(config: SynthConfig) -> Result<Self> {
        if config.frames == 0 || config.laps == 0 {
            bail!("synthetic sequence needs at least one frame and one lap (got {} frames, {} laps)", config.frames, config.laps);
        }
        if config.width < 16 || config.height < 16 || config.width > 8192 || config.height > 8192 {
            bail!("synthetic image size {}x{} is outside 16..=8192 pixels per side", config.width, config.height);
        }
        if !(config.rate_hz.is_finite() && config.rate_hz > 0.0 && config.rate_hz <= 1e6) {
            bail!("frame rate {} Hz must be positive and at most 1 MHz", config.rate_hz);
        }
        if config.start_stamp.nanos < 0 || config.start_stamp.nanos % 1000 != 0 {
            bail!("start stamp {} must be non-negative and a whole number of microseconds", config.start_stamp);
        }
        Ok(Scene {
            world: world::World::new(config.seed),
            path: path::CameraPath::new(config.seed),
            config,
        })
    }

    pub fn config(&self) -> &SynthConfig {
        &self.config
    }

    pub fn len(&self) -> usize {
        self.config.frames
    }

    pub fn is_empty(&self) -> bool {
        self.config.frames == 0
    }

    /// Length of one lap of the path in metres.
    pub fn lap_length(&self) -> f64 {
        self.path.lap_length()
    }

    /// Focal length in pixels (square pixels, principal point at the image centre); about 64°
    /// horizontal field of view, like the Kinect of the TUM RGB-D sequences.
    pub fn focal_length(&self) -> f64 {
        0.82 * self.config.width as f64
    }

    /// Position along the path in laps (0.0 = start, `laps` = one past the last frame).
    fn progress(&self, index: usize) -> f64 {
        index as f64 * self.config.laps as f64 / self.config.frames as f64
    }

    pub fn stamp(&self, index: usize) -> Stamp {
        let micros = (index as f64 * 1e6 / self.config.rate_hz).round() as i64;
        Stamp::from_nanos(self.config.start_stamp.nanos + micros * 1000)
    }

    /// Exact camera-to-world pose of frame `index`.
    pub fn pose(&self, index: usize) -> Isometry3<f64> {
        self.path.pose(self.progress(index))
    }

    fn lighting(&self, index: usize) -> world::Lighting {
        let seconds = index as f64 / self.config.rate_hz;
        let lap = self.progress(index).floor() as u64;
        let wave = |period: f64, phase: f64| (std::f64::consts::TAU * seconds / period + phase).sin() as f32;
        let phase = (self.config.seed % 1000) as f64 * 0.37;
        let exposure = 1.0 + 0.15 * wave(41.0, phase);
        let warmth = 0.06 * wave(67.0, 1.3 + phase);
        let lamps = (0..self.world.room_count())
            .map(|room| {
                let h = world::SplitMix64::new(self.config.seed ^ (lap << 8) ^ room as u64).next_f64() as f32;
                0.65 + 0.45 * h
            })
            .collect();
        world::Lighting { exposure, tint: [1.0 + warmth, 1.0, 1.0 - warmth], lamps }
    }

    /// Renders frame `index` (which need not be below `len()`; the path simply continues).
    pub fn render(&self, index: usize) -> RgbImage {
        let noise_seed = self.config.seed.wrapping_mul(0x9E37_79B9).wrapping_add(index as u64);
        self.world.render(
            &self.pose(index),
            self.config.width,
            self.config.height,
            self.focal_length(),
            &self.lighting(index),
            noise_seed,
        )
    }

    /// Stamp, image and camera-to-world pose of frame `index`.
    pub fn frame(&self, index: usize) -> (Stamp, RgbImage, Isometry3<f64>) {
        (self.stamp(index), self.render(index), self.pose(index))
    }
}

/// All frames of a sequence in order, rendered lazily (each frame uses all cores).
pub fn render_sequence(config: SynthConfig) -> Result<impl Iterator<Item = (Stamp, RgbImage, Isometry3<f64>)>> {
    let scene = Scene::new(config)?;
    Ok((0..scene.len()).map(move |i| scene.frame(i)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small(seed: u64) -> SynthConfig {
        SynthConfig { frames: 90, laps: 3, seed, width: 64, height: 48, ..SynthConfig::default() }
    }

    #[test]
    fn rendering_is_deterministic_for_a_seed() {
        let a = Scene::new(small(7)).unwrap();
        let b = Scene::new(small(7)).unwrap();
        let c = Scene::new(small(8)).unwrap();
        for i in [0, 13, 61] {
            assert_eq!(a.render(i), b.render(i));
            assert_eq!(a.pose(i), b.pose(i));
            assert_ne!(a.render(i), c.render(i), "another seed must give another scene");
        }
    }

    #[test]
    fn stamps_advance_at_the_rate_in_whole_microseconds() {
        let scene = Scene::new(small(1)).unwrap();
        let start = scene.config().start_stamp;
        assert_eq!(scene.stamp(0), start);
        assert_eq!(scene.stamp(1).nanos - start.nanos, 33_333_000);
        assert_eq!(scene.stamp(30).nanos - start.nanos, 1_000_000_000);
    }

    #[test]
    fn laps_revisit_places_with_small_differences() {
        let scene = Scene::new(small(3)).unwrap();
        // Frames 10, 40, 70 are at the same fraction of laps 1, 2, 3.
        let p: Vec<_> = [10, 40, 70].iter().map(|&i| scene.pose(i)).collect();
        for other in &p[1..] {
            let distance = (other.translation.vector - p[0].translation.vector).norm();
            assert!(distance > 1e-4 && distance < 0.3, "revisit offset {distance}");
            let axis_angle = (other.rotation * nalgebra::Vector3::z()).angle(&(p[0].rotation * nalgebra::Vector3::z()));
            assert!(axis_angle < 0.3, "revisit heading difference {axis_angle}");
        }
        // Half a lap later the camera is elsewhere.
        let away = (scene.pose(25).translation.vector - p[0].translation.vector).norm();
        assert!(away > 2.0, "half a lap away is only {away} m");
        // And the revisited image is close to, but not the same as, the first visit.
        let (a, b) = (scene.render(10), scene.render(40));
        assert_ne!(a, b);
        let mean_abs: f64 = a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| (*x as f64 - *y as f64).abs()).sum::<f64>()
            / a.as_raw().len() as f64;
        let c = scene.render(25);
        let mean_abs_away: f64 = a.as_raw().iter().zip(c.as_raw()).map(|(x, y)| (*x as f64 - *y as f64).abs()).sum::<f64>()
            / a.as_raw().len() as f64;
        assert!(mean_abs < mean_abs_away, "revisit differs by {mean_abs}, elsewhere by {mean_abs_away}");
    }

    #[test]
    fn bad_configs_are_refused() {
        assert!(Scene::new(SynthConfig { frames: 0, ..small(1) }).is_err());
        assert!(Scene::new(SynthConfig { laps: 0, ..small(1) }).is_err());
        assert!(Scene::new(SynthConfig { width: 2, ..small(1) }).is_err());
        assert!(Scene::new(SynthConfig { rate_hz: f64::NAN, ..small(1) }).is_err());
    }
}
