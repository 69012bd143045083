//! A small, bounds-checked reader of TensorFlow Lite flatbuffers: just the tables needed to pull
//! convolution weights out of a model (operators in graph order, tensors, quantisation, buffers).
//!
//! Why not a crate: the generated `flatbuffers` accessors read without bounds checks (unsafe on a
//! corrupt file), and the TFLite crates bind the C++ runtime. Every read here is checked, so any
//! byte string yields either a model or an error with the offset that was wrong.
//!
//! Field numbers follow TensorFlow's `schema.fbs` (v3).

use anyhow::{bail, ensure, Context, Result};

/// Byte-level access to a flatbuffer with checked reads.
#[derive(Clone, Copy)]
struct Buf<'a>(&'a [u8]);

impl<'a> Buf<'a> {
    fn bytes(&self, pos: usize, len: usize) -> Result<&'a [u8]> {
        pos.checked_add(len)
            .and_then(|end| self.0.get(pos..end))
            .with_context(|| format!("read of {len} bytes at offset {pos} is past the end ({} bytes)", self.0.len()))
    }
    fn u8(&self, pos: usize) -> Result<u8> {
        Ok(self.bytes(pos, 1)?[0])
    }
    fn u16(&self, pos: usize) -> Result<u16> {
        Ok(u16::from_le_bytes(self.bytes(pos, 2)?.try_into().unwrap()))
    }
    fn u32(&self, pos: usize) -> Result<u32> {
        Ok(u32::from_le_bytes(self.bytes(pos, 4)?.try_into().unwrap()))
    }
    fn i32(&self, pos: usize) -> Result<i32> {
        Ok(i32::from_le_bytes(self.bytes(pos, 4)?.try_into().unwrap()))
    }
    fn i64(&self, pos: usize) -> Result<i64> {
        Ok(i64::from_le_bytes(self.bytes(pos, 8)?.try_into().unwrap()))
    }
    fn f32(&self, pos: usize) -> Result<f32> {
        Ok(f32::from_le_bytes(self.bytes(pos, 4)?.try_into().unwrap()))
    }
    /// Follows a `uoffset_t` stored at `pos`.
    fn deref(&self, pos: usize) -> Result<usize> {
        let off = self.u32(pos)? as usize;
        pos.checked_add(off).context("offset overflow")
    }
}

/// One flatbuffer table.
#[derive(Clone, Copy)]
struct Table<'a> {
    buf: Buf<'a>,
    pos: usize,
    vtable: usize,
    vtable_len: usize,
}

impl<'a> Table<'a> {
    fn at(buf: Buf<'a>, pos: usize) -> Result<Self> {
        let soffset = buf.i32(pos)? as i64;
        let vtable = usize::try_from(pos as i64 - soffset)
            .with_context(|| format!("table at offset {pos} has a vtable before the file start"))?;
        let vtable_len = buf.u16(vtable)? as usize;
        ensure!(vtable_len >= 4 && vtable_len.is_multiple_of(2), "bad vtable at offset {vtable}");
        buf.bytes(vtable, vtable_len)?;
        Ok(Table { buf, pos, vtable, vtable_len })
    }

    /// Absolute position of field `index`, if present.
    fn field(&self, index: usize) -> Result<Option<usize>> {
        let slot = 4 + 2 * index;
        if slot + 2 > self.vtable_len {
            return Ok(None);
        }
        let off = self.buf.u16(self.vtable + slot)? as usize;
        Ok((off != 0).then_some(self.pos + off))
    }

    fn u8_or(&self, index: usize, default: u8) -> Result<u8> {
        self.field(index)?.map_or(Ok(default), |p| self.buf.u8(p))
    }
    fn i32_or(&self, index: usize, default: i32) -> Result<i32> {
        self.field(index)?.map_or(Ok(default), |p| self.buf.i32(p))
    }
    fn u32_or(&self, index: usize, default: u32) -> Result<u32> {
        self.field(index)?.map_or(Ok(default), |p| self.buf.u32(p))
    }

