//! The server's side of a service's calls, sans-IO: which requests to run, which are retransmissions of calls
//! running or done, and how many may run at once. The runtime runs the
//! handlers and sends the frames; time is passed in.
//!
//! At most once: a call is run once. A retransmitted request of a call
//! still running is ignored (its reply will come); one of a call done is
//! answered with the cached final frame, and if that frame was too large
//! to keep, with a failure saying so instead of running the call again.
//! A call done is remembered with its answer for a while
//! ([`ServiceLimits::remembered`], [`ServiceLimits::remember_for`]); after that, its
//! caller's session keeps a mark, the highest counter forgotten, and a
//! request at or below it is answered [`Admit::Forgotten`], never run. A
//! caller numbers its calls upwards, so a mark costs 8 bytes however many
//! calls the session makes. The marks of sessions that are no members are
//! bounded ([`ServiceLimits::sessions`], least recently used go first); a live
//! member's mark is kept for as long as it lives ([`Admission::trim_sessions`]).
//!
//! Fair shares: while the server runs half its [`ServiceLimits::concurrency`] or
//! more, a caller (one address, or one session) that already runs
//! [`ServiceLimits::share`] calls is answered busy, so one socket's flood of a
//! slow handler leaves room for everybody else.
//!
//! A call belongs to the caller whose request started it (`from`, its
//! address): a request under the same id from anyone else is refused
//! ([`Admit::Foreign`]), so nobody takes over a call or its answer by
//! reusing an id it saw.
//!
//! ```
//! use std::time::{Duration, Instant};
//! use pulicast_proto::service::{Admit, ServiceLimits, Admission};
//! use pulicast_proto::wire::service::CallId;
//!
//! let mut server = Admission::new(ServiceLimits { concurrency: 1, ..ServiceLimits::default() });
//! let now = Instant::now();
//! let (a, b) = (CallId { session: 1, counter: 1 }, CallId { session: 2, counter: 1 });
//! assert_eq!(server.admit(a, &"alice", now), Admit::Run);
//! assert_eq!(server.admit(b, &"bob", now), Admit::Busy);
//! assert_eq!(server.admit(a, &"alice", now), Admit::Running); // a retransmission
//! assert_eq!(server.admit(a, &"mallory", now), Admit::Foreign); // not hers
//! server.finish(a, b"the reply frame".to_vec(), now);
//! assert_eq!(server.admit(a, &"alice", now), Admit::Resend(b"the reply frame".to_vec()));
//! ```

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::hash::Hash;
use std::time::{Duration, Instant};

use crate::wire::service::CallId;

/// A server's bounds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ServiceLimits {
    /// Calls run at once; beyond, requests are answered busy.
    pub concurrency: usize,
    /// Calls done that are remembered (their id, and their final frame
    /// while it fits [`ServiceLimits::cache_bytes`]).
    pub remembered: usize,
    /// Bytes of final frames kept to answer retransmissions.
    pub cache_bytes: usize,
    /// How long a call done is remembered: longer than any caller keeps
    /// retransmitting.
    pub remember_for: Duration,
    /// The longest a call may run, whatever deadline its caller gave (and
    /// when it gave none): no request holds a slot longer.
    pub longest: Duration,
    /// Calls one caller (an address, or a session) may run at once while
    /// the server runs at least half its `concurrency`.
    pub share: usize,
    /// Sessions that are no members whose marks (see the module) are
    /// kept; beyond, the least recently heard is forgotten.
    pub sessions: usize,
}

impl Default for ServiceLimits {
    fn default() -> Self {
        Self {
            concurrency: 16,
            remembered: 4096,
            cache_bytes: 4 << 20,
            remember_for: Duration::from_secs(60),
            longest: Duration::from_secs(300),
            share: 4,
            sessions: 16384,
        }
    }
}

/// What to do with a request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Admit {
    /// Run it: a new call, and there is room.
    Run,
    /// Answer busy: as many calls run as may, or as many of this
    /// caller's as its share allows.
    Busy,
    /// A retransmission of a call still running: nothing to do.
    Running,
    /// A retransmission of a call done: send its final frame again.
    Resend(Vec<u8>),
    /// A retransmission of a call done whose final frame was too large to
    /// keep: answer with a failure rather than run it again.
    Lost,
    /// A request under the id of a call another caller started: ignore it.
    Foreign,
    /// A request of a call older than what the server remembers of its
    /// session (see the module): it may have run, so answer with a
    /// failure rather than run it.
    Forgotten,
}

