//! Pulicast 2.x distributed settings on the wire (what `puliconf` speaks):
//! the channels a setting uses, its confirmation (`roc_ack`) and the
//! requests of change. Sans-IO: bytes in, values out.
//!
//! A setting `NAME` owned by a node in namespace `NS`:
//! - publishes confirmations on `NS/.config/NAME`: a `roc_ack` carrying the
//!   validator's message (empty when it had nothing to say), the value's
//!   type fingerprint and the value's ZCM encoding without that
//!   fingerprint (no bytes when the value is unset);
//! - subscribes requests of change on `NS/.config/NAME.r`: a value of the
//!   setting's type, or `poke_setting` (answer with the current value),
//!   `unset_setting` or `reset_setting_to_default`.
//!
//! The setting's fleet-wide name is its confirmation channel without
//! `.config/` (`rover1/.config/max_speed` is `rover1/max_speed`).
//!
//! ```
//! use pulicast_proto::wire::setting::{self, RocAck};
//! use pulicast_proto::wire::zcm::fingerprint;
//! assert_eq!(setting::confirmation_channel("rover1", "max_speed"), "rover1/.config/max_speed");
//! assert_eq!(setting::name_of_confirmation("rover1/.config/max_speed"), Some("rover1/max_speed".into()));
//!
//! let ack = RocAck { message: "", fingerprint: fingerprint::DOUBLE_MSG, value: &1.5f64.to_be_bytes() };
//! let mut bytes = Vec::new();
//! ack.encode(&mut bytes)?;
//! assert_eq!(RocAck::decode(&bytes)?, ack);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use super::zcm::Reader;
use super::zcm_types::{POKE_SETTING, RESET_SETTING_TO_DEFAULT, ROC_ACK, UNSET_SETTING};
use super::{DecodeError, EncodeError, Fingerprint};

/// The namespace part that holds settings' channels.
pub const CONFIG: &str = ".config";

/// The namespace part that holds the channels of native settings
/// ([`crate::setting::Native`], our extension): hidden as `.config`,
/// but not where 2.x tools look, since they fail on a type they don't know.
pub const NATIVE: &str = ".settings";

/// The suffix of a request-of-change channel.
pub const REQUEST_SUFFIX: &str = ".r";

/// The confirmation channel of setting `name` owned in namespace `ns`
/// (`""` for the root).
pub fn confirmation_channel(ns: &str, name: &str) -> String {
    confirmation_channel_in(CONFIG, ns, name)
}

/// The confirmation channel of setting `name` owned in namespace `ns`, its
/// channels under `part` ([`CONFIG`] or [`NATIVE`]).
pub fn confirmation_channel_in(part: &str, ns: &str, name: &str) -> String {
    let ns = ns.trim_matches('/');
    if ns.is_empty() {
        format!("{part}/{name}")
    } else {
        format!("{ns}/{part}/{name}")
    }
}

/// The request-of-change channel of setting `name` owned in namespace `ns`.
pub fn request_channel(ns: &str, name: &str) -> String {
    confirmation_channel(ns, name) + REQUEST_SUFFIX
}

/// Whether `channel` is a setting's confirmation channel (as 2.x tells,
/// except that `.config` must be a whole part of the name: 2.x also takes
/// `my.config/x`, which no setting of its own is ever called).
pub fn is_confirmation(channel: &str) -> bool {
    in_config(channel) && !channel.ends_with(REQUEST_SUFFIX)
}

/// Whether `channel` is a setting's request-of-change channel.
pub fn is_request(channel: &str) -> bool {
    in_config(channel) && channel.ends_with(REQUEST_SUFFIX)
}

fn in_config(channel: &str) -> bool {
    in_part(channel, CONFIG)
}

fn in_part(channel: &str, part: &str) -> bool {
    let inner = format!("{part}/");
    channel.starts_with(&inner) || channel.contains(&format!("/{inner}"))
}

/// The fleet-wide name of the setting whose confirmation channel is
/// `channel`: the channel without its `.config/` part. `None` for any other
/// channel.
pub fn name_of_confirmation(channel: &str) -> Option<String> {
    name_in(channel, CONFIG)
}

/// Like [`name_of_confirmation`], for a 2.x setting's channel or a native
/// one's (under [`NATIVE`]).
pub fn name_of_any_confirmation(channel: &str) -> Option<String> {
    name_in(channel, CONFIG).or_else(|| name_in(channel, NATIVE))
}