    fn table(&self, index: usize) -> Result<Option<Table<'a>>> {
        match self.field(index)? {
            Some(p) => Ok(Some(Table::at(self.buf, self.buf.deref(p)?)?)),
            None => Ok(None),
        }
    }

    /// A vector field: (position of first element, length).
    fn vector(&self, index: usize, elem_size: usize) -> Result<(usize, usize)> {
        let Some(p) = self.field(index)? else { return Ok((0, 0)) };
        let start = self.buf.deref(p)?;
        let len = self.buf.u32(start)? as usize;
        let bytes = len.checked_mul(elem_size).context("vector length overflow")?;
        self.buf.bytes(start + 4, bytes)?;
        Ok((start + 4, len))
    }

    fn bytes(&self, index: usize) -> Result<&'a [u8]> {
        let (pos, len) = self.vector(index, 1)?;
        if len == 0 {
            return Ok(&[]);
        }
        self.buf.bytes(pos, len)
    }

    fn string(&self, index: usize) -> Result<String> {
        Ok(String::from_utf8_lossy(self.bytes(index)?).into_owned())
    }

    fn i32s(&self, index: usize) -> Result<Vec<i32>> {
        let (pos, len) = self.vector(index, 4)?;
        (0..len).map(|i| self.buf.i32(pos + 4 * i)).collect()
    }
    fn i64s(&self, index: usize) -> Result<Vec<i64>> {
        let (pos, len) = self.vector(index, 8)?;
        (0..len).map(|i| self.buf.i64(pos + 8 * i)).collect()
    }
    fn f32s(&self, index: usize) -> Result<Vec<f32>> {
        let (pos, len) = self.vector(index, 4)?;
        (0..len).map(|i| self.buf.f32(pos + 4 * i)).collect()
    }
    fn tables(&self, index: usize) -> Result<Vec<Table<'a>>> {
        let (pos, len) = self.vector(index, 4)?;
        (0..len).map(|i| Table::at(self.buf, self.buf.deref(pos + 4 * i)?)).collect()
    }
}

/// TFLite `TensorType` values this reader understands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TensorType {
    Float32,
    Int32,
    UInt8,
    Int8,
    Other(u8),
}

impl TensorType {
    fn from_code(code: u8) -> Self {
        match code {
            0 => TensorType::Float32,
            2 => TensorType::Int32,
            3 => TensorType::UInt8,
            9 => TensorType::Int8,
            other => TensorType::Other(other),
        }
    }
}

/// A tensor of the graph with its constant data, if any.
#[derive(Clone, Debug)]
pub struct TfTensor {
    pub name: String,
    pub shape: Vec<usize>,
    pub dtype: TensorType,
    pub scales: Vec<f32>,
    pub zero_points: Vec<i64>,
    /// Axis that per-channel scales run along.
    pub quantized_dimension: usize,
    pub data: Vec<u8>,
}

impl TfTensor {
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }

    /// De-quantised (or plain float) values, in the tensor's own layout.
    pub fn to_f32(&self) -> Result<Vec<f32>> {
        let n = self.numel();
        let width = match self.dtype {
            TensorType::Float32 | TensorType::Int32 => 4,
            TensorType::UInt8 | TensorType::Int8 => 1,
            TensorType::Other(code) => bail!("tensor '{}' has unsupported type code {code}", self.name),
        };
        ensure!(
            self.data.len() == n * width,
            "tensor '{}' of shape {:?} holds {} bytes, expected {}",
            self.name,
            self.shape,
            self.data.len(),
            n * width
        );
        if self.dtype == TensorType::Float32 {
            return Ok(self.data.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect());
        }
        ensure!(!self.scales.is_empty(), "quantised tensor '{}' has no scale", self.name);
        // Per-tensor (one scale) or per-channel along `quantized_dimension`.
        let stride: usize = self.shape.iter().skip(self.quantized_dimension + 1).product();
        let channels = self.shape.get(self.quantized_dimension).copied().unwrap_or(1);
        ensure!(
            self.scales.len() == 1 || self.scales.len() == channels,
            "tensor '{}' has {} scales for {} channels",
            self.name,
            self.scales.len(),
            channels
        );
        let param = |i: usize| {
            let c = if self.scales.len() == 1 { 0 } else { (i / stride.max(1)) % channels };
            (self.scales[c], self.zero_points.get(c).or(self.zero_points.first()).copied().unwrap_or(0))
        };
        let values = (0..n)
            .map(|i| {
                let q = match self.dtype {
                    TensorType::UInt8 => self.data[i] as i64,
                    TensorType::Int8 => self.data[i] as i8 as i64,
                    _ => i32::from_le_bytes(self.data[4 * i..4 * i + 4].try_into().unwrap()) as i64,
                };
                let (scale, zero) = param(i);
                scale * (q - zero) as f32
            })
            .collect();
        Ok(values)
    }
}

