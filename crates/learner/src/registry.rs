//! [`Registry`]: the actors the learner knows, by id: their role, incarnation, what each has
//! stored, its counts and message rate limit.
//!
//! # Locks
//! Two levels, always taken in this order:
//! 1. the map (`RwLock`): read to find an actor, written to add or drop one;
//! 2. one actor's entry (`Mutex`), held while a message of that actor is checked and stored
//!    (see `ingest`), so that each actor's sequence advances one message at a time.
//!
//! No method takes the map while the caller may hold an entry; [`Registry::get`] and
//! [`Registry::entry`] release the map before returning, so callers lock the entry with no
//! other registry lock held. Methods that visit every actor ([`Registry::forget_silent`],
//! [`Registry::has_evaluator`], [`Registry::each`], [`Registry::status`]) hold the map and
//! lock each entry in turn: a caller must not hold any entry when calling them.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use hac_proto::{ActorRole, PreviousIncarnation, Registration};
use parking_lot::{Mutex, RwLock};

use crate::{IngestError, RATES_WINDOW, RateWindow, TokenBucket, Wal};

/// One registered actor.
#[derive(Debug)]
pub(crate) struct ActorEntry {
    pub(crate) role: ActorRole,
    pub(crate) hostname: String,
    /// Registration order of the actor id (stable across its incarnations): part of its seed.
    pub(crate) ordinal: u64,
    pub(crate) incarnation: u64,
    /// Every sequence up to this one is stored (0: none yet).
    pub(crate) stored_through: u64,
    pub(crate) registered_at: Instant,
    pub(crate) last_seen: Instant,
    pub(crate) episodes: u64,
    pub(crate) env_steps: u64,
    pub(crate) batches: u64,
    pub(crate) transitions: u64,
    pub(crate) duplicates: u64,
    pub(crate) weights_version: u64,
    /// How the actor reaches the learner, as its transport reported it ("" until then).
    pub(crate) transport: &'static str,
    /// `[env_steps]` over time, for the actor's env steps per second.
    pub(crate) env_steps_rate: RateWindow,
    /// The message rate limit, carried over from the actor's earlier incarnations.
    pub(crate) bucket: Option<TokenBucket>,
}

impl ActorEntry {
    pub(crate) fn new(
        role: ActorRole,
        hostname: String,
        ordinal: u64,
        incarnation: u64,
        bucket: Option<TokenBucket>,
        now: Instant,
    ) -> Self {
        Self {
            role,
            hostname,
            ordinal,
            incarnation,
            stored_through: 0,
            registered_at: now,
            last_seen: now,
            episodes: 0,
            env_steps: 0,
            batches: 0,
            transitions: 0,
            duplicates: 0,
            weights_version: 0,
            transport: "",
            env_steps_rate: RateWindow::new(now, 1, RATES_WINDOW),
            bucket,
        }
    }

    /// Refuses a message of `actor_id` numbered under another incarnation than this entry's.
    pub(crate) fn check_incarnation(&self, actor_id: &str, got: u64) -> Result<(), IngestError> {
        if got == self.incarnation {
            Ok(())
        } else {
            Err(IngestError::StaleIncarnation {
                actor: actor_id.to_string(),
                got,
                current: self.incarnation,
            })
        }
    }
}

/// How a registration was admitted by [`Registry::admit`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Admitted {
    /// The actor registered again under the incarnation its link named, which the registry
    /// still knew (a resumed learner recovered it).
    Kept { incarnation: u64, ordinal: u64 },
    /// A fresh incarnation.
    New { incarnation: u64, ordinal: u64 },
}

/// The actors the learner knows; see the module docs for its locks.
#[derive(Debug)]
pub(crate) struct Registry {
    actors: RwLock<HashMap<String, Arc<Mutex<ActorEntry>>>>,
    /// The next new actor id's registration order (ids forgotten and back get a new one).
    next_ordinal: AtomicU64,
    next_incarnation: AtomicU64,
    /// `forget_actors_after`.
    forget_after: Duration,
    /// `max_actor_messages_per_second`: each new actor id's token bucket.
    max_rate: Option<f64>,
}

