//! Services on the wire (our extension to the 2.x protocol): the
//! frames of a call, carried as the payload of ordinary packets, so that
//! fragmentation, sealing and the receive path apply to them unchanged.
//! Sans-IO: bytes in, values out.
//!
//! A service `NAME` served in namespace `NS` takes requests on the hidden
//! channel `NS/.services/NAME` (2.x tools never look there). A caller
//! multicasts a [`Frame::Request`] on it; a server sends [`Frame::Progress`],
//! then one [`Frame::Reply`] or [`Frame::Failure`] (or [`Frame::Busy`])
//! straight back to the address the request came from, on the same channel
//! name, and [`Frame::Running`] to a request sent again while its call
//! runs; a caller that gives up sends [`Frame::Cancel`]. Every frame names
//! its call by a [`CallId`]: the caller's session and a counter, so a
//! retransmitted request is recognised and answered from a cache instead
//! of run twice.
//!
//! Layout (big-endian): the magic `PSVC`, a version byte (1), a kind byte,
//! the call id (16 bytes), then by kind:
//!
//! | kind | body |
//! |---|---|
//! | 1 request | target node (u8 length, UTF-8; empty: any server), deadline hint in ms (u32), the request message |
//! | 2 progress | sequence number (u32, from 0), the progress message |
//! | 3 reply | progress messages sent before it (u32), the reply message |
//! | 4 failure | code (u16), message (u16 length, UTF-8), server node (u8 length, UTF-8) |
//! | 5 cancel | nothing |
//! | 6 busy | nothing |
//! | 7 running | nothing |
//!
//! Messages are whole messages, their type's fingerprint first, as on any
//! channel.
//!
//! ```
//! use pulicast_proto::wire::service::{CallId, Frame};
//! let call = CallId { session: 7, counter: 1 };
//! let frame = Frame::Request { call, target: "", deadline_ms: 500, message: b"12345678" };
//! let mut bytes = Vec::new();
//! frame.encode(&mut bytes)?;
//! assert_eq!(Frame::decode(&bytes)?, frame);
//! assert_eq!(pulicast_proto::wire::service::request_channel("rover1", "plan"), "rover1/.services/plan");
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use super::{DecodeError, EncodeError};

/// What every service frame starts with.
pub const MAGIC: [u8; 4] = *b"PSVC";

/// The frame layout's version.
pub const VERSION: u8 = 1;

/// The hidden namespace part that holds services' request channels.
pub const SERVICES: &str = ".services";

/// Bytes before a frame's body: magic, version, kind, call id.
pub const HEADER_LEN: usize = 4 + 1 + 1 + 16;

/// The request channel of service `name` served in namespace `ns` (`""`
/// for the root).
pub fn request_channel(ns: &str, name: &str) -> String {
    let ns = ns.trim_matches('/');
    if ns.is_empty() {
        format!("{SERVICES}/{name}")
    } else {
        format!("{ns}/{SERVICES}/{name}")
    }
}

/// The request channel of the service whose full name is `service`
/// (`rover1/arm/plan` is served on `rover1/arm/.services/plan`).
pub fn request_channel_of(service: &str) -> String {
    let service = service.trim_matches('/');
    match service.rsplit_once('/') {
        Some((ns, name)) => request_channel(ns, name),
        None => request_channel("", service),
    }
}

/// The character that ends a service's name where a node's begins
/// (`plan@planner_a`), and that starts the names of what discovery
/// announces beside a request channel ([`REPLY`], [`PROGRESS`],
/// [`SEALED`]): no service name has it.
pub const TARGET_MARK: char = '@';

/// Announced beside request channel `R` as `R@reply`: published by servers
/// and subscribed by clients, with the reply type. Nothing is sent on it.
pub const REPLY: &str = "@reply";
/// `R@progress`: as [`REPLY`], with the progress type.
pub const PROGRESS: &str = "@progress";
/// `R@sealed`: published by a server whose keys seal the service, so a
/// caller without them is told at once rather than timing out.
pub const SEALED: &str = "@sealed";

