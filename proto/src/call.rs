//! The caller's side of one service call, sans-IO:
//! when to send the request (again), what the server's frames mean, the
//! progress messages in order, the deadline and cancelling. The runtime
//! sends what [`Call::poll_transmit`] gives, feeds what it hears to
//! [`Call::handle`], and wakes at [`Call::poll_timeout`].
//!
//! The request is sent again, less and less often, until the call ends: a
//! lost request or a lost reply is made up for, and the server runs the
//! call once whatever it hears (see [`super::service::Admission`]).
//!
//! ```
//! use std::time::{Duration, Instant};
//! use pulicast_proto::call::{Call, Event};
//! use pulicast_proto::wire::service::{CallId, Frame};
//!
//! let now = Instant::now();
//! let id = CallId { session: 1, counter: 1 };
//! let mut call = Call::new(id, b"request frame".to_vec(), now, now + Duration::from_secs(1));
//! assert_eq!(call.poll_transmit(now).as_deref(), Some(&b"request frame"[..]));
//! call.handle(&Frame::Progress { call: id, seq: 0, message: b"half" }, now);
//! call.handle(&Frame::Reply { call: id, progress: 1, message: b"done" }, now);
//! assert_eq!(call.poll_event(), Some(Event::Progress(b"half".to_vec())));
//! assert_eq!(call.poll_event(), Some(Event::Reply { message: b"done".to_vec(), missed_progress: 0 }));
//! assert!(call.is_done());
//! ```

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use crate::wire::service::{CallId, Frame};

/// The first wait before the request is sent again; it doubles up to
/// [`MAX_RESEND`].
pub const FIRST_RESEND: Duration = Duration::from_millis(50);

/// The longest wait between two sends of a request.
pub const MAX_RESEND: Duration = Duration::from_secs(1);

/// Progress messages held while an earlier one is missing; beyond, the
/// earliest missing ones are given up.
pub const MAX_EARLY_PROGRESS: usize = 64;

/// Progress messages delivered in order but not yet taken by the caller,
/// at most; beyond, the oldest are dropped (and counted as missed), so a
/// caller that does not read progress holds a bounded amount.
pub const MAX_QUEUED_PROGRESS: usize = 1024;

/// Bytes of progress messages waiting, early or in order, at most.
pub const MAX_PROGRESS_BYTES: usize = 16 << 20;

/// How many times a cancel is sent (it is not answered).
const CANCELS: u32 = 3;

/// What the caller is told.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Event {
    /// A progress message, in the order the handler sent them.
    Progress(Vec<u8>),
    /// The reply: the call is done.
    Reply {
        /// The reply message.
        message: Vec<u8>,
        /// Progress messages that never arrived.
        missed_progress: u32,
    },
    /// The server's handler failed: the call is done.
    Failed {
        /// The code.
        code: u16,
        /// Why.
        message: String,
        /// The server node.
        node: String,
    },
    /// The server runs as many calls as it may: the call is done.
    Busy,
    /// No reply by the deadline: the call is done.
    TimedOut,
}

impl Event {
    /// Whether it ends the call (all but progress do).
    pub fn is_final(&self) -> bool {
        !matches!(self, Event::Progress(_))
    }
}

/// One call in flight: see the module.
#[derive(Debug)]
pub struct Call {
    id: CallId,
    request: Vec<u8>,
    deadline: Instant,
    next_send: Instant,
    resend: Duration,
    /// The next progress message to deliver (past `u32::MAX` once the
    /// last one came), and those that came early.
    next_progress: u64,
    early: BTreeMap<u32, Vec<u8>>,
    skipped: u32,
    events: VecDeque<Event>,
    done: bool,
    /// Cancel frames still to send, and when the next one is due.
    cancels: Option<(u32, Instant)>,
    /// Requests given out to send so far.
    transmissions: u32,
    /// Whether the server said anything of the call yet.
    heard: bool,
    /// Bytes of progress messages held (early or queued).
    progress_bytes: usize,
}

