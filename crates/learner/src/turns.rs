//! Episode turns (`episodes_in_flight` > 0): [`Turns`] lets at most that many training episodes
//! be played or wait to be trained on at once, over all actors, granting turns in the order
//! asked.
//!
//! # Locks
//! [`Turns`] owns one mutex (the holders and the line) and a condition variable on it. Its
//! methods take the mutex themselves and call nothing outside this module while holding it,
//! except the two closures of [`Turns::wait`], which may only read atomics. Callers may hold
//! the publisher's lock when calling [`Turns::wake`] (the learner's lock order puts the turns
//! after the publisher), and must hold no lock when calling [`Turns::wait`], which blocks.

use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

use parking_lot::{Condvar, Mutex};

/// The answer to [`Learner::await_turn`](crate::Learner::await_turn).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Turn {
    /// The actor may play its next training episode now.
    pub granted: bool,
    /// Training episodes every level had trained on (and published) when the answer was given.
    pub episodes: u64,
    /// With turns on, the index of the episode the turn is for: episodes received plus turns
    /// held when it was granted (with one episode in flight, the episodes trained on). The actor
    /// draws that episode's random streams from it and the run's seed, so that which trainer
    /// plays an episode does not change the episode. `None` when not granted or turns are off.
    pub episode: Option<u64>,
}

/// What [`Turns::wait`] answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Grant {
    /// Turns are off: play at once.
    Free,
    /// The turn for the episode with this index.
    Episode(u64),
    /// Not yet; ask again.
    NotYet,
}

/// Episode turns in status.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TurnStatus {
    /// `episodes_in_flight` (0: no turns).
    pub limit: u32,
    /// Turns granted whose episode has not arrived yet.
    pub held: u64,
    /// Trainers waiting for a turn now.
    pub waiting: u64,
    pub granted: u64,
    /// Turns whose lease ran out before their episode arrived.
    pub expired: u64,
}

/// The default [`LearnerOptions::turn_lease`](crate::LearnerOptions::turn_lease).
pub const TURN_LEASE: Duration = Duration::from_secs(60);

/// The longest a single [`Learner::await_turn`](crate::Learner::await_turn) call waits; actors ask again.
pub const MAX_TURN_WAIT: Duration = Duration::from_secs(10);

/// How long a place in the line for turns is kept after the call holding it ended without a
/// turn.
const PLACE_KEPT: Duration = Duration::from_secs(2);

/// A place in the line for turns.
#[derive(Debug)]
struct Waiter {
    actor: String,
    incarnation: u64,
    /// A call is waiting on this place now.
    asking: bool,
    /// When the last call on this place ended.
    left_at: Instant,
}

/// Who holds and who waits for episode turns.
#[derive(Debug, Default)]
struct TurnState {
    /// Actor id -> its turn.
    holders: HashMap<String, Held>,
    /// Places in line by ticket, served lowest first among the actors asking now. A place
    /// outlives the call that took it by [`PLACE_KEPT`], so that an actor asking again after
    /// its call timed out keeps its place instead of going to the back.
    waiting: BTreeMap<u64, Waiter>,
    next_ticket: u64,
    /// The lowest episode index the next turn may be for: an index is never given twice, even
    /// while an arriving episode is counted as received and still holds its turn.
    next_episode: u64,
    granted: u64,
    expired: u64,
}

/// A turn granted and not used up yet.
#[derive(Debug, Clone, Copy)]
struct Held {
    incarnation: u64,
    granted_at: Instant,
    /// The index of the episode it is for ([`Turn::episode`]).
    episode: u64,
}

/// Episode turns: who holds one, who waits, and the counts for status. See the module docs.
#[derive(Debug)]
pub(crate) struct Turns {
    state: Mutex<TurnState>,
    /// Signalled when a turn may have become free (a publication, a turn given back).
    changed: Condvar,
    /// `episodes_in_flight`; 0: no turns, every call is granted at once.
    limit: u32,
    /// How long a granted turn is held without its episode arriving.
    lease: Duration,
}

/// The run is finished: no more turns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct RunFinished;

impl Turns {
    pub(crate) fn new(limit: u32, lease: Duration) -> Self {
        Self {
            state: Mutex::default(),
            changed: Condvar::new(),
            limit,
            lease,
        }
    }

    /// `actor_id` registered again: a turn held, or a place in line kept, by an earlier
    /// incarnation will never be used, so it is given back. Locks: the turns' mutex.
    pub(crate) fn forget(&self, actor_id: &str) {
        let mut turns = self.state.lock();
        let held = turns.holders.remove(actor_id).is_some();
        let places = turns.waiting.len();
        turns.waiting.retain(|_, w| w.asking || w.actor != actor_id);
        if held || turns.waiting.len() != places {
            self.changed.notify_all();
        }
    }

