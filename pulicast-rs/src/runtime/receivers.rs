//! The receive side of a node's state: its receive sockets and one
//! receiver per socket, with what is summed over them.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use super::delivery::{Delivery, Outbox};
use crate::proto::receiver::{self, KeyUse};
use crate::proto::Receiver;
use crate::sync::lock;
use crate::transport::ReceivePool;

/// One receive socket's receiver, and its handlers' outbox.
pub(super) struct Shard {
    receiver: Mutex<Receiver<Delivery>>,
    pub(super) outbox: Arc<Mutex<Outbox>>,
    /// The outbox being handed out; held while its handlers run, so that
    /// messages reach each handler in the order they came. Swapped with
    /// `outbox`, so both keep their capacity.
    pub(super) calling: Mutex<Outbox>,
}

impl Shard {
    /// See [`Receiver::add_own_port`].
    pub(super) fn add_own_port(&self, port: u16) {
        self.lock().add_own_port(port);
    }

    fn new(receiver: Receiver<Delivery>) -> Arc<Self> {
        Arc::new(Self {
            receiver: Mutex::new(receiver),
            outbox: Arc::default(),
            calling: Mutex::default(),
        })
    }

    /// The receiver, locked.
    pub(super) fn lock(&self) -> MutexGuard<'_, Receiver<Delivery>> {
        lock(&self.receiver)
    }
}

/// The receive path of a node: its sockets and their receivers.
pub(super) struct Receiving {
    /// The receive path (dispatch, leads, reassembly and opening), one
    /// receiver per socket of the pool.
    pub(super) receivers: Receivers,
    /// The receive sockets. Lock order: pool, then a receiver, then the
    /// reassembly the receivers share.
    pub(super) pool: Mutex<ReceivePool>,
    /// Receive sockets open: read by `stats` without the pool's lock, so a
    /// log layer may call `Node::stats` from a line written under it.
    pub(super) sockets: AtomicUsize,
}

impl Receiving {
    pub(super) fn new(first: Receiver<Delivery>, pool: ReceivePool) -> Self {
        Self {
            receivers: Receivers::new(first),
            pool: Mutex::new(pool),
            sockets: AtomicUsize::new(0),
        }
    }

    /// Closes every socket and drops every subscriber, which closes their
    /// queues. Under the pool's lock, which a subscription checks the
    /// node's stop under, so none outlives it.
    pub(super) fn close(&self) {
        let mut pool = lock(&self.pool);
        for shard in self.receivers.all() {
            shard.lock().clear();
        }
        pool.close();
        self.sockets.store(0, Ordering::Relaxed);
    }
}

/// The node's receivers: the one at index `i` serves the pool's socket
/// `i` ([`ReceivePool::socket_of`]), so each socket is read under its own
/// receiver's lock and sockets are read in parallel. They share one
/// reassembly ([`Receiver::sibling`]).
pub(super) struct Receivers {
    /// By pool socket.
    pooled: Mutex<Vec<Arc<Shard>>>,
    /// Receivers of sockets outside the pool (the send socket, where
    /// service replies come).
    other: Mutex<Vec<Arc<Shard>>>,
}

impl Receivers {
    /// The first receiver; the others are its siblings. It exists before
    /// any socket does, so counts and key uses always have one to read.
    pub(super) fn new(first: Receiver<Delivery>) -> Self {
        Self {
            pooled: Mutex::new(vec![Shard::new(first)]),
            other: Mutex::new(Vec::new()),
        }
    }

    /// The receiver of socket `index`, made if it is new.
    pub(super) fn get(&self, index: usize) -> Arc<Shard> {
        let mut shards = lock(&self.pooled);
        while shards.len() <= index {
            let sibling = shards[0].lock().sibling();
            shards.push(Shard::new(sibling));
        }
        Arc::clone(&shards[index])
    }

    /// A new receiver for a socket outside the pool, without gossip.
    pub(super) fn add_other(&self) -> Arc<Shard> {
        let mut sibling = self.get(0).lock().sibling();
        sibling.set_gossip(false);
        let shard = Shard::new(sibling);
        lock(&self.other).push(Arc::clone(&shard));
        shard
    }

    /// Every receiver, to read or clear each under its own lock.
    pub(super) fn all(&self) -> Vec<Arc<Shard>> {
        let mut all = lock(&self.pooled).clone();
        all.extend(lock(&self.other).iter().cloned());
        all
    }

    /// What all receivers did so far, summed.
    pub(super) fn counts(&self) -> receiver::ReceiveCounts {
        let mut sum = receiver::ReceiveCounts::default();
        for shard in self.all() {
            sum.add(shard.lock().counts());
        }
        sum
    }

    /// What each namespace's keys met, over all receivers.
    pub(super) fn key_uses(&self) -> Vec<KeyUse> {
        let mut sum: Vec<KeyUse> = Vec::new();
        for shard in self.all() {
            for used in shard.lock().key_uses() {
                match sum.iter_mut().find(|u| u.namespace == used.namespace) {
                    Some(u) => {
                        u.opened += used.opened;
                        u.not_opened += used.not_opened;
                        u.unsealed += used.unsealed;
                    }
                    None => sum.push(used),
                }
            }
        }
        sum
    }
}
