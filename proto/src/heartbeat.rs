//! The Pulicast 2.x heartbeat as a node sends and hears it, sans-IO: what
//! fits one datagram ([`announce`]) and what a heartbeat heard on
//! `__nodes` means ([`hear`]). The table of peers it feeds is
//! [`pulicast_discovery::compat::Membership`]; the node's driver reads the
//! clock, sends, and feeds the table.

use std::time::Duration;

use pulicast_discovery::compat::{ChannelAnnouncement, Heartbeat, NODES_CHANNEL};

use super::receiver::RawMessage;
use crate::wire::{zcm, DecodeError, HEADER_OVERHEAD, MAX_DATAGRAM};

/// Bytes one channel takes in a heartbeat: string (length, bytes, NUL),
/// period, two flags.
fn cost(name: &str) -> usize {
    4 + name.len() + 1 + 8 + 2
}

/// A heartbeat that fits one datagram.
#[derive(Debug, Clone, PartialEq, Eq)]
#[must_use]
pub struct Announcement {
    /// What to send on `__nodes`.
    pub heartbeat: Heartbeat,
    /// Channels that did not fit, in the order given.
    pub left_out: usize,
}

/// The heartbeat of node `name` (2.x session `session_id`, sent every
/// `period`): `__nodes` first and always, as 2.x discoverers fail on a
/// heartbeat without it; then each of `channels` that the node publishes
/// or subscribes, while they fit one datagram.
pub fn announce(
    name: &str,
    session_id: i64,
    period: Duration,
    nodes_subscribed: bool,
    channels: impl IntoIterator<Item = ChannelAnnouncement>,
) -> Announcement {
    // The packet header, the ZCM fingerprint, the name, the session id and
    // the channel count.
    let fixed = HEADER_OVERHEAD + NODES_CHANNEL.len() + 8 + 4 + name.len() + 1 + 8 + 2;
    let mut budget = MAX_DATAGRAM.saturating_sub(fixed + cost(NODES_CHANNEL));
    let mut announced = vec![ChannelAnnouncement {
        name: NODES_CHANNEL.to_string(),
        period_ns: i64::try_from(period.as_nanos()).unwrap_or(i64::MAX),
        is_published: true,
        is_subscribed: nodes_subscribed,
    }];
    let mut left_out = 0;
    for channel in channels {
        let used = channel.is_published || channel.is_subscribed;
        if channel.name == NODES_CHANNEL || !used {
            continue;
        }
        match budget.checked_sub(cost(&channel.name)) {
            Some(rest) => {
                budget = rest;
                announced.push(channel);
            }
            None => left_out += 1,
        }
    }
    Announcement {
        heartbeat: Heartbeat {
            name: name.to_string(),
            session_id,
            channels: announced,
        },
        left_out,
    }
}

/// What a message heard on `__nodes` is.
#[derive(Debug, Clone, PartialEq, Eq)]
#[must_use]
pub enum Heard {
    /// A peer's heartbeat, for the table.
    Peer(Heartbeat),
    /// Late or a duplicate (lead below 1): like 2.x discoverers, it must
    /// not revive a peer or roll its channel list back.
    Late,
    /// This node's own, heard back.
    Own,
}

/// Decodes a message heard on `__nodes` by a node whose 2.x session is
/// `own_session`.
pub fn hear(own_session: i64, message: &RawMessage) -> Result<Heard, DecodeError> {
    if message.lead < 1 {
        return Ok(Heard::Late);
    }
    let heartbeat = zcm::decode_heartbeat(&message.payload)?;
    Ok(match heartbeat.session_id == own_session {
        true => Heard::Own,
        false => Heard::Peer(heartbeat),
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::wire::Packet;

    fn channel(name: String) -> ChannelAnnouncement {
        ChannelAnnouncement {
            name,
            period_ns: 1,
            is_published: true,
            is_subscribed: false,
        }
    }

    #[test]
    fn a_heartbeat_fits_one_datagram_and_says_what_was_left_out() {
        let many = (0..5000).map(|i| channel(format!("rover/channel_with_a_long_name_{i}")));
        let a = announce("n", 7, Duration::from_millis(100), true, many);
        assert!(a.left_out > 0);
        assert_eq!(a.heartbeat.channels[0].name, NODES_CHANNEL);
        assert_eq!(a.heartbeat.channels.len() + a.left_out, 5001);
        let mut payload = Vec::new();
        zcm::encode_heartbeat(&a.heartbeat, &mut payload);
        let mut datagram = Vec::new();
        Packet {
            channel: NODES_CHANNEL,
            seq: 0,
            payload: &payload,
        }
        .encode(&mut datagram);
        assert!(datagram.len() <= MAX_DATAGRAM, "{} bytes", datagram.len());
        // One more channel would not have fitted.
        assert!(datagram.len() + cost("rover/channel_with_a_long_name_0000") > MAX_DATAGRAM);
    }

    #[test]
    fn unused_channels_and_a_second_nodes_entry_are_not_announced() {
        let unused = ChannelAnnouncement {
            is_published: false,
            ..channel("quiet".into())
        };
        let channels = [channel(NODES_CHANNEL.into()), unused, channel("a".into())];
        let a = announce("n", 7, Duration::from_millis(100), false, channels);
        let names: Vec<&str> = a
            .heartbeat
            .channels
            .iter()
            .map(|c| c.name.as_str())
            .collect();
        assert_eq!((names, a.left_out), (vec![NODES_CHANNEL, "a"], 0));
    }

    #[test]
    fn late_own_and_malformed_heartbeats_are_told_apart() {
        let a = announce("n", 7, Duration::from_millis(100), true, []);
        let mut payload = Vec::new();
        zcm::encode_heartbeat(&a.heartbeat, &mut payload);
        let message = |lead, payload: &[u8]| RawMessage {
            payload: bytes::Bytes::copy_from_slice(payload),
            source: "10.0.0.1:1".parse().unwrap(),
            seq: 0,
            lead,
        };
        assert_eq!(hear(7, &message(1, &payload)).unwrap(), Heard::Own);
        assert_eq!(hear(8, &message(0, &payload)).unwrap(), Heard::Late);
        assert_eq!(
            hear(8, &message(1, &payload)).unwrap(),
            Heard::Peer(a.heartbeat)
        );
        assert!(hear(8, &message(1, b"junk")).is_err());
    }
}
