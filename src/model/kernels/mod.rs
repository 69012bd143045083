//! The CPU kernels the networks run on, as candle custom ops: the inference path's channels-last
//! whole-bottleneck op ([`fused`]) and its register-blocked micro-kernels ([`simd`]), the NCHW
//! depthwise convolution ([`depthwise`]), and the training path's differentiable ops with their
//! backward passes ([`train_ops`], [`depthwise_grad`], [`batch_norm_train`]). The network definitions
//! in [`crate::model`] choose between these and candle's stock ops by [`crate::model::layers::Mode`];
//! the tests beside each kernel check it against the stock ops.

pub mod batch_norm_train;
pub mod depthwise;
pub mod depthwise_grad;
pub mod fused;
pub mod matmul;
pub mod simd;
pub mod train_ops;

/// The `f32` values of a custom op's operand, which must be contiguous (`op` and `what` name it in
/// the error).
pub(crate) fn contiguous_f32<'a>(
    storage: &'a candle_core::CpuStorage,
    layout: &candle_core::Layout,
    op: &str,
    what: &str,
) -> candle_core::Result<&'a [f32]> {
    let (start, end) = layout
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg(format!("{op}: {what} must be contiguous")))?;
    Ok(&storage.as_slice::<f32>()?[start..end])
}
