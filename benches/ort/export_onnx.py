"""Builds an ONNX graph of ecm-lcd's network (MobileNetV2 or ECMobileNet) from the project's folded
safetensors weights, so that ONNX Runtime runs exactly the same network with the same weights.

Inputs (written by `ecm-lcd-bench speed --only ort`):
  --weights  safetensors with folded BatchNorm (names of src/model/weights/mod.rs: `stem`, `blocks.{i}.expand`,
             `blocks.{i}.depthwise`, `blocks.{i}.eca`, `blocks.{i}.project`, `head`, each `.weight` + `.bias`)
  --spec     JSON: {"input_size": S, "stem_stride": 2, "blocks": [{"input", "hidden", "output", "stride",
             "eca_kernel"}...]} (strides are not in the weights)
Output: an ONNX model with input `input` [1, 3, S, S] and output `features` [1, C, S/32, S/32] (the head's
ReLU6 output, what ecm-lcd's descriptors are computed from).

TensorFlow "SAME" padding is asymmetric for stride 2 (the extra row/column goes bottom/right), so every
Conv gets explicit pads computed from the static input size, as src/model/depthwise.rs same_padding does.
"""
import argparse
import json

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from safetensors.numpy import load_file


def same_padding(size, kernel, stride):
    out = -(-size // stride)
    total = max((out - 1) * stride + kernel - size, 0)
    return out, total // 2, total - total // 2


class Graph:
    def __init__(self, tensors):
        self.tensors = tensors
        self.nodes = []
        self.inits = []
        self.count = 0

    def name(self, prefix):
        self.count += 1
        return f"{prefix}_{self.count}"

    def init(self, name, array):
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(array, dtype=np.float32), name))
        return name

    def conv(self, x, unit, size, stride, groups, relu6):
        weight = self.tensors[f"{unit}.weight"]
        kernel = weight.shape[2]
        out, lo, hi = same_padding(size, kernel, stride)
        inputs = [x, self.init(f"{unit}.weight", weight)]
        if f"{unit}.bias" in self.tensors:
            inputs.append(self.init(f"{unit}.bias", self.tensors[f"{unit}.bias"]))
        y = self.name(unit)
        self.nodes.append(helper.make_node("Conv", inputs, [y], kernel_shape=[kernel, kernel], strides=[stride, stride],
                                           pads=[lo, lo, hi, hi], group=groups))
        if relu6:
            z = self.name(unit + ".relu6")
            self.nodes.append(helper.make_node("Clip", [y, "zero", "six"], [z]))
            y = z
        return y, out

    def eca(self, x, unit, channels, kernel):
        pooled, row, conv, gate, gate4, y = (self.name(unit + s) for s in (".pool", ".row", ".conv", ".sigmoid", ".gate", ".out"))
        self.nodes.append(helper.make_node("GlobalAveragePool", [x], [pooled]))
        self.nodes.append(helper.make_node("Reshape", [pooled, "shape_1_1_c_" + str(channels)], [row]))
        weight = self.tensors[f"{unit}.weight"]
        pad = (kernel - 1) // 2
        self.nodes.append(helper.make_node("Conv", [row, self.init(f"{unit}.weight", weight)], [conv], kernel_shape=[kernel], pads=[pad, pad]))
        self.nodes.append(helper.make_node("Sigmoid", [conv], [gate]))
        self.nodes.append(helper.make_node("Reshape", [gate, "shape_1_c_1_1_" + str(channels)], [gate4]))
        self.nodes.append(helper.make_node("Mul", [x, gate4], [y]))
        return y


def build(tensors, spec):
    size = spec["input_size"]
    g = Graph(tensors)
    g.inits.append(numpy_helper.from_array(np.array(0.0, dtype=np.float32), "zero"))
    g.inits.append(numpy_helper.from_array(np.array(6.0, dtype=np.float32), "six"))
    for b in (b for b in spec["blocks"] if b.get("eca_kernel")):
        c = b["hidden"]
        for shape_name, shape in (("shape_1_1_c_", [1, 1, c]), ("shape_1_c_1_1_", [1, c, 1, 1])):
            if not any(i.name == shape_name + str(c) for i in g.inits):
                g.inits.append(numpy_helper.from_array(np.array(shape, dtype=np.int64), shape_name + str(c)))
    x, size = g.conv("input", "stem", size, spec["stem_stride"], 1, True)
    for i, b in enumerate(spec["blocks"]):
        unit = f"blocks.{i}"
        y, s = x, size
        if b["hidden"] != b["input"]:
            y, s = g.conv(y, unit + ".expand", s, 1, 1, True)
        y, s = g.conv(y, unit + ".depthwise", s, b["stride"], b["hidden"], True)
        if b.get("eca_kernel"):
            y = g.eca(y, unit + ".eca", b["hidden"], b["eca_kernel"])
        y, s = g.conv(y, unit + ".project", s, 1, 1, False)
        if b["stride"] == 1 and b["input"] == b["output"]:
            z = g.name(unit + ".residual")
            g.nodes.append(helper.make_node("Add", [y, x], [z]))
            y = z
        x, size = y, s
    x, size = g.conv(x, "head", size, 1, 1, True)
    g.nodes.append(helper.make_node("Identity", [x], ["features"]))
    channels = tensors["head.weight"].shape[0]
    graph = helper.make_graph(
        g.nodes, "ecm-lcd",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 3, spec["input_size"], spec["input_size"]])],
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, [1, channels, size, size])],
        g.inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], producer_name="ecm-lcd export_onnx.py")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", required=True)
    parser.add_argument("--spec", required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    with open(args.spec) as f:
        spec = json.load(f)
    onnx.save(build(load_file(args.weights), spec), args.out)


if __name__ == "__main__":
    main()
