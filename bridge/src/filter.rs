//! Which channels cross, in each direction, and with what limits.
//!
//! A pattern is a glob on the channel name (`rover*/camera/**`: `*` within
//! one part, `**` across parts) or, after `re:`, a regular expression that
//! must match the whole name (`re:rover[0-9]+/pose`).

use std::fmt;
use std::time::{Duration, Instant};

use globset::{GlobBuilder, GlobMatcher};
use regex::Regex;

/// One pattern.
#[derive(Debug, Clone)]
pub enum Pattern {
    /// A glob.
    Glob(String, GlobMatcher),
    /// A regular expression, anchored at both ends.
    Regex(String, Regex),
}

impl Pattern {
    /// Parses a pattern: a glob, or `re:` and a regular expression.
    pub fn parse(text: &str) -> Result<Self, String> {
        if let Some(re) = text.strip_prefix("re:") {
            let anchored = format!("^(?:{re})$");
            return Regex::new(&anchored)
                .map(|r| Pattern::Regex(text.to_owned(), r))
                .map_err(|e| format!("pattern {text:?}: {e}"));
        }
        GlobBuilder::new(text)
            .literal_separator(true)
            .build()
            .map(|g| Pattern::Glob(text.to_owned(), g.compile_matcher()))
            .map_err(|e| format!("pattern {text:?}: {e}"))
    }

    /// Whether a channel name matches.
    pub fn matches(&self, channel: &str) -> bool {
        match self {
            Pattern::Glob(_, g) => g.is_match(channel),
            Pattern::Regex(_, r) => r.is_match(channel),
        }
    }
}

impl fmt::Display for Pattern {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Pattern::Glob(t, _) | Pattern::Regex(t, _) => f.write_str(t),
        }
    }
}

/// Allow and deny lists for one direction: a channel crosses if the allow
/// list is empty or one of its patterns matches, and no deny pattern does.
#[derive(Debug, Clone, Default)]
pub struct Filter {
    /// Patterns a channel must match one of (none: every channel).
    pub allow: Vec<Pattern>,
    /// Patterns that keep a channel from crossing.
    pub deny: Vec<Pattern>,
}

impl Filter {
    /// Whether `channel` crosses.
    pub fn passes(&self, channel: &str) -> bool {
        (self.allow.is_empty() || self.allow.iter().any(|p| p.matches(channel)))
            && !self.deny.iter().any(|p| p.matches(channel))
    }
}

/// How urgent a channel's samples are on the Zenoh link, highest first
/// (Zenoh's priorities).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum Priority {
    /// Zenoh `RealTime`.
    RealTime,
    /// Zenoh `InteractiveHigh`.
    InteractiveHigh,
    /// Zenoh `InteractiveLow`.
    InteractiveLow,
    /// Zenoh `DataHigh`.
    DataHigh,
    /// Zenoh `Data`, the default.
    #[default]
    Data,
    /// Zenoh `DataLow`.
    DataLow,
    /// Zenoh `Background`.
    Background,
}

impl Priority {
    /// Zenoh's value.
    pub fn zenoh(self) -> zenoh::qos::Priority {
        use zenoh::qos::Priority as Z;
        match self {
            Priority::RealTime => Z::RealTime,
            Priority::InteractiveHigh => Z::InteractiveHigh,
            Priority::InteractiveLow => Z::InteractiveLow,
            Priority::DataHigh => Z::DataHigh,
            Priority::Data => Z::Data,
            Priority::DataLow => Z::DataLow,
            Priority::Background => Z::Background,
        }
    }
}

/// A limit for the channels matching a pattern: at most `max_rate`
/// messages a second cross (downsampling: the first after each interval
/// goes, the rest are dropped and counted), at `priority`.
#[derive(Debug, Clone)]
pub struct Limit {
    /// Which channels.
    pub pattern: Pattern,
    /// Most messages a second, if limited.
    pub max_rate: Option<f64>,
    /// Their priority on the link.
    pub priority: Priority,
}