impl Registry {
    pub(crate) fn new(
        next_incarnation: u64,
        forget_after: Duration,
        max_rate: Option<f64>,
    ) -> Self {
        Self {
            actors: RwLock::default(),
            next_ordinal: AtomicU64::new(0),
            next_incarnation: AtomicU64::new(next_incarnation),
            forget_after,
            max_rate,
        }
    }

    /// `id`'s entry, if the actor is registered. Locks: the map, read, released on return.
    pub(crate) fn get(&self, id: &str) -> Option<Arc<Mutex<ActorEntry>>> {
        self.actors.read().get(id).cloned()
    }

    /// `id`'s entry, or [`IngestError::UnknownActor`]. Locks: as [`get`](Self::get).
    pub(crate) fn entry(&self, id: &str) -> Result<Arc<Mutex<ActorEntry>>, IngestError> {
        self.get(id)
            .ok_or_else(|| IngestError::UnknownActor(id.to_string()))
    }

    /// The incarnation the next registration gets. No lock.
    pub(crate) fn next_incarnation(&self) -> u64 {
        self.next_incarnation.load(Ordering::Relaxed)
    }

    /// Drops every actor not heard from for `forget_actors_after` (at registrations and status
    /// reads, so the registry stays bounded by the actors alive lately). Locks: the map (read,
    /// then written if some actor is to go) and each entry in turn.
    pub(crate) fn forget_silent(&self, now: Instant) {
        let limit = self.forget_after;
        let silent = |a: &Arc<Mutex<ActorEntry>>| now.duration_since(a.lock().last_seen) >= limit;
        if !self.actors.read().values().any(silent) {
            return;
        }
        let mut actors = self.actors.write();
        let before = actors.len();
        actors.retain(|_, a| !silent(a));
        tracing::info!(forgotten = before - actors.len(), after = ?limit, "silent actors forgotten");
    }

    /// Admits `registration`: under `previous` if the registry knows the actor under exactly
    /// that incarnation with every sequence before `previous.resend_from` stored (its role and
    /// hostname updated), else under a fresh incarnation above every one handed out and above
    /// `previous`'s (the entry replaced; the ordinal and rate limit of an id already known
    /// kept). Locks: the entry of a known actor, then the map, written.
    pub(crate) fn admit(
        &self,
        registration: &Registration,
        previous: Option<PreviousIncarnation>,
        now: Instant,
    ) -> Admitted {
        if let Some(previous) = previous {
            if let Some(ordinal) = self.keep_incarnation(registration, previous, now) {
                return Admitted::Kept {
                    incarnation: previous.incarnation,
                    ordinal,
                };
            }
            self.next_incarnation
                .fetch_max(previous.incarnation.saturating_add(1), Ordering::Relaxed);
        }
        let incarnation = self.next_incarnation.fetch_add(1, Ordering::Relaxed);
        let mut actors = self.actors.write();
        let (ordinal, bucket) = match actors.get(&registration.actor_id) {
            Some(earlier) => {
                let earlier = earlier.lock();
                (earlier.ordinal, earlier.bucket.clone())
            }
            None => (self.next_ordinal.fetch_add(1, Ordering::Relaxed), None),
        };
        let bucket = bucket.or_else(|| self.max_rate.map(|rate| TokenBucket::new(rate, now)));
        actors.insert(
            registration.actor_id.clone(),
            Arc::new(Mutex::new(ActorEntry::new(
                registration.role,
                registration.hostname.clone(),
                ordinal,
                incarnation,
                bucket,
                now,
            ))),
        );
        Admitted::New {
            incarnation,
            ordinal,
        }
    }

    /// The ordinal of an actor registering again under `previous`, if [`admit`](Self::admit)
    /// keeps that incarnation. Locks: the map (read, released), then the entry.
    fn keep_incarnation(
        &self,
        registration: &Registration,
        previous: PreviousIncarnation,
        now: Instant,
    ) -> Option<u64> {
        let entry = self.get(&registration.actor_id)?;
        let mut actor = entry.lock();
        let keep = actor.incarnation == previous.incarnation
            && previous.resend_from <= actor.stored_through + 1
            && (actor.role == registration.role || actor.hostname.is_empty());
        if !keep {
            return None;
        }
        actor.role = registration.role;
        actor.hostname.clone_from(&registration.hostname);
        actor.last_seen = now;
        Some(actor.ordinal)
    }

