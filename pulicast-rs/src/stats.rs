//! Counters of what a node received, delivered and dropped, and rate-limited
//! logging of drops.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

use crate::proto::receiver::{Cause, Dropped};
use crate::proto::secure::OpenError;
use crate::wire::{DecodeError, DropReason};

/// At most one log line per drop reason per this interval; the lines in
/// between are counted and reported with the next one.
const LOG_INTERVAL: Duration = Duration::from_secs(1);

/// A snapshot of a node's counters, from [`crate::Node::stats`].
///
/// # Example
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use pulicast::DropReason;
/// let stats = node.stats();
/// println!("received {}, delivered {}", stats.messages_received, stats.messages_delivered);
/// if stats.dropped(DropReason::QueueOverflow) > 0 {
///     eprintln!("a subscriber is too slow (see NodeBuilder::queue_capacity)");
/// }
/// for reason in DropReason::ALL {
///     let n = stats.dropped(reason);
///     if n > 0 { println!("{}: {n}", reason.label()); }
/// }
/// # }
/// ```
#[derive(Debug, Clone, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct Stats {
    /// Datagrams read from the receive sockets.
    pub datagrams_received: u64,
    /// Valid messages for channels this node subscribes. A message is
    /// counted once it has been queued for (or dropped by) every
    /// subscription, so a snapshot that counts it also counts its
    /// [`crate::DropReason::QueueOverflow`].
    pub messages_received: u64,
    /// Messages handed to the user (after decoding, and after ordering for
    /// ordered subscriptions).
    pub messages_delivered: u64,
    /// Messages skipped by ordered subscriptions because their lead was < 1.
    pub out_of_order_skipped: u64,
    /// Messages published.
    pub messages_sent: u64,
    /// Calls of [`crate::Channel::subscribe_with`] handlers that panicked
    /// (the panic is caught and logged; the handler is called again for
    /// the next message).
    pub handler_panics: u64,
    /// Answers of service calls that came after their call had ended: a
    /// retransmitted request crossed the reply, and the server sent it
    /// again. Expected now and then on a lossy link; not a drop.
    pub late_answers: u64,
    /// Datagrams of messages in fragments that waited before leaving, so
    /// that a burst fits the subscribers' receive buffers
    /// ([`crate::NodeBuilder::fragment_rate`]).
    pub paced_datagrams: u64,
    /// How long those datagrams waited in all.
    pub paced_wait: Duration,
    /// Receive sockets open (more open as channels exceed the kernel's
    /// per-socket group membership limit).
    pub receive_sockets: usize,
    /// Dropped data, per reason, in the order of [`DropReason::ALL`].
    pub dropped: [u64; DropReason::ALL.len()],
}

impl Stats {
    /// How many were dropped for `reason`.
    pub fn dropped(&self, reason: DropReason) -> u64 {
        self.dropped[reason.index()]
    }

    /// All drops together.
    pub fn dropped_total(&self) -> u64 {
        self.dropped.iter().sum()
    }
}

/// The live counters behind [`Stats`] that the receiver does not keep:
/// shared by the node's tasks and handles. (What the receive path counts
/// is in [`crate::proto::receiver::ReceiveCounts`].)
#[derive(Debug)]
pub(crate) struct Counters {
    pub messages_delivered: AtomicU64,
    pub out_of_order_skipped: AtomicU64,
    pub messages_sent: AtomicU64,
    /// Datagrams paced, and their wait in nanoseconds.
    pub paced: AtomicU64,
    pub paced_ns: AtomicU64,
    handler_panics: AtomicU64,
    /// Blocking receives called inside a handler (they don't wait).
    blocking_in_handler: AtomicU64,
    dropped: [AtomicU64; DropReason::ALL.len()],
    /// The node's one drop log, shared with the receive path.
    pub(crate) log: DropLog,
}

impl Counters {
    pub(crate) fn new() -> Self {
        Self {
            messages_delivered: AtomicU64::new(0),
            out_of_order_skipped: AtomicU64::new(0),
            messages_sent: AtomicU64::new(0),
            paced: AtomicU64::new(0),
            paced_ns: AtomicU64::new(0),
            handler_panics: AtomicU64::new(0),
            blocking_in_handler: AtomicU64::new(0),
            dropped: Default::default(),
            log: DropLog::default(),
        }
    }

