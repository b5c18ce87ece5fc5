//! A call that walks its candidates in order (the nearest provider
//! first, as `proto::nearest` orders them): a server that is busy, gone,
//! or silent within its share of the deadline is passed over and the call
//! goes to the next; the first one that says it has the call keeps it.
//!
//! "Says it has the call": any frame of it, `Running` included, which a
//! server sends when a request comes again while its call runs. So a
//! slow handler is never mistaken for a silent one once its server has
//! heard a resend, and a call is moved on only while no server is known
//! to run it. A request that reached a server whose answers were all lost
//! may still run there; it is cancelled as it is left (see
//! `docs/services.md`, "The nearest server").

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::calling::{CallDriver, CallTo};
use super::services::RequestTx;
use super::Inner;
use crate::proto::call::Event;
use crate::sync::lock;
use crate::wire::service::code;

/// The shortest a walk waits for a server to say it has the call before
/// it tries the next: the first resend goes out after 50 ms, and the
/// server answers it at once, so this leaves a loaded machine time.
pub(crate) const MIN_SHARE: Duration = Duration::from_millis(300);

/// Servers passed over that a client remembers, at most: beyond, the
/// expired are forgotten, and then no more are noted.
const MAX_PASSED: usize = 256;

/// What a client's walks remember between calls, by service name and
/// server session key: who answered last (the next call tries it first
/// among equals), and who was passed over lately (tried after all the
/// others until then: one silent server costs one call its share, not
/// every call).
#[derive(Debug, Default)]
pub(crate) struct Memory {
    last: Option<(Arc<str>, i64)>,
    passed: HashMap<(Arc<str>, i64), Instant>,
}

impl Memory {
    /// Who answered last.
    pub(crate) fn last(&self) -> Option<&(Arc<str>, i64)> {
        self.last.as_ref()
    }

    /// Whether `key`'s server of `service` was passed over lately.
    pub(crate) fn passed_lately(&self, service: &str, key: i64, now: Instant) -> bool {
        self.passed
            .iter()
            .any(|((s, k), until)| **s == *service && *k == key && *until > now)
    }

    fn answered(&mut self, service: &Arc<str>, key: i64) {
        self.passed.retain(|(s, k), _| !(s == service && *k == key));
        self.last = Some((Arc::clone(service), key));
    }

    fn passed_over(&mut self, service: &Arc<str>, key: i64, why: &Passed, now: Instant) {
        let lately = match why {
            Passed::Busy => Duration::from_secs(1),
            Passed::Gone | Passed::Silent(_) | Passed::Unreachable(_) => Duration::from_secs(10),
            // Not the server's doing, or never tried.
            Passed::NotSent(_) | Passed::Refused(_) | Passed::NotTried => return,
        };
        if self.passed.len() >= MAX_PASSED {
            self.passed.retain(|_, until| *until > now);
        }
        if self.passed.len() < MAX_PASSED {
            self.passed.insert((Arc::clone(service), key), now + lately);
        }
    }
}

/// A client's [`Memory`], shared by its calls.
pub(crate) type Remembered = Arc<Mutex<Memory>>;

/// One server a walk may call.
pub(crate) struct Candidate {
    /// The server node.
    pub(crate) node: String,
    /// Its session key.
    pub(crate) key: i64,
    /// The service's full name where this server serves it.
    pub(crate) service: Arc<str>,
    /// Where its requests leave from.
    pub(crate) request: Arc<RequestTx>,
    /// Where it goes.
    pub(crate) to: CallTo,
    /// Whether a bridge answers for it (it is on another site).
    pub(crate) relayed: bool,
}

/// Why a server was passed over.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Passed {
    /// It answered busy.
    Busy,
    /// Discovery saw it go before it answered.
    Gone,
    /// It said nothing of the call for this long.
    Silent(Duration),
    /// A bridge could not run the call on the server's site (its words).
    Unreachable(String),
    /// The request could not be sent.
    NotSent(String),
    /// It can't answer this client (types, keys): found before the call,
    /// or answered by the server (the request did not decode there).
    Refused(String),
    /// Not tried: the deadline passed first.
    NotTried,
}

impl std::fmt::Display for Passed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Passed::Busy => f.write_str("busy"),
            Passed::Gone => f.write_str("gone before it answered"),
            Passed::Silent(after) => write!(f, "silent for {} ms", after.as_millis()),
            Passed::Unreachable(why) => write!(f, "unreachable: {why}"),
            Passed::NotSent(why) => write!(f, "request not sent: {why}"),
            Passed::Refused(why) => f.write_str(why),
            Passed::NotTried => f.write_str("not tried: the deadline passed first"),
        }
    }
}

/// A server passed over, and why.
#[derive(Debug, Clone)]
pub(crate) struct Tried {
    /// The server node.
    pub(crate) node: String,
    /// The service's name there.
    pub(crate) service: Arc<str>,
    /// Why.
    pub(crate) why: Passed,
}