    /// The entry of the actor that stored a message read back from the write-ahead log under
    /// `incarnation`: registered as a trainer if the registry does not know it yet, or anew
    /// under `incarnation` if that is not its current one (ordinal and rate limit kept). Locks:
    /// the map (written, released), then the entry (released on return).
    pub(crate) fn entry_for_record(
        &self,
        actor_id: &str,
        incarnation: u64,
        now: Instant,
    ) -> Arc<Mutex<ActorEntry>> {
        let entry = self
            .actors
            .write()
            .entry(actor_id.to_string())
            .or_insert_with(|| {
                let ordinal = self.next_ordinal.fetch_add(1, Ordering::Relaxed);
                Arc::new(Mutex::new(ActorEntry::new(
                    ActorRole::Trainer,
                    String::new(),
                    ordinal,
                    incarnation,
                    None,
                    now,
                )))
            })
            .clone();
        {
            let mut actor = entry.lock();
            if actor.incarnation != incarnation {
                let (ordinal, bucket) = (actor.ordinal, actor.bucket.take());
                *actor = ActorEntry::new(
                    ActorRole::Trainer,
                    String::new(),
                    ordinal,
                    incarnation,
                    bucket,
                    now,
                );
            }
        }
        self.next_incarnation
            .fetch_max(incarnation.saturating_add(1), Ordering::Relaxed);
        entry
    }

    /// Puts an actor saved in a checkpoint into the registry of a learner being built. Locks:
    /// the map, written.
    pub(crate) fn restore(&self, id: String, entry: ActorEntry) {
        self.next_ordinal
            .fetch_max(entry.ordinal + 1, Ordering::Relaxed);
        self.actors.write().insert(id, Arc::new(Mutex::new(entry)));
    }

    /// Whether an evaluator is registered. Locks: the map (read) and each entry in turn; the
    /// caller must hold no entry.
    pub(crate) fn has_evaluator(&self) -> bool {
        self.actors
            .read()
            .values()
            .any(|a| a.lock().role == ActorRole::Evaluator)
    }

    /// Calls `f` with every actor, in no particular order. Locks: the map (read) and each entry
    /// in turn, while `f` runs; the caller must hold no entry.
    pub(crate) fn each(&self, mut f: impl FnMut(&str, &mut ActorEntry)) {
        for (id, entry) in self.actors.read().iter() {
            f(id, &mut entry.lock());
        }
    }

    /// How many actors are registered. Locks: the map, read.
    pub(crate) fn len(&self) -> usize {
        self.actors.read().len()
    }

    /// Every actor for status, sorted by id, with its weights lag behind `weights_version` and
    /// what the log holds of it. Locks: as [`each`](Self::each), and the log's own.
    pub(crate) fn status(
        &self,
        now: Instant,
        weights_version: u64,
        wal: Option<&Wal>,
    ) -> Vec<crate::RegisteredActor> {
        let mut actors = Vec::with_capacity(self.len());
        self.each(|id, a| {
            let env_steps = a.env_steps;
            let (_, rate) = a.env_steps_rate.rates(now, &[env_steps]);
            actors.push(crate::RegisteredActor {
                actor_id: id.to_string(),
                role: a.role,
                hostname: a.hostname.clone(),
                incarnation: a.incarnation,
                registered_for: now.saturating_duration_since(a.registered_at),
                last_seen_ago: now.saturating_duration_since(a.last_seen),
                episodes: a.episodes,
                env_steps,
                transitions: a.transitions,
                duplicates: a.duplicates,
                weights_version: a.weights_version,
                weights_lag: weights_version.saturating_sub(a.weights_version),
                transport: a.transport,
                env_steps_per_s: rate[0],
                stored_through: a.stored_through,
                durable_through: match wal {
                    Some(wal) => wal.durable_through(id, a.incarnation),
                    None => a.stored_through,
                },
            });
        });
        actors.sort_by(|a, b| a.actor_id.cmp(&b.actor_id));
        actors
    }
}