impl Call {
    /// A call whose encoded request frame is `request`, ending by
    /// `deadline`.
    pub fn new(id: CallId, request: Vec<u8>, now: Instant, deadline: Instant) -> Self {
        Self {
            id,
            request,
            deadline,
            next_send: now,
            resend: FIRST_RESEND,
            next_progress: 0,
            early: BTreeMap::new(),
            skipped: 0,
            events: VecDeque::new(),
            done: false,
            cancels: None,
            transmissions: 0,
            heard: false,
            progress_bytes: 0,
        }
    }

    /// The call's id.
    pub fn id(&self) -> CallId {
        self.id
    }

    /// Whether the call has ended (its last event may still be waiting in
    /// [`Call::poll_event`]).
    pub fn is_done(&self) -> bool {
        self.done
    }

    /// The request's bytes if a send (the first, or again) is due while
    /// the call runs; `None` otherwise. Cancels are due by
    /// [`Call::poll_cancel`].
    pub fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>> {
        if self.done || now < self.next_send {
            return None;
        }
        self.next_send = now + self.resend;
        self.resend = (self.resend * 2).min(MAX_RESEND);
        self.transmissions += 1;
        Some(self.request.clone())
    }

    /// How many times [`Call::poll_transmit`] gave the request out (a
    /// path that can't lose it sends only the first).
    pub fn transmissions(&self) -> u32 {
        self.transmissions
    }

    /// Whether the server has said it has the call: any frame of it
    /// (running, progress, an end). A caller choosing among servers goes
    /// elsewhere only while this is false, so no call runs twice for
    /// want of patience.
    pub fn heard(&self) -> bool {
        self.heard
    }

    /// Whether an event waits in [`Call::poll_event`].
    pub fn has_event(&self) -> bool {
        !self.events.is_empty()
    }

    /// Whether a cancel frame is due now (sent a few times, unanswered).
    pub fn poll_cancel(&mut self, now: Instant) -> bool {
        match &mut self.cancels {
            Some((left, next)) if *left > 0 && now >= *next => {
                *left -= 1;
                *next = now + FIRST_RESEND;
                true
            }
            _ => false,
        }
    }

