//! A learned linear projection of descriptors: PCA to fewer dimensions, optionally whitened, learned
//! without labels from a set of descriptors (a folder of images, `synth` output, a keyframe history).
//!
//! `y = normalise(W (x - mean))`: `W`'s rows are the principal axes of the centred training
//! descriptors, largest variance first; whitened, each row is divided by the square root of its
//! variance plus a regulariser (a tenth of the mean variance), so that rare directions are not blown
//! up. The output is a unit vector, so scores mean what they mean for the unit-vector modes.
//!
//! The axes come from the eigenvectors of the samples' Gram matrix (`X Xᵀ`, samples x samples), which
//! is small when descriptors are longer than the training set is large. At most `samples - 1`
//! dimensions can be learned.
//!
//! Saved as safetensors: tensors `mean` `[in]` and `rows` `[out, in]` (f32), with one metadata entry
//! (`ecm_lcd_projection`, sorted JSON) naming the descriptor it applies to (`descriptor`, e.g.
//! `regional-3x3-mac@blocks.16`), `whitened`, and the network it was learned on (`network`: another
//! network's descriptors of that name are refused); files from before hold `descriptor` and
//! `whitened` as entries of their own. The file's SHA-256 is part of the keyframe database's
//! identity ([`Projection::identity`]).

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use crate::model::weights::fetch::sha256_hex;
use anyhow::{bail, ensure, Context, Result};

use super::l2_normalise;

/// Projections files are small (a 256 x 2880 projection is 3 MB); anything much larger is refused.
const MAX_FILE_BYTES: u64 = 256 << 20;

#[derive(Clone, Debug, PartialEq)]
pub struct Projection {
    /// Subtracted first, `in_dim()` values.
    pub mean: Vec<f32>,
    /// `out_dim()` rows of `in_dim()` values.
    pub rows: Vec<Vec<f32>>,
    pub whitened: bool,
    /// The descriptor (name, tap included) the projection was learned on and applies to.
    pub descriptor: String,
    /// The network whose descriptors it was learned on ([`network_name`]; `None` in files from
    /// before it was recorded): another network's descriptors of the same name are other values.
    pub network: Option<String>,
    /// SHA-256 of the saved file (hex), empty until saved or loaded.
    pub sha256: String,
}

/// The least share of the descriptors' total variance an axis must hold to be a direction they
/// vary along, not rounding noise ([`Projection::learn`]).
const SPANNED_SHARE: f64 = 1e-9;

