//! The node's side of Pulicast 2.x: sending heartbeats, feeding those it
//! hears to the 2.x table, logging what the table says, and pausing
//! batching where a 2.x node subscribes.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use pulicast_discovery::compat::{self, ChannelAnnouncement, Peer};

use super::{delivery, ChannelState, Inner};
use crate::proto::heartbeat::{self, Heard};
use crate::proto::receiver::RawMessage;
use crate::queue::Queue;
use crate::sync::lock;
use crate::wire::{zcm, DropReason};

/// The 2.x table (bytes held) up to which a channel that begins batching
/// is checked against it at once; above, it waits for the next tick.
const SCAN_AT_ONCE_BYTES: usize = 1 << 20;

impl Inner {
    /// Whether a 2.x-only peer subscribes `name`, as a channel begins to
    /// batch: looked up at once in a table of ordinary size, so its first
    /// messages batch; `None` in a table larger than
    /// [`SCAN_AT_ONCE_BYTES`] (a flood of fake 2.x nodes), which the next
    /// tick works out for every channel in one pass.
    pub(super) fn legacy_subscribes_now(&self, name: &str) -> Option<bool> {
        let gossip = self.fleet.gossip_keys();
        let membership = self.membership();
        if membership.bytes() > SCAN_AT_ONCE_BYTES {
            return None;
        }
        let subscribes = membership
            .peers()
            .filter(|p| {
                p.session_id != self.identity.compat_session_id && !gossip.contains(&p.session_id)
            })
            .any(|p| p.channels.iter().any(|c| c.is_subscribed && c.name == name));
        Some(subscribes)
    }

    /// Marks the batching channels that a Pulicast 2.x node subscribes, which
    /// can't read batches, so they are published one message per datagram:
    /// worked out from what changed in the 2.x table and the gossip keys
    /// since the last tick ([`Eligibility`]).
    ///
    /// A heartbeat peer that is not a gossip member counts as 2.x. A node of
    /// ours whose heartbeat arrives before its gossip does looks like one for
    /// a moment too; batching pauses then, but the log only speaks of peers
    /// that stayed 2.x-only past the grace period.
    pub(super) fn update_batching_eligibility(&self) {
        if !self.sending.flusher.is_used() {
            return;
        }
        let gossip = self.fleet.gossip_keys();
        let mut view = lock(&self.sending.batching_view);
        let changes = view.update(&self.membership(), gossip);
        let changed: Vec<(Arc<ChannelState>, bool)> = {
            let table = self.channels.table();
            changes
                .into_iter()
                .filter_map(|(name, blocked)| Some((Arc::clone(table.get(&name)?), blocked)))
                .collect()
        };
        for (channel, blocked) in changed {
            lock(&channel.tx).set_legacy_subscriber(blocked);
        }
        let settled = view.settled(Instant::now(), |name| {
            let channel = self.channels.table().get(name).cloned();
            channel.is_some_and(|c| lock(&c.tx).is_batching())
        });
        drop(view);
        // Said once per channel, and in one line per tick however many
        // channels (a bridge importing for thousands of fake 2.x nodes).
        if let Some((channel, session)) = settled.first() {
            let peer = self.membership().peer(*session).map(|p| p.name.clone());
            tracing::warn!(
                channel = %channel,
                peer = %peer.as_deref().unwrap_or("?"),
                channels = settled.len(),
                "not batching: a Pulicast 2.x node subscribes this channel and can't read batches \
                 (channels: how many more channels were found so just now)"
            );
        }
    }

    /// Forgets channels nobody holds, publishes or subscribes, so names
    /// made on the fly cost nothing lasting, whether the node sends 2.x
    /// heartbeats or not. Published ones stay: their sequence numbers must
    /// continue if the channel is made again.
    pub(super) fn forget_unused_channels(&self) {
        self.channels.table().retain(|_, state| {
            Arc::strong_count(state) > 1
                || state.published.load(Ordering::Relaxed)
                || state.announced_subscribers() > 0
        });
    }

    /// Sends the 2.x heartbeat: every channel this node uses that fits one
    /// datagram (see [`heartbeat::announce`]).
    pub(super) fn send_heartbeat(&self, nodes: &ChannelState) {
        let announcement = {
            let table = self.channels.table();
            let channels = table.values().map(|state| ChannelAnnouncement {
                name: state.name.to_string(),
                period_ns: lock(&state.period).period_ns as i64,
                is_published: state.published.load(Ordering::Relaxed),
                is_subscribed: state.announced_subscribers() > 0,
            });
            // `__nodes` is announced published only, though every node hears
            // it: 2.x puliconf takes a node that subscribes `__nodes` for a
            // tool and ignores the settings it owns. Listening to heartbeats
            // is part of being a node here, not a tool's choice.
            heartbeat::announce(
                &self.identity.name,
                self.identity.compat_session_id,
                self.tuning.heartbeat_period,
                false,
                channels,
            )
        };
        let left_out = announcement.left_out;
        if left_out > 0
            && !self
                .sending
                .heartbeat_truncated
                .swap(true, Ordering::Relaxed)
        {
            tracing::warn!(
                left_out,
                "more channels than one heartbeat datagram holds; announcing those that fit"
            );
        }
        let sent = self.publish_with(nodes, |buf| {
            zcm::encode_heartbeat(&announcement.heartbeat, buf);
            Ok(())
        });
        if let Err(e) = sent {
            if !self.is_stopped() {
                tracing::debug!("heartbeat not sent: {e}");
            }
        }
    }