    /// What these counters hold; the receive path's fields are left zero.
    pub(crate) fn snapshot(&self) -> Stats {
        Stats {
            datagrams_received: 0,
            messages_received: 0,
            messages_delivered: self.messages_delivered.load(Relaxed),
            out_of_order_skipped: self.out_of_order_skipped.load(Relaxed),
            messages_sent: self.messages_sent.load(Relaxed),
            paced_datagrams: self.paced.load(Relaxed),
            paced_wait: Duration::from_nanos(self.paced_ns.load(Relaxed)),
            handler_panics: self.handler_panics.load(Relaxed),
            receive_sockets: 0,
            late_answers: 0,
            dropped: std::array::from_fn(|i| self.dropped[i].load(Relaxed)),
        }
    }

    /// Logs (the 1st, 2nd, 4th, 8th, ... time) that a handler called a
    /// blocking receive, which returned at once instead of waiting.
    pub(crate) fn blocking_receive_in_handler(&self) {
        let n = self.blocking_in_handler.fetch_add(1, Relaxed) + 1;
        if n.is_power_of_two() {
            tracing::warn!(
                times = n,
                "a blocking receive was called inside a subscription handler and returned \
                 without waiting: the handler runs on the thread that receives for the node, \
                 so waiting there would stop the node; use try_recv, or receive on another thread"
            );
        }
    }

    /// Counts a handler's panic, and logs the 1st, 2nd, 4th, 8th, ...
    pub(crate) fn handler_panicked(&self) {
        let n = self.handler_panics.fetch_add(1, Relaxed) + 1;
        if n.is_power_of_two() {
            tracing::error!(
                panics = n,
                "a subscription handler panicked; the panic was caught and the \
                 handler is called again for the next message"
            );
        }
    }

    /// Counts a dropped datagram or message and logs it, rate-limited.
    pub(crate) fn drop_decode(
        &self,
        err: &DecodeError,
        channel: Option<&str>,
        source: impl std::fmt::Display,
    ) {
        let reason = err.reason();
        if let Some(suppressed) = self.count_drop(reason) {
            if let DecodeError::WrongType {
                expected_name,
                found,
                ..
            } = err
            {
                let found = describe_type(*found);
                return tracing::warn!(
                    reason = reason.label(),
                    channel = channel.unwrap_or("?"),
                    %source,
                    suppressed,
                    "dropped a message of another type: expected {expected_name}, got {found}"
                );
            }
            tracing::warn!(
                reason = reason.label(),
                channel = channel.unwrap_or("?"),
                %source,
                suppressed,
                "dropped received data: {err}"
            );
        }
    }

    /// Counts a discovery datagram that did not decode and logs it, rate-limited.
    pub(crate) fn drop_discovery(
        &self,
        err: &pulicast_discovery::wire::WireError,
        source: impl std::fmt::Display,
    ) {
        if let Some(suppressed) = self.count_drop(DropReason::MalformedDiscovery) {
            tracing::warn!(%source, suppressed, "dropped a discovery datagram: {err}");
        }
    }

    /// Counts a discovery datagram the discovery task had no room for and
    /// logs it, rate-limited.
    pub(crate) fn drop_discovery_backlog(&self, source: impl std::fmt::Display) {
        if let Some(suppressed) = self.count_drop(DropReason::DiscoveryBacklog) {
            tracing::warn!(
                %source,
                suppressed,
                "dropped a discovery datagram: the discovery task is behind, or this source holds its share of the queue"
            );
        }
    }

    /// Counts a relayed member list from an address that does not speak for
    /// a live member, and logs it, rate-limited.
    pub(crate) fn drop_relay(&self, source: impl std::fmt::Display, bridge: i64) {
        if let Some(suppressed) = self.count_drop(DropReason::UntrustedRelay) {
            tracing::warn!(
                %source,
                bridge,
                suppressed,
                "dropped relayed members: the sender is not a live member heard from that address"
            );
        }
    }

    /// Counts one drop; returns `Some(suppressed)` when this one should be
    /// logged, `suppressed` being the drops not logged since the last line.
    pub(crate) fn count_drop(&self, reason: DropReason) -> Option<u64> {
        self.dropped[reason.index()].fetch_add(1, Relaxed);
        self.log.due(reason)
    }
}