fn name_in(channel: &str, part: &str) -> Option<String> {
    if !in_part(channel, part) || channel.ends_with(REQUEST_SUFFIX) {
        return None;
    }
    // The innermost part: the setting's own name has no hidden part.
    let inner = format!("{part}/");
    let at = channel.rfind(&inner)?;
    let (ns, rest) = channel.split_at(at);
    let name = &rest[inner.len()..];
    (!name.is_empty()).then(|| format!("{ns}{name}"))
}

/// The confirmation channel that request channel `channel` belongs to.
pub fn confirmation_of_request(channel: &str) -> Option<&str> {
    is_request(channel).then(|| &channel[..channel.len() - REQUEST_SUFFIX.len()])
}

/// A setting's confirmation: what its owner answers every request with,
/// and sends when the setting is made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RocAck<'a> {
    /// The validator's message (why a request was refused, or a warning);
    /// empty when it had nothing to say.
    pub message: &'a str,
    /// The fingerprint of the setting's type.
    pub fingerprint: Fingerprint,
    /// The value's ZCM encoding without its fingerprint; empty when the
    /// setting has no value (unset).
    pub value: &'a [u8],
}

/// Most bytes a confirmation's value may have: its length is an `int16_t`.
pub const MAX_VALUE_LEN: usize = i16::MAX as usize;

impl<'a> RocAck<'a> {
    /// Appends the `roc_ack` message, fingerprint first. Fails when the
    /// value is longer than [`MAX_VALUE_LEN`] (2.x can't carry it).
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        let len = i16::try_from(self.value.len()).map_err(|_| EncodeError {
            type_name: "roc_ack",
            reason: format!(
                "a setting's value is at most {MAX_VALUE_LEN} bytes encoded, this one {}",
                self.value.len()
            ),
        })?;
        out.extend_from_slice(&ROC_ACK.fingerprint().0);
        super::zcm::write_string(out, self.message);
        out.extend_from_slice(&self.fingerprint.0);
        out.extend_from_slice(&len.to_be_bytes());
        out.extend_from_slice(self.value);
        Ok(())
    }

    /// Reads a `roc_ack` message (fingerprint included); a view into
    /// `payload`.
    pub fn decode(payload: &'a [u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(payload);
        r.expect_fingerprint(ROC_ACK.fingerprint(), "roc_ack")?;
        let message = r.string()?;
        let fingerprint = r.fingerprint()?;
        let len = i16::from_be_bytes(r.array()?);
        let len = usize::try_from(len)
            .map_err(|_| DecodeError::Malformed(format!("roc_ack value length {len}")))?;
        let value = r.take(len)?;
        r.finish()?;
        Ok(Self {
            message,
            fingerprint,
            value,
        })
    }

    /// Whether the setting has a value (an unset one is confirmed with no
    /// bytes).
    pub fn is_set(&self) -> bool {
        !self.value.is_empty()
    }
}

/// A request of change, as a setting's owner receives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request<'a> {
    /// Answer with the current value, changing nothing.
    Poke,
    /// Make the value unset.
    Unset,
    /// Go back to the default value.
    Reset,
    /// Take this value: a whole message, its fingerprint first, which the
    /// owner checks against the setting's type.
    Value(&'a [u8]),
}

impl<'a> Request<'a> {
    /// Tells the request in `payload` apart by its fingerprint.
    pub fn decode(payload: &'a [u8]) -> Result<Self, DecodeError> {
        let Some(found) = Fingerprint::of_payload(payload) else {
            return Err(DecodeError::Truncated {
                offset: payload.len(),
                needed: 8 - payload.len(),
            });
        };
        for (ty, request) in [
            (&POKE_SETTING, Request::Poke),
            (&UNSET_SETTING, Request::Unset),
            (&RESET_SETTING_TO_DEFAULT, Request::Reset),
        ] {
            if found == ty.fingerprint() {
                // Members-less messages: the fingerprint and nothing else.
                return match payload.len() - 8 {
                    0 => Ok(request),
                    count => Err(DecodeError::TrailingBytes { count }),
                };
            }
        }
        Ok(Request::Value(payload))
    }

