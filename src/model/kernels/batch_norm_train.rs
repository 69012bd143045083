//! Training-mode BatchNorm as one candle custom op with a hand-written backward, replacing
//! candle-nn's composition of a dozen generic ops (a transposed copy, means, broadcasts, and their
//! backward passes), which took most of a training step on the CPU.
//!
//! It computes exactly what `candle_nn::BatchNorm::forward_train` does, on `[B, C, ...]`:
//! per channel, over the batch and spatial positions (`M` values), the mean and the biased
//! variance normalise the input, `y = gamma (x - mean) / sqrt(var + eps) + beta`; the running
//! statistics move by `momentum` towards the batch mean and the *unbiased* variance
//! (`var * M / (M - 1)`), candle's convention, which [`crate::train`]'s precise BN relies on.
//!
//! Backward (with `x̂ = (x - mean) / sqrt(var + eps)`): `dbeta = Σ dy`, `dgamma = Σ dy x̂`,
//! `dx = gamma / sqrt(var + eps) (dy - dbeta / M - x̂ dgamma / M)`. Statistics are recomputed
//! rather than cached, so the ops stay stateless: in the forward pass once for the running
//! statistics and once for `y`, in the backward pass once with both gradient sums. Each plane is
//! summed in `f32` lanes, the planes in `f64`.
//! Tests compare values and gradients with candle-nn's BatchNorm.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, InplaceOp2, Layout, Result, Shape, Tensor};
use candle_nn::BatchNorm;
use rayon::prelude::*;

fn contiguous<'a>(storage: &'a CpuStorage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    super::contiguous_f32(storage, layout, "batch norm (training)", what)
}

/// `[B, C, rest...]` as (batch, channels, plane size).
fn split_shape(shape: &Shape) -> Result<(usize, usize, usize)> {
    let dims = shape.dims();
    if dims.len() < 2 {
        candle_core::bail!("batch norm input must be [B, C, ...], got {shape:?}");
    }
    Ok((dims[0], dims[1], dims[2..].iter().product()))
}

/// Per channel: mean and biased variance of `x`, and (when `dy` is given) `Σ dy` and `Σ dy x̂`.
struct ChannelStats {
    mean: f64,
    var: f64,
    sum_dy: f64,
    sum_dy_xhat: f64,
}

/// Independent partial sums: the compiler keeps them in vector registers, where one running
/// `f64` sum is a chain of dependent scalar additions.
const LANES: usize = 16;

/// `Σ f(i)` over `0..len` in [`LANES`] independent `f32` sums, totalled in `f64`.
#[inline(always)]
fn lane_sum(len: usize, f: impl Fn(usize) -> f32) -> f64 {
    let mut lanes = [0f32; LANES];
    let whole = len / LANES * LANES;
    for start in (0..whole).step_by(LANES) {
        for (l, lane) in lanes.iter_mut().enumerate() {
            *lane += f(start + l);
        }
    }
    lanes.iter().map(|&v| v as f64).sum::<f64>() + (whole..len).map(|i| f(i) as f64).sum::<f64>()
}

/// Per channel, the sum over the batch of `per_plane(channel, plane)` for each `[B, C]` plane.
/// The planes are visited in memory order, many to a task: the deep layers' planes hold only a
/// few values each, and visiting them channel by channel strode across the whole batch.
fn channel_sums(
    (batch, channels, plane): (usize, usize, usize),
    per_plane: impl Fn(usize, usize) -> f64 + Sync,
) -> Vec<f64> {
    let per_task = (4096 / plane.max(1)).max(1);
    let sums: Vec<f64> =
        (0..batch * channels).into_par_iter().with_min_len(per_task).map(|p| per_plane(p % channels, p)).collect();
    let mut totals = vec![0f64; channels];
    for row in sums.chunks(channels) {
        for (t, s) in totals.iter_mut().zip(row) {
            *t += s;
        }
    }
    totals
}