    /// When [`Call::handle_timeout`] must run next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        let cancel = self.cancels.filter(|(left, _)| *left > 0).map(|(_, at)| at);
        match (self.done, cancel) {
            (true, at) => at,
            (false, Some(at)) => Some(at.min(self.next_send).min(self.deadline)),
            (false, None) => Some(self.next_send.min(self.deadline)),
        }
    }

    /// Ends the call at its deadline.
    pub fn handle_timeout(&mut self, now: Instant) {
        if !self.done && now >= self.deadline {
            self.finish(Event::TimedOut);
        }
    }

    /// Gives up the call (the caller dropped it or cancelled): nothing
    /// more is delivered, and a few cancel frames are due
    /// ([`Call::poll_cancel`]) so the server's handler learns of it.
    pub fn cancel(&mut self, now: Instant) {
        if self.done {
            return;
        }
        self.done = true;
        self.events.clear();
        self.early.clear();
        self.progress_bytes = 0;
        self.cancels = Some((CANCELS, now));
    }

    /// Takes a frame heard for this service; frames of other calls are
    /// ignored (false).
    pub fn handle(&mut self, frame: &Frame<'_>, _now: Instant) -> bool {
        if frame.call() != self.id {
            return false;
        }
        if self.done {
            return true;
        }
        if !matches!(frame, Frame::Request { .. } | Frame::Cancel { .. }) {
            self.heard = true;
        }
        match *frame {
            Frame::Progress { seq, message, .. } => self.progress(seq, message),
            Frame::Reply {
                progress, message, ..
            } => {
                // What came early is delivered, what never came is counted.
                while let Some((seq, early)) = self.early.pop_first() {
                    if seq >= progress {
                        break;
                    }
                    self.skip_to(u64::from(seq));
                    self.next_progress += 1;
                    self.events.push_back(Event::Progress(early));
                }
                self.early.clear();
                self.skip_to(u64::from(progress));
                let missed = self.skipped;
                self.finish(Event::Reply {
                    message: message.to_vec(),
                    missed_progress: missed,
                });
            }
            Frame::Failure {
                code,
                message,
                node,
                ..
            } => self.finish(Event::Failed {
                code,
                message: message.to_string(),
                node: node.to_string(),
            }),
            Frame::Busy { .. } => self.finish(Event::Busy),
            // Heard above; the reply comes later.
            Frame::Running { .. } => {}
            // Frames only callers send.
            Frame::Request { .. } | Frame::Cancel { .. } => {}
        }
        true
    }

    fn progress(&mut self, seq: u32, message: &[u8]) {
        if u64::from(seq) < self.next_progress || self.early.contains_key(&seq) {
            return; // a duplicate
        }
        self.early.insert(seq, message.to_vec());
        self.progress_bytes += message.len();
        if self.early.len() > MAX_EARLY_PROGRESS {
            // Too much waits on one lost message: give it up.
            if let Some((&first, _)) = self.early.first_key_value() {
                self.skip_to(u64::from(first));
            }
        }
        while let Some(message) = u32::try_from(self.next_progress)
            .ok()
            .and_then(|next| self.early.remove(&next))
        {
            self.next_progress += 1;
            self.events.push_back(Event::Progress(message));
        }
        self.bound_progress();
    }

    /// Gives up the progress messages before `seq` not delivered yet.
    fn skip_to(&mut self, seq: u64) {
        if seq > self.next_progress {
            let gap = u32::try_from(seq - self.next_progress).unwrap_or(u32::MAX);
            self.skipped = self.skipped.saturating_add(gap);
            self.next_progress = seq;
        }
    }

    /// Drops the oldest progress waiting while there is too much of it.
    fn bound_progress(&mut self) {
        let queued = |events: &VecDeque<Event>| {
            events
                .iter()
                .filter(|e| matches!(e, Event::Progress(_)))
                .count()
        };
        while queued(&self.events) > MAX_QUEUED_PROGRESS
            || (self.progress_bytes > MAX_PROGRESS_BYTES && !self.events.is_empty())
        {
            match self.events.pop_front() {
                Some(Event::Progress(dropped)) => {
                    self.progress_bytes = self.progress_bytes.saturating_sub(dropped.len());
                    self.skipped = self.skipped.saturating_add(1);
                }
                Some(other) => {
                    self.events.push_front(other);
                    break;
                }
                None => break,
            }
        }
        // Early messages over the bytes bound: the latest go.
        while self.progress_bytes > MAX_PROGRESS_BYTES {
            let Some((_, dropped)) = self.early.pop_last() else {
                break;
            };
            self.progress_bytes = self.progress_bytes.saturating_sub(dropped.len());
        }
    }

    fn finish(&mut self, event: Event) {
        self.done = true;
        self.events.push_back(event);
    }

    /// The next event for the caller, in order.
    pub fn poll_event(&mut self) -> Option<Event> {
        let event = self.events.pop_front();
        if let Some(Event::Progress(m)) = &event {
            self.progress_bytes = self.progress_bytes.saturating_sub(m.len());
        }
        event
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::{Admission, Admit, ServiceLimits};

    const ID: CallId = CallId {
        session: 5,
        counter: 1,
    };

    fn events(call: &mut Call) -> Vec<Event> {
        std::iter::from_fn(|| call.poll_event()).collect()
    }

    #[test]
    fn the_request_is_sent_again_less_and_less_often_until_the_deadline() {
        let t = Instant::now();
        let mut call = Call::new(ID, b"req".to_vec(), t, t + Duration::from_secs(3));
        let mut sends = Vec::new();
        let mut now = t;
        while !call.is_done() {
            if call.poll_transmit(now).is_some() {
                sends.push(now - t);
            }
            now = call.poll_timeout().unwrap_or(now);
            call.handle_timeout(now);
        }
        assert_eq!(events(&mut call), [Event::TimedOut]);
        let ms: Vec<u128> = sends.iter().map(Duration::as_millis).collect();
        assert_eq!(ms, [0, 50, 150, 350, 750, 1550, 2550]);
        assert_eq!(call.poll_transmit(now), None);
    }

    #[test]
    fn progress_is_delivered_in_order_and_gaps_are_counted() {
        let t = Instant::now();
        let mut call = Call::new(ID, vec![], t, t + Duration::from_secs(1));
        let p = |seq, message: &'static [u8]| Frame::Progress {
            call: ID,
            seq,
            message,
        };
        call.handle(&p(1, b"b"), t);
        call.handle(&p(0, b"a"), t);
        call.handle(&p(0, b"a"), t); // a duplicate
        call.handle(&p(3, b"d"), t); // 2 is lost
        let other = CallId {
            session: 5,
            counter: 2,
        };
        assert!(!call.handle(&Frame::Busy { call: other }, t));
        call.handle(
            &Frame::Reply {
                call: ID,
                progress: 4,
                message: b"r",
            },
            t,
        );
        assert_eq!(
            events(&mut call),
            [
                Event::Progress(b"a".to_vec()),
                Event::Progress(b"b".to_vec()),
                Event::Progress(b"d".to_vec()),
                Event::Reply {
                    message: b"r".to_vec(),
                    missed_progress: 1
                },
            ]
        );
        // After the end, nothing more.
        call.handle(&p(9, b"late"), t);
        assert_eq!(call.poll_event(), None);
    }

    #[test]
    fn progress_a_caller_does_not_read_is_bounded_and_counted() {
        let t = Instant::now();
        let mut call = Call::new(ID, vec![], t, t + Duration::from_secs(1));
        let n = MAX_QUEUED_PROGRESS as u32 + 100;
        for seq in 0..n {
            let message = [1u8; 8];
            call.handle(
                &Frame::Progress {
                    call: ID,
                    seq,
                    message: &message,
                },
                t,
            );
        }
        call.handle(
            &Frame::Reply {
                call: ID,
                progress: n,
                message: b"r",
            },
            t,
        );
        let all = events(&mut call);
        assert_eq!(all.len(), MAX_QUEUED_PROGRESS + 1);
        assert_eq!(
            all.last(),
            Some(&Event::Reply {
                message: b"r".to_vec(),
                missed_progress: 100
            })
        );

        // Bytes too: a few huge messages, and the oldest go.
        let mut call = Call::new(ID, vec![], t, t + Duration::from_secs(1));
        let big = vec![0u8; MAX_PROGRESS_BYTES / 4 + 1];
        for seq in 0..8 {
            call.handle(
                &Frame::Progress {
                    call: ID,
                    seq,
                    message: &big,
                },
                t,
            );
        }
        let held: usize = std::iter::from_fn(|| call.poll_event())
            .map(|e| match e {
                Event::Progress(m) => m.len(),
                _ => 0,
            })
            .sum();
        assert!(held <= MAX_PROGRESS_BYTES, "{held}");
    }

    #[test]
    fn sequence_numbers_at_the_end_of_their_range_neither_panic_nor_repeat() {
        let t = Instant::now();
        let mut call = Call::new(ID, vec![], t, t + Duration::from_secs(1));
        // 65 early ones near the top make the call give up the gap.
        for seq in (u32::MAX - 64)..=u32::MAX {
            call.handle(
                &Frame::Progress {
                    call: ID,
                    seq,
                    message: b"x",
                },
                t,
            );
        }
        call.handle(
            &Frame::Progress {
                call: ID,
                seq: u32::MAX,
                message: b"x",
            },
            t,
        );
        call.handle(
            &Frame::Progress {
                call: ID,
                seq: 0,
                message: b"again",
            },
            t,
        );
        let all = events(&mut call);
        assert_eq!(all.len(), 65);
        assert!(all.iter().all(|e| *e == Event::Progress(b"x".to_vec())));
        call.handle(
            &Frame::Reply {
                call: ID,
                progress: u32::MAX,
                message: b"r",
            },
            t,
        );
        assert!(matches!(call.poll_event(), Some(Event::Reply { .. })));
    }

    #[test]
    fn running_is_heard_and_ends_nothing() {
        let t = Instant::now();
        let mut call = Call::new(ID, vec![], t, t + Duration::from_secs(1));
        assert!(!call.heard());
        // Another call's frame, or a caller's own, says nothing of this one.
        let other = CallId {
            session: 1,
            counter: 9,
        };
        call.handle(&Frame::Running { call: other }, t);
        call.handle(&Frame::Cancel { call: ID }, t);
        assert!(!call.heard());
        call.handle(&Frame::Running { call: ID }, t);
        assert!(call.heard());
        assert!(!call.is_done() && !call.has_event());
        let mut busy = Call::new(ID, vec![], t, t + Duration::from_secs(1));
        busy.handle(&Frame::Busy { call: ID }, t);
        assert!(busy.heard(), "busy is an answer too");
    }

    #[test]
    fn busy_failure_and_cancel_end_the_call() {
        let t = Instant::now();
        let deadline = t + Duration::from_secs(1);
        let mut busy = Call::new(ID, vec![], t, deadline);
        busy.handle(&Frame::Busy { call: ID }, t);
        assert_eq!(events(&mut busy), [Event::Busy]);
        let mut failed = Call::new(ID, vec![], t, deadline);
        failed.handle(
            &Frame::Failure {
                call: ID,
                code: 3,
                message: "no path",
                node: "planner",
            },
            t,
        );
        assert!(matches!(
            &events(&mut failed)[..],
            [Event::Failed { code: 3, .. }]
        ));
        let mut cancelled = Call::new(ID, vec![], t, deadline);
        cancelled.cancel(t);
        let mut cancels = 0;
        let mut now = t;
        while let Some(at) = cancelled.poll_timeout() {
            now = at.max(now);
            if cancelled.poll_cancel(now) {
                cancels += 1;
            } else {
                break;
            }
        }
        assert_eq!(cancels, CANCELS);
        assert_eq!(cancelled.poll_transmit(now), None);
        assert_eq!(cancelled.poll_event(), None);
    }

    /// A small deterministic random source (no dependency, no clock).
    struct Lcg(u64);
    impl Lcg {
        fn lose(&mut self, percent: u64) -> bool {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 33) % 100 < percent
        }
    }

    /// Calls through a link that loses 30 % of frames each way: every call
    /// ends with its reply before its deadline, and runs once at the server.
    #[test]
    fn under_thirty_percent_loss_each_call_runs_once_and_ends() {
        let mut link = Lcg(42);
        let mut server = Admission::new(ServiceLimits::default());
        let mut runs = std::collections::HashMap::new();
        let t0 = Instant::now();
        for counter in 0..200 {
            let id = CallId {
                session: 1,
                counter,
            };
            let mut request = Vec::new();
            Frame::Request {
                call: id,
                target: "",
                deadline_ms: 10_000,
                message: b"req",
            }
            .encode(&mut request)
            .unwrap_or_default();
            let mut call = Call::new(id, request, t0, t0 + Duration::from_secs(10));
            let mut now = t0;
            while !call.is_done() {
                if let Some(bytes) = call.poll_transmit(now) {
                    if !link.lose(30) {
                        let Ok(Frame::Request { call: id, .. }) = Frame::decode(&bytes) else {
                            panic!("not a request");
                        };
                        let answer = match server.admit(id, &"caller", now) {
                            Admit::Run => {
                                *runs.entry(id).or_insert(0) += 1;
                                let mut reply = Vec::new();
                                Frame::Reply {
                                    call: id,
                                    progress: 0,
                                    message: b"ok",
                                }
                                .encode(&mut reply)
                                .unwrap_or_default();
                                server.finish(id, reply.clone(), now);
                                Some(reply)
                            }
                            Admit::Resend(reply) => Some(reply),
                            other => panic!("{other:?}"),
                        };
                        if let Some(reply) = answer.filter(|_| !link.lose(30)) {
                            let frame = Frame::decode(&reply).unwrap_or(Frame::Busy { call: id });
                            call.handle(&frame, now);
                        }
                    }
                }
                now = call.poll_timeout().unwrap_or(now);
                call.handle_timeout(now);
            }
            assert!(
                matches!(call.poll_event(), Some(Event::Reply { .. })),
                "call {counter} did not get its reply"
            );
        }
        assert_eq!(runs.len(), 200);
        assert!(runs.values().all(|n| *n == 1));
        assert!(server.counts().resent > 0, "no reply was lost and resent");
    }
}
