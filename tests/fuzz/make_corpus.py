#!/usr/bin/env python3
"""Writes the small seed corpus of the fuzz targets (tests/fuzz/corpus/<target>/), all of our own making:
ROS image messages packed here, tiny synthetic bags and images from `ecm-lcd synth`, a minimal TFLite
model (one quantised convolution, built with the `flatbuffers` package), a JPEG from Pillow, safetensors and params YAML.
Usage: make_corpus.py ECM_LCD_BINARY   (needs `flatbuffers` and `pillow`: run.sh installs it in a venv under target/)
"""
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile

import flatbuffers
import PIL.Image

HERE = os.path.dirname(os.path.abspath(__file__))
CORPUS = os.path.join(HERE, "corpus")


def put(target, name, data):
    os.makedirs(os.path.join(CORPUS, target), exist_ok=True)
    with open(os.path.join(CORPUS, target, name), "wb") as f:
        f.write(data)


def ros1_string(b):
    return struct.pack("<I", len(b)) + b


def ros1_header(frame_id=b"cam"):
    return struct.pack("<III", 7, 1000, 500) + ros1_string(frame_id)


class Cdr:
    """Little-endian CDR with alignment relative to the body (after the 4-byte encapsulation)."""

    def __init__(self):
        self.body = b""

    def align(self, n):
        self.body += b"\0" * (-len(self.body) % n)

    def u32(self, v):
        self.align(4)
        self.body += struct.pack("<I", v)

    def i32(self, v):
        self.align(4)
        self.body += struct.pack("<i", v)

    def u8(self, v):
        self.body += bytes([v])

    def string(self, s):
        self.u32(len(s) + 1)
        self.body += s + b"\0"

    def bytes(self, b):
        self.u32(len(b))
        self.body += b

    def header(self):
        self.i32(1000)
        self.u32(500)
        self.string(b"cam")

    def done(self):
        return b"\0\x01\0\0" + self.body


def raw_ros1(w, h, encoding, step, data, big=0):
    return ros1_header() + struct.pack("<II", h, w) + ros1_string(encoding) + bytes([big]) + struct.pack("<I", step) + ros1_string(data)


def raw_cdr(w, h, encoding, step, data, big=0):
    c = Cdr()
    c.header()
    c.u32(h)
    c.u32(w)
    c.string(encoding)
    c.u8(big)
    c.u32(step)
    c.bytes(data)
    return c.done()


def compressed_ros1(fmt, data):
    return ros1_header() + ros1_string(fmt) + ros1_string(data)


def compressed_cdr(fmt, data):
    c = Cdr()
    c.header()
    c.string(fmt)
    c.bytes(data)
    return c.done()


def tflite_model():
    """One CONV_2D (uint8 weights, per-tensor quantisation), three tensors, two buffers."""
    b = flatbuffers.Builder(256)

    def vec_i32(values):
        b.StartVector(4, len(values), 4)
        for v in reversed(values):
            b.PrependInt32(v)
        return b.EndVector()

    def vec_off(offsets):
        b.StartVector(4, len(offsets), 4)
        for o in reversed(offsets):
            b.PrependUOffsetTRelative(o)
        return b.EndVector()

    weight_bytes = bytes(range(2 * 3 * 3 * 3))
    data = b.CreateByteVector(weight_bytes)
    b.StartObject(1)
    b.PrependUOffsetTRelativeSlot(0, data, 0)
    buffer1 = b.EndObject()
    b.StartObject(1)
    buffer0 = b.EndObject()

    b.StartVector(4, 1, 4)
    b.PrependFloat32(0.02)
    scales = b.EndVector()
    b.StartVector(8, 1, 8)
    b.PrependInt64(128)
    zeros = b.EndVector()
    b.StartObject(7)
    b.PrependUOffsetTRelativeSlot(2, scales, 0)
    b.PrependUOffsetTRelativeSlot(3, zeros, 0)
    quant = b.EndObject()

    def tensor(name, shape, dtype, buffer, q=None):
        n = b.CreateString(name)
        s = vec_i32(shape)
        b.StartObject(5)
        b.PrependUOffsetTRelativeSlot(0, s, 0)
        b.PrependUint8Slot(1, dtype, 255)
        b.PrependUint32Slot(2, buffer, 99)
        b.PrependUOffsetTRelativeSlot(3, n, 0)
        if q is not None:
            b.PrependUOffsetTRelativeSlot(4, q, 0)
        return b.EndObject()

    t_in = tensor("input", [1, 4, 4, 3], 0, 0)
    t_w = tensor("conv/weights", [2, 3, 3, 3], 3, 1, quant)
    t_out = tensor("output", [1, 4, 4, 2], 0, 0)

    b.StartObject(4)
    b.PrependUint8Slot(0, 0, 255)  # padding SAME
    b.PrependInt32Slot(1, 1, 0)
    b.PrependInt32Slot(2, 1, 0)
    b.PrependUint8Slot(3, 3, 255)  # RELU6
    options = b.EndObject()
    op_in = vec_i32([0, 1, -1])
    op_out = vec_i32([2])
    b.StartObject(5)
    b.PrependUint32Slot(0, 0, 99)
    b.PrependUOffsetTRelativeSlot(1, op_in, 0)
    b.PrependUOffsetTRelativeSlot(2, op_out, 0)
    b.PrependUint8Slot(3, 1, 255)
    b.PrependUOffsetTRelativeSlot(4, options, 0)
    op = b.EndObject()

    tensors = vec_off([t_in, t_w, t_out])
    g_in = vec_i32([0])
    g_out = vec_i32([2])
    ops = vec_off([op])
    b.StartObject(5)
    b.PrependUOffsetTRelativeSlot(0, tensors, 0)
    b.PrependUOffsetTRelativeSlot(1, g_in, 0)
    b.PrependUOffsetTRelativeSlot(2, g_out, 0)
    b.PrependUOffsetTRelativeSlot(3, ops, 0)
    graph = b.EndObject()

    b.StartObject(4)
    b.PrependInt8Slot(0, 3, 99)
    b.PrependInt32Slot(3, 3, 99)
    opcode = b.EndObject()

    opcodes = vec_off([opcode])
    graphs = vec_off([graph])
    buffers = vec_off([buffer0, buffer1])
    b.StartObject(5)
    b.PrependUint32Slot(0, 3, 0)
    b.PrependUOffsetTRelativeSlot(1, opcodes, 0)
    b.PrependUOffsetTRelativeSlot(2, graphs, 0)
    b.PrependUOffsetTRelativeSlot(4, buffers, 0)
    model = b.EndObject()
    b.Finish(model, file_identifier=b"TFL3")
    return bytes(b.Output())