fn channel_stats(
    x: &[f32],
    dy: Option<&[f32]>,
    dims @ (batch, channels, plane): (usize, usize, usize),
    eps: f64,
) -> Vec<ChannelStats> {
    let m = (batch * plane) as f64;
    let values = |p: usize| &x[p * plane..(p + 1) * plane];
    let mean: Vec<f64> = channel_sums(dims, |_, p| {
        let x = values(p);
        lane_sum(x.len(), |i| x[i])
    })
    .into_iter()
    .map(|s| s / m)
    .collect();
    let var: Vec<f64> = channel_sums(dims, |c, p| {
        let (x, mean) = (values(p), mean[c] as f32);
        lane_sum(x.len(), |i| (x[i] - mean) * (x[i] - mean))
    })
    .into_iter()
    .map(|s| s / m)
    .collect();
    let (sum_dy, sum_dy_centred) = match dy {
        Some(dy) => {
            let gradients = |p: usize| &dy[p * plane..(p + 1) * plane];
            let sum_dy = channel_sums(dims, |_, p| {
                let g = gradients(p);
                lane_sum(g.len(), |i| g[i])
            });
            let centred = channel_sums(dims, |c, p| {
                let (g, x, mean) = (gradients(p), values(p), mean[c] as f32);
                lane_sum(g.len(), |i| g[i] * (x[i] - mean))
            });
            (sum_dy, centred)
        }
        None => (vec![0.0; channels], vec![0.0; channels]),
    };
    (0..channels)
        .map(|c| ChannelStats {
            mean: mean[c],
            var: var[c],
            sum_dy: sum_dy[c],
            sum_dy_xhat: sum_dy_centred[c] / (var[c] + eps).sqrt(),
        })
        .collect()
}

/// `(x, gamma, beta) -> y`.
struct BatchNormTrain {
    eps: f64,
}

impl CustomOp3 for BatchNormTrain {
    fn name(&self) -> &'static str {
        "batch-norm-train"
    }

    fn cpu_fwd(
        &self,
        s_x: &CpuStorage,
        l_x: &Layout,
        s_g: &CpuStorage,
        l_g: &Layout,
        s_b: &CpuStorage,
        l_b: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let dims = split_shape(l_x.shape())?;
        let (x, gamma, beta) =
            (contiguous(s_x, l_x, "input")?, contiguous(s_g, l_g, "gamma")?, contiguous(s_b, l_b, "beta")?);
        let channels = dims.1;
        if gamma.len() != channels || beta.len() != channels {
            candle_core::bail!(
                "batch norm: {} / {} affine parameters for {channels} channels",
                gamma.len(),
                beta.len()
            );
        }
        let stats = channel_stats(x, None, dims, self.eps);
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(dims.2.max(1)).zip(x.par_chunks(dims.2.max(1))).enumerate().for_each(|(p, (y, x))| {
            let (c, s) = (p % channels, &stats[p % channels]);
            let scale = gamma[c] as f64 / (s.var + self.eps).sqrt();
            let shift = beta[c] as f64 - s.mean * scale;
            let (scale, shift) = (scale as f32, shift as f32);
            for (y, &x) in y.iter_mut().zip(x) {
                *y = x * scale + shift;
            }
        });
        Ok((CpuStorage::F32(out), l_x.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        gamma: &Tensor,
        _beta: &Tensor,
        _res: &Tensor,
        dy: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let dy = dy.contiguous()?;
        // One read of `x` and `dy` gives both parameter gradients and the statistics, from which
        // the input gradient is a per-channel affine map of `dy` and `x`.
        let stats = x.apply_op2_no_bwd(&dy, &BackwardStats { eps: self.eps })?;
        let rows = stats.to_vec2::<f64>()?;
        let (sum_dy_xhat, sum_dy, mean, var) = (&rows[0], &rows[1], &rows[2], &rows[3]);
        let channels = gamma.elem_count();
        let m = (x.elem_count() / channels.max(1)) as f64;
        let mut coefficients = vec![0f32; 3 * channels];
        for (c, &g) in gamma.to_vec1::<f32>()?.iter().enumerate() {
            let inv_std = 1.0 / (var[c] + self.eps).sqrt();
            // dx = a dy + b x + d, expanded so the inner loop is two multiply-adds.
            let a = g as f64 * inv_std;
            let b = -a * sum_dy_xhat[c] / m * inv_std;
            let d = -a * sum_dy[c] / m - b * mean[c];
            (coefficients[c], coefficients[channels + c], coefficients[2 * channels + c]) =
                (a as f32, b as f32, d as f32);
        }
        let coefficients = Tensor::from_vec(coefficients, (3, channels), x.device())?;
        let dx = x.apply_op3_no_bwd(&dy, &coefficients, &InputGradient)?;
        let params = stats.narrow(0, 0, 2)?.to_dtype(candle_core::DType::F32)?;
        Ok((Some(dx), Some(params.get(0)?), Some(params.get(1)?)))
    }
}

/// `(x, dy, [a; b; d]) -> dx = a dy + b x + d`, with `[3, C]` per-channel coefficients.
struct InputGradient;

impl CustomOp3 for InputGradient {
    fn name(&self) -> &'static str {
        "batch-norm-train-input-grad"
    }

    fn cpu_fwd(
        &self,
        s_x: &CpuStorage,
        l_x: &Layout,
        s_d: &CpuStorage,
        l_d: &Layout,
        s_c: &CpuStorage,
        l_c: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let dims = split_shape(l_x.shape())?;
        if l_d.shape() != l_x.shape() {
            candle_core::bail!("batch norm gradient {:?} for input {:?}", l_d.shape(), l_x.shape());
        }
        let (x, dy, coefficients) =
            (contiguous(s_x, l_x, "input")?, contiguous(s_d, l_d, "gradient")?, contiguous(s_c, l_c, "coefficients")?);
        let channels = dims.1;
        if coefficients.len() != 3 * channels {
            candle_core::bail!("batch norm: {} gradient coefficients for {channels} channels", coefficients.len());
        }
        let plane = dims.2.max(1);
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(plane).zip(x.par_chunks(plane).zip(dy.par_chunks(plane))).enumerate().for_each(
            |(p, (dx, (x, dy)))| {
                let c = p % channels;
                let (a, b, d) = (coefficients[c], coefficients[channels + c], coefficients[2 * channels + c]);
                for ((o, &x), &g) in dx.iter_mut().zip(x).zip(dy) {
                    *o = a * g + b * x + d;
                }
            },
        );
        Ok((CpuStorage::F32(out), l_x.shape().clone()))
    }
}

