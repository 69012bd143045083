//! Where the weights come from, for every command, in this order:
//! 1. `--weights PATH` (safetensors, or a `.tflite` imported on the fly);
//! 2. `$ECM_LCD_WEIGHTS`;
//! 3. the per-user cache (`$ECM_LCD_CACHE`, else e.g. `~/.cache/ecm-lcd/`), holding the
//!    MobileNetV2 weights imported earlier;
//! 4. `mobilenet_v2_1.0_224_quant.tflite` in the shared data folder (`$ECM_LCD_SHARED`,
//!    `../shared`, or the `shared` folder beside the source tree), imported and cached;
//! 5. the same file downloaded from its public upstream (`$ECM_LCD_WEIGHTS_URL` overrides the
//!    address; `ECM_LCD_OFFLINE=1` forbids it), SHA-256 checked, cached, imported.
//!
//! If all fail, the error says what was tried and how to get the file. Never a random init.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use super::fetch::sha256_hex;
use super::Weights;

/// The public MobileNetV2 file (Coral test data, Apache-2.0) and its checksum.
pub const UPSTREAM_FILE: &str = "mobilenet_v2_1.0_224_quant.tflite";
pub const UPSTREAM_SHA256: &str = "7aad0c74c5e3c06e5eb3c827e13304fdd68a83da6087d92ee169c24ff9fd4776";
pub const UPSTREAM_URL: &str = "https://github.com/google-coral/test_data/raw/master/mobilenet_v2_1.0_224_quant.tflite";
/// Name of the imported weights in the cache.
pub const CACHED_WEIGHTS: &str = "mobilenet_v2_1.0_224.safetensors";

/// Weights together with where they came from.
#[derive(Clone, Debug)]
pub struct Resolved {
    pub weights: Weights,
    /// The file read (a safetensors or TFLite file).
    pub path: PathBuf,
    /// SHA-256 of the weights as a safetensors file, lower-case hex: of the file read, or for a
    /// TFLite file of its import as [`Weights::save`] would write it (what the cache holds), so that
    /// a database made with either is the same network's.
    pub sha256: String,
}

impl Resolved {
    /// One line for logs: file, hash, architecture.
    pub fn describe(&self) -> String {
        format!(
            "{} ({}, sha256 {}, {})",
            self.path.display(),
            self.weights.arch,
            &self.sha256[..16],
            self.weights.source
        )
    }
}

/// The per-user cache folder.
pub fn cache_dir() -> Option<PathBuf> {
    std::env::var_os("ECM_LCD_CACHE").map(PathBuf::from).or_else(|| dirs::cache_dir().map(|d| d.join("ecm-lcd")))
}

/// Reads a weights file: a TFLite model (named `.tflite`, or carrying TFLite's `TFL3` file
/// identifier) is imported, anything else is read as safetensors.
pub fn load_file(path: &Path) -> Result<Resolved> {
    let bytes = crate::io::read_capped(path, crate::io::limits::WEIGHTS_FILE, "weights file")?;
    let is_tflite =
        path.extension().is_some_and(|e| e.eq_ignore_ascii_case("tflite")) || bytes.get(4..8) == Some(b"TFL3");
    let (weights, sha256) = if is_tflite {
        let weights = super::import::import_tflite_file(path, &bytes)?;
        let sha256 = sha256_hex(&weights.to_bytes()?);
        (weights, sha256)
    } else {
        let weights = Weights::from_bytes(&bytes)
            .with_context(|| format!("{} is not a valid ecm-lcd weights file", path.display()))?;
        (weights, sha256_hex(&bytes))
    };
    Ok(Resolved { weights, path: path.to_path_buf(), sha256 })
}

/// Finds weights as described in the module documentation.
pub fn resolve(explicit: Option<&Path>) -> Result<Resolved> {
    if let Some(path) = explicit {
        return load_file(path);
    }
    if let Some(path) = std::env::var_os("ECM_LCD_WEIGHTS") {
        return load_file(Path::new(&path)).context("from $ECM_LCD_WEIGHTS");
    }
    let cache = cache_dir();
    let mut tried = Vec::new();
    if let Some(cached) = cache.as_ref().map(|d| d.join(CACHED_WEIGHTS)) {
        if cached.is_file() {
            match load_file(&cached) {
                Ok(r) => return Ok(r),
                Err(e) => log::warn!("ignoring cached weights: {e:#}"),
            }
        }
        tried.push(cached.display().to_string());
    }
    let mut tflites: Vec<PathBuf> =
        crate::runtime::shared_dirs().into_iter().map(|d| d.join("models").join(UPSTREAM_FILE)).collect();
    if let Some(dir) = &cache {
        tflites.push(dir.join(UPSTREAM_FILE));
    }
    for tflite in &tflites {
        if tflite.is_file() {
            return import_and_cache(tflite, cache.as_deref());
        }
        tried.push(tflite.display().to_string());
    }
    let offline = std::env::var("ECM_LCD_OFFLINE").is_ok_and(|v| v == "1");
    let url = std::env::var("ECM_LCD_WEIGHTS_URL").unwrap_or_else(|_| UPSTREAM_URL.to_string());
    let download_error = match (&cache, offline) {
        (Some(dir), false) => {
            let dest = dir.join(UPSTREAM_FILE);
            log::info!("downloading {url} (3.6 MB) to {}", dest.display());
            match super::fetch::fetch_verified(&url, UPSTREAM_SHA256, &dest) {
                Ok(()) => return import_and_cache(&dest, Some(dir)),
                Err(e) => format!("{e:#}"),
            }
        }
        (None, _) => "no cache folder to download into (set ECM_LCD_CACHE)".to_string(),
        (_, true) => "downloads are off (ECM_LCD_OFFLINE=1)".to_string(),
    };
    bail!(
        "no network weights found. Tried: {}; download: {download_error}. \
         Get the public file {UPSTREAM_FILE} (Coral test data, github.com/google-coral/test_data, \
         sha256 {UPSTREAM_SHA256}) and pass --weights FILE, set ECM_LCD_WEIGHTS=FILE, or put it in {}",
        tried.join(", "),
        cache.map(|d| d.display().to_string()).unwrap_or_else(|| "$ECM_LCD_CACHE".into())
    )
}

/// Imports a TFLite file and, where a cache folder exists, saves the result there.
fn import_and_cache(tflite: &Path, cache: Option<&Path>) -> Result<Resolved> {
    let resolved = load_file(tflite)?;
    if let Some(dir) = cache {
        let dest = dir.join(CACHED_WEIGHTS);
        match resolved.weights.save(&dest) {
            Ok(()) => {
                log::info!("imported {} into {}", tflite.display(), dest.display());
                return load_file(&dest);
            }
            Err(e) => log::warn!("could not cache imported weights: {e:#}"),
        }
    }
    Ok(resolved)
}