/// What a server counts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ServiceCounts {
    /// Calls run.
    pub run: u64,
    /// Requests answered busy.
    pub busy: u64,
    /// Retransmissions of calls running, ignored.
    pub duplicates: u64,
    /// Retransmissions of calls done, answered from the cache.
    pub resent: u64,
    /// Retransmissions of calls done whose answer was not kept.
    pub lost: u64,
    /// Requests under the id of another caller's call, refused.
    pub foreign: u64,
    /// Requests answered busy because their caller ran its share (also
    /// counted in `busy`).
    pub over_share: u64,
    /// Requests of calls older than their session's mark, refused.
    pub forgotten: u64,
    /// Marks of sessions forgotten to stay within [`ServiceLimits::sessions`].
    pub sessions_forgotten: u64,
}

/// What a server keeps of a session once its calls done are forgotten.
#[derive(Debug, Clone, Copy)]
struct Mark {
    /// The highest counter of a call forgotten.
    below: u64,
    /// When it was last heard, in `Admission::tick`s (its key in `Admission::heard`).
    heard: u64,
}

#[derive(Debug)]
struct Done<A> {
    call: CallId,
    from: A,
    at: Instant,
    frame: Option<Vec<u8>>,
}

/// One service's calls at one server: see the module. `A` tells callers
/// apart (the runtime uses their addresses).
#[derive(Debug)]
pub struct Admission<A> {
    limits: ServiceLimits,
    running: HashMap<CallId, A>,
    /// Calls done, oldest first.
    done: VecDeque<Done<A>>,
    /// Where each call done is in `done`, by its position counted from the
    /// first ever pushed (`popped` + index).
    index: HashMap<CallId, u64>,
    popped: u64,
    cached_bytes: usize,
    counts: ServiceCounts,
    /// Calls running, by caller address and by session.
    held: HashMap<A, usize>,
    held_by_session: HashMap<i64, usize>,
    marks: HashMap<i64, Mark>,
    /// Sessions with a mark, least recently heard first.
    heard: BTreeMap<u64, i64>,
    tick: u64,
}

impl<A: Clone + Eq + Hash> Admission<A> {
    /// A server within `limits`.
    pub fn new(limits: ServiceLimits) -> Self {
        Self {
            limits,
            running: HashMap::new(),
            done: VecDeque::new(),
            index: HashMap::new(),
            popped: 0,
            cached_bytes: 0,
            counts: ServiceCounts::default(),
            held: HashMap::new(),
            held_by_session: HashMap::new(),
            marks: HashMap::new(),
            heard: BTreeMap::new(),
            tick: 0,
        }
    }

    /// Decides on a request of `call` from caller `from`, heard at `now`.
    pub fn admit(&mut self, call: CallId, from: &A, now: Instant) -> Admit {
        self.expire(now);
        if let Some(owner) = self.running.get(&call) {
            if owner != from {
                self.counts.foreign += 1;
                return Admit::Foreign;
            }
            self.counts.duplicates += 1;
            return Admit::Running;
        }
        if let Some(at) = self.index.get(&call) {
            let position = usize::try_from(at - self.popped).unwrap_or(usize::MAX);
            if let Some(done) = self.done.get(position) {
                if done.from != *from {
                    self.counts.foreign += 1;
                    return Admit::Foreign;
                }
                return match &done.frame {
                    Some(frame) => {
                        self.counts.resent += 1;
                        Admit::Resend(frame.clone())
                    }
                    None => {
                        self.counts.lost += 1;
                        Admit::Lost
                    }
                };
            }
        }
        if let Some(mark) = self.marks.get(&call.session).copied() {
            self.hear(call.session, mark);
            if call.counter <= mark.below {
                self.counts.forgotten += 1;
                return Admit::Forgotten;
            }
        }
        if self.running.len() >= self.limits.concurrency {
            self.counts.busy += 1;
            return Admit::Busy;
        }
        let contended = self.running.len() * 2 >= self.limits.concurrency;
        let held = self.held.get(from).copied().unwrap_or(0);
        let held_by_session = self.held_by_session.get(&call.session).copied();
        if contended && held.max(held_by_session.unwrap_or(0)) >= self.limits.share {
            self.counts.busy += 1;
            self.counts.over_share += 1;
            return Admit::Busy;
        }
        self.counts.run += 1;
        self.running.insert(call, from.clone());
        *self.held.entry(from.clone()).or_default() += 1;
        *self.held_by_session.entry(call.session).or_default() += 1;
        Admit::Run
    }

