//! HAC replay: each level's transitions, stored FIFO and sampled uniformly for its trainer.
//!
//! - [`ReplayTable`] (in `table`): one level's replay. `S` shards, each a ring buffer behind its
//!   own lock, so ingest runs in parallel; the sampler draws a batch across shards in proportion
//!   to their fill, straight into a preallocated [`Batch`](hac_core::Batch); its contents save to
//!   and restore from safetensors for checkpoints (`table::snapshot`).
//! - `ring`: a shard's storage, a fixed-capacity FIFO ring in structure-of-arrays `f32` layout
//!   (the same layout as `Batch`, so sampling copies contiguous slices).
//! - [`RateLimiter`] (in `rate_limiter`): one level's updates-per-episode ratio, shared by ingest
//!   (admission, backpressure) and the level's trainer (one grant per update).
//! - [`Replay`]: one table per level; the [`TransitionSink`] the hierarchy rollout feeds.

#![forbid(unsafe_code)]

mod rate_limiter;
mod ring;
mod table;

pub use rate_limiter::{
    RateLimiter, RateLimiterConfig, RateLimiterConfigError, RateLimiterCounts, RateLimiterStatus,
    WaitError,
};
pub use table::{DimensionMismatch, ReplayTable, SampleError, SnapshotError};

use hac_core::{AgentConfig, EnvSpec, Transition, TransitionSink};

/// The replay of a whole hierarchy: table `i` holds level `i`'s transitions.
#[derive(Debug)]
pub struct Replay {
    tables: Vec<ReplayTable>,
}

impl Replay {
    /// Table `i` becomes level `i`'s.
    pub fn new(tables: Vec<ReplayTable>) -> Self {
        Self { tables }
    }

    /// The reference sizing: each level gets its dimensions from `spec` and its capacity from
    /// [`AgentConfig::replay_capacity`], split over `shards` shards; level `i` keeps
    /// `extra_widths[i]` extra values per transition beside (none where the slice ends: HAC's
    /// levels).
    ///
    /// # Panics
    /// If `shards` is zero or exceeds a level's capacity.
    pub fn for_agent(
        spec: &EnvSpec,
        config: &AgentConfig,
        shards: usize,
        extra_widths: &[usize],
    ) -> Self {
        let tables = (0..config.levels)
            .map(|level| {
                ReplayTable::with_extra(
                    spec.level_dims(level, config.levels),
                    extra_widths.get(level).copied().unwrap_or(0),
                    config.replay_capacity(level),
                    shards,
                )
            })
            .collect();
        Self::new(tables)
    }

    pub fn levels(&self) -> usize {
        self.tables.len()
    }

    /// Level `level`'s table.
    ///
    /// # Panics
    /// If `level >= self.levels()`.
    pub fn table(&self, level: usize) -> &ReplayTable {
        &self.tables[level]
    }
}

/// Inserts into the level's table, round robin over its shards.
impl TransitionSink for Replay {
    fn push(&mut self, level: usize, transition: &Transition<'_>) {
        self.tables[level].insert(transition);
    }
}

/// Inserting needs only `&Replay`, so several rollouts on their own threads can feed one shared
/// replay (`&mut &*replay` where a `&mut impl TransitionSink` is wanted).
impl TransitionSink for &Replay {
    fn push(&mut self, level: usize, transition: &Transition<'_>) {
        self.tables[level].insert(transition);
    }
}

#[cfg(test)]
mod tests {
    use hac_core::{Batch, LevelDims, Rng, TransitionKind};

    use super::*;

    #[test]
    fn push_goes_to_the_level_table() {
        let dims = |action| LevelDims {
            state: 2,
            goal: 1,
            action,
        };
        let mut replay = Replay::new(vec![
            ReplayTable::new(dims(1), 4, 1),
            ReplayTable::new(dims(2), 4, 2),
        ]);
        let t = Transition {
            kind: TransitionKind::HindsightGoal,
            state: &[1.0, 2.0],
            action: &[3.0, 4.0],
            reward: -1.0,
            next_state: &[5.0, 6.0],
            goal: &[7.0],
            terminal: true,
            extra: &[],
        };
        replay.push(1, &t);
        (&replay).push(1, &t);

        assert_eq!(replay.levels(), 2);
        assert!(replay.table(0).is_empty());
        assert_eq!(replay.table(1).shard_lens().collect::<Vec<_>>(), [1, 1]);

        let mut batch = Batch::zeros(dims(2), 1);
        replay
            .table(1)
            .sample(&mut Rng::seed_from(0), &mut batch)
            .unwrap();
        assert_eq!(batch.states, [1.0, 2.0]);
        assert_eq!(batch.actions, [3.0, 4.0]);
        assert_eq!(batch.rewards, [-1.0]);
        assert_eq!(batch.next_states, [5.0, 6.0]);
        assert_eq!(batch.goals, [7.0]);
        assert_eq!(batch.terminals, [1.0]);
    }
}