def safetensors_file(metadata, tensors):
    """tensors: name -> (dtype, shape, raw bytes)."""
    header, offset, blob = {"__metadata__": metadata}, 0, b""
    for name, (dtype, shape, raw) in tensors.items():
        header[name] = {"dtype": dtype, "shape": shape, "data_offsets": [offset, offset + len(raw)]}
        offset += len(raw)
        blob += raw
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text + blob


def main():
    exe = sys.argv[1]
    shutil.rmtree(CORPUS, ignore_errors=True)
    pixels = bytes(range(4 * 3 * 3))
    put("image_msg", "ros1_rgb8", b"\0" + raw_ros1(4, 3, b"rgb8", 12, pixels))
    put("image_msg", "cdr_mono16_be", b"\1" + raw_cdr(2, 3, b"mono16", 4, bytes(range(12)), big=1))
    put("image_msg", "fields_bgra8", b"\2" + struct.pack("<HHH", 2, 2, 8) + bytes([3, 0]) + bytes(range(16)))

    with tempfile.TemporaryDirectory() as tmp:
        seq = os.path.join(tmp, "seq")
        common = ["--frames", "2", "--laps", "1", "--width", "16", "--height", "16"]
        subprocess.run([exe, "synth", "-o", seq, *common, "--ros1-bag", os.path.join(tmp, "a.bag"),
                        "--ros2-bag", os.path.join(tmp, "mcap"), "--ros2-storage", "mcap", "--bag-images", "jpeg"],
                       check=True, capture_output=True)
        subprocess.run([exe, "synth", "-o", os.path.join(tmp, "seq2"), *common, "--ros1-bag", os.path.join(tmp, "raw.bag"),
                        "--ros2-bag", os.path.join(tmp, "sqlite"), "--ros2-storage", "sqlite3", "--bag-images", "rgb8"],
                       check=True, capture_output=True)
        first_png = os.path.join(seq, "rgb", sorted(os.listdir(os.path.join(seq, "rgb")))[0])
        png = open(first_png, "rb").read()
        PIL.Image.open(first_png).convert("RGB").save(os.path.join(tmp, "a.jpg"), quality=80)
        jpeg = open(os.path.join(tmp, "a.jpg"), "rb").read()
        put("compressed_image", "ros1_jpeg", b"\0" + compressed_ros1(b"jpeg", jpeg))
        put("compressed_image", "cdr_png", b"\1" + compressed_cdr(b"rgb8; png compressed bgr8", png))
        put("compressed_image", "raw_jpeg", b"\2" + jpeg)
        put("compressed_image", "raw_png", b"\5" + png)
        put("ros1_bag", "lz4_jpeg.bag", open(os.path.join(tmp, "a.bag"), "rb").read())
        put("ros1_bag", "lz4_rgb8.bag", open(os.path.join(tmp, "raw.bag"), "rb").read())
        for d, target, ext in [("mcap", "mcap", ".mcap"), ("sqlite", "ros2_sqlite", ".db3")]:
            storage = [f for f in os.listdir(os.path.join(tmp, d)) if f.endswith(ext)][0]
            put(target, "two_frames" + ext, open(os.path.join(tmp, d, storage), "rb").read())

    put("tum", "two_frames", b"# timestamp filename\n1.0 a.png\n1.5 a.png\n\0# gt\n1.0 0 0 0 0 0 0 1\n1.5 0.1 0 0 0 0 0.7071068 0.7071068\n")
    put("tflite", "one_conv.tflite", tflite_model())
    put("safetensors", "tiny.safetensors", safetensors_file(
        {"format": "ecm-lcd-weights/1", "arch": "ecmobilenet", "classes": "10"},
        {"stem.weight": ("F32", [2, 3, 1, 1], struct.pack("<6f", *range(6))), "head.bias": ("F16", [2], b"\0<\0<")}))
    put("params_yaml", "node.yaml", b"/ecm_lcd:\n  ros__parameters:\n    detector:\n      min_score: 0.5\n      min_history: 3\n    descriptor:\n      mode: paper\n    input_size: 160\n")
    put("params_yaml", "wildcard.yaml", b"/**:\n  ros__parameters:\n    detector.exclude_recent.seconds: 2.0\n    selection.every_nth: 2\n")
    total = sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(CORPUS) for f in fs)
    print(f"seed corpus written to {CORPUS}: {total} bytes")


if __name__ == "__main__":
    main()
