//! Synthetic indoor sequences with loops and exact ground truth, rendered by the project itself.
//!
//! A camera walks a smooth closed path through three connected, textured rooms ([`world`]) for
//! several laps ([`path`]); each lap is perturbed a little (position, height, heading, pitch,
//! roll) and the lighting drifts (global exposure and colour, per-lap lamp strength), so a
//! revisited place looks alike but never pixel-identical. Everything derives from the seed.
//!
//! [`Difficulty`] makes a sequence hard on purpose, the way real revisits are hard: identical rooms
//! (perceptual aliasing), a different illumination on every other lap (night), a sideways and yaw
//! offset between laps, grayscale output, sensor noise and blur; [`Difficulty::hard`] is the preset
//! (`ecm-lcd synth --preset hard`), used with a low resolution ([`SynthConfig::hard`]).
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

use crate::types::{DepthImage, Stamp};
use anyhow::{bail, Result};
use image::RgbImage;
use nalgebra::Isometry3;

/// The most frames one sequence may have (over 9 hours at 30 Hz): its poses are kept in memory.
pub const MAX_FRAMES: usize = 1_000_000;

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
    pub difficulty: Difficulty,
    /// Also render depth images (written as TUM `depth/` and `depth.txt`).
    pub depth: bool,
    /// How the odometry trajectory written beside the ground truth drifts.
    pub drift: OdometryDrift,
}

/// Errors of a simulated odometry (a visual or wheel odometry's typical faults), applied to each
/// frame-to-frame motion: a scale error, a heading bias proportional to the distance travelled, and
/// seeded Gaussian noise. The drifted trajectory starts at the true first pose.
#[derive(Clone, Debug, PartialEq)]
pub struct OdometryDrift {
    /// Factor on every translation (1 = exact).
    pub scale: f64,
    /// Heading error about the world's up axis, in degrees per metre travelled.
    pub yaw_deg_per_m: f64,
    /// Standard deviation of the heading noise, degrees per square root of a metre.
    pub yaw_noise_deg: f64,
    /// Standard deviation of the translation noise as a fraction of each step's length.
    pub translation_noise: f64,
}

impl OdometryDrift {
    /// The odometry a tracker with these errors would report along `truth` (camera-to-world poses in
    /// order), seeded: each true step between consecutive poses is drifted and chained on from the
    /// first true pose. The heading error turns about the world's z axis (up in `synth`'s worlds).
    pub fn apply(&self, truth: &[Isometry3<f64>], seed: u64) -> Vec<Isometry3<f64>> {
        let mut rng = world::SplitMix64::new(seed ^ 0x6F64_6F6D_6574_7279);
        let mut gaussian = move || {
            let (u1, u2) = (rng.next_f64().max(1e-12), rng.next_f64());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let Some(&first) = truth.first() else { return Vec::new() };
        let mut poses = Vec::with_capacity(truth.len());
        let mut odometry = first;
        poses.push(odometry);
        for pair in truth.windows(2) {
            let step = pair[0].inverse() * pair[1];
            let length = step.translation.vector.norm();
            let noise = nalgebra::Vector3::new(gaussian(), gaussian(), gaussian()) * self.translation_noise * length;
            let translation = step.translation.vector * self.scale + noise;
            let yaw = (self.yaw_deg_per_m * length + self.yaw_noise_deg * length.sqrt() * gaussian()).to_radians();
            // Heading error about world up, expressed in the previous camera's frame.
            let up = odometry.rotation.inverse() * nalgebra::Vector3::z_axis();
            let error = nalgebra::UnitQuaternion::from_axis_angle(&up, yaw);
            let drifted = Isometry3::from_parts(translation.into(), error * step.rotation);
            odometry *= drifted;
            poses.push(odometry);
        }
        poses
    }
}

impl Default for OdometryDrift {
    fn default() -> Self {
        OdometryDrift { scale: 1.03, yaw_deg_per_m: 1.0, yaw_noise_deg: 0.3, translation_noise: 0.05 }
    }
}

/// What makes revisits hard to recognise (module doc). The default adds nothing.
#[derive(Clone, Debug, PartialEq)]
pub struct Difficulty {
    /// Every room decorated alike.
    pub aliasing: bool,
    /// Sideways offset in metres of every lap after the first, alternating in sign.
    pub lap_offset_m: f64,
    /// Extra heading in degrees of every lap after the first, alternating in sign.
    pub lap_yaw_deg: f64,
    /// Exposure factor on every second lap (1 = unchanged; 0.3 is a dim, night-like lap), which also
    /// turns that lap's light warm (a lower colour temperature).
    pub night_exposure: f64,
    /// Grayscale images (still written as RGB).
    pub grayscale: bool,
    /// Standard deviation of Gaussian sensor noise, in 8-bit grey levels.
    pub noise: f64,
    /// Standard deviation of a Gaussian blur, in pixels (0 = none).
    pub blur: f64,
}

impl Default for Difficulty {
    fn default() -> Self {
        Difficulty {
            aliasing: false,
            lap_offset_m: 0.0,
            lap_yaw_deg: 0.0,
            night_exposure: 1.0,
            grayscale: false,
            noise: 0.0,
            blur: 0.0,
        }
    }
}

impl Difficulty {
    /// The `hard` preset: every difficulty at once.
    pub fn hard() -> Self {
        Difficulty {
            aliasing: true,
            lap_offset_m: 0.35,
            lap_yaw_deg: 12.0,
            night_exposure: 0.3,
            grayscale: true,
            noise: 6.0,
            blur: 0.8,
        }
    }

