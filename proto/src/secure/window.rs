//! Replay windows: which counters of one (channel, stream) an opener has
//! seen, as a sliding window over the last 64, and how a channel's windows
//! move to another opener without forgetting what they refused.

/// The replay windows of one channel, taken out of one [`Opener`] to go
/// into another ([`Opener::take_windows`], [`Opener::put_windows`]): a
/// channel handled by another receiver keeps what it saw.
///
/// [`Opener`]: super::Opener
/// [`Opener::take_windows`]: super::Opener::take_windows
/// [`Opener::put_windows`]: super::Opener::put_windows
#[derive(Debug, Default)]
pub struct ChannelWindows(pub(super) Vec<(u64, Window)>);

impl ChannelWindows {
    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

/// Which counters of one (channel, session) have been seen.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Window {
    pub(super) highest: u64,
    /// Bit i: counter `highest - i` seen.
    pub(super) seen: u64,
    pub(super) used: u64,
}

impl Window {
    /// Marks `counter` seen; the caller checked it is new
    /// ([`Window::refuses`]).
    pub(super) fn mark(&mut self, counter: u64) {
        debug_assert!(!self.refuses(counter));
        if self.seen == 0 || counter > self.highest {
            // A stream's first counter marks everything before it seen: a
            // receiver that joins late must not take recorded earlier ones.
            self.seen = if self.seen == 0 {
                u64::MAX
            } else {
                let shift = counter - self.highest;
                (if shift >= 64 { 0 } else { self.seen << shift }) | 1
            };
            self.highest = counter;
            return;
        }
        self.seen |= 1 << (self.highest - counter);
    }

    /// Takes in what `other` saw of the same stream: afterwards this
    /// window refuses every counter either of them refused.
    pub(super) fn merge(&mut self, other: &Window) {
        if other.seen == 0 {
            return;
        }
        if self.seen == 0 {
            *self = Window {
                used: self.used,
                ..*other
            };
            return;
        }
        let highest = self.highest.max(other.highest);
        let aligned = |w: &Window| {
            let shift = highest - w.highest;
            if shift >= 64 {
                0
            } else {
                w.seen << shift
            }
        };
        self.seen = aligned(self) | aligned(other);
        self.highest = highest;
    }

    /// Whether `counter` was seen already, or is too old to tell.
    pub(super) fn refuses(&self, counter: u64) -> bool {
        if self.seen == 0 || counter > self.highest {
            return false;
        }
        let back = self.highest - counter;
        back >= 64 || self.seen & (1 << back) != 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_merge_is_the_union_of_what_either_refuses() {
        // Gaps come from datagrams out of order: 101..=104 after 105, and
        // 101, 102, 104..=109 after 103 and 110.
        let mut a = Window::default();
        for c in [100, 105] {
            a.mark(c);
        }
        let mut b = Window::default();
        for c in [100, 103, 110] {
            b.mark(c);
        }
        let mut merged = a;
        merged.merge(&b);
        for c in 0..=200u64 {
            assert_eq!(
                merged.refuses(c),
                a.refuses(c) || b.refuses(c),
                "counter {c}"
            );
        }
        assert!(!merged.refuses(104) && merged.refuses(103) && merged.refuses(105));
        let mut empty = Window::default();
        empty.merge(&a);
        assert!(empty.refuses(105) && !empty.refuses(104));
    }
}
