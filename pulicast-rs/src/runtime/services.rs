//! Services as a node runs them: its calls in flight, the frames that
//! answer them, and the servers of this node that its own calls reach
//! without the network. The decisions are the sans-IO
//! [`crate::proto::call::Call`] and [`crate::proto::service::Admission`];
//! the typed API is `crate::service`.
//!
//! Answers come straight back to the socket a request left from: the
//! node's service socket, opened with its first client. Its requests
//! leave from it (sealed for its address, as the send socket's datagrams
//! are for theirs), and a receive loop on the node's runtime reads it into
//! a receiver outside the pool (so fragments, seals and drops are handled
//! and counted as anywhere else) whose only subscriptions are the request
//! channels of services this node calls. An answer wakes the caller's own
//! runtime, with no thread in between.

use std::collections::HashMap;
use std::net::{SocketAddr, SocketAddrV4};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

use bytes::BytesMut;
use tokio::net::UdpSocket;

use super::delivery::Handler;
use super::receivers::Shard;
use super::{send, ChannelState, Inner};
use crate::error::{Error, Result};
use crate::proto::call::Call;
use crate::proto::receiver::RawMessage;
use crate::proto::ChannelTx;
use crate::stats::Counters;
use crate::sync::lock;
use crate::transport;
use crate::wire::service::{CallId, Frame};
use crate::wire::DecodeError;
use crate::wire::{DropReason, MAX_DATAGRAM};

/// Where a server's frames for one call go.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
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

/// The socket a node's calls leave from and their answers come to.
pub(crate) struct ServiceSocket {
    socket: UdpSocket,
    /// Its address, as sealed datagrams carry it.
    origin: SocketAddrV4,
    /// The receiver its datagrams go to.
    shard: Arc<Shard>,
    /// Held while datagrams are read and handled (with the buffer they
    /// are read into), so that they are handled in the order they came,
    /// whoever reads: the answer task, or a caller waiting for its answer.
    reading: Mutex<Vec<u8>>,
    /// Whether a waiting caller reads the socket: one at a time, so an
    /// answer does not wake every caller.
    seat: AtomicBool,
}

/// A client's side of a request channel: its own sequence numbers and
/// sealer (for the service socket's address).
pub(crate) struct RequestTx {
    pub(crate) socket: Arc<ServiceSocket>,
    tx: Mutex<ChannelTx>,
    to: SocketAddr,
}

/// Sends one datagram from the (non-blocking) service socket, waiting
/// while its send buffer is full, as the blocking send socket would: on a
/// real interface the fragments of a large request fill it. Sent past
/// tokio's readiness, which a full buffer would leave unset until its
/// reactor looked again.
fn send_waiting(
    socket: &UdpSocket,
    datagram: &[u8],
    to: &socket2::SockAddr,
) -> std::io::Result<()> {
    use rustix::event::{poll, PollFd, PollFlags, Timespec};
    let raw = socket2::SockRef::from(socket);
    let wait = Timespec::try_from(Duration::from_secs(1)).ok();
    loop {
        match raw.send_to(datagram, to) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                let mut fds = [PollFd::new(socket, PollFlags::OUT)];
                match poll(&mut fds, wait.as_ref()) {
                    Ok(n) if n > 0 => {}
                    // A second without room: give it up (the call sends
                    // it again).
                    _ => return Err(e),
                }
            }
            other => return other.map(drop),
        }
    }
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

/// A request channel's answers reaching this node: the subscription's id,
/// how many clients hold it, and their side of the channel.
type Answered = (u64, usize, Arc<RequestTx>);

