//! Service calls between sites, as the bridges carry them on Zenoh.
//!
//! On the caller's site, the bridge answers for the servers of other sites
//! that it makes present there (`pulicast::ServerBuilder::serve_for`): a
//! call to one of them becomes a Zenoh query to the bridge of the server's
//! site, on `<prefix>/@puli/call/<key>`, carrying a [`CallRequest`]. That
//! bridge calls the server on its site (with the caller's remaining
//! deadline) and answers the query with a [`CallAnswer`] per progress
//! message, then one with the reply or the failure. A call the caller
//! cancels is cancelled there by a [`CallCancel`] put on
//! `<prefix>/@puli/cancel/<key>`.
//!
//! Each is `PBCL`, a version byte (1), then the value in postcard.

use pulicast::MAX_MESSAGE;
use serde::{Deserialize, Serialize};

const MAGIC: [u8; 4] = *b"PBCL";
const VERSION: u8 = 1;

/// Longest service or node name taken.
pub const MAX_NAME: usize = 255;

/// A call for a server of the receiving bridge's site.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CallRequest {
    /// The calling bridge's session key.
    pub bridge: i64,
    /// The call's number at that bridge (for a cancel).
    pub id: u64,
    /// The service's full name (`rover1/plan`).
    pub service: String,
    /// The server's node name.
    pub target: String,
    /// What is left of the caller's deadline, in milliseconds.
    pub deadline_ms: u32,
    /// The request message, fingerprint first.
    pub message: Vec<u8>,
}

/// One answer to a [`CallRequest`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum CallAnswer {
    /// A progress message, in order.
    Progress(Vec<u8>),
    /// The reply: the call is done.
    Reply(Vec<u8>),
    /// The call failed: the server's failure, or why the bridge could not
    /// run it (code `UNREACHABLE`).
    Failure {
        /// The failure code (`pulicast::Fault`'s constants).
        code: u16,
        /// Why.
        message: String,
    },
}

/// A caller cancelled a call.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CallCancel {
    /// The calling bridge.
    pub bridge: i64,
    /// The call's number there.
    pub id: u64,
}

/// Why call bytes were refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadCall(pub String);

impl std::fmt::Display for BadCall {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "bad call from Zenoh: {}", self.0)
    }
}

fn encode<T: Serialize>(value: &T) -> Vec<u8> {
    let mut out = MAGIC.to_vec();
    out.push(VERSION);
    postcard::to_extend(value, out).unwrap_or_default()
}

/// Decodes a value, refusing more bytes than a message and its names need
/// before it costs memory.
fn decode<'a, T: Deserialize<'a>>(bytes: &'a [u8]) -> Result<T, BadCall> {
    if bytes.len() > MAX_MESSAGE + 4 * MAX_NAME + 64 {
        return Err(BadCall("too large".into()));
    }
    let body = bytes
        .strip_prefix(&MAGIC)
        .and_then(|rest| rest.strip_prefix(&[VERSION]))
        .ok_or_else(|| BadCall("not a call (magic or version)".into()))?;
    let (value, rest) = postcard::take_from_bytes::<T>(body).map_err(|e| BadCall(e.to_string()))?;
    if !rest.is_empty() {
        return Err(BadCall(format!("{} trailing bytes", rest.len())));
    }
    Ok(value)
}

impl CallRequest {
    /// The bytes.
    pub fn encode(&self) -> Vec<u8> {
        encode(self)
    }

    /// Reads a request; names over [`MAX_NAME`] and messages over
    /// pulicast's largest are refused.
    pub fn decode(bytes: &[u8]) -> Result<Self, BadCall> {
        let request: CallRequest = decode(bytes)?;
        if request.service.len() > MAX_NAME || request.target.len() > MAX_NAME {
            return Err(BadCall("a name too long".into()));
        }
        if request.message.len() > MAX_MESSAGE {
            return Err(BadCall("a message too large".into()));
        }
        Ok(request)
    }
}

impl CallAnswer {
    /// The bytes.
    pub fn encode(&self) -> Vec<u8> {
        encode(self)
    }

    /// Reads an answer.
    pub fn decode(bytes: &[u8]) -> Result<Self, BadCall> {
        decode(bytes)
    }
}

impl CallCancel {
    /// The bytes.
    pub fn encode(&self) -> Vec<u8> {
        encode(self)
    }

    /// Reads a cancel.
    pub fn decode(bytes: &[u8]) -> Result<Self, BadCall> {
        decode(bytes)
    }
}

/// A service's full name from its request channel (`rover1/.services/plan`
/// is `rover1/plan`), if the channel is one.
pub fn service_of(request_channel: &str) -> Option<String> {
    let (namespace, name) = match request_channel.rsplit_once("/.services/") {
        Some((ns, name)) => (ns, name),
        None => ("", request_channel.strip_prefix(".services/")?),
    };
    if name.is_empty() || name.contains('/') || name.contains('@') {
        return None;
    }
    Some(match namespace {
        "" => name.to_owned(),
        ns => format!("{ns}/{name}"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calls_round_trip_and_junk_is_refused() {
        let request = CallRequest {
            bridge: -3,
            id: 9,
            service: "rover1/plan".into(),
            target: "planner".into(),
            deadline_ms: 1500,
            message: vec![1, 2, 3],
        };
        let bytes = request.encode();
        assert_eq!(CallRequest::decode(&bytes), Ok(request.clone()));
        for len in 0..bytes.len() {
            assert!(CallRequest::decode(&bytes[..len]).is_err());
        }
        let mut long = request;
        long.target = "t".repeat(MAX_NAME + 1);
        assert!(CallRequest::decode(&long.encode()).is_err());
        for answer in [
            CallAnswer::Progress(vec![7]),
            CallAnswer::Reply(vec![]),
            CallAnswer::Failure {
                code: 8,
                message: "gone".into(),
            },
        ] {
            assert_eq!(CallAnswer::decode(&answer.encode()), Ok(answer));
        }
        let cancel = CallCancel { bridge: 1, id: 2 };
        assert_eq!(CallCancel::decode(&cancel.encode()), Ok(cancel));
        assert!(CallCancel::decode(b"PBCL\x02").is_err());
        assert!(CallAnswer::decode(&vec![0; MAX_MESSAGE * 2]).is_err());
    }

    #[test]
    fn services_are_named_from_their_request_channels() {
        assert_eq!(
            service_of("rover1/.services/plan").as_deref(),
            Some("rover1/plan")
        );
        assert_eq!(service_of(".services/ping").as_deref(), Some("ping"));
        assert_eq!(service_of("a/b/.services/go").as_deref(), Some("a/b/go"));
        assert_eq!(service_of("rover1/.services/plan@reply"), None);
        assert_eq!(service_of("rover1/pose"), None);
        assert_eq!(service_of("rover1/.services/"), None);
    }
}
