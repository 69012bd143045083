//! A ROS 2 service server that answers both request framings ROS 2 RMWs put on the wire.
//!
//! rmw_fastrtps (and rmw_connextdds) send the bare request and carry the request id in the DATA
//! message's inline QoS (related sample identity); rmw_cyclonedds_cpp puts a 16-byte header before
//! the request (the lower 8 bytes of the client's GUID and a 64-bit sequence number) and expects the
//! same header before the reply. ros2-client's `Server` is built for one mapping, so a node serving
//! one of them leaves users of the other hanging. This server reads the raw payload and decides per
//! request: the request is decoded bare and, failing that, after a Cyclone header; a decoding counts
//! only if it consumes the whole payload (up to CDR's final padding of at most 3 bytes). A Cyclone
//! header never passes as a bare request: its GUID bytes would have to be a request that ends
//! exactly where the payload does (the unit test covers the zero GUID a bare-only server misread as
//! an empty request). A payload that decodes neither way is logged as a warning with its size and
//! first bytes; with no request id to answer to, it gets no reply.
//!
//! The reply goes out in the request's framing, with the related sample identity in the inline QoS
//! as well (harmless to Cyclone clients, needed by Fast DDS ones).
//!
//! The reader and writer are created on the participant directly: ros2-client 0.12 offers no way to
//! attach them to a node's `ros_discovery_info`, so graph tools see the service by its topic names
//! but not under the node.

use std::marker::PhantomData;

use anyhow::{anyhow, Result};
use log::warn;
use ros2_client::dds::rustdds::{
    self, bytes::Bytes, mio1, no_key, policy, serialization, QosPolicies, QosPolicyBuilder, RepresentationIdentifier,
    SampleIdentity, SequenceNumber, Timestamp, TopicKind, WriteOptionsBuilder, GUID,
};
use ros2_client::{Context, Message};
use serde::{Deserialize, Serialize};

/// How a request arrived, and so how its reply is framed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Framing {
    /// No header; the request id travels in the inline QoS (rmw_fastrtps, rmw_connextdds).
    Bare,
    /// The 16-byte header of rmw_cyclonedds_cpp.
    CycloneHeader,
}

/// rmw_cyclonedds_cpp's request and reply header (`cdds_request_header_t`: the client's GUID as a
/// `uint64`, its lower 8 bytes, and the request's `int64` sequence number). Echoed byte for byte.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CycloneHeader {
    pub guid_low: [u8; 8],
    pub sequence: i64,
}

impl Message for CycloneHeader {}

/// Size of [`CycloneHeader`] on the wire.
const CYCLONE_HEADER_LEN: usize = 16;

/// Where a request came from: what its reply must echo.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RequestId {
    pub framing: Framing,
    /// The identity the reply names in its inline QoS.
    pub sample: SampleIdentity,
    /// The Cyclone header to echo (for [`Framing::CycloneHeader`]).
    pub header: Option<CycloneHeader>,
}

/// Serialized data after the encapsulation header, as received or to send.
#[derive(Clone, Debug)]
pub struct Payload {
    bytes: Bytes,
    encoding: RepresentationIdentifier,
}

/// Passes payloads through unchanged (the framing is decided above the DDS layer).
pub struct PayloadAdapter;

#[derive(Debug, thiserror::Error)]
#[error("payload adapter: {0}")]
pub struct PayloadError(String);

impl no_key::DeserializerAdapter<Payload> for PayloadAdapter {
    type Error = PayloadError;
    type Decoded = Payload;

    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &[RepresentationIdentifier::CDR_LE, RepresentationIdentifier::CDR_BE]
    }

    fn transform_decoded(decoded: Payload) -> Payload {
        decoded
    }
}

#[derive(Clone)]
pub struct PayloadDecoder;

impl<'de> no_key::Decode<'de, Payload> for PayloadDecoder {
    type Error = PayloadError;

