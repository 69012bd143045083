//! `ecm-lcd synth`: renders a synthetic looping indoor sequence into a TUM RGB-D folder.

use anyhow::{bail, Result};
use ecm_lcd::io::image_msg::written_topics;
use ecm_lcd::io::image_msg::WireEncoding;
use ecm_lcd::io::ros1bag::{write_ros1_bag_calibrated, Ros1Compression};
use ecm_lcd::io::ros2bag::{write_ros2_bag_calibrated, Ros2Storage};
use ecm_lcd::synth::{write_tum_folder, Scene, SynthConfig};
use ecm_lcd::verification::Intrinsics;
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Output folder (created; must not already hold an rgb.txt).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Number of frames.
    #[arg(long, default_value_t = SynthConfig::default().frames)]
    pub frames: usize,
    /// Number of laps of the closed path, spread over the frames.
    #[arg(long, default_value_t = SynthConfig::default().laps)]
    pub laps: usize,
    /// Seed of textures, furniture, posters, per-lap perturbation and lighting.
    #[arg(long, default_value_t = SynthConfig::default().seed)]
    pub seed: u64,
    /// Image width (default 320, or 160 with `--preset hard`).
    #[arg(long)]
    pub width: Option<u32>,
    /// Image height (default 240, or 120 with `--preset hard`).
    #[arg(long)]
    pub height: Option<u32>,
    /// `easy` (no difficulty) or `hard`: identical rooms, a night lap every second lap, laps 0.35 m
    /// and 12 degrees apart, grayscale, noise and blur, at 160x120. The options below override it.
    #[arg(long, value_enum, default_value_t = Preset::Easy)]
    pub preset: Preset,
    /// Decorate every room alike (perceptual aliasing).
    #[arg(long)]
    pub aliasing: Option<bool>,
    /// Sideways offset in metres of every lap after the first, alternating in sign.
    #[arg(long)]
    pub lap_offset: Option<f64>,
    /// Extra heading in degrees of every lap after the first, alternating in sign.
    #[arg(long)]
    pub lap_yaw: Option<f64>,
    /// Exposure factor of every second lap (1 = unchanged, 0.3 = night).
    #[arg(long)]
    pub night_exposure: Option<f64>,
    /// Grayscale images.
    #[arg(long)]
    pub grayscale: Option<bool>,
    /// Gaussian sensor noise, standard deviation in grey levels.
    #[arg(long)]
    pub noise: Option<f64>,
    /// Gaussian blur, standard deviation in pixels.
    #[arg(long)]
    pub blur: Option<f64>,
    /// Also write depth images (`depth/`, `depth.txt`; 16-bit PNG, 5000 per metre, as TUM RGB-D).
    #[arg(long)]
    pub depth: bool,
    /// Frame rate of the stamps (frames per second).
    #[arg(long, default_value_t = SynthConfig::default().rate_hz)]
    pub rate: f64,
    /// Also write the frames as a ROS 1 bag (lz4 chunks) to this file, with the camera's
    /// `sensor_msgs/CameraInfo` beside each frame on `/camera/rgb/camera_info`.
    #[arg(long)]
    pub ros1_bag: Option<PathBuf>,
    /// Also write the frames as a ROS 2 bag into this (new) folder, with the camera's `CameraInfo`
    /// as in the ROS 1 bag.
    #[arg(long)]
    pub ros2_bag: Option<PathBuf>,
    /// Storage of the ROS 2 bag.
    #[arg(long, value_enum, default_value_t = Ros2StorageArg::Mcap)]
    pub ros2_storage: Ros2StorageArg,
    /// Image messages in the bags: raw rgb8 `sensor_msgs/Image`, or JPEG `CompressedImage`.
    #[arg(long, value_enum, default_value_t = BagImages::Jpeg)]
    pub bag_images: BagImages,
    /// JPEG quality for `--bag-images jpeg`.
    #[arg(long, default_value_t = 85, value_parser = clap::value_parser!(u8).range(1..=100))]
    pub jpeg_quality: u8,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Preset {
    Easy,
    Hard,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum Ros2StorageArg {
    Sqlite3,
    Mcap,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum BagImages {
    Rgb8,
    Jpeg,
}

/// The TUM RGB-D bags' camera topic (raw) and its compressed variant.
const RAW_TOPIC: &str = "/camera/rgb/image_color";
const COMPRESSED_TOPIC: &str = "/camera/rgb/image_color/compressed";

pub fn run(args: Args) -> Result<()> {
    if args.output.join("rgb.txt").exists() {
        bail!("{} already holds a sequence (rgb.txt); choose an empty folder", args.output.display());
    }
    // Before anything is written: a bag is always new, in a folder that exists (or is the output
    // folder, which synth makes), and no two outputs are one path.
    for (flag, bag) in [("--ros1-bag", &args.ros1_bag), ("--ros2-bag", &args.ros2_bag)] {
        let Some(bag) = bag else { continue };
        if bag.exists() {
            bail!("{flag} {} already exists; synth writes a new bag (choose another path)", bag.display());
        }
        let absolute = |path: &std::path::Path| std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
        let output = absolute(&args.output);
        if absolute(bag) == output {
            bail!("{flag} {} is the output folder -o; choose another path", bag.display());
        }
        let folder = bag.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
        let in_output = absolute(folder) == output;
        // Inside the output folder, not one of the sequence's own files.
        let name = bag.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        const SEQUENCE: [&str; 7] =
            ["rgb.txt", "depth.txt", "groundtruth.txt", "odometry.txt", "camera.yaml", "rgb", "depth"];
        if in_output && SEQUENCE.contains(&name) {
            bail!("{flag} {} is a file of the sequence synth writes in -o; choose another name", bag.display());
        }
        if !folder.is_dir() && !in_output {
            bail!("{flag} {}: the folder {} does not exist", bag.display(), folder.display());
        }
    }
    if let (Some(ros1), Some(ros2)) = (&args.ros1_bag, &args.ros2_bag) {
        if std::path::absolute(ros1).ok() == std::path::absolute(ros2).ok() {
            bail!("--ros1-bag and --ros2-bag are both {}; choose two paths", ros1.display());
        }
    }
    let base = match args.preset {
        Preset::Easy => SynthConfig::default(),
        Preset::Hard => SynthConfig::hard(),
    };
    let mut difficulty = base.difficulty.clone();
    difficulty.aliasing = args.aliasing.unwrap_or(difficulty.aliasing);
    difficulty.lap_offset_m = args.lap_offset.unwrap_or(difficulty.lap_offset_m);
    difficulty.lap_yaw_deg = args.lap_yaw.unwrap_or(difficulty.lap_yaw_deg);
    difficulty.night_exposure = args.night_exposure.unwrap_or(difficulty.night_exposure);
    difficulty.grayscale = args.grayscale.unwrap_or(difficulty.grayscale);
    difficulty.noise = args.noise.unwrap_or(difficulty.noise);
    difficulty.blur = args.blur.unwrap_or(difficulty.blur);
    let config = SynthConfig {
        frames: args.frames,
        laps: args.laps,
        seed: args.seed,
        width: args.width.unwrap_or(base.width),
        height: args.height.unwrap_or(base.height),
        rate_hz: args.rate,
        difficulty,
        depth: args.depth,
        ..base
    };
    let scene = Scene::new(config)?;
    let started = Instant::now();
    write_tum_folder(&scene, &args.output)?;
    let seconds = started.elapsed().as_secs_f64();
    log::info!(
        "wrote {} frames ({} laps of {:.1} m) to {} in {:.1} s ({:.1} ms/frame including PNG encoding)",
        scene.len(),
        args.laps,
        scene.lap_length(),
        args.output.display(),
        seconds,
        seconds * 1e3 / scene.len() as f64
    );
    // The renderer's pinhole camera, which verification needs and the folder cannot name: as a
    // params file beside the frames, for `--config`.
    // The renderer casts its rays through pixel centres at x + 0.5 about the image's centre: the
    // principal point, in pixel-centre coordinates, is (W - 1) / 2, (H - 1) / 2.
    let (width, height) = (scene.config().width as f64, scene.config().height as f64);
    let (focal, cx, cy) = (scene.focal_length(), (width - 1.0) / 2.0, (height - 1.0) / 2.0);
    let camera = args.output.join("camera.yaml");
    let yaml = format!(
        "# The camera `ecm-lcd synth` rendered these frames with: `--config {}` turns verification on.\n\
         ecm_lcd:\n  ros__parameters:\n    camera.fx: {focal}\n    camera.fy: {focal}\n    camera.cx: {cx}\n    camera.cy: {cy}\n",
        camera.display()
    );
    ecm_lcd::io::output::write_replacing(&camera, yaml.as_bytes())?;
    log::info!(
        "camera fx = fy = {focal}, cx = {cx}, cy = {cy} in {}: give \
         --config {} for verified loops",
        camera.display(),
        camera.display()
    );
    let (encoding, topic) = match args.bag_images {
        BagImages::Rgb8 => (WireEncoding::Rgb8, RAW_TOPIC),
        BagImages::Jpeg => (WireEncoding::Jpeg { quality: args.jpeg_quality }, COMPRESSED_TOPIC),
    };
    let frames = || (0..scene.len()).map(|i| (scene.stamp(i), scene.render(i)));
    // The bags carry the camera too, as a driver's `camera_info` beside the images.
    let intrinsics =
        Intrinsics { fx: focal, fy: focal, cx, cy, size: Some([scene.config().width, scene.config().height]) };
    let info_topic = &written_topics(topic, encoding, Some(&intrinsics))[1].0;
    if let Some(path) = &args.ros1_bag {
        let n = write_ros1_bag_calibrated(path, topic, frames(), encoding, Ros1Compression::Lz4, Some(&intrinsics))?;
        log::info!("wrote {n} messages on {topic} and {info_topic} to the ROS 1 bag {}", path.display());
    }
    if let Some(dir) = &args.ros2_bag {
        let storage = match args.ros2_storage {
            Ros2StorageArg::Sqlite3 => Ros2Storage::Sqlite3,
            Ros2StorageArg::Mcap => Ros2Storage::Mcap,
        };
        let n = write_ros2_bag_calibrated(dir, storage, topic, frames(), encoding, Some(&intrinsics))?;
        log::info!("wrote {n} messages on {topic} and {info_topic} to the ROS 2 bag {}", dir.display());
    }
    Ok(())
}