impl Projection {
    /// Learns the projection of `samples` (descriptors of one kind, named `descriptor`) onto `dims`
    /// axes (module doc).
    pub fn learn(samples: &[Vec<f32>], dims: usize, whiten: bool, descriptor: &str) -> Result<Projection> {
        ensure!(samples.len() >= 2, "learning a projection needs at least 2 descriptors, got {}", samples.len());
        let n = samples[0].len();
        ensure!(samples.iter().all(|s| s.len() == n), "the descriptors to learn from differ in length");
        ensure!(
            dims >= 1 && dims < samples.len() && dims <= n,
            "{dims} dimensions cannot be learned from {} descriptors of {n} values (at most {})",
            samples.len(),
            (samples.len() - 1).min(n)
        );
        ensure!(samples.iter().flatten().all(|v| v.is_finite()), "the descriptors to learn from are not all finite");
        let count = samples.len();
        let mut mean = vec![0f64; n];
        for s in samples {
            mean.iter_mut().zip(s).for_each(|(m, &x)| *m += x as f64 / count as f64);
        }
        let centred: Vec<Vec<f64>> =
            samples.iter().map(|s| s.iter().zip(&mean).map(|(&x, m)| x as f64 - m).collect()).collect();
        let gram = nalgebra::DMatrix::from_fn(count, count, |i, j| {
            centred[i].iter().zip(&centred[j]).map(|(a, b)| a * b).sum::<f64>()
        });
        let eigen = nalgebra::SymmetricEigen::new(gram);
        let mut order: Vec<usize> = (0..count).collect();
        order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
        // Variance along axis k is lambda_k / count; the regulariser is a tenth of the mean variance.
        let total: f64 = eigen.eigenvalues.iter().map(|e| e.max(0.0)).sum();
        // An axis that holds next to none of the variance is rounding noise (the images repeat, or
        // are too few): its direction is arbitrary, and whitening would blow it up.
        let spanned = order.iter().filter(|&&k| eigen.eigenvalues[k] > SPANNED_SHARE * total).count();
        ensure!(
            dims <= spanned,
            "the {count} descriptors vary along only {spanned} directions, fewer than the {dims} dimensions asked for \
             (images that repeat, or too few): learn from more varied images, or ask for at most {spanned}"
        );
        let regulariser = 0.1 * total / count as f64 / count as f64;
        let rows = order
            .iter()
            .take(dims)
            .map(|&k| {
                // The axis is Xᵀ u (u the Gram eigenvector), normalised.
                let mut axis = vec![0f64; n];
                for (row, x) in centred.iter().enumerate() {
                    let u = eigen.eigenvectors[(row, k)];
                    axis.iter_mut().zip(x).for_each(|(a, x)| *a += u * x);
                }
                let norm = axis.iter().map(|a| a * a).sum::<f64>().sqrt().max(1e-300);
                let variance = eigen.eigenvalues[k].max(0.0) / count as f64;
                let scale = if whiten { 1.0 / (norm * (variance + regulariser).sqrt()) } else { 1.0 / norm };
                axis.iter().map(|a| (a * scale) as f32).collect()
            })
            .collect();
        Ok(Projection {
            mean: mean.into_iter().map(|m| m as f32).collect(),
            rows,
            whitened: whiten,
            descriptor: descriptor.to_string(),
            network: None,
            sha256: String::new(),
        })
    }

    pub fn in_dim(&self) -> usize {
        self.mean.len()
    }

    pub fn out_dim(&self) -> usize {
        self.rows.len()
    }

    /// The projected, unit-length descriptor of `v` (`in_dim()` values).
    pub fn apply(&self, v: &[f32]) -> Vec<f32> {
        let centred: Vec<f32> = v.iter().zip(&self.mean).map(|(x, m)| x - m).collect();
        let mut out: Vec<f32> =
            self.rows.iter().map(|row| row.iter().zip(&centred).map(|(a, b)| a * b).sum()).collect();
        l2_normalise(&mut out);
        out
    }

    /// What the projection adds to the descriptor's name in the keyframe database's identity, e.g.
    /// `+pca256w:1a2b3c4d5e6f` (`w` when whitened; 12 hex digits of the file's SHA-256).
    pub fn identity(&self) -> String {
        let hash: String = self.sha256.chars().take(12).collect();
        format!("+pca{}{}:{hash}", self.out_dim(), if self.whitened { "w" } else { "" })
    }

    /// Writes the projection to `path` (safetensors, module doc) and records the file's hash.
    pub fn save(&mut self, path: &Path) -> Result<()> {
        let flat: Vec<f32> = self.rows.iter().flatten().copied().collect();
        let tensors = [
            (
                "mean",
                safetensors::tensor::TensorView::new(
                    safetensors::Dtype::F32,
                    vec![self.in_dim()],
                    bytemuck::cast_slice(&self.mean),
                )?,
            ),
            (
                "rows",
                safetensors::tensor::TensorView::new(
                    safetensors::Dtype::F32,
                    vec![self.out_dim(), self.in_dim()],
                    bytemuck::cast_slice(&flat),
                )?,
            ),
        ];
        // One entry holding the fields as sorted JSON: safetensors writes its metadata map in hash
        // order, which differs from run to run, and the file's SHA-256 is part of a keyframe
        // database's identity, so the same projection must always give the same bytes.
        let mut fields =
            BTreeMap::from([("descriptor", self.descriptor.clone()), ("whitened", self.whitened.to_string())]);
        if let Some(network) = &self.network {
            fields.insert("network", network.clone());
        }
        let metadata = HashMap::from([(METADATA_KEY.to_string(), serde_json::to_string(&fields)?)]);
        let bytes = safetensors::serialize(tensors, Some(metadata)).context("serialising the projection")?;
        crate::io::output::write_replacing(path, &bytes)?;
        self.sha256 = sha256_hex(&bytes);
        Ok(())
    }

