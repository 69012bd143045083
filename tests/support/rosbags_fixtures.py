"""Independent bag fixtures for ecm-lcd's io tests, written and read with `rosbags` (PyPI).

  rosbags_fixtures.py write OUTDIR   writes ros1_none.bag, ros1_bz2.bag, ros1_lz4.bag,
                                     ros2_sqlite3/ and ros2_mcap/, each with one topic per
                                     image encoding (see TOPICS), FRAMES frames per topic,
                                     two depth topics (see DEPTH_TOPICS) and /camera_info
                                     (CAMERA_K, see camera_info_message).
  rosbags_fixtures.py tum-bag DIR BAG FX FY CX CY  writes TUM folder DIR (with depth.txt) as a
                                     ROS 1 bag laid out like TUM's bags (see tum_bag).
  rosbags_fixtures.py read BAG TOPIC prints one JSON line per message of TOPIC: header stamp,
                                     receive time, the message fields and sha256 of its data.

The pixel pattern is defined here and mirrored in tests/io_fixtures.rs (keep them in step).
Raw images carry row padding (step > width * bytes per pixel) filled with 0xAB. ROS 1 and
sqlite3 bags get their messages written out of time order (receive time still follows the
frame index), so readers must sort; MCAP is written in order.
"""
import hashlib
import io
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image as PilImage
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

WIDTH, HEIGHT, FRAMES = 16, 12, 5
PAD = 4
WRITE_ORDER_SHUFFLED = [0, 2, 1, 4, 3]
TOPICS = ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16_le", "mono16_be", "jpeg", "png"]
# Depth topics: every frame but DEPTH_MISSING has a depth image, stamped DEPTH_DELAY_NS after it.
DEPTH_TOPICS = ["depth16", "depth32"]
DEPTH_MISSING = 3
DEPTH_DELAY_NS = 7_000_000
# The calibration on /camera_info, beside every image topic: fx, fy, cx, cy.
CAMERA_K = (525.25, 526.5, 7.75, 5.5)


def header_stamp(i):
    return 1341847980 + i, 722988000 + i * 1001


def receive_time(i):
    sec, nsec = header_stamp(i)
    return sec * 10**9 + nsec + 5_000_000


def rgb_pattern(i):
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    r = (x * 13 + i * 29) & 255
    g = (y * 17 + i * 7) & 255
    b = (x * y * 3 + i) & 255
    return np.stack([r, g, b], axis=-1).astype(np.uint8)


def mono8_pattern(i):
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    return ((x * 9 + y * 14 + i * 5) & 255).astype(np.uint8)


def mono16_pattern(i):
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    return ((x * 2000 + y * 3000 + i * 111) & 0xFFFF).astype(np.uint16)


def padded(rows):
    """rows: (HEIGHT, row_bytes) uint8 -> bytes with PAD bytes of 0xAB after each row."""
    pad = np.full((rows.shape[0], PAD), 0xAB, dtype=np.uint8)
    return np.concatenate([rows, pad], axis=1).tobytes(), rows.shape[1] + PAD


def raw_fields(topic, i):
    rgb = rgb_pattern(i)
    big = 0
    if topic == "rgb8":
        rows = rgb
    elif topic == "bgr8":
        rows = rgb[..., ::-1]
    elif topic == "rgba8":
        rows = np.concatenate([rgb, np.full((HEIGHT, WIDTH, 1), 77, np.uint8)], axis=-1)
    elif topic == "bgra8":
        rows = np.concatenate([rgb[..., ::-1], np.full((HEIGHT, WIDTH, 1), 77, np.uint8)], axis=-1)
    elif topic == "mono8":
        rows = mono8_pattern(i)
    else:
        big = 1 if topic == "mono16_be" else 0
        rows = mono16_pattern(i).astype(">u2" if big else "<u2").view(np.uint8)
    data, step = padded(np.ascontiguousarray(rows).reshape(HEIGHT, -1))
    encoding = "mono16" if topic.startswith("mono16") else topic
    return encoding, big, step, data


def compressed_fields(topic, i):
    out = io.BytesIO()
    image = PilImage.fromarray(rgb_pattern(i), "RGB")
    if topic == "jpeg":
        # 4:4:4 so that the test measures decoding, not chroma subsampling of a busy 16x12 pattern.
        image.save(out, format="JPEG", quality=95, subsampling=0)
        return "rgb8; jpeg compressed bgr8", out.getvalue()
    image.save(out, format="PNG")
    return "png", out.getvalue()


