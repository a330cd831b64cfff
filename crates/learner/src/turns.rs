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
    /// Actor id -> (incarnation, when granted).
    holders: HashMap<String, (u64, Instant)>,
    /// Places in line by ticket, served lowest first among the actors asking now. A place
    /// outlives the call that took it by [`PLACE_KEPT`], so that an actor asking again after
    /// its call timed out keeps its place instead of going to the back.
    waiting: BTreeMap<u64, Waiter>,
    next_ticket: u64,
    granted: u64,
    expired: u64,
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
            .is_some_and(|&(held, _)| held == incarnation)
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

    /// Waits up to `wait` (at most [`MAX_TURN_WAIT`]) for `actor_id`'s turn; `Ok(true)`:
    /// granted (or already held by this incarnation), `Ok(false)`: not yet, the place in line
    /// is kept for [`PLACE_KEPT`]. `untrained()` is the number of episodes received and not
    /// yet trained on and published, `finished()` whether the run is over; both are read under
    /// the turns' mutex and may only read atomics. Granted at once when turns are off.
    ///
    /// Locks: the turns' mutex, released while waiting on the condition variable. The caller
    /// must hold no lock.
    pub(crate) fn wait(
        &self,
        actor_id: &str,
        incarnation: u64,
        wait: Duration,
        untrained: impl Fn() -> u64,
        finished: impl Fn() -> bool,
    ) -> Result<bool, RunFinished> {
        let limit = u64::from(self.limit);
        if limit == 0 {
            return Ok(true);
        }
        let deadline = Instant::now() + wait.min(MAX_TURN_WAIT);
        let mut turns = self.state.lock();
        if turns
            .holders
            .get(actor_id)
            .is_some_and(|&(held, _)| held == incarnation)
        {
            return Ok(true);
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
                .retain(|_, &mut (_, at)| now.duration_since(at) < lease);
            turns.expired += (before - turns.holders.len()) as u64;
            let in_flight = turns.holders.len() as u64 + untrained();
            let first = turns
                .waiting
                .iter()
                .find(|(_, w)| w.asking)
                .map(|(&t, _)| t);
            if first == Some(ticket) && in_flight < limit {
                turns
                    .holders
                    .insert(actor_id.to_string(), (incarnation, now));
                turns.granted += 1;
                leave(&mut turns, false);
                return Ok(true);
            }
            if now >= deadline {
                leave(&mut turns, true);
                return Ok(false);
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