    /// Appends this request as a message.
    pub fn encode(&self, out: &mut Vec<u8>) {
        match self {
            Request::Poke => out.extend_from_slice(&POKE_SETTING.fingerprint().0),
            Request::Unset => out.extend_from_slice(&UNSET_SETTING.fingerprint().0),
            Request::Reset => out.extend_from_slice(&RESET_SETTING_TO_DEFAULT.fingerprint().0),
            Request::Value(message) => out.extend_from_slice(message),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::zcm::fingerprint;

    #[test]
    fn native_settings_live_where_2x_tools_do_not_look() {
        let native = confirmation_channel_in(NATIVE, "rover1", "limits");
        assert_eq!(native, "rover1/.settings/limits");
        assert!(!is_confirmation(&native) && !is_request(&(native.clone() + ".r")));
        assert_eq!(name_of_confirmation(&native), None);
        assert_eq!(
            name_of_any_confirmation(&native),
            Some("rover1/limits".into())
        );
        assert_eq!(name_of_any_confirmation("rover1/.settings/limits.r"), None);
        assert_eq!(
            name_of_any_confirmation("rover1/.config/gain"),
            Some("rover1/gain".into())
        );
        assert_eq!(name_of_any_confirmation("rover1/settings/gain"), None);
    }

    #[test]
    fn channels_and_names() {
        assert_eq!(confirmation_channel("", "gain"), ".config/gain");
        assert_eq!(
            confirmation_channel("/rover1/", "arm/gain"),
            "rover1/.config/arm/gain"
        );
        assert_eq!(request_channel("rover1", "gain"), "rover1/.config/gain.r");
        assert!(is_confirmation("rover1/.config/gain"));
        assert!(!is_confirmation("rover1/.config/gain.r"));
        assert!(is_request("rover1/.config/gain.r"));
        assert!(!is_request("rover1/config/gain.r"));
        assert!(!is_confirmation("rover1/my.config/gain"));
        assert_eq!(
            name_of_confirmation("rover1/.config/arm/gain"),
            Some("rover1/arm/gain".into())
        );
        assert_eq!(name_of_confirmation(".config/gain"), Some("gain".into()));
        assert_eq!(name_of_confirmation("rover1/.config/"), None);
        assert_eq!(name_of_confirmation("rover1/gain"), None);
        assert_eq!(
            confirmation_of_request("rover1/.config/gain.r"),
            Some("rover1/.config/gain")
        );
    }

    #[test]
    fn confirmations_round_trip_and_bad_ones_are_errors() {
        let ack = RocAck {
            message: "must be at least 0",
            fingerprint: fingerprint::INT64_MSG,
            value: &7i64.to_be_bytes(),
        };
        let mut bytes = Vec::new();
        ack.encode(&mut bytes).unwrap();
        assert_eq!(RocAck::decode(&bytes).unwrap(), ack);
        // Every truncation fails, none panics.
        for cut in 0..bytes.len() {
            assert!(RocAck::decode(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        // A negative length, and bytes after the value.
        let len_at = 8 + 4 + ack.message.len() + 1 + 8;
        let mut negative = bytes.clone();
        negative[len_at..len_at + 2].copy_from_slice(&(-1i16).to_be_bytes());
        assert!(matches!(
            RocAck::decode(&negative),
            Err(DecodeError::Malformed(_))
        ));
        let mut longer = bytes.clone();
        longer.push(0);
        assert_eq!(
            RocAck::decode(&longer),
            Err(DecodeError::TrailingBytes { count: 1 })
        );
        let huge = vec![0; MAX_VALUE_LEN + 1];
        let too_long = RocAck {
            value: &huge,
            ..ack
        };
        assert!(too_long.encode(&mut Vec::new()).is_err());
    }

    #[test]
    fn requests_are_told_apart_by_fingerprint() {
        for request in [Request::Poke, Request::Unset, Request::Reset] {
            let mut bytes = Vec::new();
            request.encode(&mut bytes);
            assert_eq!(Request::decode(&bytes), Ok(request));
            bytes.push(1);
            assert!(Request::decode(&bytes).is_err());
        }
        let mut value = Vec::new();
        crate::wire::zcm::Primitive::Double(2.5).encode(&mut value);
        assert_eq!(Request::decode(&value), Ok(Request::Value(&value)));
        assert!(Request::decode(&[1, 2, 3]).is_err());
    }
}
