//! The learner's `hac.v1.Status` answer: [`learner_status`] from a snapshot, and the learner as a
//! [`StatusSource`] ([`LearnerSource`]) for [`StatusGrpc`](hac_transport::grpc::StatusGrpc).

use std::sync::Arc;

use hac_learner::{Learner, LearnerStatus};
use hac_proto::pb;
use hac_transport::grpc::{StatusSource, role_name};

/// A shared [`Learner`] as a [`StatusSource`]: its status with the most recent evaluations.
#[derive(Debug, Clone)]
pub struct LearnerSource(pub Arc<Learner>);

impl StatusSource for LearnerSource {
    fn node_status(&self, max_evaluations: usize) -> pb::NodeStatus {
        let learner = &self.0;
        pb::NodeStatus {
            node: Some(pb::node_status::Node::Learner(learner_status(
                learner,
                &learner.status(),
                max_evaluations,
            ))),
        }
    }
}

/// The learner's status message from its snapshot and the last `max_evaluations` points of its
/// curve.
pub fn learner_status(
    learner: &Learner,
    status: &LearnerStatus,
    max_evaluations: usize,
) -> pb::LearnerStatus {
    let run = learner.run_config();
    let (evaluations_total, curve) = learner.recent_curve(max_evaluations);
    let rates = &status.rates;
    let trouble = learner.trouble().latest().and_then(|t| (*t).clone());
    pb::LearnerStatus {
        state: if status.finished {
            "draining"
        } else if trouble.is_some() {
            "unhealthy"
        } else {
            "serving"
        }
        .into(),
        trouble: trouble.unwrap_or_default(),
        run_config_digest: status.run_config_digest.clone(),
        env: run.env.clone(),
        levels: run.levels as u32,
        algo: run.algo.name().into(),
        seed: run.seed,
        episode_budget: run.episodes,
        uptime_seconds: status.uptime.as_secs_f64(),
        weights_version: status.weights_version,
        messages: status.messages,
        batches: status.batches,
        transitions: status.transitions,
        episodes: status.episodes,
        successes: status.successes,
        env_steps: status.env_steps,
        duplicates: status.duplicates,
        rates_window_seconds: rates.window.as_secs_f64(),
        transitions_per_second: rates.transitions_per_s,
        batches_per_second: rates.batches_per_s,
        episodes_per_second: rates.episodes_per_s,
        env_steps_per_second: rates.env_steps_per_s,
        updates_per_second: rates.updates_per_s,
        level_status: status
            .levels
            .iter()
            .enumerate()
            .map(|(level, l)| pb::LevelStatus {
                level: level as u32,
                updates: l.updates,
                updates_per_second: l.updates_per_s,
                replay_size: l.replay_len as u64,
                replay_capacity: l.replay_capacity as u64,
                shard_sizes: l.shard_lens.iter().map(|&n| n as u64).collect(),
                transitions_inserted: l.transitions_inserted,
                critic_loss: l.last.map(|u| u.critic_loss),
                actor_loss: l.last.map(|u| u.actor_loss),
                mean_q: l.last.map(|u| u.mean_q),
                update_deficit: l.limiter.deficit,
                trainer_wait_seconds: l.limiter.trainer_blocked.as_secs_f64(),
                ingest_waits: l.limiter.ingest_refused,
                ingest_wait_seconds: l.limiter.ingest_blocked.as_secs_f64(),
                diverged_updates: l.diverged_updates,
                diverged_in_a_row: l.diverged_in_a_row,
            })
            .collect(),
        rejected: status
            .rejected
            .iter()
            .map(|&(reason, count)| pb::RejectCount {
                reason: reason.name().into(),
                count,
            })
            .collect(),
        actor_rate_limit_waits: status.throttled,
        actor_rate_limit_wait_seconds: status.throttled_for.as_secs_f64(),
        episodes_in_flight: status.turns.limit,
        turns_held: status.turns.held,
        turns_waiting: status.turns.waiting,
        turns_granted: status.turns.granted,
        turns_expired: status.turns.expired,
        wal: status.wal.map(|w| pb::WalStatus {
            bytes: w.bytes,
            segments: w.segments,
            appended: w.appended,
            committed: w.committed,
            commits: w.commits,
            last_commit_seconds: w.last_commit.as_secs_f64(),
            failed: w.failed,
        }),
        actors: status
            .actors
            .iter()
            .map(|a| pb::RegisteredActor {
                actor_id: a.actor_id.clone(),
                role: role_name(a.role).into(),
                hostname: a.hostname.clone(),
                incarnation: a.incarnation,
                transport: a.transport.into(),
                connected_seconds: a.registered_for.as_secs_f64(),
                last_seen_seconds: a.last_seen_ago.as_secs_f64(),
                episodes: a.episodes,
                env_steps: a.env_steps,
                env_steps_per_second: a.env_steps_per_s,
                transitions: a.transitions,
                duplicates: a.duplicates,
                weights_version: a.weights_version,
                weights_lag: a.weights_lag,
                stored_through: a.stored_through,
                durable_through: a.durable_through,
            })
            .collect(),
        evaluations: curve
            .iter()
            .map(|r| pb::EvaluationPoint {
                round: r.round as u64,
                episodes: r.episodes,
                env_steps: r.env_steps,
                success_rate: r.success_rate,
                elapsed_seconds: r.elapsed_s,
            })
            .collect(),
        evaluations_total: evaluations_total as u64,
    }
}