    fn decode_bytes(self, input: &'de [u8], encoding: RepresentationIdentifier) -> Result<Payload, PayloadError> {
        Ok(Payload { bytes: Bytes::copy_from_slice(input), encoding })
    }
}

impl no_key::DefaultDecoder<Payload> for PayloadAdapter {
    type Decoder = PayloadDecoder;
    const DECODER: PayloadDecoder = PayloadDecoder;
}

impl no_key::SerializerAdapter<Payload> for PayloadAdapter {
    type Error = PayloadError;

    fn output_encoding() -> RepresentationIdentifier {
        RepresentationIdentifier::CDR_LE
    }

    fn to_bytes(value: &Payload) -> Result<Bytes, PayloadError> {
        Ok(value.bytes.clone())
    }
}

/// Decodes `T` from `bytes`, and only if that consumes all of them (CDR pads the end to a multiple of 4).
fn decode_exactly<T: for<'de> Deserialize<'de>>(bytes: &[u8], encoding: RepresentationIdentifier) -> Option<T> {
    let (value, used) = serialization::deserialize_from_cdr_with_rep_id::<T>(bytes, encoding).ok()?;
    (bytes.len() >= used && bytes.len() - used <= 3).then_some(value)
}

/// A request's framing, id and value (module doc: how the framing is decided); `None` if it decodes neither way.
pub fn decode_request<R: for<'de> Deserialize<'de>>(
    payload: &[u8],
    encoding: RepresentationIdentifier,
    inline_identity: Option<SampleIdentity>,
    own_identity: SampleIdentity,
) -> Option<(RequestId, R)> {
    // The id a bare request's reply names: the related sample identity where the client sent one
    // (Fast DDS; it may leave the sequence number unknown, meaning the request's own), else the
    // request sample's own identity.
    let bare_sample = match inline_identity {
        Some(mut identity) => {
            if identity.sequence_number == SequenceNumber::UNKNOWN {
                identity.sequence_number = own_identity.sequence_number;
            }
            identity
        }
        None => own_identity,
    };
    if let Some(request) = decode_exactly::<R>(payload, encoding) {
        return Some((RequestId { framing: Framing::Bare, sample: bare_sample, header: None }, request));
    }
    let header: CycloneHeader =
        serialization::deserialize_from_cdr_with_rep_id::<CycloneHeader>(payload.get(..CYCLONE_HEADER_LEN)?, encoding)
            .ok()?
            .0;
    let request = decode_exactly::<R>(&payload[CYCLONE_HEADER_LEN..], encoding)?;
    // The client's GUID: its upper half is the request writer's (its participant's) prefix.
    let mut guid = own_identity.writer_guid.to_bytes();
    guid[8..].copy_from_slice(&header.guid_low);
    let sample =
        SampleIdentity { writer_guid: GUID::from_bytes(guid), sequence_number: SequenceNumber::from(header.sequence) };
    Some((RequestId { framing: Framing::CycloneHeader, sample, header: Some(header) }, request))
}

/// The reply payload for `id`: `response` after the Cyclone header where the request had one.
pub fn encode_reply<S: Serialize>(id: &RequestId, response: &S) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    if let (Framing::CycloneHeader, Some(header)) = (id.framing, &id.header) {
        serialization::to_writer_with_rep_id(&mut out, header, RepresentationIdentifier::CDR_LE)
            .map_err(|e| anyhow!("encoding the reply header: {e}"))?;
    }
    serialization::to_writer_with_rep_id(&mut out, response, RepresentationIdentifier::CDR_LE)
        .map_err(|e| anyhow!("encoding the reply: {e}"))?;
    Ok(out)
}

/// A service `name` (e.g. `/ecm_lcd/set_parameters`) of type `package/Type`, both framings.
pub struct FramedServer<Req, Resp> {
    requests: no_key::SimpleDataReader<Payload, PayloadAdapter>,
    replies: no_key::DataWriter<Payload, PayloadAdapter>,
    name: String,
    types: PhantomData<(Req, Resp)>,
}

