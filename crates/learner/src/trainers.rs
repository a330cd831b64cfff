//! The trainers: one thread per level, each taking the updates its rate limiter grants,
//! handing every finished update to the publisher, answering checkpoint requests between
//! updates, and reporting when a level starts or stops failing.
//!
//! # Locks
//! A trainer holds no lock while it samples and updates (the replay shards and the limiter
//! lock themselves inside their calls). After each update it takes its level's slot
//! ([`Publisher::update_done`](crate::publisher::Publisher::update_done)), then, with the slot
//! released, the publisher ([`Shared::maybe_publish`]); a checkpoint request is answered
//! between two updates with no lock held (see `checkpoint`).

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use hac_core::{Batch, Rng};
use hac_nn::{LearnerBackup, LevelModel};
use hac_replay::WaitError;

use crate::{Shared, hiro};

impl Shared {
    /// The trainer thread of `level`: takes each update the rate limiter grants, offers the
    /// weights for publication when caught up or every `publish_every_updates`, answers
    /// checkpoint requests between updates; returns the trained networks and its random stream
    /// once the limiter is closed.
    pub(crate) fn train_level(
        &self,
        level: usize,
        mut learner: LevelModel,
        mut rng: Rng,
        mut batch: Batch,
    ) -> (LevelModel, Rng) {
        let limiter = &self.limiters[level];
        let table = self.replay.table(level);
        let mut backup = LearnerBackup::default();
        let mut hiro = self.run.hiro().map(|h| {
            let env = self
                .run
                .make_env()
                .expect("the run's environment was made at start");
            hiro::HiroPrep::new(level, env, h.c, h.candidates)
        });
        loop {
            if self.snapshots.requested[level].load(Ordering::Acquire) {
                self.serve_snapshot(level, &learner, &rng);
            }
            match limiter.acquire_update(Duration::from_millis(50)) {
                Ok(()) => {}
                Err(WaitError::TimedOut) => {
                    self.maybe_publish();
                    continue;
                }
                Err(WaitError::Closed) => break,
            }
            // Granted updates are owed for credited episodes, which need a table holding at
            // least one batch.
            table
                .sample(&mut rng, &mut batch)
                .expect("an update is granted only once the table holds a batch");
            // A diverged update is undone and still counts as done: the schedule goes on with
            // the last good weights, which are all that is ever published.
            let outcome = match (&mut learner, &mut hiro) {
                (LevelModel::Hac(l), _) => l.update_or_undo(&batch, &mut backup),
                (LevelModel::Td3(l), Some(prep)) => {
                    let next_goals = prep.prepare(&mut batch, self.publisher.covering(), &mut rng);
                    l.update_or_undo(&batch, next_goals, &mut rng, &mut backup)
                }
                (LevelModel::Td3(_), None) => unreachable!("TD3 levels are HIRO's"),
            };
            // Whether the level started or stopped failing: reported once its slot is released.
            if self
                .publisher
                .update_done(level, outcome, &learner, limiter)
            {
                self.report_trouble();
            }
            self.maybe_publish();
        }
        (learner, rng)
    }

    /// Publishes why the learner is unhealthy (the first failing level), if that changed.
    /// Locks: each slot in turn, then none while publishing.
    fn report_trouble(&self) {
        let trouble = self.publisher.failing();
        if self.trouble.latest().as_deref() != Some(&trouble) {
            if let Some(why) = &trouble {
                tracing::error!(reason = %why, "learner unhealthy");
            }
            self.trouble.publish(Arc::new(trouble));
        }
    }
}