/// The service a request channel belongs to (`rover1/plan` for
/// `rover1/.services/plan`); `None` for any other channel, and for what
/// is announced beside one (`rover1/.services/plan@reply`).
pub fn service_of(channel: &str) -> Option<String> {
    let inner = format!("{SERVICES}/");
    let at = if channel.starts_with(&inner) {
        0
    } else {
        channel.find(&format!("/{inner}"))? + 1
    };
    let name = &channel[at + inner.len()..];
    (!name.is_empty() && !name.contains(TARGET_MARK) && !name.contains('/'))
        .then(|| format!("{}{name}", &channel[..at]))
}

/// Failure codes: those below [`code::APPLICATION`] are pulicast's own,
/// the rest a server's handlers choose.
pub mod code {
    /// The request did not decode as the server's request type.
    pub const BAD_REQUEST: u16 = 1;
    /// The handler panicked.
    pub const PANICKED: u16 = 2;
    /// The caller cancelled the call.
    pub const CANCELLED: u16 = 3;
    /// The call's deadline passed at the server.
    pub const DEADLINE: u16 = 4;
    /// The call ran, and its answer was too large to keep for a
    /// retransmitted request (it is not run again).
    pub const LOST: u16 = 5;
    /// The reply did not encode as the server's reply type.
    pub const BAD_REPLY: u16 = 6;
    /// The server left the fleet, or failed, before it answered: a
    /// caller's own conclusion from discovery, never sent.
    pub const SERVER_GONE: u16 = 7;
    /// A bridge could not run the call on the server's site: the site is
    /// out of reach, the server is not there (any more), busy, or refused
    /// the bridge's call (its types or keys).
    pub const UNREACHABLE: u16 = 8;
    /// The first code for handlers' own failures (and what
    /// `Fault::msg` uses).
    pub const APPLICATION: u16 = 1000;
}

/// Names one call: the caller's session (the first 8 bytes of its session
/// UUID, as in discovery) and a counter the caller never repeats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct CallId {
    /// The caller's session.
    pub session: i64,
    /// The call's number in that session.
    pub counter: u64,
}

/// One frame of a call; messages are views into the decoded bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame<'a> {
    /// Run this call (sent again until answered).
    Request {
        /// The call.
        call: CallId,
        /// The server node that should answer (`name@node`); empty: any.
        target: &'a str,
        /// How long the caller waits, in ms from sending: a server that
        /// can't start in time need not.
        deadline_ms: u32,
        /// The request message.
        message: &'a [u8],
    },
    /// A message the handler sent before its reply.
    Progress {
        /// The call.
        call: CallId,
        /// Its number, from 0, so the caller delivers them in order.
        seq: u32,
        /// The progress message.
        message: &'a [u8],
    },
    /// The call's result.
    Reply {
        /// The call.
        call: CallId,
        /// How many progress messages came before it, so the caller
        /// knows whether it missed any.
        progress: u32,
        /// The reply message.
        message: &'a [u8],
    },
    /// The call failed at the server.
    Failure {
        /// The call.
        call: CallId,
        /// What failed (see the service's documentation; 0: unspecified).
        code: u16,
        /// Why, for a person.
        message: &'a str,
        /// The server node that says so.
        node: &'a str,
    },
    /// The caller gave up: stop working on it.
    Cancel {
        /// The call.
        call: CallId,
    },
    /// The server runs as many calls as it may: try later or elsewhere.
    Busy {
        /// The call.
        call: CallId,
    },
    /// The call runs: the answer to a request sent again while its call
    /// runs, so a caller that would try another server after a silence
    /// knows this one has it. (A node from before this frame drops it as
    /// malformed, and counts it.)
    Running {
        /// The call.
        call: CallId,
    },
}

impl<'a> Frame<'a> {
    /// The call the frame belongs to.
    pub fn call(&self) -> CallId {
        match *self {
            Frame::Request { call, .. }
            | Frame::Progress { call, .. }
            | Frame::Reply { call, .. }
            | Frame::Failure { call, .. }
            | Frame::Cancel { call }
            | Frame::Busy { call }
            | Frame::Running { call } => call,
        }
    }

    fn kind(&self) -> u8 {
        match self {
            Frame::Request { .. } => 1,
            Frame::Progress { .. } => 2,
            Frame::Reply { .. } => 3,
            Frame::Failure { .. } => 4,
            Frame::Cancel { .. } => 5,
            Frame::Busy { .. } => 6,
            Frame::Running { .. } => 7,
        }
    }