impl<Req: for<'de> Deserialize<'de>, Resp: Serialize> FramedServer<Req, Resp> {
    /// `name` is the fully qualified service name; `package` and `type_name` its type
    /// (`rcl_interfaces`, `SetParameters`).
    pub fn new(context: &Context, name: &str, package: &str, type_name: &str) -> Result<Self> {
        let participant = context.domain_participant();
        let qos: QosPolicies = QosPolicyBuilder::new()
            .reliability(policy::Reliability::Reliable { max_blocking_time: rustdds::Duration::from_millis(100) })
            .durability(policy::Durability::Volatile)
            .history(policy::History::KeepLast { depth: 16 })
            .build();
        let relative = name.trim_start_matches('/');
        // ROS 2's DDS names: `rq/<name>Request` of `pkg::srv::dds_::Type_Request_`, `rr/<name>Reply`
        // of `pkg::srv::dds_::Type_Response_`.
        let topic = |kind: &str, topic_suffix: &str, type_suffix: &str| {
            participant.create_topic(
                format!("{kind}/{relative}{topic_suffix}"),
                format!("{package}::srv::dds_::{type_name}_{type_suffix}_"),
                &qos,
                TopicKind::NoKey,
            )
        };
        let request_topic = topic("rq", "Request", "Request").map_err(|e| anyhow!("service {name}: {e:?}"))?;
        let reply_topic = topic("rr", "Reply", "Response").map_err(|e| anyhow!("service {name}: {e:?}"))?;
        let subscriber = participant.create_subscriber(&qos).map_err(|e| anyhow!("service {name}: {e:?}"))?;
        let publisher = participant.create_publisher(&qos).map_err(|e| anyhow!("service {name}: {e:?}"))?;
        Ok(FramedServer {
            requests: subscriber
                .create_simple_datareader_no_key::<Payload, PayloadAdapter>(&request_topic, None)
                .map_err(|e| anyhow!("service {name}: {e:?}"))?,
            replies: publisher
                .create_datawriter_no_key::<Payload, PayloadAdapter>(&reply_topic, None)
                .map_err(|e| anyhow!("service {name}: {e:?}"))?,
            name: name.to_string(),
            types: PhantomData,
        })
    }

    /// The next waiting request that decodes; undecodable ones are logged and skipped.
    pub fn receive(&self) -> Option<(RequestId, Req)> {
        self.requests.drain_read_notifications();
        loop {
            let change = match self.requests.try_take_one() {
                Ok(Some(change)) => change,
                Ok(None) => return None,
                Err(e) => {
                    warn!("{}: cannot read a request: {e:?}", self.name);
                    continue;
                }
            };
            let own = SampleIdentity { writer_guid: change.writer_guid, sequence_number: change.sequence_number };
            let payload = &change.sample;
            match decode_request::<Req>(&payload.bytes, payload.encoding, change.write_options.related_sample_identity(), own)
            {
                Some(found) => return Some(found),
                None => warn!(
                    "{}: a request of {} bytes decodes neither bare nor with a Cyclone header (starts {:02x?}); not answered",
                    self.name,
                    payload.bytes.len(),
                    &payload.bytes[..payload.bytes.len().min(24)]
                ),
            }
        }
    }

    /// Sends `response` to the request `id`, framed as the request was.
    pub fn reply(&self, id: &RequestId, response: &Resp) -> Result<()> {
        let bytes = encode_reply(id, response)?;
        let options =
            WriteOptionsBuilder::new().source_timestamp(Timestamp::now()).related_sample_identity(id.sample).build();
        self.replies
            .write_with_options(
                Payload { bytes: Bytes::from(bytes), encoding: RepresentationIdentifier::CDR_LE },
                options,
            )
            .map(drop)
            .map_err(|e| anyhow!("{}: reply not sent: {e:?}", self.name))
    }
}

