//! Model sub-commands: `import-weights`, `model-info`, `classify`, `embed`.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use serde::Serialize;

use ecm_lcd::model::embedder::Embedder;
use ecm_lcd::model::weights::{import, resolve};
use ecm_lcd::model::Arch;
use ecm_lcd::preprocess::read_image;

/// Which weights and network every model-using command runs.
#[derive(clap::Args, Debug, Clone)]
pub struct NetworkArgs {
    /// Weights file (safetensors, or a .tflite to import); default: see README "Weights".
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// Network architecture: ecmobilenet or mobilenetv2 (default: that of ECMobileNet weights, which
    /// serve no other; otherwise mobilenetv2, the detector's default network, whose ImageNet
    /// classifier the weights are).
    #[arg(long)]
    pub arch: Option<Arch>,
    /// Input size (a multiple of 32; default: the size a training run beside the weights trained at,
    /// else 224).
    #[arg(long)]
    pub size: Option<usize>,
    /// Run stock candle operations instead of the fast kernels (for verification).
    #[arg(long)]
    pub reference: bool,
}

impl NetworkArgs {
    /// Resolves the weights, logs which ones run, and builds the embedder (`default_arch` unless
    /// `--arch` or ECMobileNet weights say otherwise).
    pub fn embedder(&self, default_arch: Arch, with_classifier: bool) -> Result<(Embedder, resolve::Resolved)> {
        // A network trained at another size answers wrongly at 224 without a word.
        let trained_at = self.weights.as_deref().and_then(ecm_lcd::train::input_size_of);
        let size = self.size.or(trained_at).unwrap_or(224);
        let (mut embedder, resolved) =
            Embedder::from_weights(self.weights.as_deref(), self.arch, default_arch, size, with_classifier)?;
        embedder.set_reference(self.reference);
        Ok((embedder, resolved))
    }
}

#[derive(clap::Args, Debug)]
pub struct ImportArgs {
    /// The TFLite model (MobileNetV2 1.0, e.g. mobilenet_v2_1.0_224_quant.tflite).
    pub tflite: PathBuf,
    /// Output safetensors file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Architecture to write: mobilenetv2 as imported, or ecmobilenet initialised from it.
    #[arg(long, default_value = "mobilenetv2")]
    pub arch: Arch,
}