    /// Moves `session`'s mark to the most recently heard.
    fn hear(&mut self, session: i64, mut mark: Mark) {
        self.heard.remove(&mark.heard);
        self.tick += 1;
        mark.heard = self.tick;
        self.heard.insert(self.tick, session);
        self.marks.insert(session, mark);
    }

    /// The call ended; `frame` is its final frame (reply or failure), kept
    /// to answer retransmissions while the cache holds it.
    pub fn finish(&mut self, call: CallId, frame: Vec<u8>, now: Instant) {
        let Some(from) = self.running.remove(&call) else {
            return;
        };
        release(&mut self.held, &from);
        release(&mut self.held_by_session, &call.session);
        let frame = (frame.len() <= self.limits.cache_bytes).then_some(frame);
        self.cached_bytes += frame.as_ref().map_or(0, Vec::len);
        self.index
            .insert(call, self.popped + self.done.len() as u64);
        self.done.push_back(Done {
            call,
            from,
            at: now,
            frame,
        });
        // Over the bytes bound: the oldest answers go first, their ids
        // stay (a retransmission then gets `Lost`, not a second run).
        let mut i = 0;
        while self.cached_bytes > self.limits.cache_bytes && i < self.done.len() {
            if let Some(dropped) = self.done[i].frame.take() {
                self.cached_bytes -= dropped.len();
            }
            i += 1;
        }
        while self.done.len() > self.limits.remembered {
            self.pop_oldest();
        }
    }

    /// Whether `call` runs now: a cancel for it should reach its handler,
    /// which then ends it as any call, by [`Admission::finish`].
    pub fn is_running(&self, call: CallId) -> bool {
        self.running.contains_key(&call)
    }

    /// Forgets calls done longer ago than [`ServiceLimits::remember_for`].
    pub fn expire(&mut self, now: Instant) {
        while self
            .done
            .front()
            .is_some_and(|d| now.saturating_duration_since(d.at) > self.limits.remember_for)
        {
            self.pop_oldest();
        }
    }

    fn pop_oldest(&mut self) {
        if let Some(done) = self.done.pop_front() {
            self.popped += 1;
            self.index.remove(&done.call);
            self.cached_bytes -= done.frame.map_or(0, |f| f.len());
            let CallId { session, counter } = done.call;
            let mark = self.marks.get(&session).copied().unwrap_or(Mark {
                below: counter,
                heard: 0,
            });
            let below = mark.below.max(counter);
            self.hear(session, Mark { below, ..mark });
        }
    }

    /// Whether more sessions are marked than [`ServiceLimits::sessions`], so that
    /// [`Admission::trim_sessions`] has work.
    pub fn over_sessions(&self) -> bool {
        self.marks.len() > self.limits.sessions
    }

    /// Forgets the marks of the least recently heard sessions for which
    /// `live` is false, down to nine tenths of [`ServiceLimits::sessions`] (so
    /// that a flood of new sessions trims once per many calls). A live
    /// caller's mark is never forgotten: its requests are refused for as
    /// long as it lives, which bounds the marks by the members.
    pub fn trim_sessions(&mut self, live: impl Fn(i64) -> bool) {
        if !self.over_sessions() {
            return;
        }
        let target = self.limits.sessions - self.limits.sessions / 10;
        let mut excess = self.marks.len().saturating_sub(target);
        let mut gone = Vec::new();
        for (&heard, &session) in &self.heard {
            if excess == 0 {
                break;
            }
            if !live(session) {
                gone.push((heard, session));
                excess -= 1;
            }
        }
        for (heard, session) in gone {
            self.heard.remove(&heard);
            self.marks.remove(&session);
            self.counts.sessions_forgotten += 1;
        }
    }