/// The list of what was tried, for an error: `node (service): why; ...`.
pub(crate) fn tried_text(tried: &[Tried]) -> String {
    let each: Vec<String> = tried
        .iter()
        .map(|t| format!("{} ({}): {}", t.node, t.service, t.why))
        .collect();
    each.join("; ")
}

/// The server called now.
struct Current {
    node: String,
    key: i64,
    service: Arc<str>,
    /// How long it was given to say it has the call.
    share: Duration,
    /// This node's own server: it runs what it is handed, so it has the
    /// call from the start.
    local: bool,
    relayed: bool,
    call: CallDriver,
}

/// One call walking its candidates: see the module.
pub(crate) struct Walk {
    inner: Arc<Inner>,
    message: Vec<u8>,
    deadline: Instant,
    left: VecDeque<Candidate>,
    current: Option<Current>,
    tried: Vec<Tried>,
    /// Whether the caller was given an event of the current server's
    /// call: from then on the call is that server's, whatever comes.
    delivered: bool,
    /// Whether every candidate was passed over.
    exhausted: bool,
    memory: Remembered,
}

impl Walk {
    /// Calls the first of `candidates` that takes the request, `tried`
    /// holding those passed over before (refused by the client's checks).
    /// Fails with the whole list when no request could be sent.
    pub(crate) fn start(
        inner: &Arc<Inner>,
        candidates: Vec<Candidate>,
        tried: Vec<Tried>,
        message: &[u8],
        deadline: Instant,
        memory: Remembered,
    ) -> Result<Self, Vec<Tried>> {
        let mut walk = Self {
            inner: Arc::clone(inner),
            message: message.to_vec(),
            deadline,
            left: candidates.into(),
            current: None,
            tried,
            delivered: false,
            exhausted: false,
            memory,
        };
        match walk.call_next() {
            true => Ok(walk),
            false => Err(walk.tried),
        }
    }

    /// Calls the next candidate that takes the request; false when none
    /// is left (or the deadline passed).
    fn call_next(&mut self) -> bool {
        while let Some(candidate) = self.left.pop_front() {
            let now = Instant::now();
            let remaining = self.deadline.saturating_duration_since(now);
            if remaining.is_zero() {
                let not_tried = std::iter::once(candidate).chain(self.left.drain(..));
                self.tried.extend(not_tried.map(|c| Tried {
                    node: c.node,
                    service: c.service,
                    why: Passed::NotTried,
                }));
                return false;
            }
            // Its share of what is left; the last waits to the deadline.
            let share = if self.left.is_empty() {
                remaining
            } else {
                let shares = u32::try_from(self.left.len() + 1).unwrap_or(u32::MAX);
                (remaining / shares).max(MIN_SHARE).min(remaining)
            };
            let local = matches!(candidate.to, CallTo::Local(_));
            let launched = CallDriver::launch(
                &self.inner,
                &candidate.request,
                Arc::clone(&candidate.service),
                &candidate.node,
                candidate.to,
                &self.message,
                self.deadline,
            );
            match launched {
                Ok(mut call) => {
                    // This node's own server runs what it is handed: it
                    // is never silent, only slow.
                    if !local {
                        call.give_up_unheard_at(now + share);
                    }
                    self.current = Some(Current {
                        node: candidate.node,
                        key: candidate.key,
                        service: candidate.service,
                        share,
                        local,
                        relayed: candidate.relayed,
                        call,
                    });
                    return true;
                }
                Err(e) => self.tried.push(Tried {
                    node: candidate.node,
                    service: candidate.service,
                    why: Passed::NotSent(e.to_string()),
                }),
            }
        }
        false
    }

    /// What the caller is given for `event` of the current call: `Some`
    /// to hand over, `None` to wait for the next server's.
    fn take(&mut self, event: Option<Event>) -> Option<Option<Event>> {
        let Some(current) = &self.current else {
            return Some(None);
        };
        // Once the server has the call, nothing moves it: only what says
        // the call never ran there passes a server over.
        let has_it = current.local || current.call.heard();
        let why = match &event {
            _ if self.delivered => None,
            // Busy, and a request that did not decode: the handler never
            // ran, whatever the server said before.
            Some(Event::Busy) => Some(Passed::Busy),
            Some(Event::Failed { code, message, .. }) if *code == code::BAD_REQUEST => {
                Some(Passed::Refused(format!("refused the request: {message}")))
            }
            _ if has_it => None,
            Some(Event::Failed { code, .. })
                if *code == code::SERVER_GONE && current.call.server_went() =>
            {
                Some(Passed::Gone)
            }
            Some(Event::TimedOut) => Some(Passed::Silent(current.share)),
            // A bridge that could not run the call on the server's site
            // (out of reach, gone or busy there). From a server here, code
            // 8 is its handler's own.
            Some(Event::Failed { code, message, .. })
                if *code == code::UNREACHABLE && current.relayed =>
            {
                Some(Passed::Unreachable(message.clone()))
            }
            _ => None,
        };
        let Some(why) = why else {
            if event.is_some() {
                self.delivered = true;
                if current.call.heard() {
                    lock(&self.memory).answered(&current.service, current.key);
                }
            }
            return Some(event);
        };
        tracing::debug!(
            service = %current.service,
            node = %current.node,
            "passed over ({why}); trying the next server"
        );
        lock(&self.memory).passed_over(&current.service, current.key, &why, Instant::now());
        self.tried.push(Tried {
            node: current.node.clone(),
            service: Arc::clone(&current.service),
            why,
        });
        if self.call_next() {
            return None;
        }
        // The last event stands for the walk's end; the tried list says
        // the rest.
        self.exhausted = true;
        self.delivered = true;
        Some(event)
    }