impl<Req, Resp> mio1::event::Source for FramedServer<Req, Resp> {
    fn register(
        &mut self,
        registry: &mio1::Registry,
        token: mio1::Token,
        interest: mio1::Interest,
    ) -> std::io::Result<()> {
        self.requests.register(registry, token, interest)
    }

    fn reregister(
        &mut self,
        registry: &mio1::Registry,
        token: mio1::Token,
        interest: mio1::Interest,
    ) -> std::io::Result<()> {
        self.requests.reregister(registry, token, interest)
    }

    fn deregister(&mut self, registry: &mio1::Registry) -> std::io::Result<()> {
        self.requests.deregister(registry)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_client::rcl_interfaces::GetParametersRequest;

    fn identity(sequence: i64) -> SampleIdentity {
        SampleIdentity { writer_guid: GUID::from_bytes([7; 16]), sequence_number: SequenceNumber::from(sequence) }
    }

    fn request(names: &[&str]) -> GetParametersRequest {
        GetParametersRequest { names: names.iter().map(|n| n.to_string()).collect() }
    }

    fn cdr<S: Serialize>(value: &S) -> Vec<u8> {
        let mut out = Vec::new();
        serialization::to_writer_with_rep_id(&mut out, value, RepresentationIdentifier::CDR_LE).unwrap();
        out
    }

    #[test]
    fn both_framings_are_recognised_and_answered_in_kind() {
        let le = RepresentationIdentifier::CDR_LE;
        for names in [&[][..], &["detector.min_score"][..], &["a", "bb", "ccc"][..]] {
            // Bare, with the id in the inline QoS (Fast DDS) or without (a plain DDS peer).
            let bare = cdr(&request(names));
            let (id, got) = decode_request::<GetParametersRequest>(&bare, le, Some(identity(9)), identity(3)).unwrap();
            assert_eq!((id.framing, got.names.len(), id.sample), (Framing::Bare, names.len(), identity(9)));
            let (id, _) = decode_request::<GetParametersRequest>(&bare, le, None, identity(3)).unwrap();
            assert_eq!((id.framing, id.sample), (Framing::Bare, identity(3)));
            assert_eq!(encode_reply(&id, &request(&["x"])).unwrap(), cdr(&request(&["x"])));

            // Cyclone: the header first, including a zero GUID half (read as an empty request by
            // a bare-only server).
            for guid_low in [[0u8; 8], [1, 2, 3, 4, 5, 6, 7, 8]] {
                let header = CycloneHeader { guid_low, sequence: 42 };
                let framed = [cdr(&header), cdr(&request(names))].concat();
                // ros2-client's Cyclone mapping also sends the id inline: the header still decides.
                let (with_inline, _) =
                    decode_request::<GetParametersRequest>(&framed, le, Some(identity(9)), identity(3)).unwrap();
                assert_eq!(with_inline.framing, Framing::CycloneHeader);
                let (id, got) = decode_request::<GetParametersRequest>(&framed, le, None, identity(3)).unwrap();
                assert_eq!(id.framing, Framing::CycloneHeader, "{names:?} {guid_low:?}");
                assert_eq!(got.names, request(names).names);
                assert_eq!(id.header, Some(header));
                assert_eq!(i64::from(id.sample.sequence_number), 42);
                assert_eq!(&id.sample.writer_guid.to_bytes()[8..], &guid_low);
                let reply = encode_reply(&id, &request(&["x"])).unwrap();
                assert_eq!(reply, [cdr(&header), cdr(&request(&["x"]))].concat());
            }
        }
        // Neither: too short for a header, and garbage.
        assert!(decode_request::<GetParametersRequest>(&[1, 2], le, None, identity(1)).is_none());
        assert!(decode_request::<GetParametersRequest>(&[0xff; 40], le, None, identity(1)).is_none());
    }
}
