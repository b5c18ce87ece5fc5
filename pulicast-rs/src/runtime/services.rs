//! Services as a node runs them: its calls in flight, the frames that
//! answer them, and the servers of this node that its own calls reach
//! without the network. The decisions are the sans-IO
//! [`crate::proto::call::Call`] and [`crate::proto::service::Server`];
//! the typed API is `crate::service`.
//!
//! Answers come straight back to the socket a request left from: the
//! node's send socket. It is read by a thread of its own, started with the
//! first call, that hands each datagram to a receiver outside the pool (so
//! fragments, seals and drops are handled and counted as anywhere else)
//! whose only subscriptions are the request channels of services this
//! node calls.

use std::collections::HashMap;

use super::receive::{Handler, Shard};
use super::*;
use crate::proto::call::Call;
use crate::wire::service::{CallId, Frame};
use crate::wire::DecodeError;

/// How long the reply thread waits in one receive before it looks whether
/// the node stopped.
const REPLY_POLL: Duration = Duration::from_millis(250);

/// Where a server's frames for one call go.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ReplyTo {
    /// To the address the request came from.
    Network(SocketAddr),
    /// To a call of this node (the in-process path).
    Local,
}

/// A service this node serves, as its own calls reach it.
pub(crate) trait LocalServer: Send + Sync {
    /// Takes one frame a caller sent (a request or a cancel).
    fn frame(&self, frame: &[u8], from: ReplyTo);
}

/// Who may answer a call.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Answerer {
    /// This node's own server.
    Local,
    /// The server whose datagrams come from this address.
    At(SocketAddr),
}

/// One call of this node in flight.
pub(crate) struct Pending {
    pub(crate) state: Mutex<PendingState>,
    /// Wakes an async caller (one waits per call).
    pub(crate) notify: tokio::sync::Notify,
    /// Wakes a blocking caller.
    pub(crate) changed: std::sync::Condvar,
}

/// A call's state, under [`Pending::state`].
pub(crate) struct PendingState {
    pub(crate) call: Call,
    pub(crate) answerer: Answerer,
}

impl Pending {
    pub(crate) fn new(call: Call, answerer: Answerer) -> Arc<Self> {
        Arc::new(Self {
            state: Mutex::new(PendingState { call, answerer }),
            notify: tokio::sync::Notify::new(),
            changed: std::sync::Condvar::new(),
        })
    }

    fn wake(&self) {
        self.notify.notify_one();
        self.changed.notify_all();
    }
}

/// What the runtime keeps of services: see the module.
#[derive(Default)]
pub(crate) struct Services {
    /// The last call counter given out (never repeated in a session).
    counter: AtomicU64,
    /// Calls in flight, by counter.
    pending: Mutex<HashMap<u64, Arc<Pending>>>,
    /// The receiver of the send socket, once a call started it.
    replies: Mutex<Option<Arc<Shard>>>,
    /// Per request channel: the subscription its answers reach, and how
    /// many clients hold it.
    subscribed: Mutex<HashMap<Arc<str>, (u64, usize)>>,
    /// This node's servers, by request channel.
    servers: Mutex<HashMap<Arc<str>, Arc<dyn LocalServer>>>,
    /// Answers to calls that had ended (retransmitted answers: normal).
    late: AtomicU64,
}

impl Inner {
    /// A new call id of this node.
    pub(crate) fn next_call(&self) -> CallId {
        CallId {
            session: self.compat_session_id,
            counter: self.services.counter.fetch_add(1, Ordering::Relaxed) + 1,
        }
    }

    /// Registers a call in flight, to be found by its answers.
    pub(crate) fn add_call(&self, id: CallId, pending: Arc<Pending>) {
        lock(&self.services.pending).insert(id.counter, pending);
    }

    /// Forgets a call (it ended, or its caller let go).
    pub(crate) fn remove_call(&self, id: CallId) {
        lock(&self.services.pending).remove(&id.counter);
    }

    /// Answers heard for calls that had already ended.
    pub(crate) fn late_answers(&self) -> u64 {
        self.services.late.load(Ordering::Relaxed)
    }

    /// Lets answers on request channel `channel` reach this node's calls,
    /// for one more client; starts reading the send socket on first use.
    pub(crate) fn hold_answers(self: &Arc<Self>, channel: &Arc<ChannelState>) -> Result<()> {
        let shard = self.reply_shard()?;
        let mut subscribed = lock(&self.services.subscribed);
        if let Some((_, holders)) = subscribed.get_mut(channel.name()) {
            *holders += 1;
            return Ok(());
        }
        let weak = Arc::downgrade(self);
        let name = Arc::clone(channel.name());
        let handler = Arc::new(Handler::new(move |m: RawMessage, _: &Counters| {
            if let Some(inner) = weak.upgrade() {
                inner.deliver_answer(&name, &m.payload, Some(m.source));
            }
            true
        }));
        let id = self.subscribe_other(&shard, channel, handler)?;
        subscribed.insert(Arc::clone(channel.name()), (id, 1));
        Ok(())
    }

    /// Lets go of what [`Inner::hold_answers`] took.
    pub(crate) fn release_answers(&self, channel: &Arc<ChannelState>) {
        let mut subscribed = lock(&self.services.subscribed);
        let Some((id, holders)) = subscribed.get_mut(channel.name()) else {
            return;
        };
        *holders -= 1;
        if *holders > 0 {
            return;
        }
        let id = *id;
        subscribed.remove(channel.name());
        drop(subscribed);
        if let Some(shard) = lock(&self.services.replies).clone() {
            let _removed = shard.lock().unsubscribe(channel.name(), id);
        }
    }

