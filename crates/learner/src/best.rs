//! The best weights of a run: the snapshot behind its best test round.
//!
//! A run's last weights are not always its best: a pendulum run can reach 100% greedy test
//! success and end at a few percent. Every evaluation report names the weights version it
//! tested, so the learner keeps the most recent snapshots it published ([`RecentSnapshots`]) and,
//! when a report beats every earlier round, keeps that version's snapshot as
//! [`BestWeights`] (the earliest round wins a tie: the first time the run got there).
//!
//! The snapshot holds what actors act with: each level's actor network as safetensors, the
//! same bytes the weights stream carries. That is what a greedy evaluation or an exported
//! policy needs; the critics and optimiser state of that moment are not kept.

use std::collections::VecDeque;
use std::sync::Arc;

use hac_proto::{BestWeights, WeightsSnapshot};

/// How many of the newest published snapshots stay available to become the best. Evaluations
/// test a version the evaluator received a moment ago (the lockstep trainer, the current one);
/// an evaluation of a version older than this many publications cannot become the best.
pub const RECENT_SNAPSHOTS: usize = 64;

/// The newest published snapshots, oldest first; a bounded ring of shared pointers (publishing
/// already made each snapshot, so keeping one costs no copy).
#[derive(Debug, Default)]
pub(crate) struct RecentSnapshots {
    ring: VecDeque<Arc<WeightsSnapshot>>,
}

impl RecentSnapshots {
    pub(crate) fn push(&mut self, snapshot: Arc<WeightsSnapshot>) {
        if self.ring.len() == RECENT_SNAPSHOTS {
            self.ring.pop_front();
        }
        self.ring.push_back(snapshot);
    }

    /// The snapshot of `version`, if it is still kept.
    pub(crate) fn get(&self, version: u64) -> Option<&Arc<WeightsSnapshot>> {
        // Versions increase along the ring.
        let i = self
            .ring
            .binary_search_by_key(&version, |s| s.version)
            .ok()?;
        self.ring.get(i)
    }
}

/// Whether a round with `success_rate` replaces `best` (strictly better; the first round of a
/// run always does).
pub(crate) fn improves(best: Option<&BestWeights>, success_rate: f32) -> bool {
    best.is_none_or(|b| success_rate > b.success_rate)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn snapshot(version: u64) -> Arc<WeightsSnapshot> {
        Arc::new(WeightsSnapshot {
            version,
            levels: vec![vec![version as u8]],
            episodes: version * 10,
            run_finished: false,
            learner_start: 7,
        })
    }

    #[test]
    fn the_ring_keeps_the_newest_versions_and_finds_them() {
        let mut recent = RecentSnapshots::default();
        for v in 1..=(RECENT_SNAPSHOTS as u64 + 5) {
            recent.push(snapshot(v));
        }
        assert!(recent.get(5).is_none(), "fell out of the ring");
        assert_eq!(recent.get(6).unwrap().version, 6);
        let newest = RECENT_SNAPSHOTS as u64 + 5;
        assert_eq!(recent.get(newest).unwrap().levels, vec![vec![newest as u8]]);
        assert!(recent.get(newest + 1).is_none());
    }

    #[test]
    fn only_a_strictly_better_round_replaces_the_best() {
        let best = BestWeights {
            round: 3,
            episodes: 150,
            env_steps: 0,
            success_rate: 0.9,
            snapshot: snapshot(4),
        };
        assert!(improves(None, 0.0));
        assert!(!improves(Some(&best), 0.9));
        assert!(!improves(Some(&best), 0.5));
        assert!(improves(Some(&best), 0.91));
    }
}
