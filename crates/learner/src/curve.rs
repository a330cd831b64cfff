//! [`Curve`]: the learning curve (one point per evaluation report) and the weights of its best
//! round.
//!
//! # Locks
//! One mutex over the points and what the next point's rates are measured from. The best
//! weights are judged and republished under it, so that rounds are judged in the order they
//! joined the curve. Nothing else is taken under it.

use std::sync::Arc;
use std::time::Instant;

use hac_agent::{LevelReport, RoundReport};
use hac_proto::{BestWeights, Published, WeightsSnapshot};
use parking_lot::Mutex;

use crate::LevelStatus;
use crate::best::{self, RECENT_SNAPSHOTS};

#[derive(Debug)]
struct CurveState {
    points: Vec<RoundReport>,
    last_at: Instant,
    last_env_steps: u64,
    last_updates: u64,
}

/// What a new point of the curve is made of (besides its place and rates).
#[derive(Debug)]
pub(crate) struct Round<'a> {
    /// Training episodes the evaluated weights had been trained on.
    pub(crate) episodes: u64,
    pub(crate) env_steps: u64,
    pub(crate) success_rate: f32,
    pub(crate) elapsed_s: f64,
    pub(crate) levels: &'a [LevelStatus],
    /// The evaluated weights: their version, and their snapshot if it is still kept.
    pub(crate) weights_version: u64,
    pub(crate) snapshot: Option<Arc<WeightsSnapshot>>,
}

/// The learning curve and the best round's weights; see the module docs.
#[derive(Debug)]
pub(crate) struct Curve {
    state: Mutex<CurveState>,
    best: Published<BestWeights>,
}

impl Curve {
    /// A curve holding `points`, whose last point was taken at `env_steps` env steps and
    /// `updates` updates (0 for a new run).
    pub(crate) fn new(points: Vec<RoundReport>, env_steps: u64, updates: u64) -> Self {
        Self {
            state: Mutex::new(CurveState {
                points,
                last_at: Instant::now(),
                last_env_steps: env_steps,
                last_updates: updates,
            }),
            best: Published::default(),
        }
    }

    /// The weights of the best round so far, waitable. No lock.
    pub(crate) fn best(&self) -> &Published<BestWeights> {
        &self.best
    }

    /// Every point. Locks: the curve.
    pub(crate) fn points(&self) -> Vec<RoundReport> {
        self.state.lock().points.clone()
    }

    /// The last `max` points (all of them for 0), and how many there are. Locks: the curve.
    pub(crate) fn recent(&self, max: usize) -> (usize, Vec<RoundReport>) {
        let curve = self.state.lock();
        let total = curve.points.len();
        let from = if max == 0 {
            0
        } else {
            total.saturating_sub(max)
        };
        (total, curve.points[from..].to_vec())
    }

    /// The points, and the env steps and updates the last was taken at (for a checkpoint).
    /// Locks: the curve.
    pub(crate) fn capture(&self) -> (Vec<RoundReport>, u64, u64) {
        let c = self.state.lock();
        (c.points.clone(), c.last_env_steps, c.last_updates)
    }

    /// Adds `round` as the next point, with the rates since the previous one, and makes its
    /// weights the best if it beats every earlier round. Locks: the curve.
    pub(crate) fn add(&self, round: Round<'_>) -> RoundReport {
        let updates: u64 = round.levels.iter().map(|l| l.updates).sum();
        let mut curve = self.state.lock();
        let dt = curve.last_at.elapsed().as_secs_f64();
        let rate = |n: u64| if dt > 0.0 { n as f64 / dt } else { 0.0 };
        let report = RoundReport {
            round: curve.points.len() + 1,
            episodes: round.episodes,
            env_steps: round.env_steps,
            success_rate: round.success_rate,
            elapsed_s: round.elapsed_s,
            env_steps_per_s: rate(round.env_steps.saturating_sub(curve.last_env_steps)),
            updates_per_s: rate(updates.saturating_sub(curve.last_updates)),
            levels: round
                .levels
                .iter()
                .map(|l| {
                    let last = l.last.unwrap_or_default();
                    LevelReport {
                        updates: l.updates,
                        replay_len: l.replay_len,
                        critic_loss: last.critic_loss,
                        actor_loss: last.actor_loss,
                        mean_q: last.mean_q,
                    }
                })
                .collect(),
        };
        curve.points.push(report.clone());
        curve.last_at = Instant::now();
        curve.last_env_steps = round.env_steps;
        curve.last_updates = updates;
        // Under the curve's lock: rounds are judged in the order they joined the curve.
        if best::improves(self.best.latest().as_deref(), round.success_rate) {
            match round.snapshot {
                Some(snapshot) => self.best.publish(Arc::new(BestWeights {
                    round: report.round,
                    episodes: round.episodes,
                    env_steps: round.env_steps,
                    success_rate: round.success_rate,
                    snapshot,
                })),
                None => tracing::warn!(
                    round = report.round,
                    weights_version = round.weights_version,
                    kept = RECENT_SNAPSHOTS,
                    "the best test round so far evaluated weights older than the snapshots kept: \
                     the best weights stay those of an earlier round"
                ),
            }
        }
        report
    }
}