/// What the runtime keeps of services: see the module.
#[derive(Default)]
pub(crate) struct Services {
    /// The last call counter given out (never repeated in a session).
    counter: AtomicU64,
    /// Calls in flight, by counter.
    pending: Mutex<HashMap<u64, Arc<Pending>>>,
    /// The service socket, once a client opened it.
    replies: Mutex<Option<Arc<ServiceSocket>>>,
    /// Per request channel: the subscription its answers reach, and how
    /// many clients hold it.
    /// Their clients share one side of the channel (one sequence of
    /// numbers from one address: fragments of two clients' requests must
    /// never be taken for one message's).
    subscribed: Mutex<HashMap<Arc<str>, Answered>>,
    /// This node's servers, by request channel.
    servers: Mutex<HashMap<Arc<str>, Arc<dyn LocalServer>>>,
    /// Answers to calls that had ended (retransmitted answers: normal).
    late: AtomicU64,
}

impl ServiceSocket {
    /// Waits until the socket may hold a datagram.
    pub(crate) async fn readable(&self) -> std::io::Result<()> {
        self.socket.readable().await
    }

    /// Takes the seat of the waiting caller that reads the socket, if it
    /// is free; give it back with [`ServiceSocket::leave_seat`].
    pub(crate) fn take_seat(&self) -> bool {
        !self.seat.swap(true, Ordering::AcqRel)
    }

    /// Gives the seat back.
    pub(crate) fn leave_seat(&self) {
        self.seat.store(false, Ordering::Release);
    }
}

