"""A parameter client on Eclipse Cyclone DDS (not RustDDS) that frames its requests as one ROS 2 RMW does.

Usage: cyclone_params.py bare|cyclone NODE   (NODE: the node's name, e.g. ecm_lcd)
  bare:    the request alone, as rmw_fastrtps puts it on the wire (minus its inline QoS)
  cyclone: rmw_cyclonedds_cpp's 16-byte header {uint64 client guid, int64 sequence} first; the reply
           must carry the same header.
Calls list_parameters, describe_parameters, set_parameters (an invalid detector.min_score 7.0, then
0.85) and get_parameters, printing one line per answer:
  LIST <count> <names containing detector.min_score: yes|no>
  DESCRIBE <name> <description non-empty: yes|no> <floating-point range from..to>
  SET <successful 0|1> <reason>
  GET <type> <double value>
Types use the ROS 2 DDS names and plain CDR (XCDR1), as rmw_cyclonedds does.
"""
import sys
import time
from dataclasses import dataclass

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, int64, sequence, uint8, uint64
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

FRAMING = sys.argv[1]
NODE = sys.argv[2]
CYCLONE = FRAMING == "cyclone"
PREFIX = "rcl_interfaces::msg::dds_::"
SRV = "rcl_interfaces::srv::dds_::"


@dataclass
class ParameterValue(IdlStruct, typename=PREFIX + "ParameterValue_"):
    type: uint8
    bool_value: bool
    integer_value: int64
    double_value: float64
    string_value: str
    byte_array_value: sequence[uint8]
    bool_array_value: sequence[bool]
    integer_array_value: sequence[int64]
    double_array_value: sequence[float64]
    string_array_value: sequence[str]


@dataclass
class Parameter(IdlStruct, typename=PREFIX + "Parameter_"):
    name: str
    value: ParameterValue


@dataclass
class SetParametersResult(IdlStruct, typename=PREFIX + "SetParametersResult_"):
    successful: bool
    reason: str


@dataclass
class ListParametersResult(IdlStruct, typename=PREFIX + "ListParametersResult_"):
    names: sequence[str]
    prefixes: sequence[str]


@dataclass
class FloatingPointRange(IdlStruct, typename=PREFIX + "FloatingPointRange_"):
    from_value: float64
    to_value: float64
    step: float64


@dataclass
class IntegerRange(IdlStruct, typename=PREFIX + "IntegerRange_"):
    from_value: int64
    to_value: int64
    step: uint64


@dataclass
class ParameterDescriptor(IdlStruct, typename=PREFIX + "ParameterDescriptor_"):
    name: str
    type: uint8
    description: str
    additional_constraints: str
    read_only: bool
    dynamic_typing: bool
    floating_point_range: sequence[FloatingPointRange]
    integer_range: sequence[IntegerRange]


# Each service's request and response, with rmw_cyclonedds's header fields first when framed so.
if CYCLONE:
    @dataclass
    class SetRequest(IdlStruct, typename=SRV + "SetParameters_Request_"):
        guid: uint64
        seq: int64
        parameters: sequence[Parameter]

    @dataclass
    class SetResponse(IdlStruct, typename=SRV + "SetParameters_Response_"):
        guid: uint64
        seq: int64
        results: sequence[SetParametersResult]

    @dataclass
    class GetRequest(IdlStruct, typename=SRV + "GetParameters_Request_"):
        guid: uint64
        seq: int64
        names: sequence[str]

    @dataclass
    class GetResponse(IdlStruct, typename=SRV + "GetParameters_Response_"):
        guid: uint64
        seq: int64
        values: sequence[ParameterValue]

    @dataclass
    class ListRequest(IdlStruct, typename=SRV + "ListParameters_Request_"):
        guid: uint64
        seq: int64
        prefixes: sequence[str]
        depth: uint64

    @dataclass
    class ListResponse(IdlStruct, typename=SRV + "ListParameters_Response_"):
        guid: uint64
        seq: int64
        result: ListParametersResult

    @dataclass
    class DescribeRequest(IdlStruct, typename=SRV + "DescribeParameters_Request_"):
        guid: uint64
        seq: int64
        names: sequence[str]

    @dataclass
    class DescribeResponse(IdlStruct, typename=SRV + "DescribeParameters_Response_"):
        guid: uint64
        seq: int64
        descriptors: sequence[ParameterDescriptor]