def make_message(store, ros1, topic, i):
    types = store.types
    sec, nsec = header_stamp(i)
    stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    if ros1:
        header = types["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id="camera")
    else:
        header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="camera")
    if topic in ("jpeg", "png"):
        fmt, data = compressed_fields(topic, i)
        msg = types["sensor_msgs/msg/CompressedImage"](header=header, format=fmt, data=np.frombuffer(data, np.uint8))
        return "sensor_msgs/msg/CompressedImage", msg
    encoding, big, step, data = raw_fields(topic, i)
    msg = types["sensor_msgs/msg/Image"](
        header=header, height=HEIGHT, width=WIDTH, encoding=encoding, is_bigendian=big, step=step,
        data=np.frombuffer(data, np.uint8))
    return "sensor_msgs/msg/Image", msg


def depth_mm_pattern(i):
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    mm = (500 + x * 10 + y * 20 + i).astype(np.uint16)
    mm[0, 0] = 0  # unknown depth
    return mm


def make_depth_message(store, ros1, topic, i):
    """Depth of frame i, stamped 7 ms after its colour frame: depth16 is 16UC1 millimetres,
    big-endian; depth32 is 32FC1 metres, little-endian, with NaN as unknown."""
    types = store.types
    sec, nsec = header_stamp(i)
    stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec + DEPTH_DELAY_NS)
    if ros1:
        header = types["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id="depth")
    else:
        header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="depth")
    mm = depth_mm_pattern(i)
    if topic == "depth16":
        encoding, big, rows = "16UC1", 1, mm.astype(">u2").view(np.uint8)
    else:
        metres = (mm / 1000.0).astype("<f4")
        metres[0, 0] = np.nan
        encoding, big, rows = "32FC1", 0, metres.view(np.uint8)
    data, step = padded(np.ascontiguousarray(rows).reshape(HEIGHT, -1))
    msg = types["sensor_msgs/msg/Image"](
        header=header, height=HEIGHT, width=WIDTH, encoding=encoding, is_bigendian=big, step=step,
        data=np.frombuffer(data, np.uint8))
    return "sensor_msgs/msg/Image", msg


def camera_info_message(store, ros1, stamp_ns, frame_id, width, height, k, seq=0):
    """sensor_msgs/CameraInfo with intrinsics k = (fx, fy, cx, cy), plumb-bob distortion; the ROS 1
    type names its arrays D, K, R, P, the ROS 2 type d, k, r, p."""
    types = store.types
    stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    if ros1:
        header = types["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame_id)
    else:
        header = types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)
    fx, fy, cx, cy = k
    arrays = {
        "D": np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
        "K": np.array([fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]),
        "R": np.eye(3).ravel(),
        "P": np.array([fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]),
    }
    if not ros1:
        arrays = {name.lower(): value for name, value in arrays.items()}
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    msg = types["sensor_msgs/msg/CameraInfo"](header=header, height=height, width=width,
                                              distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                                              **arrays)
    return "sensor_msgs/msg/CameraInfo", msg


def msgtype_of(topic):
    return "sensor_msgs/msg/CompressedImage" if topic in ("jpeg", "png") else "sensor_msgs/msg/Image"