    fn check(&self) -> Result<()> {
        let finite = [self.lap_offset_m, self.lap_yaw_deg, self.night_exposure, self.noise, self.blur]
            .iter()
            .all(|v| v.is_finite());
        if !finite
            || self.lap_offset_m.abs() > 0.6
            || self.lap_yaw_deg.abs() > 45.0
            || !(0.05..=1.0).contains(&self.night_exposure)
            || !(0.0..=64.0).contains(&self.noise)
            || !(0.0..=10.0).contains(&self.blur)
        {
            bail!(
                "synthetic difficulty out of range: lap offset {} m (|.| <= 0.6), lap yaw {} deg (|.| <= 45), night exposure {} (0.05..=1), noise {} (0..=64), blur {} px (0..=10)",
                self.lap_offset_m,
                self.lap_yaw_deg,
                self.night_exposure,
                self.noise,
                self.blur
            );
        }
        Ok(())
    }
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
            difficulty: Difficulty::default(),
            depth: false,
            drift: OdometryDrift::default(),
        }
    }
}

impl SynthConfig {
    /// The `hard` preset at a low resolution (160x120): what `ecm-lcd synth --preset hard` renders.
    pub fn hard() -> Self {
        SynthConfig { width: 160, height: 120, difficulty: Difficulty::hard(), ..SynthConfig::default() }
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
            bail!(
                "synthetic sequence needs at least one frame and one lap (got {} frames, {} laps)",
                config.frames,
                config.laps
            );
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
        if config.frames > MAX_FRAMES {
            bail!("{} frames are more than the {MAX_FRAMES} a synthetic sequence holds", config.frames);
        }
        // The last stamp must still be a stamp (nanoseconds in an i64: until the year 2262).
        let last_secs = config.start_stamp.nanos as f64 / 1e9 + (config.frames - 1) as f64 / config.rate_hz;
        if last_secs >= i64::MAX as f64 / 1e9 {
            bail!("{} frames at {} Hz run past the last stamp a timestamp holds", config.frames, config.rate_hz);
        }
        config.difficulty.check()?;
        let d = &config.difficulty;
        Ok(Scene {
            world: world::World::new(config.seed, d.aliasing),
            path: path::CameraPath::new(config.seed).with_lap_offsets(d.lap_offset_m, d.lap_yaw_deg.to_radians()),
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
        // Every second lap dimmer and warmer (night), when asked for.
        let night = lap % 2 == 1 && self.config.difficulty.night_exposure < 1.0;
        let (exposure, warmth) = if night {
            (exposure * self.config.difficulty.night_exposure as f32, warmth + 0.25)
        } else {
            (exposure, warmth)
        };
        world::Lighting { exposure, tint: [1.0 + warmth, 1.0, 1.0 - warmth], lamps }
    }

    /// The camera's own faults ([`Difficulty`]): blur, noise, grayscale, in that order.
    fn degrade(&self, image: RgbImage, noise_seed: u64) -> RgbImage {
        let d = &self.config.difficulty;
        let mut image = if d.blur > 0.0 { image::imageops::blur(&image, d.blur as f32) } else { image };
        if d.noise > 0.0 {
            let mut rng = world::SplitMix64::new(noise_seed ^ 0x6E6F_6973_6532);
            for pixel in image.pixels_mut() {
                // Box-Muller; one draw per pixel, the same for its three channels (luminance noise).
                let (u1, u2) = (rng.next_f64().max(1e-12), rng.next_f64());
                let n = d.noise * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
                pixel.0.iter_mut().for_each(|c| *c = (*c as f64 + n).round().clamp(0.0, 255.0) as u8);
            }
        }
        if d.grayscale {
            for pixel in image.pixels_mut() {
                let [r, g, b] = pixel.0.map(|c| c as f64);
                let y = (0.299 * r + 0.587 * g + 0.114 * b).round() as u8;
                pixel.0 = [y, y, y];
            }
        }
        image
    }

    /// Renders frame `index` (which need not be below `len()`; the path simply continues).
    pub fn render(&self, index: usize) -> RgbImage {
        let noise_seed = self.config.seed.wrapping_mul(0x9E37_79B9).wrapping_add(index as u64);
        let image = self.world.render(
            &self.pose(index),
            self.config.width,
            self.config.height,
            self.focal_length(),
            &self.lighting(index),
            noise_seed,
        );
        self.degrade(image, noise_seed)
    }

    /// Depth image of frame `index`, registered to [`Scene::render`]'s image.
    pub fn depth(&self, index: usize) -> DepthImage {
        let (width, height) = (self.config.width, self.config.height);
        DepthImage { width, height, metres: self.world.depth(&self.pose(index), width, height, self.focal_length()) }
    }

    /// The drifted odometry trajectory of the whole sequence ([`OdometryDrift`]), camera-to-world.
    pub fn odometry(&self) -> Vec<Isometry3<f64>> {
        let truth: Vec<Isometry3<f64>> = (0..self.len()).map(|index| self.pose(index)).collect();
        self.config.drift.apply(&truth, self.config.seed)
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
    fn drift_applies_to_any_trajectory_and_without_errors_reproduces_it() {
        let scene = Scene::new(small(3)).unwrap();
        let truth: Vec<Isometry3<f64>> = (0..scene.len()).map(|i| scene.pose(i)).collect();
        let exact = OdometryDrift { scale: 1.0, yaw_deg_per_m: 0.0, yaw_noise_deg: 0.0, translation_noise: 0.0 };
        for (got, want) in exact.apply(&truth, 7).iter().zip(&truth) {
            assert!((got.translation.vector - want.translation.vector).norm() < 1e-9);
            assert!(got.rotation.angle_to(&want.rotation) < 1e-9);
        }
        assert_eq!(OdometryDrift::default().apply(&truth, 3), scene.odometry(), "the scene's odometry is this");
        let drifted = OdometryDrift::default().apply(&truth, 3);
        let end = (drifted.last().unwrap().translation.vector - truth.last().unwrap().translation.vector).norm();
        assert!(end > 0.5, "three laps of 3% scale and 1 deg/m heading error end {end} m off");
        assert!(OdometryDrift::default().apply(&[], 3).is_empty());
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
        let mean_abs_away: f64 =
            a.as_raw().iter().zip(c.as_raw()).map(|(x, y)| (*x as f64 - *y as f64).abs()).sum::<f64>()
                / a.as_raw().len() as f64;
        assert!(mean_abs < mean_abs_away, "revisit differs by {mean_abs}, elsewhere by {mean_abs_away}");
    }

    fn with(difficulty: Difficulty) -> Scene {
        Scene::new(SynthConfig { difficulty, ..small(3) }).unwrap()
    }

    fn mean_grey(image: &RgbImage) -> f64 {
        image.as_raw().iter().map(|&v| v as f64).sum::<f64>() / image.as_raw().len() as f64
    }

    #[test]
    fn each_difficulty_does_what_it_says_and_the_default_adds_nothing() {
        let plain = with(Difficulty::default());
        // Frames 10, 40, 70: the same place on laps 1, 2, 3.
        let offset = with(Difficulty { lap_offset_m: 0.3, lap_yaw_deg: 10.0, ..Difficulty::default() });
        assert_eq!(offset.pose(10), plain.pose(10), "the first lap is never offset");
        for frame in [40, 70] {
            let (a, b) = (plain.pose(frame), offset.pose(frame));
            let moved = b.translation.vector - a.translation.vector;
            assert!((moved.norm() - 0.3).abs() < 1e-6 && moved.z.abs() < 1e-9, "frame {frame} moved {moved:?}");
            let yaw = (a.rotation.inverse() * b.rotation).angle().to_degrees();
            assert!((yaw - 10.0).abs() < 1e-6, "frame {frame} turned {yaw} degrees");
        }
        // Alternating sides: laps 2 and 3 are offset in opposite directions (in the camera's x).
        let side = |f: usize| {
            (plain.pose(f).rotation.inverse() * (offset.pose(f).translation.vector - plain.pose(f).translation.vector))
                .x
        };
        assert!(side(40) * side(70) < 0.0, "laps 2 and 3 lie on opposite sides: {} and {}", side(40), side(70));

        let night = with(Difficulty { night_exposure: 0.3, ..Difficulty::default() });
        assert_eq!(night.render(10), plain.render(10), "the first lap is by day");
        let (dark, day) = (mean_grey(&night.render(40)), mean_grey(&plain.render(40)));
        // Exposure 0.3 in linear light is about 0.58 after the sRGB-like encoding.
        assert!(dark < 0.65 * day, "the second lap is a night lap: mean grey {dark} against {day}");
        assert_eq!(night.render(70), plain.render(70), "the third lap is by day again");

        let gray = with(Difficulty { grayscale: true, ..Difficulty::default() }).render(10);
        assert!(gray.pixels().all(|p| p.0[0] == p.0[1] && p.0[1] == p.0[2]));
        assert!(plain.render(10).pixels().any(|p| p.0[0] != p.0[2]));

        let noisy = with(Difficulty { noise: 8.0, ..Difficulty::default() }).render(10);
        let clean = plain.render(10);
        let deviation =
            (noisy.as_raw().iter().zip(clean.as_raw()).map(|(a, b)| (*a as f64 - *b as f64).powi(2)).sum::<f64>()
                / clean.as_raw().len() as f64)
                .sqrt();
        assert!((5.0..9.0).contains(&deviation), "noise of 8 grey levels measured as {deviation}");

        let blurred = with(Difficulty { blur: 1.5, ..Difficulty::default() }).render(10);
        let sharpness =
            |image: &RgbImage| image.as_raw().windows(4).map(|w| (w[3] as f64 - w[0] as f64).abs()).sum::<f64>();
        assert!(sharpness(&blurred) < 0.8 * sharpness(&clean), "blur must soften edges");
    }

    #[test]
    fn aliasing_decorates_every_room_alike() {
        // The mean colour of a frame per room: with aliasing the rooms' colours agree far more.
        let spread = |aliasing: bool| {
            let scene = with(Difficulty { aliasing, ..Difficulty::default() });
            let colours: Vec<[f64; 3]> = [2, 12, 22]
                .iter()
                .map(|&i| {
                    let image = scene.render(i);
                    let n = (image.width() * image.height()) as f64;
                    let mut sum = [0.0; 3];
                    image.pixels().for_each(|p| (0..3).for_each(|c| sum[c] += p.0[c] as f64 / n));
                    sum
                })
                .collect();
            let chroma = |c: &[f64; 3]| [c[0] - c[1], c[2] - c[1]];
            let (a, b) = (chroma(&colours[0]), chroma(&colours[2]));
            ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
        };
        let (alike, distinct) = (spread(true), spread(false));
        assert!(alike < distinct, "room colours differ by {alike} with aliasing, {distinct} without");
    }

    #[test]
    fn bad_configs_are_refused() {
        for bad in [
            Difficulty { lap_offset_m: 2.0, ..Difficulty::default() },
            Difficulty { night_exposure: 0.0, ..Difficulty::default() },
            Difficulty { noise: f64::NAN, ..Difficulty::default() },
            Difficulty { blur: -1.0, ..Difficulty::default() },
        ] {
            assert!(Scene::new(SynthConfig { difficulty: bad, ..small(1) }).is_err());
        }
        assert!(Scene::new(SynthConfig { frames: 0, ..small(1) }).is_err());
        assert!(Scene::new(SynthConfig { laps: 0, ..small(1) }).is_err());
        assert!(Scene::new(SynthConfig { width: 2, ..small(1) }).is_err());
        assert!(Scene::new(SynthConfig { rate_hz: f64::NAN, ..small(1) }).is_err());
        // Too many frames to hold, or stamps past what a timestamp holds.
        assert!(Scene::new(SynthConfig { frames: MAX_FRAMES + 1, ..small(1) }).is_err());
        assert!(Scene::new(SynthConfig { frames: 100, rate_hz: 1e-9, ..small(1) }).is_err());
        assert!(Scene::new(SynthConfig { frames: MAX_FRAMES, ..small(1) }).is_ok());
    }
}