    /// An episode summary of `actor_id`'s `incarnation` was stored: the turn it was played in
    /// (if any) is used up; the episode counts as in flight until it is trained on. Locks: the
    /// turns' mutex.
    pub(crate) fn episode_arrived(&self, actor_id: &str, incarnation: u64) {
        let mut turns = self.state.lock();
        if turns
            .holders
            .get(actor_id)
            .is_some_and(|held| held.incarnation == incarnation)
        {
            turns.holders.remove(actor_id);
        }
    }

    /// Wakes every waiter, after a publication. Takes the turns' mutex (briefly, so that a
    /// waiter between its check and its wait still wakes) and releases it before notifying.
    pub(crate) fn wake(&self) {
        drop(self.state.lock());
        self.changed.notify_all();
    }

    /// Waits up to `wait` (at most [`MAX_TURN_WAIT`]) for `actor_id`'s turn: the episode it is
    /// for when granted (or already held by this incarnation), [`Grant::NotYet`] with the place
    /// in line kept for [`PLACE_KEPT`]. `received()` is the number of training episodes
    /// received, `untrained()` those not yet trained on and published, `finished()` whether the
    /// run is over; all three are read under the turns' mutex and may only read atomics.
    /// [`Grant::Free`] at once when turns are off.
    ///
    /// Locks: the turns' mutex, released while waiting on the condition variable. The caller
    /// must hold no lock.
    pub(crate) fn wait(
        &self,
        actor_id: &str,
        incarnation: u64,
        wait: Duration,
        received: impl Fn() -> u64,
        untrained: impl Fn() -> u64,
        finished: impl Fn() -> bool,
    ) -> Result<Grant, RunFinished> {
        let limit = u64::from(self.limit);
        if limit == 0 {
            return Ok(Grant::Free);
        }
        let deadline = Instant::now() + wait.min(MAX_TURN_WAIT);
        let mut turns = self.state.lock();
        if let Some(held) = turns.holders.get(actor_id)
            && held.incarnation == incarnation
        {
            return Ok(Grant::Episode(held.episode));
        }
        let kept = turns
            .waiting
            .iter()
            .find(|(_, w)| w.actor == actor_id && w.incarnation == incarnation)
            .map(|(&ticket, _)| ticket);
        let ticket = kept.unwrap_or_else(|| {
            let ticket = turns.next_ticket;
            turns.next_ticket += 1;
            ticket
        });
        turns.waiting.insert(
            ticket,
            Waiter {
                actor: actor_id.to_string(),
                incarnation,
                asking: true,
                left_at: Instant::now(),
            },
        );
        let leave = |turns: &mut TurnState, keep_place: bool| {
            match turns.waiting.get_mut(&ticket) {
                Some(w) if keep_place => {
                    w.asking = false;
                    w.left_at = Instant::now();
                }
                _ => {
                    turns.waiting.remove(&ticket);
                }
            }
            // The next in line may be able to go now.
            self.changed.notify_all();
        };
        loop {
            if finished() {
                leave(&mut turns, false);
                return Err(RunFinished);
            }
            let now = Instant::now();
            turns
                .waiting
                .retain(|_, w| w.asking || now.duration_since(w.left_at) < PLACE_KEPT);
            let before = turns.holders.len();
            let lease = self.lease;
            turns
                .holders
                .retain(|_, held| now.duration_since(held.granted_at) < lease);
            turns.expired += (before - turns.holders.len()) as u64;
            let in_flight = turns.holders.len() as u64 + untrained();
            let first = turns
                .waiting
                .iter()
                .find(|(_, w)| w.asking)
                .map(|(&t, _)| t);
            if first == Some(ticket) && in_flight < limit {
                let episode = (received() + turns.holders.len() as u64).max(turns.next_episode);
                turns.next_episode = episode + 1;
                turns.holders.insert(
                    actor_id.to_string(),
                    Held {
                        incarnation,
                        granted_at: now,
                        episode,
                    },
                );
                turns.granted += 1;
                leave(&mut turns, false);
                return Ok(Grant::Episode(episode));
            }
            if now >= deadline {
                leave(&mut turns, true);
                return Ok(Grant::NotYet);
            }
            // Publications and episode summaries wake waiters; the slice bounds how late an
            // expired lease is noticed.
            let slice = (deadline - now).min(Duration::from_millis(100));
            self.changed.wait_for(&mut turns, slice);
        }
    }

    /// Turns in status. Locks: the turns' mutex.
    pub(crate) fn status(&self) -> TurnStatus {
        let turns = self.state.lock();
        TurnStatus {
            limit: self.limit,
            held: turns.holders.len() as u64,
            waiting: turns.waiting.values().filter(|w| w.asking).count() as u64,
            granted: turns.granted,
            expired: turns.expired,
        }
    }
}