impl Limit {
    /// Parses `PATTERN=RATE[,priority=NAME]` or `PATTERN=priority=NAME`,
    /// with RATE in messages a second (`10`, `0.5`, `10hz`).
    ///
    /// ```
    /// let limit = puli_bridge::filter::Limit::parse("rover*/camera/**=5hz,priority=data-low").unwrap();
    /// assert_eq!(limit.max_rate, Some(5.0));
    /// assert!(limit.pattern.matches("rover1/camera/left"));
    /// ```
    pub fn parse(text: &str) -> Result<Self, String> {
        let (pattern, spec) = text
            .split_once('=')
            .ok_or_else(|| format!("limit {text:?}: expected PATTERN=RATE[,priority=NAME]"))?;
        let pattern = Pattern::parse(pattern)?;
        let mut limit = Limit {
            pattern,
            max_rate: None,
            priority: Priority::default(),
        };
        for part in spec.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            if let Some(name) = part.strip_prefix("priority=") {
                limit.priority = clap::ValueEnum::from_str(name, true)
                    .map_err(|_| format!("limit {text:?}: unknown priority {name:?} (real-time, interactive-high, interactive-low, data-high, data, data-low, background)"))?;
            } else {
                let number = part.strip_suffix("hz").unwrap_or(part);
                let rate: f64 = number.parse().map_err(|_| {
                    format!("limit {text:?}: {part:?} is not a rate in messages a second")
                })?;
                if !(rate.is_finite() && rate >= MIN_RATE) {
                    return Err(format!(
                        "limit {text:?}: the rate must be at least {MIN_RATE} (one message in 1000 s)"
                    ));
                }
                limit.max_rate = Some(rate);
            }
        }
        Ok(limit)
    }

    /// The first limit whose pattern matches `channel`.
    pub fn find<'l>(limits: &'l [Limit], channel: &str) -> Option<&'l Limit> {
        limits.iter().find(|l| l.pattern.matches(channel))
    }
}

/// The lowest rate a limit may have, in messages a second.
pub const MIN_RATE: f64 = 0.001;

/// Downsampling of one channel: lets one message through per interval.
#[derive(Debug, Clone)]
pub struct RateGate {
    interval: Duration,
    next: Option<Instant>,
}

impl RateGate {
    /// A gate for `rate` messages a second; `None` lets everything through.
    pub fn new(rate: Option<f64>) -> Self {
        Self {
            interval: rate
                .and_then(|r| Duration::try_from_secs_f64(1.0 / r).ok())
                .unwrap_or(Duration::ZERO),
            next: None,
        }
    }

    /// [`RateGate::admit`] now; an open gate reads no clock.
    pub fn admit_now(&mut self) -> bool {
        self.interval.is_zero() || self.admit(Instant::now())
    }

    /// Whether a message arriving at `now` goes through.
    pub fn admit(&mut self, now: Instant) -> bool {
        if self.interval.is_zero() {
            return true;
        }
        match self.next {
            Some(next) if now < next => false,
            _ => {
                // From the slot, not from `now`: a steady stream keeps its
                // rate instead of drifting by each message's lateness, but
                // a pause doesn't bank a burst.
                let slot = self.next.filter(|n| now - *n < self.interval);
                self.next = Some(slot.unwrap_or(now) + self.interval);
                true
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn globs_stop_at_slashes_unless_doubled_and_regexes_match_whole_names() {
        let one = Pattern::parse("rover*/pose").unwrap();
        assert!(one.matches("rover1/pose"));
        assert!(!one.matches("rover1/arm/pose"));
        let deep = Pattern::parse("rover1/**").unwrap();
        assert!(deep.matches("rover1/arm/pose"));
        let re = Pattern::parse("re:rover[0-9]+/pose").unwrap();
        assert!(re.matches("rover12/pose"));
        assert!(!re.matches("xrover12/pose"));
        assert!(!re.matches("rover12/pose2"));
        assert!(Pattern::parse("re:(").is_err());
        assert!(Pattern::parse("a/[").is_err());
    }

    #[test]
    fn deny_wins_and_an_empty_allow_list_allows_all() {
        let filter = Filter {
            allow: vec![],
            deny: vec![Pattern::parse("**/camera/**").unwrap()],
        };
        assert!(filter.passes("rover1/pose"));
        assert!(!filter.passes("rover1/camera/left"));
        let only = Filter {
            allow: vec![Pattern::parse("rover1/*").unwrap()],
            deny: vec![],
        };
        assert!(only.passes("rover1/pose"));
        assert!(!only.passes("rover2/pose"));
    }

    #[test]
    fn limits_parse_and_refuse_nonsense() {
        let l = Limit::parse("a/**=10").unwrap();
        assert_eq!((l.max_rate, l.priority), (Some(10.0), Priority::Data));
        let l = Limit::parse("a/**=priority=real-time").unwrap();
        assert_eq!((l.max_rate, l.priority), (None, Priority::RealTime));
        assert!(Limit::parse("a/**").is_err());
        assert!(Limit::parse("a/**=0").is_err());
        assert!(Limit::parse("a/**=1e-20").is_err());
        let _ = RateGate::new(Some(1e-300));
        assert!(Limit::parse("a/**=fast").is_err());
        assert!(Limit::parse("a/**=1,priority=urgent").is_err());
    }

    #[test]
    fn a_gate_lets_one_message_through_per_interval() {
        let mut gate = RateGate::new(Some(10.0));
        let t0 = Instant::now();
        let admitted = (0..1000)
            .filter(|i| gate.admit(t0 + Duration::from_millis(*i)))
            .count();
        assert_eq!(admitted, 10);
        let mut open = RateGate::new(None);
        assert!((0..100).all(|_| open.admit(t0)));
    }
}