    /// Appends the frame; fails for strings longer than their length
    /// field holds.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        let too_long = |what: &str, len: usize, max: usize| EncodeError {
            type_name: "service frame",
            reason: format!("{what} of {len} bytes, at most {max}"),
        };
        let short = |s: &str, what: &str| {
            u8::try_from(s.len()).map_err(|_| too_long(what, s.len(), u8::MAX.into()))
        };
        // Checked before anything is written, so a failure leaves `out` as it was.
        let lengths = match self {
            Frame::Request { target, .. } => vec![short(target, "a target node name")?],
            Frame::Failure { message, node, .. } => {
                u16::try_from(message.len())
                    .map_err(|_| too_long("a failure message", message.len(), u16::MAX.into()))?;
                vec![short(node, "a node name")?]
            }
            _ => Vec::new(),
        };
        out.extend_from_slice(&MAGIC);
        out.push(VERSION);
        out.push(self.kind());
        let call = self.call();
        out.extend_from_slice(&call.session.to_be_bytes());
        out.extend_from_slice(&call.counter.to_be_bytes());
        match *self {
            Frame::Request {
                target,
                deadline_ms,
                message,
                ..
            } => {
                out.push(lengths[0]);
                out.extend_from_slice(target.as_bytes());
                out.extend_from_slice(&deadline_ms.to_be_bytes());
                out.extend_from_slice(message);
            }
            Frame::Progress { seq, message, .. } => {
                out.extend_from_slice(&seq.to_be_bytes());
                out.extend_from_slice(message);
            }
            Frame::Reply {
                progress, message, ..
            } => {
                out.extend_from_slice(&progress.to_be_bytes());
                out.extend_from_slice(message);
            }
            Frame::Failure {
                code,
                message,
                node,
                ..
            } => {
                out.extend_from_slice(&code.to_be_bytes());
                // Checked above to fit.
                let len = message.len() as u16;
                out.extend_from_slice(&len.to_be_bytes());
                out.extend_from_slice(message.as_bytes());
                out.push(lengths[0]);
                out.extend_from_slice(node.as_bytes());
            }
            Frame::Cancel { .. } | Frame::Busy { .. } | Frame::Running { .. } => {}
        }
        Ok(())
    }

    /// Reads a frame; a view into `bytes`.
    pub fn decode(bytes: &'a [u8]) -> Result<Self, DecodeError> {
        let mut r = Cursor { bytes, at: 0 };
        if r.take(4)? != MAGIC {
            return Err(DecodeError::Malformed("not a service frame".into()));
        }
        let version = r.u8()?;
        if version != VERSION {
            return Err(DecodeError::Malformed(format!(
                "service frame version {version}, this node reads {VERSION}"
            )));
        }
        let kind = r.u8()?;
        let call = CallId {
            session: i64::from_be_bytes(r.array()?),
            counter: u64::from_be_bytes(r.array()?),
        };
        let frame = match kind {
            1 => {
                let len = usize::from(r.u8()?);
                let target = r.text(len)?;
                let deadline_ms = u32::from_be_bytes(r.array()?);
                Frame::Request {
                    call,
                    target,
                    deadline_ms,
                    message: r.rest(),
                }
            }
            2 => Frame::Progress {
                call,
                seq: u32::from_be_bytes(r.array()?),
                message: r.rest(),
            },
            3 => Frame::Reply {
                call,
                progress: u32::from_be_bytes(r.array()?),
                message: r.rest(),
            },
            4 => {
                let code = u16::from_be_bytes(r.array()?);
                let len = usize::from(u16::from_be_bytes(r.array()?));
                let message = r.text(len)?;
                let len = usize::from(r.u8()?);
                let node = r.text(len)?;
                r.finish()?;
                Frame::Failure {
                    call,
                    code,
                    message,
                    node,
                }
            }
            5..=7 => {
                r.finish()?;
                match kind {
                    5 => Frame::Cancel { call },
                    6 => Frame::Busy { call },
                    _ => Frame::Running { call },
                }
            }
            other => {
                return Err(DecodeError::Malformed(format!(
                    "unknown service frame kind {other}"
                )))
            }
        };
        Ok(frame)
    }
}

/// Whether `payload` is a service frame (by its magic).
pub fn is_frame(payload: &[u8]) -> bool {
    payload.starts_with(&MAGIC)
}

struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|end| *end <= self.bytes.len());
        let Some(end) = end else {
            return Err(DecodeError::Truncated {
                offset: self.at,
                needed: n - (self.bytes.len() - self.at),
            });
        };
        let taken = &self.bytes[self.at..end];
        self.at = end;
        Ok(taken)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        let mut out = [0; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    fn u8(&mut self) -> Result<u8, DecodeError> {
        Ok(self.take(1)?[0])
    }

    fn text(&mut self, len: usize) -> Result<&'a str, DecodeError> {
        std::str::from_utf8(self.take(len)?)
            .map_err(|_| DecodeError::Malformed("a service frame's text is not UTF-8".into()))
    }

    fn rest(&mut self) -> &'a [u8] {
        let rest = &self.bytes[self.at..];
        self.at = self.bytes.len();
        rest
    }

    fn finish(&self) -> Result<(), DecodeError> {
        match self.bytes.len() - self.at {
            0 => Ok(()),
            count => Err(DecodeError::TrailingBytes { count }),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    const CALL: CallId = CallId {
        session: -3,
        counter: u64::MAX,
    };

    fn round_trip(frame: Frame<'_>) {
        let mut bytes = Vec::new();
        frame.encode(&mut bytes).unwrap();
        assert!(is_frame(&bytes));
        assert_eq!(Frame::decode(&bytes).unwrap(), frame);
        // Every cut of it is refused or a shorter frame, never a panic.
        for cut in 0..bytes.len() {
            let _ = Frame::decode(&bytes[..cut]);
        }
    }

    #[test]
    fn every_kind_round_trips() {
        round_trip(Frame::Request {
            call: CALL,
            target: "planner_2",
            deadline_ms: 1500,
            message: b"fingerpr+request",
        });
        round_trip(Frame::Request {
            call: CALL,
            target: "",
            deadline_ms: 0,
            message: b"",
        });
        round_trip(Frame::Progress {
            call: CALL,
            seq: 7,
            message: b"fingerpr50%",
        });
        round_trip(Frame::Reply {
            call: CALL,
            progress: 8,
            message: b"fingerprdone",
        });
        round_trip(Frame::Failure {
            call: CALL,
            code: 404,
            message: "no path to the goal",
            node: "planner",
        });
        round_trip(Frame::Cancel { call: CALL });
        round_trip(Frame::Busy { call: CALL });
        round_trip(Frame::Running { call: CALL });
    }

    #[test]
    fn bad_frames_are_refused_and_long_names_not_encoded() {
        assert!(Frame::decode(b"PULI....").is_err());
        let mut bytes = Vec::new();
        Frame::Busy { call: CALL }.encode(&mut bytes).unwrap();
        let mut trailing = bytes.clone();
        trailing.push(0);
        assert!(matches!(
            Frame::decode(&trailing),
            Err(DecodeError::TrailingBytes { count: 1 })
        ));
        let mut version = bytes.clone();
        version[4] = 9;
        assert!(Frame::decode(&version).is_err());
        let mut kind = bytes;
        kind[5] = 77;
        assert!(Frame::decode(&kind).is_err());
        let long = "n".repeat(256);
        let mut out = vec![1, 2];
        let request = Frame::Request {
            call: CALL,
            target: &long,
            deadline_ms: 0,
            message: b"",
        };
        assert!(request.encode(&mut out).is_err());
        assert_eq!(out, [1, 2], "nothing written on failure");
    }

    #[test]
    fn request_channels_and_service_names() {
        assert_eq!(request_channel("", "plan"), ".services/plan");
        assert_eq!(request_channel("/rover1/", "plan"), "rover1/.services/plan");
        assert_eq!(
            request_channel_of("rover1/arm/plan"),
            "rover1/arm/.services/plan"
        );
        assert_eq!(request_channel_of("plan"), ".services/plan");
        assert_eq!(
            service_of("rover1/arm/.services/plan"),
            Some("rover1/arm/plan".into())
        );
        // What is announced beside a request channel is no service.
        assert_eq!(service_of("rover1/.services/plan@reply"), None);
        assert_eq!(service_of("rover1/.services/arm/plan"), None);
        assert_eq!(service_of(".services/plan"), Some("plan".into()));
        assert_eq!(service_of("rover1/services/plan"), None);
        assert_eq!(service_of("rover1/.services/"), None);
    }
}