    /// Feeds a message heard on `__nodes` to the 2.x table.
    pub(super) fn handle_heartbeat(&self, message: RawMessage) {
        match heartbeat::hear(self.identity.compat_session_id, &message) {
            Ok(Heard::Peer(heartbeat)) => {
                self.membership()
                    .handle_heartbeat(Instant::now(), message.source, heartbeat);
                self.log_membership_events();
            }
            Ok(Heard::Late) => {
                self.counters
                    .out_of_order_skipped
                    .fetch_add(1, Ordering::Relaxed);
            }
            Ok(Heard::Own) => {}
            Err(e) => {
                let channel = Some(compat::NODES_CHANNEL);
                self.counters.drop_decode(&e, channel, message.source);
            }
        }
    }

    pub(super) fn log_membership_events(&self) {
        let mut expired = Vec::new();
        let mut suspicious = Vec::new();
        let mut membership = self.membership();
        while let Some(event) = membership.poll_event() {
            match event {
                compat::Event::Joined {
                    name,
                    session_id,
                    address,
                } => {
                    tracing::debug!(peer = %name, session_id, %address, "peer joined");
                }
                compat::Event::Expired { name, session_id } => {
                    tracing::debug!(peer = %name, session_id, "peer missed its heartbeats");
                    expired.push((session_id, name));
                }
                compat::Event::Suspicious { session_id, what } => {
                    tracing::warn!(session_id, "peer session changed: {what}");
                    suspicious.push((session_id, what));
                }
                compat::Event::Evicted {
                    session_id,
                    name,
                    bytes,
                } => {
                    tracing::warn!(
                        peer = %name,
                        session_id,
                        bytes,
                        "2.x peer table full in bytes; dropped a larger peer to make room"
                    );
                    expired.push((session_id, name));
                }
                compat::Event::Rejected { session_id }
                    if self
                        .counters
                        .count_drop(DropReason::MalformedPayload)
                        .is_some() =>
                {
                    tracing::warn!(session_id, "peer table full; ignoring a new session");
                }
                _ => {}
            }
        }
        drop(membership);
        for (key, what) in suspicious {
            self.fleet
                .compat_suspicious(key, format!("2.x heartbeat: {what}"));
        }
        self.announce_settled_compat(&expired);
    }

    /// Tells discovery about 2.x peers that settled or expired. Called for
    /// every heartbeat received, so it costs time in the number of peers,
    /// never in their channels: only peers announced for the first time are
    /// copied. (Copying every peer's channel list for every heartbeat made a
    /// flood of large fake heartbeats cost time quadratic in their size.)
    pub(super) fn announce_settled_compat(&self, expired: &[(i64, String)]) {
        let now = Instant::now();
        let settled: Vec<i64> = self
            .membership()
            .peers()
            .filter(|p| {
                p.session_id != self.identity.compat_session_id && self.fleet.is_settled(now, p)
            })
            .map(|p| p.session_id)
            .collect();
        let new = self.fleet.unannounced_compat(&settled);
        if new.is_empty() && expired.is_empty() {
            return;
        }
        let peers: Vec<Peer> = {
            let membership = self.membership();
            new.iter()
                .filter_map(|id| membership.peer(*id).cloned())
                .collect()
        };
        self.fleet.update_compat(now, &peers, expired);
    }

    /// The 2.x heartbeat table's peers, without this node.
    pub(crate) fn compat_peers(&self) -> Vec<Peer> {
        self.membership()
            .peers()
            .filter(|p| p.session_id != self.identity.compat_session_id)
            .cloned()
            .collect()
    }
}

/// A subscriber of the node's own (`__nodes`), removed when its task ends
/// however it ends, so its queue never fills unread.
pub(super) struct OwnSubscriber {
    pub(super) inner: Arc<Inner>,
    pub(super) channel: Arc<ChannelState>,
    pub(super) id: u64,
    pub(super) queue: Arc<Queue<delivery::Queued>>,
}

impl Drop for OwnSubscriber {
    fn drop(&mut self) {
        self.inner.unsubscribe(&self.channel, self.id, false);
    }
}

/// Announces the node and tracks its peers until the node stops.
pub(super) async fn heartbeat_loop(
    inner: Arc<Inner>,
    nodes: Arc<ChannelState>,
    heartbeats: OwnSubscriber,
) {
    let mut tick = tokio::time::interval(inner.tuning.heartbeat_period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Types are compared about once a second, not every heartbeat.
    let mut last_type_check = Instant::now();
    loop {
        let expiry = inner.membership().poll_timeout();
        let expire = async {
            match expiry {
                // Deadlines are inclusive, so wake just after.
                Some(at) => tokio::time::sleep_until((at + Duration::from_millis(1)).into()).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = tick.tick() => {
                inner.forget_unused_channels();
                if inner.tuning.compat_heartbeat {
                    inner.send_heartbeat(&nodes);
                }
                inner.log_membership_events();
                // Which channels 2.x peers subscribe, once a tick rather
                // than for every heartbeat.
                inner.update_batching_eligibility();
                inner.expire_fragments();
                if last_type_check.elapsed() >= Duration::from_secs(1) {
                    last_type_check = Instant::now();
                    inner.warn_type_mismatches();
                }
            }
            _ = expire => {
                inner.membership().handle_timeout(Instant::now());
                inner.log_membership_events();
            }
            received = heartbeats.queue.recv() => match received {
                Some(message) => inner.handle_heartbeat(message),
                None => return,
            },
        }
    }
}
