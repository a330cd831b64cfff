//! [`Held`]: the messages an actor link keeps until the learner says they are durable, numbered,
//! with the two watermarks of the learner's acks. Shared by the gRPC and the shared-memory links.
//!
//! Sequences `durable_through + 1 ..= durable_through + len()` are held, in order; of those,
//! `..= acked_through` are acknowledged (stored by the learner, maybe only in its memory) and the
//! rest are not. A message leaves when an ack says it is durable (in the learner's write-ahead
//! log, or stored by a learner without one), never before: a learner killed and resumed may lack
//! what it acknowledged after its log's last commit, and gets it again from here.

use std::collections::VecDeque;

/// Messages kept until durable; see the module docs. No locks and no allocation beyond the
/// queue's own growth (its capacity is kept as messages come and go).
#[derive(Debug)]
pub(crate) struct Held<T> {
    items: VecDeque<T>,
    durable_through: u64,
    acked_through: u64,
}

impl<T> Default for Held<T> {
    fn default() -> Self {
        Self {
            items: VecDeque::new(),
            durable_through: 0,
            acked_through: 0,
        }
    }
}

impl<T> Held<T> {
    /// Messages held, acknowledged ones included.
    pub fn len(&self) -> usize {
        self.items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    /// Every message up to this sequence is durable (none is held).
    pub fn durable_through(&self) -> u64 {
        self.durable_through
    }

    /// Every message up to this sequence is acknowledged.
    pub fn acked_through(&self) -> u64 {
        self.acked_through
    }

    /// The sequence of the newest message held (`durable_through` if none is).
    pub fn last(&self) -> u64 {
        self.durable_through + self.items.len() as u64
    }

    /// The sequence the next message pushed gets.
    pub fn next_sequence(&self) -> u64 {
        self.last() + 1
    }

    /// Messages not yet acknowledged.
    pub fn unacked(&self) -> usize {
        (self.last() - self.acked_through) as usize
    }

    /// Messages acknowledged and not yet durable (the ack-durable gap).
    pub fn undurable(&self) -> usize {
        self.items.len() - self.unacked()
    }

    /// Whether one more message may be pushed: fewer than `window` unacknowledged and fewer
    /// than `max_held` held.
    pub fn has_room(&self, window: usize, max_held: usize) -> bool {
        self.unacked() < window && self.items.len() < max_held
    }

    /// The message numbered `sequence`, if it is held.
    pub fn get(&self, sequence: u64) -> Option<&T> {
        let index = sequence.checked_sub(self.durable_through + 1)?;
        self.items.get(usize::try_from(index).ok()?)
    }

    /// The message after `sent_through`, if one is held (the oldest held if `sent_through` is
    /// below them).
    pub fn after(&self, sent_through: u64) -> Option<&T> {
        self.get(sent_through.max(self.durable_through) + 1)
    }

    /// Whether a message after `sent_through` is held.
    pub fn has_after(&self, sent_through: u64) -> bool {
        sent_through.max(self.durable_through) < self.last()
    }

    /// Holds `item` as the next sequence; returns that sequence.
    pub fn push(&mut self, item: T) -> u64 {
        self.items.push_back(item);
        self.last()
    }

    /// Applies an ack's watermarks, never past what is held and never back (durable never past
    /// acknowledged); hands each message that became durable to `released`, oldest first.
    pub fn acknowledge(
        &mut self,
        acked_through: u64,
        durable_through: u64,
        mut released: impl FnMut(T),
    ) {
        self.acked_through = self.acked_through.max(acked_through.min(self.last()));
        let durable = durable_through.min(self.acked_through);
        while self.durable_through < durable {
            if let Some(item) = self.items.pop_front() {
                released(item);
            }
            self.durable_through += 1;
        }
    }

    /// Forgets the acknowledgements that are not durable: the learner that gave them may be gone
    /// (a restarted one acknowledges again what it has, as duplicates).
    pub fn rewind(&mut self) {
        self.acked_through = self.durable_through;
    }

    /// Numbers the held messages from sequence 1 again, nothing acknowledged (a fresh
    /// incarnation).
    pub fn renumber(&mut self) {
        self.durable_through = 0;
        self.acked_through = 0;
    }

    /// The held messages with their sequences, oldest first (to renumber their contents).
    pub fn numbered_mut(&mut self) -> impl Iterator<Item = (u64, &mut T)> {
        (self.durable_through + 1..).zip(self.items.iter_mut())
    }

    /// Numbers what comes next after `sequence`, all of it durable, if nothing is held (a
    /// numbering begun elsewhere goes on here).
    pub fn continue_after(&mut self, sequence: u64) {
        if self.items.is_empty() {
            self.durable_through = sequence;
            self.acked_through = sequence;
        }
    }

    /// Takes every held message out, oldest first; nothing is held after.
    pub fn take_all(&mut self) -> VecDeque<T> {
        self.durable_through = self.last();
        self.acked_through = self.durable_through;
        std::mem::take(&mut self.items)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn held(n: u64) -> Held<u64> {
        let mut held = Held::default();
        for i in 1..=n {
            assert_eq!(held.push(i * 10), i);
        }
        held
    }

    #[test]
    fn messages_stay_until_durable_not_just_acknowledged() {
        let mut held = held(5);
        assert_eq!((held.len(), held.unacked(), held.undurable()), (5, 5, 0));
        let mut released = Vec::new();
        held.acknowledge(3, 0, |m| released.push(m));
        assert!(released.is_empty(), "acknowledged is not durable");
        assert_eq!((held.len(), held.unacked(), held.undurable()), (5, 2, 3));
        assert_eq!(held.get(1), Some(&10));
        held.acknowledge(4, 2, |m| released.push(m));
        assert_eq!(released, [10, 20]);
        assert_eq!((held.durable_through(), held.acked_through()), (2, 4));
        assert_eq!((held.len(), held.unacked(), held.undurable()), (3, 1, 2));
        assert_eq!(held.get(2), None, "released");
        assert_eq!(held.get(3), Some(&30));
        assert_eq!(held.next_sequence(), 6);
        held.acknowledge(5, 5, |m| released.push(m));
        assert_eq!(released, [10, 20, 30, 40, 50]);
        assert!(held.is_empty());
        assert_eq!((held.durable_through(), held.next_sequence()), (5, 6));
    }

    #[test]
    fn watermarks_never_go_back_nor_past_what_is_held_and_durable_never_past_acked() {
        let mut held = held(4);
        let mut released = 0;
        // An ack beyond what was sent (another numbering) counts only what is held.
        held.acknowledge(9, 0, |_| released += 1);
        assert_eq!(held.acked_through(), 4);
        let mut held = self::held(4);
        held.acknowledge(2, 3, |_| released += 1);
        assert_eq!((held.acked_through(), held.durable_through()), (2, 2));
        // A stale ack moves nothing back.
        held.acknowledge(1, 1, |_| released += 1);
        assert_eq!((held.acked_through(), held.durable_through()), (2, 2));
        assert_eq!(released, 2);
    }

    #[test]
    fn the_bounds_are_the_window_of_unacknowledged_and_the_most_held() {
        let mut held = held(3);
        assert!(held.has_room(4, 8));
        assert!(!held.has_room(3, 8), "window full");
        held.acknowledge(3, 0, |_| {});
        assert!(held.has_room(3, 8));
        for i in 4..=8 {
            held.push(i);
        }
        assert_eq!((held.unacked(), held.len()), (5, 8));
        assert!(!held.has_room(16, 8), "held full, though acknowledged");
        held.acknowledge(3, 1, |_| {});
        assert!(held.has_room(16, 8));
    }

    #[test]
    fn a_rewind_resends_from_the_oldest_not_durable_and_renumbering_starts_at_one() {
        let mut held = held(6);
        held.acknowledge(5, 2, |_| {});
        assert!(!held.has_after(6));
        assert_eq!(held.after(0), Some(&30), "below the held: the oldest");
        assert_eq!(held.after(4), Some(&50));
        held.rewind();
        assert_eq!(
            (held.acked_through(), held.unacked(), held.undurable()),
            (2, 4, 0)
        );
        assert!(held.has_after(2));
        held.renumber();
        let renumbered: Vec<(u64, u64)> = held.numbered_mut().map(|(s, m)| (s, *m)).collect();
        assert_eq!(renumbered, [(1, 30), (2, 40), (3, 50), (4, 60)]);
        assert_eq!((held.durable_through(), held.next_sequence()), (0, 5));
        assert_eq!(held.get(1), Some(&30));
        let all: Vec<u64> = held.take_all().into_iter().collect();
        assert_eq!(all, [30, 40, 50, 60]);
        assert!(held.is_empty());
        assert_eq!(held.next_sequence(), 5, "the numbering goes on");
        held.continue_after(40);
        assert_eq!((held.durable_through(), held.acked_through()), (40, 40));
        assert_eq!(held.push(1), 41);
        held.continue_after(7);
        assert_eq!(held.next_sequence(), 42, "not while anything is held");
    }
}
