//! [`Adder`]: collects the rollout's transitions into one batch per level and hands full
//! batches on as ingest items.

use hac_core::{Batch, LevelDims, Transition, TransitionSink};
use hac_proto::{DecodedBatch, IngestItem};

/// A [`TransitionSink`] that packs transitions per level into structure-of-arrays batches of at
/// most `max_len` transitions. Full batches queue up in order; [`drain`](Self::drain) takes them
/// (after closing every partly filled batch) so the actor can send them between episodes.
///
/// Appending never allocates once a level's batch has reached its capacity; each batch handed
/// on is a fresh allocation (one per `max_len` transitions, not per step).
#[derive(Debug)]
pub struct Adder {
    open: Vec<Batch>,
    max_len: usize,
    weights_version: u64,
    ready: Vec<IngestItem>,
}

impl Adder {
    /// An adder for levels of `dims`, batches of at most `max_len` (>= 1) transitions.
    pub fn new(dims: &[LevelDims], max_len: usize) -> Self {
        Self::with_extra(dims, &[], max_len)
    }

    /// [`new`](Self::new) for levels whose transitions carry `extra_widths[level]` extra values
    /// each (missing entries: none), as the learner's admission says.
    pub fn with_extra(dims: &[LevelDims], extra_widths: &[usize], max_len: usize) -> Self {
        let max_len = max_len.max(1);
        let extra = |level: usize| extra_widths.get(level).copied().unwrap_or(0);
        Self {
            open: dims
                .iter()
                .enumerate()
                .map(|(level, &d)| Self::empty(d, extra(level), max_len))
                .collect(),
            max_len,
            weights_version: 0,
            ready: Vec::new(),
        }
    }

    fn empty(dims: LevelDims, extra_width: usize, max_len: usize) -> Batch {
        Batch {
            dims,
            len: 0,
            states: Vec::with_capacity(dims.state * max_len),
            actions: Vec::with_capacity(dims.action * max_len),
            rewards: Vec::with_capacity(max_len),
            next_states: Vec::with_capacity(dims.state * max_len),
            goals: Vec::with_capacity(dims.goal * max_len),
            terminals: Vec::with_capacity(max_len),
            extra_width,
            extra: Vec::with_capacity(extra_width * max_len),
        }
    }

    /// Tags the following transitions with the weights version that produces them.
    pub fn set_weights_version(&mut self, version: u64) {
        self.weights_version = version;
    }

    fn close(&mut self, level: usize) {
        let batch = &mut self.open[level];
        if batch.len == 0 {
            return;
        }
        let full = std::mem::replace(
            batch,
            Self::empty(batch.dims, batch.extra_width, self.max_len),
        );
        self.ready.push(IngestItem::Batch(DecodedBatch {
            level,
            weights_version: self.weights_version,
            batch: full,
        }));
    }

    /// Closes every partly filled batch and returns all batches in the order they filled up,
    /// leaving the adder empty.
    pub fn drain(&mut self) -> std::vec::Drain<'_, IngestItem> {
        for level in 0..self.open.len() {
            self.close(level);
        }
        self.ready.drain(..)
    }
}

impl TransitionSink for Adder {
    fn push(&mut self, level: usize, t: &Transition<'_>) {
        let batch = &mut self.open[level];
        batch.states.extend_from_slice(t.state);
        batch.actions.extend_from_slice(t.action);
        batch.rewards.push(t.reward);
        batch.next_states.extend_from_slice(t.next_state);
        batch.goals.extend_from_slice(t.goal);
        batch.terminals.push(if t.terminal { 1.0 } else { 0.0 });
        debug_assert_eq!(
            t.extra.len(),
            batch.extra_width,
            "extra values of another width"
        );
        batch.extra.extend_from_slice(t.extra);
        batch.len += 1;
        if batch.len == self.max_len {
            self.close(level);
        }
    }
}

#[cfg(test)]
mod tests {
    use hac_core::TransitionKind;

    use super::*;

    const DIMS: [LevelDims; 2] = [
        LevelDims {
            state: 2,
            goal: 1,
            action: 1,
        },
        LevelDims {
            state: 2,
            goal: 1,
            action: 1,
        },
    ];

    fn push(adder: &mut Adder, level: usize, x: f32) {
        adder.push(
            level,
            &Transition {
                kind: TransitionKind::HindsightAction,
                state: &[x, x],
                action: &[x],
                reward: -x,
                next_state: &[x + 1.0, x + 1.0],
                goal: &[x],
                terminal: x > 2.0,
                extra: &[],
            },
        );
    }

    #[test]
    fn batches_fill_in_order_and_drain_closes_the_rest() {
        let mut adder = Adder::new(&DIMS, 2);
        adder.set_weights_version(7);
        for x in 0..3 {
            push(&mut adder, 0, x as f32);
        }
        push(&mut adder, 1, 5.0);
        let items: Vec<_> = adder.drain().collect();
        let summary: Vec<(usize, usize, u64)> = items
            .iter()
            .map(|i| match i {
                IngestItem::Batch(b) => (b.level, b.batch.len, b.weights_version),
                IngestItem::Episode { .. } => panic!("only batches"),
            })
            .collect();
        // The full level-0 batch first, then the partial ones level by level.
        assert_eq!(summary, [(0, 2, 7), (0, 1, 7), (1, 1, 7)]);
        let IngestItem::Batch(first) = &items[0] else {
            unreachable!()
        };
        assert_eq!(first.batch.states, [0.0, 0.0, 1.0, 1.0]);
        assert_eq!(first.batch.terminals, [0.0, 0.0]);
        assert_eq!(adder.drain().count(), 0);
    }
}