    /// The next event of the call, from whichever server has it; `None`
    /// after the end.
    pub(crate) async fn next(&mut self) -> Option<Event> {
        loop {
            let event = match &mut self.current {
                Some(current) => current.call.next(&current.node).await,
                None => None,
            };
            if let Some(event) = self.take(event) {
                return event;
            }
        }
    }

    /// Like [`Walk::next`], blocking the thread.
    pub(crate) fn next_blocking(&mut self) -> Option<Event> {
        loop {
            let event = match &mut self.current {
                Some(current) => current.call.next_blocking(&current.node),
                None => None,
            };
            if let Some(event) = self.take(event) {
                return event;
            }
        }
    }

    /// The server called now (or last).
    pub(crate) fn node(&self) -> &str {
        self.current.as_ref().map_or("", |c| c.node.as_str())
    }

    /// The service's name at the server called now (or last).
    pub(crate) fn service(&self) -> Option<&Arc<str>> {
        self.current.as_ref().map(|c| &c.service)
    }

    /// Whether every server was passed over: [`Walk::tried`] says why.
    pub(crate) fn exhausted(&self) -> bool {
        self.exhausted
    }

    /// The servers passed over so far, and why.
    pub(crate) fn tried(&self) -> &[Tried] {
        &self.tried
    }

    /// Whether the call's last event was its reply.
    pub(crate) fn replied(&self) -> bool {
        self.current.as_ref().is_some_and(|c| c.call.replied())
    }

    /// Whether discovery saw the current server go.
    pub(crate) fn server_went(&self) -> bool {
        self.current.as_ref().is_some_and(|c| c.call.server_went())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn servers_passed_over_are_remembered_for_a_while_and_bounded() {
        let now = Instant::now();
        let laser: Arc<str> = "rover1/laser".into();
        let mut memory = Memory::default();
        memory.passed_over(&laser, 1, &Passed::Busy, now);
        memory.passed_over(&laser, 2, &Passed::Silent(Duration::from_secs(1)), now);
        memory.passed_over(&laser, 3, &Passed::Refused("types".into()), now);
        let later = |secs| now + Duration::from_secs(secs);
        assert!(memory.passed_lately("rover1/laser", 1, now));
        assert!(
            !memory.passed_lately("rover1/laser", 1, later(2)),
            "busy: 1 s"
        );
        assert!(memory.passed_lately("rover1/laser", 2, later(9)));
        assert!(
            !memory.passed_lately("rover1/laser", 2, later(11)),
            "silent: 10 s"
        );
        assert!(
            !memory.passed_lately("rover1/laser", 3, now),
            "refusal is not the server's doing"
        );
        assert!(
            !memory.passed_lately("laser", 2, now),
            "another name is another server"
        );
        // An answer clears it, and is the last.
        memory.answered(&laser, 2);
        assert!(!memory.passed_lately("rover1/laser", 2, now));
        assert_eq!(memory.last(), Some(&(Arc::clone(&laser), 2)));
        // However many pass, the memory is bounded; expired ones make room.
        for key in 0..1000 {
            memory.passed_over(&laser, key, &Passed::Gone, now);
        }
        assert_eq!(memory.passed.len(), MAX_PASSED);
        memory.passed_over(&laser, 5000, &Passed::Gone, later(11));
        assert!(memory.passed_lately("rover1/laser", 5000, later(11)));
        assert_eq!(memory.passed.len(), 1);
    }

    #[test]
    fn the_tried_list_says_who_and_why() {
        let tried = [
            Tried {
                node: "a".into(),
                service: "rover1/laser".into(),
                why: Passed::Busy,
            },
            Tried {
                node: "b".into(),
                service: "laser".into(),
                why: Passed::Silent(Duration::from_millis(1250)),
            },
        ];
        assert_eq!(
            tried_text(&tried),
            "a (rover1/laser): busy; b (laser): silent for 1250 ms"
        );
    }
}
