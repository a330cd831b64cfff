//! What actors send the learner: ingest messages (transition batches and episode summaries),
//! checked and stored exactly once, and evaluation reports, which extend the curve. Also the
//! write-ahead log's replay at start, which stores its records as ingest did.
//!
//! # Locks
//! An ingest message, in order: the gate (shared; [`Learner::ingest_ref`](crate::Learner)
//! takes it), the sender's registry entry (held while the message is checked, logged and
//! stored, so that an actor's sequence advances one message at a time), and under the entry:
//! the log's append, the `counting` lock (shared, while a batch is inserted into its replay
//! shard and counted), the shard's own lock and the rate limiter's. The entry is released
//! before an episode summary's effects: the turns', then each level's slot (the publisher's
//! [`episode_counted`](crate::publisher::Publisher::episode_counted)), then publishing.
//!
//! An evaluation report takes the gate (shared), the reporter's entry (released before the
//! registry is scanned for evaluators), the publisher's state, then the curve.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use hac_proto::{
    ActorRole, Evaluation, IngestItemRef, IngestRef, RejectReason, WireError, check_batch,
};

use crate::curve::Round;
use crate::registry::ActorEntry;
use crate::{IngestError, Shared, Stored, wal};

/// Counters for status; monotone.
#[derive(Debug, Default)]
pub(crate) struct Counters {
    pub(crate) messages: AtomicU64,
    pub(crate) duplicates: AtomicU64,
    pub(crate) batches: AtomicU64,
    pub(crate) transitions: AtomicU64,
    pub(crate) episodes: AtomicU64,
    pub(crate) successes: AtomicU64,
    pub(crate) env_steps: AtomicU64,
    pub(crate) rejected: [AtomicU64; RejectReason::ALL.len()],
    /// Messages the per-actor rate limit held back, and the waits it imposed (nanoseconds).
    pub(crate) throttled: AtomicU64,
    pub(crate) throttled_ns: AtomicU64,
}

impl Counters {
    /// Counts a refusal under `reason`.
    pub(crate) fn reject(&self, reason: RejectReason) {
        let index = RejectReason::ALL
            .iter()
            .position(|&r| r == reason)
            .expect("every reason is listed");
        self.rejected[index].fetch_add(1, Ordering::Relaxed);
    }
}

impl Shared {
    /// Checks and stores one ingest message; see the crate docs. The caller holds the gate
    /// (shared). Locks: see the module docs.
    pub(crate) fn ingest(&self, msg: &IngestRef<'_>) -> Result<Stored, IngestError> {
        let counters = &self.counters;
        counters.messages.fetch_add(1, Ordering::Relaxed);
        let entry = self.registry.entry(msg.actor_id)?;
        let mut actor = entry.lock();
        actor.check_incarnation(msg.actor_id, msg.incarnation)?;
        actor.last_seen = Instant::now();
        if msg.sequence == 0 {
            return Err(WireError::missing("ingest_request.sequence").into());
        }
        if msg.sequence <= actor.stored_through {
            actor.duplicates += 1;
            counters.duplicates.fetch_add(1, Ordering::Relaxed);
            return Ok(Stored::Duplicate);
        }
        let expected = actor.stored_through + 1;
        if msg.sequence != expected {
            return Err(IngestError::SequenceGap {
                actor: msg.actor_id.to_string(),
                got: msg.sequence,
                expected,
            });
        }
        if actor.role == ActorRole::Evaluator {
            return Err(IngestError::WrongRole(msg.actor_id.to_string()));
        }
        if self.is_finished() {
            return Err(IngestError::Finished);
        }
        // Admission by meaning: nothing below may fail, so what the log holds is exactly what
        // is stored.
        let shard = match msg.item {
            IngestItemRef::Batch { level, batch, .. } => {
                check_batch(level, batch, &self.dims, self.options.max_batch_transitions)?;
                self.limits[level]
                    .check(&batch)
                    .map_err(|source| IngestError::OutOfRange {
                        actor: msg.actor_id.to_string(),
                        source,
                    })?;
                // Batches go round the shards in the order they are stored, whoever sent them:
                // writers rarely meet, one actor alone fills every shard, and under episode
                // turns (one episode in flight) the shards' contents, so the minibatches drawn
                // from them, do not depend on which trainer played which episode.
                (counters.batches.load(Ordering::Relaxed)
                    % self.replay.table(level).shard_count() as u64) as usize
            }
            IngestItemRef::Episode { env_steps, .. } => {
                if env_steps > self.max_episode_actions {
                    return Err(IngestError::EpisodeTooLong {
                        actor: msg.actor_id.to_string(),
                        got: env_steps,
                        max: self.max_episode_actions,
                    });
                }
                0
            }
        };
        if let Some(wal) = &self.wal {
            wal.append(shard as u32, msg);
        }
        let episode = self.store(&mut actor, msg, shard);
        if episode {
            let incarnation = actor.incarnation;
            drop(actor);
            self.turns.episode_arrived(msg.actor_id, incarnation);
            self.count_episode();
            self.maybe_publish();
        }
        Ok(Stored::New)
    }

