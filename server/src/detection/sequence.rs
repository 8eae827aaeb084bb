//! Batch sequence numbers of one session: which were applied, so that a resent batch is
//! acknowledged without being scored twice and a number that goes backwards is refused, and
//! `last_seq` never regresses. Pure: it decides, the session manager acts.
//!
//! A session remembers its last applied number and which of the [`WINDOW`] numbers before it were
//! applied (a replay window, as in IPsec's anti-replay check). Sequence number 0 means "not
//! sequenced": such a batch is always scored and leaves `last_seq` as it is. A session continued
//! from a snapshot knows only its `last_seq` as applied.

/// How many numbers before the last applied one are remembered.
pub(super) const WINDOW: u64 = 64;

/// What a batch's sequence number is to a session.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum SeqCheck {
    /// Not applied before (or not sequenced): score it.
    New,
    /// Already applied: acknowledge it without scoring.
    Duplicate,
    /// Before the last applied number and not applied: refuse it.
    Backwards { last_seq: u64 },
}

/// The sequence numbers a session applied.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct AppliedSeqs {
    last: u64,
    /// Bit `i` set: `last - i` was applied (bit 0 is `last` itself, once anything was applied).
    window: u64,
}

impl AppliedSeqs {
    /// A session continued from a snapshot whose last applied number is `last_seq`.
    pub(super) fn resumed(last_seq: u64) -> Self {
        AppliedSeqs {
            last: last_seq,
            window: u64::from(last_seq > 0),
        }
    }

    /// The last applied number (0: none).
    pub(super) fn last(self) -> u64 {
        self.last
    }

    pub(super) fn check(self, seq: u64) -> SeqCheck {
        if seq == 0 || seq > self.last {
            return SeqCheck::New;
        }
        let behind = self.last - seq;
        if behind < WINDOW && self.window & (1 << behind) != 0 {
            SeqCheck::Duplicate
        } else {
            SeqCheck::Backwards {
                last_seq: self.last,
            }
        }
    }

    /// Records `seq` as applied (a [`SeqCheck::New`] one; 0 changes nothing).
    pub(super) fn apply(&mut self, seq: u64) {
        if seq == 0 {
            return;
        }
        if seq > self.last {
            let ahead = seq - self.last;
            self.window = if ahead >= WINDOW {
                1
            } else {
                (self.window << ahead) | 1
            };
            self.last = seq;
        } else {
            let behind = self.last - seq;
            if behind < WINDOW {
                self.window |= 1 << behind;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resent_batch_is_a_duplicate_and_an_unapplied_older_one_goes_backwards() {
        let mut applied = AppliedSeqs::default();
        assert_eq!(applied.check(1), SeqCheck::New);
        for seq in [1, 2, 3, 5] {
            applied.apply(seq);
        }
        assert_eq!(applied.last(), 5);
        for seq in [5, 3, 2, 1] {
            assert_eq!(applied.check(seq), SeqCheck::Duplicate, "{seq}");
        }
        // 4 was skipped: arriving late, it goes backwards.
        assert_eq!(applied.check(4), SeqCheck::Backwards { last_seq: 5 });
        assert_eq!(applied.check(6), SeqCheck::New);
        assert_eq!(applied.check(0), SeqCheck::New, "0 is not sequenced");
        applied.apply(0);
        assert_eq!(applied.last(), 5, "0 never moves last_seq");
    }

    #[test]
    fn the_window_forgets_what_is_older_than_it() {
        let mut applied = AppliedSeqs::default();
        applied.apply(1);
        applied.apply(WINDOW);
        assert_eq!(
            applied.check(1),
            SeqCheck::Duplicate,
            "63 behind: remembered"
        );
        applied.apply(WINDOW + 1);
        assert_eq!(
            applied.check(1),
            SeqCheck::Backwards {
                last_seq: WINDOW + 1
            }
        );
        applied.apply(1_000);
        assert_eq!(
            applied.check(WINDOW + 1),
            SeqCheck::Backwards { last_seq: 1_000 }
        );
        assert_eq!(applied.check(1_000), SeqCheck::Duplicate);
    }

    #[test]
    fn a_resumed_session_knows_its_last_seq_only() {
        let resumed = AppliedSeqs::resumed(9);
        assert_eq!(resumed.check(9), SeqCheck::Duplicate);
        assert_eq!(resumed.check(8), SeqCheck::Backwards { last_seq: 9 });
        assert_eq!(resumed.check(10), SeqCheck::New);
        assert_eq!(AppliedSeqs::resumed(0), AppliedSeqs::default());
        assert_eq!(AppliedSeqs::default().check(1), SeqCheck::New);
    }
}