    /// Reads a projection written by [`Projection::save`].
    pub fn load(path: &Path) -> Result<Projection> {
        let bytes = crate::io::read_capped(path, MAX_FILE_BYTES, "projection")?;
        let context = || format!("{} is not a descriptor projection (safetensors with mean and rows)", path.display());
        let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).with_context(context)?;
        let tensors = safetensors::SafeTensors::deserialize(&bytes).with_context(context)?;
        let mut metadata = header.metadata().clone().unwrap_or_default();
        // Files from before the fields were one JSON entry hold them as entries of their own.
        if let Some(fields) = metadata.get(METADATA_KEY) {
            let fields: HashMap<String, String> = serde_json::from_str(fields)
                .with_context(|| format!("{}: its `{METADATA_KEY}` metadata is not JSON", path.display()))?;
            metadata.extend(fields);
        }
        let network = metadata.get("network").cloned();
        let Some(descriptor) = metadata.get("descriptor").cloned() else {
            bail!("{}: no `descriptor` in its metadata", path.display())
        };
        let whitened = metadata.get("whitened").is_some_and(|w| w == "true");
        let floats = |name: &str| -> Result<(Vec<f32>, Vec<usize>)> {
            let t = tensors.tensor(name).with_context(context)?;
            ensure!(t.dtype() == safetensors::Dtype::F32, "{}: `{name}` is not f32", path.display());
            let values: Vec<f32> =
                t.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
            ensure!(values.iter().all(|v| v.is_finite()), "{}: `{name}` holds non-finite values", path.display());
            Ok((values, t.shape().to_vec()))
        };
        let (mean, mean_shape) = floats("mean")?;
        let (flat, rows_shape) = floats("rows")?;
        ensure!(
            mean_shape.len() == 1 && rows_shape.len() == 2 && rows_shape[1] == mean_shape[0] && rows_shape[0] >= 1,
            "{}: shapes mean {mean_shape:?} and rows {rows_shape:?} do not fit together",
            path.display()
        );
        let rows = flat.chunks_exact(rows_shape[1]).map(<[f32]>::to_vec).collect();
        Ok(Projection { mean, rows, whitened, descriptor, network, sha256: sha256_hex(&bytes) })
    }
}

/// The metadata entry of a projection file.
const METADATA_KEY: &str = "ecm_lcd_projection";