/// `(x, dy) -> [[dgamma...], [dbeta...], [mean...], [var...]]` in `f64`.
struct BackwardStats {
    eps: f64,
}

impl CustomOp2 for BackwardStats {
    fn name(&self) -> &'static str {
        "batch-norm-train-backward-stats"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout, s_d: &CpuStorage, l_d: &Layout) -> Result<(CpuStorage, Shape)> {
        let dims = split_shape(l_x.shape())?;
        if l_d.shape() != l_x.shape() {
            candle_core::bail!("batch norm gradient {:?} for input {:?}", l_d.shape(), l_x.shape());
        }
        let stats =
            channel_stats(contiguous(s_x, l_x, "input")?, Some(contiguous(s_d, l_d, "gradient")?), dims, self.eps);
        let fields: [fn(&ChannelStats) -> f64; 4] = [|s| s.sum_dy_xhat, |s| s.sum_dy, |s| s.mean, |s| s.var];
        let out: Vec<f64> = fields.iter().flat_map(|field| stats.iter().map(field)).collect();
        Ok((CpuStorage::F64(out), Shape::from_dims(&[4, dims.1])))
    }
}

/// `x -> [[mean...], [biased var...]]` in `f64`, read by [`RunningUpdate`].
struct BatchStats;

impl CustomOp1 for BatchStats {
    fn name(&self) -> &'static str {
        "batch-norm-batch-stats"
    }

    fn cpu_fwd(&self, s_x: &CpuStorage, l_x: &Layout) -> Result<(CpuStorage, Shape)> {
        let dims = split_shape(l_x.shape())?;
        let stats = channel_stats(contiguous(s_x, l_x, "input")?, None, dims, 0.0);
        let out: Vec<f64> = stats.iter().map(|s| s.mean).chain(stats.iter().map(|s| s.var)).collect();
        Ok((CpuStorage::F64(out), Shape::from_dims(&[2, dims.1])))
    }
}

/// Moves running statistics in place: `running = (1 - momentum) running + momentum batch`,
/// where `batch` is the mean (`variance_count == None`) or, for `Some(M)`, the biased variance
/// times `M / (M - 1)`, both read from [`BatchStats`]' rows.
struct RunningUpdate {
    momentum: f64,
    variance_count: Option<usize>,
}

