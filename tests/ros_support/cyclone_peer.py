"""An independent DDS peer (Eclipse Cyclone DDS, not RustDDS) for the ecm-lcd node test.

Publishes sensor_msgs/Image (rgb8) on rt/image and prints every ecm_lcd_msgs/LoopCandidate received on
rt/loop_candidates as `CANDIDATE query match rank score query_sec match_sec match_frame_id query_nanosec
match_nanosec`, then the newest diagnostic_msgs/DiagnosticArray from rt/diagnostics as
`DIAG level hardware_id message key=value ...`.
Types are declared with the ROS 2 DDS names (`pkg::msg::dds_::Type_`) and plain CDR (XCDR1), as
rmw_cyclonedds does.
Usage: cyclone_peer.py EXPECTED_CANDIDATES GREY [GREY ...]   (solid 32x24 images of those grey levels)
       cyclone_peer.py EXPECTED_CANDIDATES --frames LIST       (LIST: lines `sec nanosec width height FILE`
           with FILE raw rgb8 bytes beside LIST, or `MALFORMED short|encoding` for a broken image)
"""
import os
import sys
import time
from dataclasses import dataclass

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float32, float64, int32, sequence, uint8, uint32, uint64
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header
    height: uint32
    width: uint32
    encoding: str
    is_bigendian: uint8
    step: uint32
    data: sequence[uint8]


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
class LoopCandidate(IdlStruct, typename="ecm_lcd_msgs::msg::dds_::LoopCandidate_"):
    header: Header
    query_id: uint64
    match_id: uint64
    match_stamp: Time
    match_frame_id: str
    distance: float32
    score: float32
    rank: uint32
    num_candidates: uint32
    type: uint8
    descriptor_mode: str
    inliers: uint32
    relative_pose: Pose
    covariance: array[float64, 36]


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: uint8
    name: str
    message: str
    hardware_id: str
    values: sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header
    status: sequence[DiagnosticStatus]


def frames_from_list(path):
    """Images from a frame list (see the module doc); broken ones where it says MALFORMED."""
    images = []
    folder = os.path.dirname(path)
    with open(path) as lines:
        for line in lines:
            fields = line.split()
            header = Header(stamp=Time(sec=0, nanosec=0), frame_id="cyclone_cam")
            if fields[0] == "MALFORMED":
                # short: step * height is larger than the data; encoding: one the node does not know.
                data = [7] * (8 * 6 * 3)
                if fields[1] == "short":
                    images.append(Image(header=header, height=6, width=8, encoding="rgb8", is_bigendian=0,
                                        step=8 * 3, data=data[:50]))
                else:
                    images.append(Image(header=header, height=6, width=8, encoding="yuv_unknown", is_bigendian=0,
                                        step=8 * 3, data=data))
                continue
            sec, nanosec, width, height, name = fields
            with open(os.path.join(folder, name), "rb") as f:
                data = list(f.read())
            header.stamp = Time(sec=int(sec), nanosec=int(nanosec))
            images.append(Image(header=header, height=int(height), width=int(width), encoding="rgb8",
                                is_bigendian=0, step=int(width) * 3, data=data))
    return images


def main():
    expected = int(sys.argv[1])
    if sys.argv[2] == "--frames":
        images = frames_from_list(sys.argv[3])
    else:
        width, height = 32, 24
        images = [Image(header=Header(stamp=Time(sec=500 + i, nanosec=0), frame_id="cyclone_cam"), height=height,
                        width=width, encoding="rgb8", is_bigendian=0, step=width * 3,
                        data=[int(grey)] * (width * height * 3))
                  for i, grey in enumerate(sys.argv[2:])]
    qos = Qos(
        Policy.Reliability.Reliable(duration(milliseconds=100)),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(10),
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )
    dp = DomainParticipant(0)
    writer = DataWriter(dp, Topic(dp, "rt/image", Image), qos=qos)
    reader = DataReader(dp, Topic(dp, "rt/loop_candidates", LoopCandidate), qos=qos)
    diagnostics = DataReader(dp, Topic(dp, "rt/diagnostics", DiagnosticArray), qos=qos)
    deadline = time.time() + 20
    while writer.get_publication_matched_status().current_count == 0 or \
            reader.get_subscription_matched_status().current_count == 0:
        if time.time() > deadline:
            print("PEER-ERROR no match with the node", flush=True)
            sys.exit(2)
        time.sleep(0.05)
    time.sleep(0.3)
    got = 0

    def drain():
        # Taken while publishing too: the reader keeps only the last 10.
        taken = 0
        for c in reader.take(N=16):
            print(f"CANDIDATE {c.query_id} {c.match_id} {c.rank} {c.score:.3f} {c.header.stamp.sec} "
                  f"{c.match_stamp.sec} {c.match_frame_id} {c.header.stamp.nanosec} {c.match_stamp.nanosec}",
                  flush=True)
            taken += 1
        return taken

    for image in images:
        writer.write(image)
        time.sleep(0.05)
        got += drain()
    deadline = time.time() + 20
    while got < expected and time.time() < deadline:
        got += drain()
        time.sleep(0.05)
    # The node's /diagnostics (published every second): the first one published after the candidates
    # arrived (older ones are discarded), as one line.
    diagnostics.take(N=64)
    last = None
    deadline = time.time() + 5
    while last is None and time.time() < deadline:
        for array in diagnostics.take(N=16):
            last = array
        time.sleep(0.05)
    for array in diagnostics.take(N=16):
        last = array
    if last is not None:
        for status in last.status:
            values = " ".join(f"{kv.key}={kv.value}" for kv in status.values)
            print(f"DIAG {status.level} {status.hardware_id} {status.message} {values}", flush=True)
    print(f"PEER-DONE {got}", flush=True)


if __name__ == "__main__":
    main()