/// TFLite padding scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Padding {
    Same,
    Valid,
}

/// Fused activation of a TFLite operator.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    None,
    Relu,
    Relu6,
    Other(u8),
}

/// A convolution operator (regular or depthwise) with its options.
#[derive(Clone, Debug)]
pub struct ConvOp {
    pub depthwise: bool,
    pub stride: (usize, usize),
    pub padding: Padding,
    pub activation: Activation,
    pub input: usize,
    pub weight: usize,
    pub bias: Option<usize>,
    pub output: usize,
}

/// An operator of the graph: convolutions in detail, anything else by its builtin code.
#[derive(Clone, Debug)]
pub enum Op {
    Conv(ConvOp),
    Other { code: i32, inputs: Vec<i32>, outputs: Vec<i32> },
}

/// The first subgraph of a TFLite model.
#[derive(Clone, Debug)]
pub struct TfModel {
    pub tensors: Vec<TfTensor>,
    pub ops: Vec<Op>,
    pub inputs: Vec<usize>,
    pub outputs: Vec<usize>,
}

const CONV_2D: i32 = 3;
const DEPTHWISE_CONV_2D: i32 = 4;

impl TfModel {
    /// Parses a `.tflite` flatbuffer.
    pub fn parse(bytes: &[u8]) -> Result<Self> {
        ensure!(bytes.len() >= 8, "file is {} bytes, too short for a TFLite model", bytes.len());
        ensure!(&bytes[4..8] == b"TFL3", "not a TFLite model (file identifier is not 'TFL3')");
        let buf = Buf(bytes);
        let model = Table::at(buf, buf.deref(0)?).context("model table")?;
        let opcodes: Vec<i32> = model
            .tables(1)
            .context("operator codes")?
            .iter()
            .map(|code| {
                // Newer files put the code in field 3; old ones only in the deprecated byte field 0.
                let deprecated = code.u8_or(0, 0)? as i8 as i32;
                let builtin = code.i32_or(3, 0)?;
                Ok(builtin.max(deprecated))
            })
            .collect::<Result<_>>()?;
        let buffers: Vec<&[u8]> =
            model.tables(4).context("buffers")?.iter().map(|b| b.bytes(0)).collect::<Result<_>>()?;
        let subgraphs = model.tables(2).context("subgraphs")?;
        let graph = subgraphs.first().context("model has no subgraph")?;

        let tensors = graph
            .tables(0)
            .context("tensors")?
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let shape = t.i32s(0)?.into_iter().map(|d| d.max(0) as usize).collect();
                let dtype = TensorType::from_code(t.u8_or(1, 0)?);
                let buffer = t.u32_or(2, 0)? as usize;
                let name = t.string(3)?;
                let (scales, zero_points, quantized_dimension) = match t.table(4)? {
                    Some(q) => (q.f32s(2)?, q.i64s(3)?, q.i32_or(6, 0)?.max(0) as usize),
                    None => (vec![], vec![], 0),
                };
                let data = buffers
                    .get(buffer)
                    .with_context(|| format!("tensor {i} ('{name}') points at missing buffer {buffer}"))?
                    .to_vec();
                Ok(TfTensor { name, shape, dtype, scales, zero_points, quantized_dimension, data })
            })
            .collect::<Result<Vec<_>>>()?;

        let tensor_index = |i: i32, what: &str| -> Result<usize> {
            usize::try_from(i)
                .ok()
                .filter(|&i| i < tensors.len())
                .with_context(|| format!("{what} refers to tensor {i}, but there are {}", tensors.len()))
        };
        let ops = graph
            .tables(3)
            .context("operators")?
            .iter()
            .enumerate()
            .map(|(n, op)| {
                let index = op.u32_or(0, 0)? as usize;
                let code =
                    *opcodes.get(index).with_context(|| format!("operator {n} has unknown opcode index {index}"))?;
                let inputs = op.i32s(1)?;
                let outputs = op.i32s(2)?;
                if code != CONV_2D && code != DEPTHWISE_CONV_2D {
                    return Ok(Op::Other { code, inputs, outputs });
                }
                let depthwise = code == DEPTHWISE_CONV_2D;
                let what = format!("convolution operator {n}");
                ensure!(
                    inputs.len() >= 2 && outputs.len() == 1,
                    "{what} has {} inputs and {} outputs",
                    inputs.len(),
                    outputs.len()
                );
                let options = op.table(4)?.with_context(|| format!("{what} has no options"))?;
                // Conv2DOptions: padding, stride_w, stride_h, activation;
                // DepthwiseConv2DOptions: padding, stride_w, stride_h, depth_multiplier, activation.
                let padding = if options.u8_or(0, 0)? == 0 { Padding::Same } else { Padding::Valid };
                let stride = (options.i32_or(2, 1)?.max(1) as usize, options.i32_or(1, 1)?.max(1) as usize);
                let activation = match options.u8_or(if depthwise { 4 } else { 3 }, 0)? {
                    0 => Activation::None,
                    1 => Activation::Relu,
                    3 => Activation::Relu6,
                    other => Activation::Other(other),
                };
                let bias = match inputs.get(2) {
                    Some(&b) if b >= 0 => Some(tensor_index(b, &what)?),
                    _ => None,
                };
                Ok(Op::Conv(ConvOp {
                    depthwise,
                    stride,
                    padding,
                    activation,
                    input: tensor_index(inputs[0], &what)?,
                    weight: tensor_index(inputs[1], &what)?,
                    bias,
                    output: tensor_index(outputs[0], &what)?,
                }))
            })
            .collect::<Result<Vec<_>>>()?;
        let inputs = graph.i32s(1)?.into_iter().map(|i| tensor_index(i, "graph input")).collect::<Result<_>>()?;
        let outputs = graph.i32s(2)?.into_iter().map(|i| tensor_index(i, "graph output")).collect::<Result<_>>()?;
        Ok(TfModel { tensors, ops, inputs, outputs })
    }

    /// The convolutions in graph order.
    pub fn convolutions(&self) -> impl Iterator<Item = &ConvOp> {
        self.ops.iter().filter_map(|op| match op {
            Op::Conv(c) => Some(c),
            Op::Other { .. } => None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_short_and_foreign_files_without_panicking() {
        assert!(TfModel::parse(b"").is_err());
        assert!(TfModel::parse(b"\x10\0\0\0GIF8abcdefgh").unwrap_err().to_string().contains("TFL3"));
        // Right identifier, root offset past the end.
        let err = TfModel::parse(b"\xff\xff\0\0TFL3").unwrap_err();
        assert!(format!("{err:#}").contains("past the end"), "{err:#}");
        // Every truncation of a tiny valid-looking header errors cleanly.
        let mut bytes = [0u8; 64];
        bytes[0] = 12;
        bytes[4..8].copy_from_slice(b"TFL3");
        for len in 0..bytes.len() {
            let _ = TfModel::parse(&bytes[..len]);
        }
    }
}