/// What tells networks apart for a projection: the architecture, the weights' SHA-256 and the input
/// size, which all change the descriptors' values.
pub fn network_name(arch: &str, weights_sha256: &str, input_size: usize) -> String {
    format!("{arch}, weights sha256 {weights_sha256}, input {input_size}")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Samples spread mostly along two known directions of a 6-d space, plus a little noise.
    fn samples() -> Vec<Vec<f32>> {
        let mut state = 3u64;
        let mut uniform = move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) as f32
        };
        (0..40)
            .map(|_| {
                let (a, b) = (uniform() * 10.0, uniform() * 3.0);
                let mut v = vec![1.0 + a, 1.0 - a, b, b, 0.0, 0.5];
                v.iter_mut().for_each(|x| *x += uniform() * 0.01);
                v
            })
            .collect()
    }

    #[test]
    fn more_dimensions_than_the_descriptors_vary_along_are_refused() {
        // Six descriptors of two images, three copies each: one direction of variation.
        let repeated: Vec<Vec<f32>> =
            (0..6).map(|i| if i % 2 == 0 { vec![1.0, 0.5, 0.25] } else { vec![0.0, 0.5, 1.0] }).collect();
        let err = Projection::learn(&repeated, 2, true, "test").unwrap_err().to_string();
        assert!(err.contains("only 1 directions") && err.contains("at most 1"), "{err}");
        assert_eq!(Projection::learn(&repeated, 1, true, "test").unwrap().out_dim(), 1);
    }

    #[test]
    fn principal_axes_match_a_plain_covariance_eigendecomposition() {
        let samples = samples();
        let projection = Projection::learn(&samples, 2, false, "test").unwrap();
        // Reference: the 6x6 covariance matrix's eigenvectors, computed directly in f64.
        let n = samples.len() as f64;
        let mean: Vec<f64> = (0..6).map(|j| samples.iter().map(|s| s[j] as f64).sum::<f64>() / n).collect();
        let covariance = nalgebra::DMatrix::from_fn(6, 6, |i, j| {
            samples.iter().map(|s| (s[i] as f64 - mean[i]) * (s[j] as f64 - mean[j])).sum::<f64>() / n
        });
        let eigen = nalgebra::SymmetricEigen::new(covariance);
        let mut order: Vec<usize> = (0..6).collect();
        order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
        for (row, &k) in projection.rows.iter().zip(&order) {
            let reference = eigen.eigenvectors.column(k);
            let dot: f64 = row.iter().zip(reference.iter()).map(|(&a, &b)| a as f64 * b).sum();
            assert!((dot.abs() - 1.0).abs() < 1e-4, "axis differs from the reference: |dot| = {}", dot.abs());
        }
        for (m, r) in projection.mean.iter().zip(&mean) {
            assert!((*m as f64 - r).abs() < 1e-6);
        }
        // A projected descriptor is a unit vector: the centred input's coordinates on the axes.
        let v = &samples[5];
        let y = projection.apply(v);
        let coordinates: Vec<f64> = order
            .iter()
            .take(2)
            .map(|&k| (0..6).map(|j| (v[j] as f64 - mean[j]) * eigen.eigenvectors[(j, k)]).sum::<f64>())
            .collect();
        let norm = coordinates.iter().map(|c| c * c).sum::<f64>().sqrt();
        for (a, c) in y.iter().zip(&coordinates) {
            assert!((a.abs() as f64 - (c / norm).abs()).abs() < 1e-4, "{y:?} vs {coordinates:?}");
        }
    }

    #[test]
    fn whitened_training_coordinates_have_equal_variance_and_the_file_round_trips() {
        let samples = samples();
        let mut projection = Projection::learn(&samples, 2, true, "regional-3x3-mac@blocks.16").unwrap();
        // Before normalisation the whitened coordinates have variance about 1 / (1 + regulariser).
        let variance = |k: usize| {
            let values: Vec<f64> = samples
                .iter()
                .map(|s| {
                    projection.rows[k]
                        .iter()
                        .zip(s.iter().zip(&projection.mean))
                        .map(|(r, (x, m))| (r * (x - m)) as f64)
                        .sum()
                })
                .collect();
            values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64
        };
        let (v0, v1) = (variance(0), variance(1));
        assert!(v0 > 0.5 && v0 < 1.0 && v1 > 0.5 && v1 < 1.0, "whitened variances {v0}, {v1}");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.safetensors");
        projection.network = Some(network_name("mobilenetv2", "ab", 224));
        projection.save(&path).unwrap();
        let loaded = Projection::load(&path).unwrap();
        assert_eq!(loaded, projection);
        // The same projection always gives the same bytes (its hash is part of a database's identity).
        let bytes = std::fs::read(&path).unwrap();
        for _ in 0..8 {
            projection.save(&path).unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), bytes);
        }
        assert!(loaded.identity().starts_with("+pca2w:") && loaded.identity().len() == "+pca2w:".len() + 12);
        std::fs::write(&path, b"not a projection").unwrap();
        assert!(format!("{:#}", Projection::load(&path).unwrap_err()).contains("p.safetensors"));
        assert!(Projection::learn(&samples[..2], 2, false, "x").is_err(), "2 samples fix only 1 axis");
    }
}