def write_ros1(path, compression):
    store = get_typestore(Stores.ROS1_NOETIC)
    writer = Ros1Writer(path)
    if compression is not None:
        writer.set_compression(compression)
    with writer:
        conns = {t: writer.add_connection("/" + t, msgtype_of(t), typestore=store) for t in TOPICS + DEPTH_TOPICS}
        info = writer.add_connection("/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        for i in WRITE_ORDER_SHUFFLED:
            msgtype, msg = camera_info_message(store, True, receive_time(i), "camera", WIDTH, HEIGHT, CAMERA_K, i)
            writer.write(info, receive_time(i), store.serialize_ros1(msg, msgtype))
            for t in TOPICS:
                msgtype, msg = make_message(store, True, t, i)
                writer.write(conns[t], receive_time(i), store.serialize_ros1(msg, msgtype))
            for t in DEPTH_TOPICS if i != DEPTH_MISSING else []:
                msgtype, msg = make_depth_message(store, True, t, i)
                writer.write(conns[t], receive_time(i) + DEPTH_DELAY_NS, store.serialize_ros1(msg, msgtype))


def write_ros2(path, plugin, order):
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Ros2Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {t: writer.add_connection("/" + t, msgtype_of(t), typestore=store) for t in TOPICS + DEPTH_TOPICS}
        info = writer.add_connection("/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        for i in order:
            msgtype, msg = camera_info_message(store, False, receive_time(i), "camera", WIDTH, HEIGHT, CAMERA_K)
            writer.write(info, receive_time(i), store.serialize_cdr(msg, msgtype))
            for t in TOPICS:
                msgtype, msg = make_message(store, False, t, i)
                writer.write(conns[t], receive_time(i), store.serialize_cdr(msg, msgtype))
            for t in DEPTH_TOPICS if i != DEPTH_MISSING else []:
                msgtype, msg = make_depth_message(store, False, t, i)
                writer.write(conns[t], receive_time(i) + DEPTH_DELAY_NS, store.serialize_cdr(msg, msgtype))


def write_all(out):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_ros1(out / "ros1_none.bag", None)
    write_ros1(out / "ros1_bz2.bag", Ros1Writer.CompressionFormat.BZ2)
    write_ros1(out / "ros1_lz4.bag", Ros1Writer.CompressionFormat.LZ4)
    write_ros2(out / "ros2_sqlite3", StoragePlugin.SQLITE3, WRITE_ORDER_SHUFFLED)
    write_ros2(out / "ros2_mcap", StoragePlugin.MCAP, range(FRAMES))


def tum_bag(tum_dir, out, k):
    """A TUM folder with depth as a ROS 1 bag laid out like TUM's own: rgb8 colour on
    /camera/rgb/image_color with its calibration k = (fx, fy, cx, cy) on /camera/rgb/camera_info,
    32FC1 metres on /camera/depth/image (NaN where unknown), header stamps and receive times from
    rgb.txt and depth.txt."""
    tum_dir = Path(tum_dir)
    store = get_typestore(Stores.ROS1_NOETIC)
    types = store.types

    def listing(name):
        lines = (tum_dir / name).read_text().splitlines()
        return [line.split() for line in lines if line.strip() and not line.startswith("#")]

    def message(stamp_text, frame_id, seq, encoding, step, data, height, width):
        sec, _, frac = stamp_text.partition(".")
        nsec = int((frac + "000000000")[:9])
        stamp = types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=nsec)
        header = types["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame_id)
        msg = types["sensor_msgs/msg/Image"](header=header, height=height, width=width, encoding=encoding,
                                             is_bigendian=0, step=step, data=np.frombuffer(data, np.uint8))
        return int(sec) * 10**9 + nsec, store.serialize_ros1(msg, "sensor_msgs/msg/Image")

    items = []
    for seq, (stamp, name) in enumerate(listing("rgb.txt")):
        rgb = np.asarray(PilImage.open(tum_dir / name).convert("RGB"))
        h, w, _ = rgb.shape
        items.append(("rgb", message(stamp, "rgb", seq, "rgb8", w * 3, rgb.tobytes(), h, w)))
        time = items[-1][1][0]
        msgtype, info = camera_info_message(store, True, time, "rgb", w, h, k, seq)
        items.append(("info", (time, store.serialize_ros1(info, msgtype))))
    for seq, (stamp, name) in enumerate(listing("depth.txt")):
        units = np.asarray(PilImage.open(tum_dir / name), dtype=np.uint16)
        metres = (units / 5000.0).astype("<f4")
        metres[units == 0] = np.nan
        h, w = units.shape
        items.append(("depth", message(stamp, "depth", seq, "32FC1", w * 4, metres.tobytes(), h, w)))
    items.sort(key=lambda item: item[1][0])
    with Ros1Writer(Path(out)) as writer:
        conns = {
            "rgb": writer.add_connection("/camera/rgb/image_color", "sensor_msgs/msg/Image", typestore=store),
            "depth": writer.add_connection("/camera/depth/image", "sensor_msgs/msg/Image", typestore=store),
            "info": writer.add_connection("/camera/rgb/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store),
        }
        for kind, (time, raw) in items:
            writer.write(conns[kind], time, raw)


def read(bag, topic):
    store = get_typestore(Stores.ROS2_HUMBLE)
    with AnyReader([Path(bag)], default_typestore=store) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            raise SystemExit(f"no topic {topic} in {bag}: {[c.topic for c in reader.connections]}")
        for conn, timestamp, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            line = {
                "msgtype": conn.msgtype,
                "receive_time": timestamp,
                "sec": msg.header.stamp.sec,
                "nanosec": msg.header.stamp.nanosec,
                "sha256": hashlib.sha256(bytes(msg.data)).hexdigest(),
            }
            if hasattr(msg, "encoding"):
                line.update(encoding=msg.encoding, width=msg.width, height=msg.height, step=msg.step,
                            is_bigendian=msg.is_bigendian)
            else:
                line.update(format=msg.format)
            print(json.dumps(line))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "write":
        write_all(sys.argv[2])
    elif len(sys.argv) == 8 and sys.argv[1] == "tum-bag":
        tum_bag(sys.argv[2], sys.argv[3], tuple(float(v) for v in sys.argv[4:8]))
    elif len(sys.argv) == 4 and sys.argv[1] == "read":
        read(sys.argv[2], sys.argv[3])
    else:
        raise SystemExit(__doc__)