impl InplaceOp2 for RunningUpdate {
    fn name(&self) -> &'static str {
        "batch-norm-running-update"
    }

    fn cpu_fwd(&self, s_r: &mut CpuStorage, l_r: &Layout, s_s: &CpuStorage, l_s: &Layout) -> Result<()> {
        let channels = l_s.shape().dims2()?.1;
        let (start, end) = l_s
            .contiguous_offsets()
            .ok_or_else(|| candle_core::Error::Msg("batch norm: batch statistics must be contiguous".into()))?;
        let stats = &s_s.as_slice::<f64>()?[start..end];
        let (start, end) = l_r
            .contiguous_offsets()
            .ok_or_else(|| candle_core::Error::Msg("batch norm: running statistics must be contiguous".into()))?;
        let CpuStorage::F32(running) = s_r else { candle_core::bail!("batch norm: f32 running statistics only") };
        let running = &mut running[start..end];
        if running.len() != channels {
            candle_core::bail!("batch norm: {} running values for {channels} channels", running.len());
        }
        for (c, r) in running.iter_mut().enumerate() {
            let batch = match self.variance_count {
                None => stats[c],
                Some(m) => stats[channels + c] * m as f64 / (m as f64 - 1.0),
            };
            *r = ((1.0 - self.momentum) * *r as f64 + self.momentum * batch) as f32;
        }
        Ok(())
    }
}