    /// Stores an admitted message of `actor` (a batch into `shard` of its level's table) and
    /// counts it; true for an episode summary, whose effects on the rate limiters follow
    /// ([`count_episode`](Self::count_episode)) once the actor's entry is released. The caller
    /// holds the entry; takes `counting` (shared), the shard's and the limiter's locks.
    fn store(&self, actor: &mut ActorEntry, msg: &IngestRef<'_>, shard: usize) -> bool {
        let counters = &self.counters;
        let episode = match msg.item {
            IngestItemRef::Batch {
                level,
                weights_version,
                batch,
            } => {
                let table = self.replay.table(level);
                actor.batches += 1;
                self.limiters[level].record_insert(batch.len);
                {
                    let _counting = self.counting.read();
                    table.insert_batch_into(shard, batch);
                    counters.batches.fetch_add(1, Ordering::Relaxed);
                    counters
                        .transitions
                        .fetch_add(batch.len as u64, Ordering::Relaxed);
                }
                actor.transitions += batch.len as u64;
                actor.weights_version = actor.weights_version.max(weights_version);
                false
            }
            IngestItemRef::Episode {
                env_steps,
                success,
                weights_version,
            } => {
                actor.episodes += 1;
                actor.env_steps += env_steps;
                actor.weights_version = actor.weights_version.max(weights_version);
                counters.episodes.fetch_add(1, Ordering::Relaxed);
                counters
                    .successes
                    .fetch_add(u64::from(success), Ordering::Relaxed);
                counters.env_steps.fetch_add(env_steps, Ordering::Relaxed);
                true
            }
        };
        actor.stored_through = msg.sequence;
        episode
    }

    /// An episode summary was stored: every level's rate limiter owes its updates, and a level
    /// owing nothing covers the episode at once. Locks: each limiter, and each level's slot in
    /// turn; the caller holds no entry.
    fn count_episode(&self) {
        for (level, limiter) in self.limiters.iter().enumerate() {
            limiter.record_episode();
            self.publisher.episode_counted(level, limiter);
        }
    }

    /// Stores a message read back from the write-ahead log, as ingest stored it (same shard,
    /// same counts); registers its actor as a trainer if the registry does not know it yet, or
    /// under the record's incarnation if it was a newer one. At start, before any other thread
    /// runs.
    pub(crate) fn replay_record(&self, record: &wal::Record<'_>) {
        let msg = &record.message;
        let entry = self
            .registry
            .entry_for_record(msg.actor_id, msg.incarnation, Instant::now());
        let mut actor = entry.lock();
        if msg.sequence != actor.stored_through + 1 {
            tracing::warn!(
                actor = %msg.actor_id,
                sequence = msg.sequence,
                expected = actor.stored_through + 1,
                "write-ahead log record out of sequence"
            );
        }
        self.counters.messages.fetch_add(1, Ordering::Relaxed);
        let shard = match msg.item {
            IngestItemRef::Batch { level, .. } if level < self.dims.len() => {
                (record.shard as usize) % self.replay.table(level).shard_count()
            }
            _ => 0,
        };
        if self.store(&mut actor, msg, shard) {
            drop(actor);
            self.count_episode();
        }
    }

    /// Adds an evaluation report to the curve (see [`Learner::report_evaluation`]); may
    /// complete the run. The caller holds the gate (shared). Locks: see the module docs.
    ///
    /// [`Learner::report_evaluation`]: crate::Learner::report_evaluation
    pub(crate) fn report_evaluation(&self, evaluation: &Evaluation) -> Result<(), IngestError> {
        let entry = self.registry.entry(&evaluation.actor_id)?;
        {
            let mut actor = entry.lock();
            actor.check_incarnation(&evaluation.actor_id, evaluation.incarnation)?;
            actor.last_seen = Instant::now();
            // A trainer may evaluate itself (`--eval-every`) while the run has no evaluator;
            // once one is registered, the curve is the evaluators' alone.
            if actor.role == ActorRole::Trainer {
                drop(actor);
                if self.registry.has_evaluator() {
                    return Err(IngestError::TrainerEvaluation(evaluation.actor_id.clone()));
                }
            }
        }
        let learner_start = self.publisher.learner_start();
        if evaluation.learner_start != 0 && evaluation.learner_start != learner_start {
            return Err(IngestError::StaleWeights {
                got: evaluation.learner_start,
                current: learner_start,
            });
        }
        if evaluation.episodes == 0 {
            return Err(WireError::zero("evaluation_report.episodes").into());
        }
        if evaluation.successes > evaluation.episodes {
            return Err(WireError::SuccessesAboveEpisodes {
                successes: evaluation.successes,
                episodes: evaluation.episodes,
            }
            .into());
        }
        let (episodes, snapshot) = self.publisher.published(evaluation.weights_version).ok_or(
            IngestError::UnknownWeightsVersion(evaluation.weights_version),
        )?;
        {
            let mut actor = entry.lock();
            actor.weights_version = actor.weights_version.max(evaluation.weights_version);
        }
        let success_rate = evaluation.successes as f32 / evaluation.episodes as f32;
        let status = self.status();
        let report = self.curve.add(Round {
            episodes,
            env_steps: status.env_steps,
            success_rate,
            elapsed_s: self.elapsed().as_secs_f64(),
            levels: &status.levels,
            weights_version: evaluation.weights_version,
            snapshot,
        });
        tracing::debug!(
            episodes = report.episodes,
            success = report.success_rate,
            "evaluation"
        );
        if self
            .run
            .stop_at
            .is_some_and(|target| success_rate >= target)
        {
            self.complete("target success rate reached");
        } else if episodes >= self.run.episodes {
            self.complete("episode budget trained and evaluated");
        }
        Ok(())
    }
}