pub fn import_weights(args: ImportArgs) -> Result<()> {
    ecm_lcd::io::output::ensure_not_an_input(&args.output, &[&args.tflite])?;
    let weights = import::import_tflite(&args.tflite)?.for_arch(args.arch)?;
    weights.save(&args.output)?;
    println!(
        "wrote {} ({}, {} tensors) from {}",
        args.output.display(),
        weights.arch,
        weights.tensors.len(),
        args.tflite.display()
    );
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct InfoArgs {
    #[arg(long, default_value = "ecmobilenet")]
    pub arch: Arch,
    /// Classifier outputs, 1 to 1,000,000 (none: feature extractor only).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    pub classes: Option<u32>,
    #[arg(long, default_value_t = 224)]
    pub size: usize,
    #[arg(long)]
    pub json: bool,
}

pub fn model_info(args: InfoArgs) -> Result<()> {
    ecm_lcd::model::check_input_size(args.size)?;
    let cost = args.arch.spec().cost(args.classes.map(|k| k as usize), args.size);
    if args.json {
        println!("{}", serde_json::to_string(&cost)?);
    } else {
        let classes = args.classes.map(|k| k.to_string()).unwrap_or_else(|| "none".into());
        println!("arch      {}\nclasses   {classes}\ninput     {}x{}", args.arch, args.size, args.size);
        println!("params    {}\nmacs      {}", cost.params, cost.macs);
        println!("blocks    {}", args.arch.spec().blocks().len());
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct ClassifyArgs {
    #[command(flatten)]
    pub network: NetworkArgs,
    /// Labels file, one per line, index 0 first (default: the shared ImageNet labels).
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Number of classes to show.
    #[arg(long, default_value_t = 5)]
    pub top: usize,
    #[arg(long)]
    pub json: bool,
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
}

#[derive(Serialize)]
struct Ranked {
    index: usize,
    label: String,
    prob: f32,
}

#[derive(Serialize)]
struct Classified {
    image: String,
    top: Vec<Ranked>,
}

fn read_labels(path: Option<&Path>) -> Result<Vec<String>> {
    let path = match path {
        Some(p) => p.to_path_buf(),
        None => match ecm_lcd::runtime::shared_dirs()
            .into_iter()
            .map(|d| d.join("data/imagenet/imagenet_labels.txt"))
            .find(|p| p.is_file())
        {
            Some(p) => p,
            None => {
                log::warn!("no ImageNet labels file found (pass --labels); showing class indexes");
                return Ok(vec![]);
            }
        },
    };
    let text = ecm_lcd::io::read_capped_text(&path, ecm_lcd::io::limits::TEXT_LIST, "labels")?;
    Ok(text.lines().map(str::to_string).collect())
}

pub fn classify(args: ClassifyArgs) -> Result<()> {
    let (mut embedder, resolved) = args.network.embedder(Arch::MobileNetV2, true)?;
    let classes = embedder.network.classes().unwrap_or(0);
    // A trained checkpoint's class names are in its run record; the shared ImageNet labels only
    // name an ImageNet classifier's 1001 outputs.
    let labels = match &args.labels {
        Some(path) => {
            let labels = read_labels(Some(path))?;
            if labels.len() != classes {
                bail!(
                    "--labels {} names {} classes, the network has {classes} (one label a line, index 0 first)",
                    path.display(),
                    labels.len()
                );
            }
            labels
        }
        None => match ecm_lcd::train::class_names_of(&resolved.path, classes) {
            Some(names) => names,
            None if classes == 1001 => read_labels(None)?,
            None => vec![],
        },
    };
    let mut results = Vec::new();
    for path in &args.images {
        let probs = embedder.probabilities(&read_image(path)?)?;
        let mut order: Vec<usize> = (0..probs.len()).collect();
        order.sort_by(|&a, &b| probs[b].total_cmp(&probs[a]));
        let top = order
            .into_iter()
            .take(args.top)
            .map(|i| Ranked {
                index: i,
                label: labels.get(i).cloned().unwrap_or_else(|| format!("class {i}")),
                prob: probs[i],
            })
            .collect();
        results.push(Classified { image: path.display().to_string(), top });
    }
    let mut out = std::io::stdout().lock();
    if args.json {
        writeln!(out, "{}", serde_json::to_string_pretty(&results)?)?;
    } else {
        for r in &results {
            writeln!(out, "{}", r.image)?;
            for t in &r.top {
                writeln!(out, "  {:>6.3}  {:>4}  {}", t.prob, t.index, t.label)?;
            }
        }
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct EmbedArgs {
    #[command(flatten)]
    pub network: NetworkArgs,
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
    /// Output CSV: `image,v0,...,v1279` (the globally pooled 1280-d descriptor per image).
    #[arg(short, long)]
    pub output: PathBuf,
}

pub fn embed(args: EmbedArgs) -> Result<()> {
    let mut inputs: Vec<&std::path::Path> = args.images.iter().map(PathBuf::as_path).collect();
    inputs.extend(args.network.weights.as_deref());
    ecm_lcd::io::output::ensure_not_an_input(&args.output, &inputs)?;
    ecm_lcd::io::output::ensure_writable_outputs(&[("-o", &args.output)])?;
    let (mut embedder, resolved) = args.network.embedder(Arch::MobileNetV2, false)?;
    // The weights may come from $ECM_LCD_WEIGHTS or the cache rather than --weights.
    ecm_lcd::io::output::ensure_not_an_input(&args.output, &[&resolved.path])?;
    // Every image is read before the output is opened, so a bad image leaves an existing file as it was.
    let mut records = Vec::with_capacity(args.images.len());
    for path in &args.images {
        let pooled = embedder.feature_map(&read_image(path)?)?.global_average();
        let mut record = vec![path.display().to_string()];
        record.extend(pooled.iter().map(|v| v.to_string()));
        records.push(record);
    }
    let values = records.first().map_or(0, |record| record.len() - 1);
    let header: Vec<String> =
        std::iter::once("image".to_string()).chain((0..values).map(|i| format!("v{i}"))).collect();
    ecm_lcd::io::output::replace_with(&args.output, |file| {
        let mut writer = csv::Writer::from_writer(file);
        writer.write_record(&header)?;
        for record in &records {
            writer.write_record(record)?;
        }
        Ok(writer.flush()?)
    })?;
    println!("wrote {} descriptors of {values} values to {}", args.images.len(), args.output.display());
    Ok(())
}