/// Training-mode BatchNorm of `x` `[B, C, ...]` with `bn`'s affine parameters, updating its
/// running statistics as candle-nn does; differentiable with respect to `x`, gamma and beta.
pub fn batch_norm_train(bn: &BatchNorm, x: &Tensor) -> Result<Tensor> {
    let x = x.contiguous()?;
    let (batch, channels, plane) = split_shape(x.shape())?;
    let Some((gamma, beta)) = bn.weight_and_bias() else {
        candle_core::bail!("batch norm (training): only the affine form is supported");
    };
    let count = batch * plane;
    if count < 2 {
        candle_core::bail!("batch norm (training) needs at least two values per channel, got {:?}", x.shape());
    }
    if gamma.elem_count() != channels {
        candle_core::bail!("batch norm: {} features for input {:?}", gamma.elem_count(), x.shape());
    }
    let stats = x.detach().apply_op1_no_bwd(&BatchStats)?;
    bn.running_mean().inplace_op2(&stats, &RunningUpdate { momentum: bn.momentum(), variance_count: None })?;
    bn.running_var().inplace_op2(&stats, &RunningUpdate { momentum: bn.momentum(), variance_count: Some(count) })?;
    x.apply_op3(&gamma.contiguous()?, &beta.contiguous()?, BatchNormTrain { eps: bn.eps() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, ModuleT, Shape, Var};
    use candle_nn::{BatchNormConfig, VarBuilder, VarMap};
    use rand::{rngs::StdRng, Rng, SeedableRng};

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    /// Values of `shape` drawn from N(`mean`, `std`²) by `rng`. Seeded, so that each run compares the
    /// same numbers: candle-nn's reference works in f32, and where a channel's few values nearly
    /// coincide its rounding is amplified by up to `1 / sqrt(eps)`, past the tolerances below, in
    /// about one draw of a hundred.
    fn normal(rng: &mut StdRng, shape: impl Into<Shape>, mean: f32, std: f32) -> Result<Tensor> {
        let shape = shape.into();
        let normal = rand_distr::Normal::new(mean, std).unwrap();
        let values: Vec<f32> = (0..shape.elem_count()).map(|_| rng.sample(normal)).collect();
        Tensor::from_vec(values, shape, &Device::Cpu)
    }

    fn random_bn(channels: usize, varmap: &VarMap, rng: &mut StdRng) -> Result<BatchNorm> {
        let config = BatchNormConfig { eps: 1e-3, remove_mean: true, affine: true, momentum: 0.1 };
        let bn = candle_nn::batch_norm(channels, config, VarBuilder::from_varmap(varmap, DType::F32, &Device::Cpu))?;
        for (name, var) in varmap.data().lock().unwrap().iter() {
            if name == "weight" || name == "bias" {
                var.set(&normal(rng, channels, 0.5, 1.0)?)?;
            }
        }
        Ok(bn)
    }

    #[test]
    fn values_gradients_and_running_statistics_equal_candle_nn() -> Result<()> {
        let mut rng = StdRng::seed_from_u64(5);
        for shape in [(4usize, 3usize, 5usize, 6usize), (2, 7, 1, 1), (3, 2, 4, 1)] {
            let (ours_vars, stock_vars) = (VarMap::new(), VarMap::new());
            let ours = random_bn(shape.1, &ours_vars, &mut rng)?;
            let stock = random_bn(shape.1, &stock_vars, &mut rng)?;
            // Same parameters in both.
            for (name, var) in stock_vars.data().lock().unwrap().iter() {
                var.set(ours_vars.data().lock().unwrap()[name].as_tensor())?;
            }
            let x = Var::from_tensor(&normal(&mut rng, shape, 1.0, 2.0)?)?;
            let probe = normal(&mut rng, shape, 0.0, 1.0)?;
            let y_ours = batch_norm_train(&ours, &x)?;
            let y_stock = stock.forward_t(&x, true)?;
            assert!(max_abs_diff(&y_ours, &y_stock) < 1e-5, "forward {shape:?}");
            assert!(max_abs_diff(ours.running_mean(), stock.running_mean()) < 1e-6, "running mean {shape:?}");
            assert!(max_abs_diff(ours.running_var(), stock.running_var()) < 1e-5, "running var {shape:?}");
            let g_ours = (&y_ours * &probe)?.sum_all()?.backward()?;
            let g_stock = (&y_stock * &probe)?.sum_all()?.backward()?;
            let (w_ours, b_ours) = ours.weight_and_bias().unwrap();
            let (w_stock, b_stock) = stock.weight_and_bias().unwrap();
            for (name, a, b) in [
                ("x", g_ours.get(&x).unwrap(), g_stock.get(&x).unwrap()),
                ("gamma", g_ours.get(w_ours).unwrap(), g_stock.get(w_stock).unwrap()),
                ("beta", g_ours.get(b_ours).unwrap(), g_stock.get(b_stock).unwrap()),
            ] {
                assert_eq!(a.dims(), b.dims(), "{name}");
                let d = max_abs_diff(a, b);
                assert!(d < 1e-4, "{name} gradient {shape:?}: max diff {d}");
            }
        }
        Ok(())
    }

    /// Central differences of `sum(probe * bn(x))` at a spread of input coordinates.
    #[test]
    fn input_gradient_matches_finite_differences() -> Result<()> {
        let varmap = VarMap::new();
        let bn = random_bn(3, &varmap, &mut StdRng::seed_from_u64(6))?;
        let shape = (3, 3, 4, 4);
        let x = Var::randn(0f32, 1.0, shape, &Device::Cpu)?;
        let probe = Tensor::randn(0f32, 1.0, shape, &Device::Cpu)?;
        let loss = |x: &Tensor| -> Result<f64> {
            batch_norm_train(&bn, x)?.mul(&probe)?.sum_all()?.to_dtype(DType::F64)?.to_scalar::<f64>()
        };
        let analytic = batch_norm_train(&bn, &x)?
            .mul(&probe)?
            .sum_all()?
            .backward()?
            .get(&x)
            .unwrap()
            .flatten_all()?
            .to_vec1::<f32>()?;
        let values = x.flatten_all()?.to_vec1::<f32>()?;
        for index in (0..values.len()).step_by(7) {
            let eps = 1e-2f32;
            let at = |delta: f32| {
                let mut v = values.clone();
                v[index] += delta;
                Tensor::from_vec(v, shape, &Device::Cpu)
            };
            let numeric = (loss(&at(eps)?)? - loss(&at(-eps)?)?) / (2.0 * eps as f64);
            let a = analytic[index] as f64;
            assert!((numeric - a).abs() <= 2e-2 * (1.0 + a.abs()), "x[{index}]: numeric {numeric} analytic {a}");
        }
        Ok(())
    }

    #[test]
    fn one_value_per_channel_is_an_error() -> Result<()> {
        let bn = random_bn(2, &VarMap::new(), &mut StdRng::seed_from_u64(7))?;
        assert!(batch_norm_train(&bn, &Tensor::zeros((1, 2, 1, 1), DType::F32, &Device::Cpu)?).is_err());
        assert!(batch_norm_train(&bn, &Tensor::zeros((2, 3, 2, 2), DType::F32, &Device::Cpu)?).is_err());
        Ok(())
    }
}
