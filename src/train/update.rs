//! The optimizers' element-wise updates as in-place candle ops: one pass over each parameter
//! (and its state) per update, no temporaries. Composed of stock tensor ops, AdamW took about
//! ten full-size ops per parameter, 30-50 ms of a 200 ms step at 32 px.
//!
//! The formulas are those of [`super::Optimizer`]'s documentation (f32 arithmetic, as the stock
//! ops did); the tests compare them with the stock-op composition.

use candle_core::{CpuStorage, InplaceOp2, InplaceOp3, Layout, Result, Tensor};
use rayon::prelude::*;

/// Parameters at least this long are updated on rayon's threads.
const PARALLEL_MIN: usize = 32 * 1024;
const CHUNK: usize = 8 * 1024;

fn source<'a>(storage: &'a CpuStorage, layout: &Layout, len: usize, what: &str) -> Result<&'a [f32]> {
    let (start, end) = layout
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg(format!("optimizer update: the {what} must be contiguous")))?;
    if end - start != len {
        candle_core::bail!("optimizer update: the {what} has {} values for a parameter of {len}", end - start);
    }
    Ok(&storage.as_slice::<f32>()?[start..end])
}

fn destination<'a>(storage: &'a mut CpuStorage, layout: &Layout, what: &str) -> Result<&'a mut [f32]> {
    let (start, end) = layout
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg(format!("optimizer update: the {what} must be contiguous")))?;
    let CpuStorage::F32(data) = storage else { candle_core::bail!("optimizer update: the {what} is not f32") };
    Ok(&mut data[start..end])
}

/// `f(dst_chunk, a_chunk, b_chunk)` over matching chunks, in parallel for long tensors.
fn for_chunks(dst: &mut [f32], a: &[f32], b: &[f32], f: impl Fn(&mut [f32], &[f32], &[f32]) + Sync) {
    if dst.len() >= PARALLEL_MIN {
        dst.par_chunks_mut(CHUNK).zip(a.par_chunks(CHUNK)).zip(b.par_chunks(CHUNK)).for_each(|((d, a), b)| f(d, a, b));
    } else {
        f(dst, a, b);
    }
}

/// `m = decay m + (1 - decay) g^power` (power 1 or 2): AdamW's first and second moments.
pub struct Moment {
    pub decay: f32,
    pub squared: bool,
}

impl InplaceOp2 for Moment {
    fn name(&self) -> &'static str {
        "adamw-moment"
    }

    fn cpu_fwd(&self, s_m: &mut CpuStorage, l_m: &Layout, s_g: &CpuStorage, l_g: &Layout) -> Result<()> {
        let m = destination(s_m, l_m, "moment")?;
        let g = source(s_g, l_g, m.len(), "gradient")?;
        let (decay, rest, squared) = (self.decay, 1.0 - self.decay, self.squared);
        for_chunks(m, g, g, |m, g, _| {
            for (m, &g) in m.iter_mut().zip(g) {
                let g = if squared { g * g } else { g };
                *m = *m * decay + g * rest;
            }
        });
        Ok(())
    }
}

/// `w = w (1 - lr wd) - lr m̂ / (sqrt(v̂) + eps)` with `m̂ = m / c1`, `v̂ = v / c2`.
pub struct AdamWStep {
    pub lr: f32,
    pub weight_decay: f32,
    pub correction1: f32,
    pub correction2: f32,
    pub eps: f32,
}

impl InplaceOp3 for AdamWStep {
    fn name(&self) -> &'static str {
        "adamw-step"
    }

    fn cpu_fwd(
        &self,
        s_w: &mut CpuStorage,
        l_w: &Layout,
        s_m: &CpuStorage,
        l_m: &Layout,
        s_v: &CpuStorage,
        l_v: &Layout,
    ) -> Result<()> {
        let w = destination(s_w, l_w, "parameter")?;
        let (m, v) = (source(s_m, l_m, w.len(), "first moment")?, source(s_v, l_v, w.len(), "second moment")?);
        let keep = 1.0 - self.lr * self.weight_decay;
        for_chunks(w, m, v, |w, m, v| {
            for ((w, &m), &v) in w.iter_mut().zip(m).zip(v) {
                let update = (m / self.correction1) / ((v / self.correction2).sqrt() + self.eps);
                *w = *w * keep - update * self.lr;
            }
        });
        Ok(())
    }
}

/// SGD's momentum buffer: `b = momentum b + (g + wd w)`.
pub struct SgdMomentum {
    pub momentum: f32,
    pub weight_decay: f32,
}