impl Inner {
    /// A new call id of this node.
    pub(crate) fn next_call(&self) -> CallId {
        CallId {
            session: self.identity.compat_session_id,
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
    /// for one more client (opening the service socket on first use), and
    /// gives the client its side of the channel.
    pub(crate) fn hold_answers(
        self: &Arc<Self>,
        channel: &Arc<ChannelState>,
    ) -> Result<Arc<RequestTx>> {
        let socket = self.service_socket()?;
        let shard = Arc::clone(&socket.shard);
        let mut subscribed = lock(&self.services.subscribed);
        if let Some((_, holders, request)) = subscribed.get_mut(channel.name()) {
            *holders += 1;
            return Ok(Arc::clone(request));
        }
        let request = Arc::new(RequestTx {
            tx: Mutex::new(ChannelTx::new(
                Arc::clone(channel.name()),
                self.security
                    .as_ref()
                    .and_then(|s| s.sealer(channel.name(), socket.origin)),
            )),
            socket,
            to: SocketAddr::from((channel.group, self.identity.port)),
        });
        let weak = Arc::downgrade(self);
        let name = Arc::clone(channel.name());
        let handler = Arc::new(Handler::new(move |m: RawMessage, _: &Counters| {
            if let Some(inner) = weak.upgrade() {
                inner.deliver_answer(&name, &m.payload, Some(m.source));
            }
            true
        }));
        let id = self.subscribe_other(&shard, channel, handler)?;
        subscribed.insert(Arc::clone(channel.name()), (id, 1, Arc::clone(&request)));
        Ok(request)
    }

    /// Lets go of what [`Inner::hold_answers`] took.
    pub(crate) fn release_answers(&self, channel: &Arc<ChannelState>) {
        let mut subscribed = lock(&self.services.subscribed);
        let Some((id, holders, _)) = subscribed.get_mut(channel.name()) else {
            return;
        };
        *holders -= 1;
        if *holders > 0 {
            return;
        }
        let id = *id;
        subscribed.remove(channel.name());
        drop(subscribed);
        if let Some(socket) = lock(&self.services.replies).clone() {
            let _removed = socket.shard.lock().unsubscribe(channel.name(), id);
        }
    }

    /// The service socket, opened (and read) on first use.
    fn service_socket(self: &Arc<Self>) -> Result<Arc<ServiceSocket>> {
        let mut replies = lock(&self.services.replies);
        if let Some(opened) = &*replies {
            return Ok(Arc::clone(opened));
        }
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let socket = {
            let _runtime = self.lifecycle.runtime.enter();
            transport::service_socket(&self.sending.socket)
                .map_err(Error::io("opening the service socket"))?
        };
        let port = socket
            .local_addr()
            .map_err(Error::io("opening the service socket"))?
            .port();
        // Its requests, heard back by this node's own server's receiver,
        // are the node's own: not others' uses of the namespace's key.
        // (Receivers made later copy the first one's ports.)
        for shard in self.receiving.receivers.all() {
            shard.add_own_port(port);
        }
        let socket = Arc::new(ServiceSocket {
            socket,
            origin: SocketAddrV4::new(*self.identity.origin.ip(), port),
            shard: self.receiving.receivers.add_other(),
            reading: Mutex::new(vec![0; MAX_DATAGRAM]),
            seat: AtomicBool::new(false),
        });
        let task = self
            .lifecycle
            .runtime
            .spawn(answer_loop(Arc::downgrade(self), Arc::clone(&socket)));
        self.add_task(task);
        *replies = Some(Arc::clone(&socket));
        Ok(socket)
    }

    /// Reads and handles what the service socket holds, unless another
    /// reader is at it (it handles it then); false in that case.
    pub(crate) fn drain_answers(&self, socket: &ServiceSocket) -> bool {
        let mut scratch = match socket.reading.try_lock() {
            Ok(scratch) => scratch,
            Err(std::sync::TryLockError::Poisoned(p)) => p.into_inner(),
            Err(std::sync::TryLockError::WouldBlock) => return false,
        };
        // Bounded, so one reader can't be held here by a flood.
        for _ in 0..256 {
            match socket.socket.try_recv_from(&mut scratch) {
                Ok((len, source)) => {
                    let mut buf = BytesMut::from(&scratch[..len]);
                    let (loan, _) = self.handle_datagram(&socket.shard, &mut buf, source);
                    if let Some(loan) = loan {
                        // Reassembled by copy: answers are mostly small.
                        let _none = self.repay(&socket.shard, loan, false);
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                Err(e) => {
                    // Such as an ICMP error of an earlier send: transient.
                    tracing::debug!("receiving on the service socket failed: {e}");
                    break;
                }
            }
        }
        true
    }

    /// Sends a caller's frame (a request or a cancel) to the request
    /// channel's group, from the service socket. A full socket buffer
    /// loses the frame as the network may: the call sends it again.
    pub(crate) fn send_request(&self, request: &RequestTx, frame: &[u8]) -> Result<()> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let mut tx = lock(&request.tx);
        let unix_ms = send::wall_clock_for(&tx);
        let socket = &request.socket.socket;
        let to = socket2::SockAddr::from(request.to);
        let sent = tx
            .publish(Instant::now(), unix_ms, frame, &mut |parts| {
                let joined;
                let datagram = match parts {
                    [one] => *one,
                    more => {
                        joined = more.concat();
                        &joined
                    }
                };
                send_waiting(socket, datagram, &to)
            })
            .map_err(Error::from);
        drop(tx);
        self.note_send(&sent);
        sent.map(drop)
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
        let pending = match id.session == self.identity.compat_session_id {
            true => lock(&self.services.pending).get(&id.counter).cloned(),
            false => None,
        };
        let Some(pending) = pending else {
            let issued = self.services.counter.load(Ordering::Relaxed);
            if id.session == self.identity.compat_session_id && id.counter <= issued {
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
                if let Err(e) = self.send_frame(channel, frame, address) {
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

/// Reads the service socket until the node is gone or stopped (its task
/// is aborted then). Callers waiting for an answer read it too, so an
/// answer wakes the caller's task itself; this task reads what comes
/// while none waits.
async fn answer_loop(inner: Weak<Inner>, socket: Arc<ServiceSocket>) {
    loop {
        if socket.socket.readable().await.is_err() {
            return;
        }
        let Some(inner) = inner.upgrade() else {
            return;
        };
        if !inner.drain_answers(&socket) {
            // Another reader is at it: let it finish.
            tokio::task::yield_now().await;
        }
        drop(inner);
        tokio::task::consume_budget().await;
    }
}