/// Rate-limits drop log lines: at most one per reason per [`LOG_INTERVAL`],
/// the first drop of each reason always logged. One per node, shared by
/// every place that drops.
#[derive(Debug)]
pub(crate) struct DropLog {
    /// When each reason was last logged, in ms since `epoch` plus one (0:
    /// never).
    last_log_ms: [AtomicU64; DropReason::ALL.len()],
    /// Drops noted per reason.
    noted: [AtomicU64; DropReason::ALL.len()],
    /// `noted` when each reason was last logged.
    logged: [AtomicU64; DropReason::ALL.len()],
    epoch: Instant,
}

impl Default for DropLog {
    fn default() -> Self {
        Self {
            last_log_ms: Default::default(),
            noted: Default::default(),
            logged: Default::default(),
            epoch: Instant::now(),
        }
    }
}

impl DropLog {
    /// Notes a drop for `reason`; `Some(suppressed)` when it is to be
    /// logged, `suppressed` being the drops noted since the last line that
    /// were not (at least: the receiver keeps the details of at most
    /// [`crate::proto::receiver::MAX_DROP_DETAILS`] drops per datagram).
    pub(crate) fn due(&self, reason: DropReason) -> Option<u64> {
        let i = reason.index();
        let noted = self.noted[i].fetch_add(1, Relaxed) + 1;
        let now_ms = u64::try_from(self.epoch.elapsed().as_millis())
            .unwrap_or(u64::MAX - 1)
            .saturating_add(1);
        let last = self.last_log_ms[i].load(Relaxed);
        let due = last == 0 || now_ms.saturating_sub(last) >= LOG_INTERVAL.as_millis() as u64;
        // Only one thread wins the slot, so a burst logs one line.
        if due
            && self.last_log_ms[i]
                .compare_exchange(last, now_ms, Relaxed, Relaxed)
                .is_ok()
        {
            let logged_before = self.logged[i].swap(noted, Relaxed);
            return Some(noted.saturating_sub(logged_before).saturating_sub(1));
        }
        None
    }

    /// Logs what the receiver dropped, rate-limited.
    pub(crate) fn log(&self, dropped: &Dropped) {
        let Some(suppressed) = self.due(dropped.reason) else {
            return;
        };
        let reason = dropped.reason.label();
        let channel = dropped.channel.as_deref().unwrap_or("?");
        let source: &dyn std::fmt::Display = match &dropped.source {
            Some(source) => source,
            None => &"?",
        };
        match &dropped.cause {
            Cause::Decode(DecodeError::WrongType {
                expected_name,
                found,
                ..
            }) => {
                let found = describe_type(*found);
                tracing::warn!(
                    reason,
                    channel,
                    %source,
                    suppressed,
                    "dropped a message of another type: expected {expected_name}, got {found}"
                );
            }
            Cause::Decode(_) | Cause::Open(_) | Cause::Unsealed | Cause::Misdirected => {
                let what: &dyn std::fmt::Display = match &dropped.cause {
                    Cause::Open(OpenError::UnknownKey) => {
                        &"sealed, and this node has no key for the channel (see PULICAST_KEYS)"
                    }
                    Cause::Open(e) => e,
                    Cause::Decode(e) => e,
                    Cause::Unsealed => &"not sealed, but the channel has a key",
                    _ => &"a sealed datagram of another channel sent to the discovery socket",
                };
                tracing::warn!(reason, channel, %source, suppressed, "dropped received data: {what}");
            }
            Cause::Incomplete => {
                tracing::warn!(suppressed, "a fragmented message did not complete");
            }
            Cause::Overflow => tracing::warn!(
                suppressed,
                %channel,
                "subscription queue full; its queue policy dropped messages (counted in Node::stats)"
            ),
        }
    }
}

/// A payload's type for the log: 2.x messages are known by fingerprint;
/// native types are named by the node's discovery check, which knows what
/// the publisher announced.
fn describe_type(found: crate::wire::Fingerprint) -> String {
    match crate::wire::zcm_types::by_fingerprint(found) {
        Some(known) => known.name.to_string(),
        None => format!("type {found}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drops_are_all_counted_but_logged_rarely() {
        let c = Counters::new();
        let logged = (0..1000)
            .filter(|_| c.count_drop(DropReason::BadMagic).is_some())
            .count();
        assert_eq!(c.snapshot().dropped(DropReason::BadMagic), 1000);
        assert_eq!(c.snapshot().dropped_total(), 1000);
        assert!(logged <= 2, "logged {logged} lines for one burst");
    }
}