impl InplaceOp3 for SgdMomentum {
    fn name(&self) -> &'static str {
        "sgd-momentum"
    }

    fn cpu_fwd(
        &self,
        s_b: &mut CpuStorage,
        l_b: &Layout,
        s_g: &CpuStorage,
        l_g: &Layout,
        s_w: &CpuStorage,
        l_w: &Layout,
    ) -> Result<()> {
        let b = destination(s_b, l_b, "momentum buffer")?;
        let (g, w) = (source(s_g, l_g, b.len(), "gradient")?, source(s_w, l_w, b.len(), "parameter")?);
        for_chunks(b, g, w, |b, g, w| {
            for ((b, &g), &w) in b.iter_mut().zip(g).zip(w) {
                *b = *b * self.momentum + (g + w * self.weight_decay);
            }
        });
        Ok(())
    }
}

/// `w = w - lr b`.
pub struct SgdStep {
    pub lr: f32,
}

impl InplaceOp2 for SgdStep {
    fn name(&self) -> &'static str {
        "sgd-step"
    }

    fn cpu_fwd(&self, s_w: &mut CpuStorage, l_w: &Layout, s_b: &CpuStorage, l_b: &Layout) -> Result<()> {
        let w = destination(s_w, l_w, "parameter")?;
        let b = source(s_b, l_b, w.len(), "momentum buffer")?;
        for_chunks(w, b, b, |w, b, _| {
            for (w, &b) in w.iter_mut().zip(b) {
                *w -= self.lr * b;
            }
        });
        Ok(())
    }
}

/// A tensor with storage of its own (in-place updates must not reach a tensor it was copied from).
pub fn owned(t: &Tensor) -> Result<Tensor> {
    t.to_dtype(candle_core::DType::F32)?.contiguous()?.copy()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    /// In-place updates equal the stock-op formulas, on a long (parallel) and a short tensor.
    #[test]
    fn updates_equal_stock_formulas() -> Result<()> {
        let dev = Device::Cpu;
        for len in [100_000usize, 37] {
            let (w0, g) = (Tensor::randn(0f32, 1.0, len, &dev)?, Tensor::randn(0f32, 1.0, len, &dev)?);
            let (m0, v0) = (Tensor::randn(0f32, 0.1, len, &dev)?, Tensor::randn(0f32, 0.1, len, &dev)?.abs()?);
            let (b1, b2, lr, wd, eps, t) = (0.9f64, 0.999f64, 1e-2f64, 1e-2f64, 1e-8f64, 3);
            // Stock AdamW.
            let m = ((&m0 * b1)? + (&g * (1.0 - b1))?)?;
            let v = ((&v0 * b2)? + (g.sqr()? * (1.0 - b2))?)?;
            let update = ((&m / (1.0 - b1.powi(t)))? / ((&v / (1.0 - b2.powi(t)))?.sqrt()? + eps)?)?;
            let w = ((&w0 * (1.0 - lr * wd))? - (update * lr)?)?;
            // In place.
            let (mi, vi, wi) = (owned(&m0)?, owned(&v0)?, owned(&w0)?);
            mi.inplace_op2(&g, &Moment { decay: b1 as f32, squared: false })?;
            vi.inplace_op2(&g, &Moment { decay: b2 as f32, squared: true })?;
            let step = AdamWStep {
                lr: lr as f32,
                weight_decay: wd as f32,
                correction1: (1.0 - b1.powi(t)) as f32,
                correction2: (1.0 - b2.powi(t)) as f32,
                eps: eps as f32,
            };
            wi.inplace_op3(&mi, &vi, &step)?;
            assert!(max_abs_diff(&m, &mi) < 1e-6 && max_abs_diff(&v, &vi) < 1e-6, "moments, len {len}");
            assert!(max_abs_diff(&w, &wi) < 1e-5, "adamw weights, len {len}: {}", max_abs_diff(&w, &wi));
            // Stock SGD with momentum.
            let b = ((&m0 * 0.9)? + (&g + (&w0 * wd)?)?)?;
            let w = (&w0 - (&b * lr)?)?;
            let (bi, wi) = (owned(&m0)?, owned(&w0)?);
            bi.inplace_op3(&g, &wi, &SgdMomentum { momentum: 0.9, weight_decay: wd as f32 })?;
            wi.inplace_op2(&bi, &SgdStep { lr: lr as f32 })?;
            assert!(max_abs_diff(&b, &bi) < 1e-6 && max_abs_diff(&w, &wi) < 1e-6, "sgd, len {len}");
            // The source tensors were not touched.
            assert_eq!(max_abs_diff(&m0, &owned(&m0)?), 0.0);
        }
        Ok(())
    }

    #[test]
    fn mismatched_lengths_are_errors() -> Result<()> {
        let dev = Device::Cpu;
        let m = Tensor::zeros(4, candle_core::DType::F32, &dev)?;
        assert!(m
            .inplace_op2(&Tensor::zeros(5, candle_core::DType::F32, &dev)?, &Moment { decay: 0.9, squared: false })
            .is_err());
        Ok(())
    }
}