    /// The receiver of the send socket, made (and its thread started) on
    /// first use.
    fn reply_shard(self: &Arc<Self>) -> Result<Arc<Shard>> {
        let mut replies = lock(&self.services.replies);
        if let Some(shard) = &*replies {
            return Ok(Arc::clone(shard));
        }
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let socket = self
            .send
            .try_clone()
            .map_err(Error::io("reading the send socket"))?;
        // Only receives wait this long; sends are not touched by it.
        socket
            .set_read_timeout(Some(REPLY_POLL))
            .map_err(Error::io("reading the send socket"))?;
        let shard = self.receivers.add_other();
        let weak = Arc::downgrade(self);
        let reading = Arc::clone(&shard);
        std::thread::Builder::new()
            .name(format!("pulicast-replies-{}", self.name))
            .spawn(move || reply_loop(&weak, &socket, &reading))
            .map_err(Error::io("starting the reply thread"))?;
        *replies = Some(Arc::clone(&shard));
        Ok(shard)
    }

    /// Hands an answer (a frame a server sent) to the call it is for:
    /// `from` is where it came from, `None` for this node's own server.
    /// What is no answer to a call of this node is dropped and counted.
    pub(crate) fn deliver_answer(&self, channel: &str, payload: &[u8], from: Option<SocketAddr>) {
        let source = || from.map_or_else(|| "this node".to_string(), |a| a.to_string());
        let frame = match Frame::decode(payload) {
            Ok(Frame::Request { .. } | Frame::Cancel { .. }) => {
                let e = DecodeError::Malformed("a caller's frame where answers come".into());
                return self.counters.drop_decode(&e, Some(channel), source());
            }
            Ok(frame) => frame,
            Err(e) => return self.counters.drop_decode(&e, Some(channel), source()),
        };
        let id = frame.call();
        let pending = match id.session == self.compat_session_id {
            true => lock(&self.services.pending).get(&id.counter).cloned(),
            false => None,
        };
        let Some(pending) = pending else {
            let issued = self.services.counter.load(Ordering::Relaxed);
            if id.session == self.compat_session_id && id.counter <= issued {
                // The answer of a call that ended, sent again because a
                // retransmitted request crossed it: expected now and then.
                self.services.late.fetch_add(1, Ordering::Relaxed);
                return;
            }
            return self.drop_answer(DropReason::UnknownCall, channel, &source());
        };
        let mut state = lock(&pending.state);
        let allowed = match (state.answerer, from) {
            (Answerer::Local, None) => true,
            (Answerer::At(server), Some(from)) => server == from,
            _ => false,
        };
        if !allowed {
            drop(state);
            return self.drop_answer(DropReason::WrongSource, channel, &source());
        }
        state.call.handle(&frame, Instant::now());
        drop(state);
        pending.wake();
    }

    fn drop_answer(&self, reason: DropReason, channel: &str, source: &str) {
        if let Some(suppressed) = self.counters.count_drop(reason) {
            let why = match reason {
                DropReason::UnknownCall => "for a call this node never made",
                _ => "from another address than the call's server",
            };
            tracing::warn!(
                channel,
                source,
                suppressed,
                reason = reason.label(),
                "dropped a service answer {why}"
            );
        }
    }

    /// Sends a server's frame for one call where it goes.
    pub(crate) fn send_answer(&self, channel: &ChannelState, frame: &[u8], to: ReplyTo) {
        match to {
            ReplyTo::Network(address) => {
                if let Err(e) = self.send_frame(channel, frame, Some(address)) {
                    tracing::debug!(channel = %channel.name(), %address, "answer not sent: {e}");
                }
            }
            ReplyTo::Local => self.deliver_answer(channel.name(), frame, None),
        }
    }

    /// Makes `server` this node's server of the service on `channel`;
    /// false if it already has one.
    pub(crate) fn add_server(&self, channel: &Arc<str>, server: Arc<dyn LocalServer>) -> bool {
        let mut servers = lock(&self.services.servers);
        if servers.contains_key(channel) {
            return false;
        }
        servers.insert(Arc::clone(channel), server);
        true
    }

    /// Forgets this node's server on `channel`.
    pub(crate) fn remove_server(&self, channel: &str) {
        lock(&self.services.servers).remove(channel);
    }

    /// This node's server on `channel`, if it has one.
    pub(crate) fn local_server(&self, channel: &str) -> Option<Arc<dyn LocalServer>> {
        lock(&self.services.servers).get(channel).cloned()
    }
}

/// Reads the send socket until the node is gone or stopped. Received
/// into one buffer and copied out (a reply is one small datagram, mostly);
/// a fragment is reassembled by copy rather than received in place.
fn reply_loop(inner: &Weak<Inner>, socket: &StdUdpSocket, shard: &Arc<Shard>) {
    let mut scratch = vec![0u8; MAX_DATAGRAM];
    loop {
        let received = socket.recv_from(&mut scratch);
        let Some(inner) = inner.upgrade() else {
            return;
        };
        if inner.is_stopped() {
            return;
        }
        match received {
            Ok((len, source)) => {
                let mut buf = BytesMut::from(&scratch[..len]);
                let (loan, _) = inner.handle_datagram(shard, &mut buf, source);
                if let Some(loan) = loan {
                    let _none = inner.repay(shard, loan, false);
                }
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(e) => {
                // Such as an ICMP error of an earlier send: transient.
                tracing::debug!("receiving on the send socket failed: {e}");
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
}