else:
    @dataclass
    class SetRequest(IdlStruct, typename=SRV + "SetParameters_Request_"):
        parameters: sequence[Parameter]

    @dataclass
    class SetResponse(IdlStruct, typename=SRV + "SetParameters_Response_"):
        results: sequence[SetParametersResult]

    @dataclass
    class GetRequest(IdlStruct, typename=SRV + "GetParameters_Request_"):
        names: sequence[str]

    @dataclass
    class GetResponse(IdlStruct, typename=SRV + "GetParameters_Response_"):
        values: sequence[ParameterValue]

    @dataclass
    class ListRequest(IdlStruct, typename=SRV + "ListParameters_Request_"):
        prefixes: sequence[str]
        depth: uint64

    @dataclass
    class ListResponse(IdlStruct, typename=SRV + "ListParameters_Response_"):
        result: ListParametersResult

    @dataclass
    class DescribeRequest(IdlStruct, typename=SRV + "DescribeParameters_Request_"):
        names: sequence[str]

    @dataclass
    class DescribeResponse(IdlStruct, typename=SRV + "DescribeParameters_Response_"):
        descriptors: sequence[ParameterDescriptor]

QOS = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)),
    Policy.Durability.Volatile,
    Policy.History.KeepLast(16),
    Policy.DataRepresentation(use_cdrv0_representation=True),
)
PARTICIPANT = DomainParticipant(0)
GUID = 0x0123456789ABCDEF
SEQUENCE = [0]


def service(name, request_type, response_type):
    writer = DataWriter(PARTICIPANT, Topic(PARTICIPANT, f"rq/{NODE}/{name}Request", request_type), qos=QOS)
    reader = DataReader(PARTICIPANT, Topic(PARTICIPANT, f"rr/{NODE}/{name}Reply", response_type), qos=QOS)
    deadline = time.time() + 20
    while writer.get_publication_matched_status().current_count == 0 or \
            reader.get_subscription_matched_status().current_count == 0:
        if time.time() > deadline:
            print(f"PEER-ERROR {name}: no match with the node", flush=True)
            sys.exit(2)
        time.sleep(0.05)
    time.sleep(0.2)
    return writer, reader


def call(endpoints, request_type, **fields):
    writer, reader = endpoints
    SEQUENCE[0] += 1
    if CYCLONE:
        fields = dict(guid=GUID, seq=SEQUENCE[0], **fields)
    writer.write(request_type(**fields))
    deadline = time.time() + 10
    while time.time() < deadline:
        for reply in reader.take(N=4):
            if CYCLONE and (reply.guid != GUID or reply.seq != SEQUENCE[0]):
                print(f"PEER-ERROR a reply with header {reply.guid:x}/{reply.seq}", flush=True)
                continue
            return reply
        time.sleep(0.02)
    print(f"PEER-ERROR no reply to {request_type.__name__}", flush=True)
    sys.exit(3)


def double(value):
    return ParameterValue(type=3, bool_value=False, integer_value=0, double_value=value, string_value="",
                          byte_array_value=[], bool_array_value=[], integer_array_value=[],
                          double_array_value=[], string_array_value=[])


def main():
    listing = service("list_parameters", ListRequest, ListResponse)
    describe = service("describe_parameters", DescribeRequest, DescribeResponse)
    setting = service("set_parameters", SetRequest, SetResponse)
    getting = service("get_parameters", GetRequest, GetResponse)
    names = call(listing, ListRequest, prefixes=[], depth=0).result.names
    print(f"LIST {len(names)} {'yes' if 'detector.min_score' in names else 'no'}", flush=True)
    for d in call(describe, DescribeRequest, names=["detector.min_score"]).descriptors:
        ranges = " ".join(f"{r.from_value}..{r.to_value}" for r in d.floating_point_range)
        print(f"DESCRIBE {d.name} {'yes' if d.description else 'no'} {ranges}", flush=True)
    for value in [7.0, 0.85]:
        for r in call(setting, SetRequest, parameters=[Parameter(name="detector.min_score",
                                                                  value=double(value))]).results:
            print(f"SET {int(r.successful)} {r.reason}", flush=True)
    for v in call(getting, GetRequest, names=["detector.min_score"]).values:
        print(f"GET {v.type} {v.double_value}", flush=True)
    print("PEER-DONE", flush=True)


if __name__ == "__main__":
    main()