    /// Sessions with a mark.
    pub fn sessions(&self) -> usize {
        self.marks.len()
    }

    /// Calls running now.
    pub fn running(&self) -> usize {
        self.running.len()
    }

    /// Bytes of final frames kept.
    pub fn cached_bytes(&self) -> usize {
        self.cached_bytes
    }

    /// What it counted.
    pub fn counts(&self) -> ServiceCounts {
        self.counts
    }
}

/// One call fewer held by `who`.
fn release<K: Eq + Hash>(held: &mut HashMap<K, usize>, who: &K) {
    if let Some(n) = held.get_mut(who) {
        *n -= 1;
        if *n == 0 {
            held.remove(who);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn call(counter: u64) -> CallId {
        CallId {
            session: 9,
            counter,
        }
    }

    #[test]
    fn each_call_runs_once_however_often_it_is_asked() {
        let mut server = Admission::<u8>::new(ServiceLimits::default());
        let t = Instant::now();
        let mut runs = 0;
        // Every request is sent three times, as a lossy link makes callers do.
        for counter in 0..100 {
            for _ in 0..3 {
                match server.admit(call(counter), &1, t) {
                    Admit::Run => {
                        runs += 1;
                        server.finish(call(counter), vec![counter as u8; 10], t);
                    }
                    Admit::Resend(frame) => assert_eq!(frame, vec![counter as u8; 10]),
                    other => panic!("{other:?}"),
                }
            }
        }
        assert_eq!(runs, 100);
        let counts = server.counts();
        assert_eq!((counts.run, counts.resent), (100, 200));
    }

    #[test]
    fn concurrency_is_bounded_and_busy_counted() {
        let mut server = Admission::<u8>::new(ServiceLimits {
            concurrency: 2,
            ..ServiceLimits::default()
        });
        let t = Instant::now();
        assert_eq!(server.admit(call(1), &1, t), Admit::Run);
        assert_eq!(server.admit(call(2), &1, t), Admit::Run);
        assert_eq!(server.admit(call(3), &1, t), Admit::Busy);
        assert_eq!(server.admit(call(1), &1, t), Admit::Running);
        assert!(server.is_running(call(1)));
        // Another caller under the same id neither runs nor gets it.
        assert_eq!(server.admit(call(1), &2, t), Admit::Foreign);
        server.finish(call(1), b"r".to_vec(), t);
        assert_eq!(server.admit(call(3), &1, t), Admit::Run);
        let counts = server.counts();
        assert_eq!((counts.busy, counts.duplicates, counts.foreign), (1, 1, 1));
        // Finishing a call that never ran changes nothing.
        server.finish(call(77), b"x".to_vec(), t);
        assert_eq!(server.admit(call(77), &1, t), Admit::Busy);
        // A call done is answered to its caller only.
        server.finish(call(2), b"two".to_vec(), t);
        assert_eq!(server.admit(call(2), &2, t), Admit::Foreign);
        assert_eq!(server.admit(call(2), &1, t), Admit::Resend(b"two".to_vec()));
    }

    #[test]
    fn memory_is_bounded_and_a_forgotten_answer_is_not_a_second_run() {
        let limits = ServiceLimits {
            concurrency: 4,
            remembered: 10,
            cache_bytes: 100,
            ..ServiceLimits::default()
        };
        let mut server = Admission::<u8>::new(limits);
        let t = Instant::now();
        for counter in 0..5 {
            assert_eq!(server.admit(call(counter), &1, t), Admit::Run);
            server.finish(call(counter), vec![0; 40], t);
            assert!(server.cached_bytes() <= 100);
        }
        // The oldest answers were dropped for bytes: remembered, not rerun.
        assert_eq!(server.admit(call(0), &1, t), Admit::Lost);
        assert!(matches!(server.admit(call(4), &1, t), Admit::Resend(_)));
        // Too large to keep at all.
        assert_eq!(server.admit(call(50), &1, t), Admit::Run);
        server.finish(call(50), vec![0; 1000], t);
        assert_eq!(server.admit(call(50), &1, t), Admit::Lost);
        // Past `remembered` ids and past `remember_for`, calls are
        // forgotten, yet never run again: their session's mark refuses them.
        for counter in 100..120 {
            assert_eq!(server.admit(call(counter), &1, t), Admit::Run);
            server.finish(call(counter), vec![1], t);
        }
        assert_eq!(server.admit(call(4), &1, t), Admit::Forgotten);
        let later = t + Duration::from_secs(61);
        assert_eq!(server.admit(call(119), &1, later), Admit::Forgotten);
        assert!(server.cached_bytes() <= 100);
        assert_eq!(server.sessions(), 1, "one mark for the session's 25 calls");
        // The session's next call runs.
        assert_eq!(server.admit(call(120), &1, later), Admit::Run);
    }

    fn of(session: i64, counter: u64) -> CallId {
        CallId { session, counter }
    }

    #[test]
    fn a_request_replayed_after_any_number_of_calls_never_runs_again() {
        let limits = ServiceLimits {
            remembered: 16,
            sessions: 100,
            ..ServiceLimits::default()
        };
        let mut server = Admission::<u32>::new(limits);
        let t = Instant::now();
        let victim = of(7, 1);
        assert_eq!(server.admit(victim, &7, t), Admit::Run);
        server.finish(victim, b"moved the arm".to_vec(), t);
        // A stranger's fresh sessions, one call each, far beyond every
        // bound, push the victim's call and then its session's mark out
        // unless the victim lives.
        let mut stranger = 1_000;
        let mut flood = |server: &mut Admission<u32>, live: &dyn Fn(i64) -> bool| {
            for _ in 0..5_000 {
                stranger += 1;
                let call = of(stranger, 1);
                assert_eq!(server.admit(call, &99, t), Admit::Run);
                server.finish(call, vec![0; 8], t);
                server.trim_sessions(live);
            }
        };
        flood(&mut server, &|s| s == 7);
        assert!(server.sessions() <= 101, "{} marks", server.sessions());
        // Replayed from the victim's address or any other: not run.
        assert_eq!(server.admit(victim, &7, t), Admit::Forgotten);
        assert_eq!(server.admit(victim, &99, t), Admit::Forgotten);
        assert_eq!(server.admit(of(7, 2), &7, t), Admit::Run);
        let counts = server.counts();
        assert_eq!((counts.run, counts.forgotten), (5_002, 2));
        assert!(counts.sessions_forgotten >= 4_800);
        // Once the victim's session is gone from the fleet, its mark may go
        // as any stranger's does.
        server.finish(of(7, 2), vec![], t);
        flood(&mut server, &|_| false);
        assert!(server.sessions() <= 101);
        assert!(!server.marks.contains_key(&7));
    }

    #[test]
    fn one_caller_runs_at_most_its_share_while_the_server_is_half_full() {
        let mut server = Admission::<&str>::new(ServiceLimits {
            concurrency: 16,
            share: 4,
            ..ServiceLimits::default()
        });
        let t = Instant::now();
        let mut counter = 0;
        let mut ask = |server: &mut Admission<&str>, session: i64, from: &'static str| {
            counter += 1;
            server.admit(of(session, counter), &from, t)
        };
        // Alone, a caller fills half the server.
        let runs = (0..20)
            .filter(|_| ask(&mut server, 1, "mallory") == Admit::Run)
            .count();
        assert_eq!(runs, 8);
        // Nor do other sessions from the same address get more.
        assert_eq!(ask(&mut server, 2, "mallory"), Admit::Busy);
        // One session spread over addresses is one caller too.
        let spread = ["b1", "b2", "b3", "b4", "b5"]
            .into_iter()
            .filter(|from| ask(&mut server, 4, from) == Admit::Run)
            .count();
        assert_eq!(spread, 4);
        // Others still get their shares, until the server is full.
        let alice = (0..5)
            .filter(|_| ask(&mut server, 3, "alice") == Admit::Run)
            .count();
        assert_eq!(alice, 4);
        assert_eq!(server.running(), 16);
        assert_eq!(ask(&mut server, 5, "carol"), Admit::Busy);
        let counts = server.counts();
        assert_eq!(counts.busy, 12 + 1 + 1 + 1 + 1);
        assert_eq!(counts.over_share, 12 + 1 + 1);
    }
}
