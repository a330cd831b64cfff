//! [`ReplayTable`]: one level's replay, split into shards that writers fill in parallel.

use std::fmt;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

use hac_core::{Batch, BatchRef, LevelDims, Rng, Transition, TransitionKind};
use parking_lot::Mutex;

use crate::ring::Ring;

mod snapshot;

pub use snapshot::SnapshotError;

/// A transition whose field does not have the table's dimension.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("transition {field} has {actual} values, expected {expected}")]
pub struct DimensionMismatch {
    /// `state`, `action`, `next_state` or `goal`.
    pub field: &'static str,
    pub expected: usize,
    pub actual: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum SampleError {
    #[error("cannot sample from an empty replay table")]
    Empty,
}

/// Keeps what it wraps on its own cache lines, so that writers working on neighbouring shards (or
/// the round-robin counter) do not invalidate each other's lines. 128 bytes because x86 prefetches
/// lines in pairs and recent ARM cores use 128-byte lines.
#[derive(Default)]
#[repr(align(128))]
struct CacheLine<T>(T);

struct Shard {
    ring: Mutex<Ring>,
    capacity: usize,
    /// Transitions ever written to this shard; bumped while the ring's lock is held, so it never
    /// runs ahead of the ring. Readable without the lock, which keeps `len` and the sampler's
    /// fill snapshot off the writers' locks.
    inserted: AtomicU64,
}

impl Shard {
    fn len(&self) -> usize {
        // The minimum fits in usize because the capacity does.
        self.inserted
            .load(Ordering::Relaxed)
            .min(self.capacity as u64) as usize
    }
}

/// Working memory of [`ReplayTable::sample`], kept between calls so that sampling does not
/// allocate (`rows` grows to the largest per-shard draw once, then is reused).
struct SampleScratch {
    /// Cumulative shard fills: shard `s` holds the global rows `ends[s - 1] .. ends[s]`.
    ends: Vec<usize>,
    /// How many samples of the current batch come from each shard.
    counts: Vec<usize>,
    /// The rows drawn from the shard being copied.
    rows: Vec<usize>,
}

/// One level's replay: `S` shards, each a FIFO ring buffer of transitions in structure-of-arrays
/// `f32` layout, with the capacity split across them (the first `capacity % S` shards take one
/// row more).
///
/// Replay is FIFO as in the reference implementation. The reference drops its oldest sixth in one
/// go when it fills up; each ring here instead overwrites its single oldest row, which keeps the
/// buffer full rather than letting it fall back to five sixths.
///
/// Every method takes `&self`: each shard sits behind its own lock, so writers on different shards
/// proceed in parallel, and a sampler holds one shard's lock at a time.
pub struct ReplayTable {
    dims: LevelDims,
    /// Extra values per transition ([`Transition::extra`]).
    extra_width: usize,
    capacity: usize,
    shards: Box<[CacheLine<Shard>]>,
    round_robin: CacheLine<AtomicUsize>,
    scratch: Mutex<SampleScratch>,
}

impl ReplayTable {
    /// An empty table for transitions of `dims`, holding at most `capacity` transitions in
    /// `shards` shards.
    ///
    /// # Panics
    /// If `shards` is zero or exceeds `capacity` (every shard must hold at least one row).
    pub fn new(dims: LevelDims, capacity: usize, shards: usize) -> Self {
        Self::with_extra(dims, 0, capacity, shards)
    }

    /// [`new`](Self::new) for a level whose transitions carry `extra_width` extra values each
    /// (HIRO's high level: its low-level steps).
    pub fn with_extra(dims: LevelDims, extra_width: usize, capacity: usize, shards: usize) -> Self {
        assert!(shards > 0, "a replay table needs at least one shard");
        assert!(
            capacity >= shards,
            "replay capacity {capacity} is smaller than the shard count {shards}"
        );
        let shards: Box<[_]> = (0..shards)
            .map(|s| {
                let capacity = capacity / shards + usize::from(s < capacity % shards);
                CacheLine(Shard {
                    ring: Mutex::new(Ring::new(dims, extra_width, capacity)),
                    capacity,
                    inserted: AtomicU64::new(0),
                })
            })
            .collect();
        let scratch = SampleScratch {
            ends: vec![0; shards.len()],
            counts: vec![0; shards.len()],
            rows: Vec::new(),
        };
        Self {
            dims,
            extra_width,
            capacity,
            shards,
            round_robin: CacheLine::default(),
            scratch: Mutex::new(scratch),
        }
    }

    pub fn dims(&self) -> LevelDims {
        self.dims
    }

    /// Extra values per transition (0 for HAC's levels).
    pub fn extra_width(&self) -> usize {
        self.extra_width
    }

    /// Transitions currently stored (never more than [`capacity`](Self::capacity)).
    pub fn len(&self) -> usize {
        self.shards.iter().map(|s| s.0.len()).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn shard_count(&self) -> usize {
        self.shards.len()
    }

    /// Transitions currently stored in each shard.
    pub fn shard_lens(&self) -> impl ExactSizeIterator<Item = usize> + '_ {
        self.shards.iter().map(|s| s.0.len())
    }

    /// Transitions ever inserted, including those since overwritten.
    pub fn inserted_total(&self) -> u64 {
        self.shards
            .iter()
            .map(|s| s.0.inserted.load(Ordering::Relaxed))
            .sum()
    }

    /// Checks that every field of `t` has this table's dimension.
    pub fn check(&self, t: &Transition<'_>) -> Result<(), DimensionMismatch> {
        let LevelDims {
            state,
            action,
            goal,
        } = self.dims;
        for (field, expected, actual) in [
            ("state", state, t.state.len()),
            ("action", action, t.action.len()),
            ("next_state", state, t.next_state.len()),
            ("goal", goal, t.goal.len()),
            ("extra", self.extra_width, t.extra.len()),
        ] {
            if actual != expected {
                return Err(DimensionMismatch {
                    field,
                    expected,
                    actual,
                });
            }
        }
        Ok(())
    }

    /// Stores `t` in the next shard in round-robin order. The shared counter is the only state
    /// all writers touch; writers that must not share anything route themselves with
    /// [`insert_into`](Self::insert_into).
    ///
    /// The dimensions must match (a mismatch is a bug in the caller, caught by a debug assertion);
    /// input from outside the process goes through [`try_insert`](Self::try_insert).
    pub fn insert(&self, t: &Transition<'_>) {
        let shard = self.round_robin.0.fetch_add(1, Ordering::Relaxed) % self.shards.len();
        self.insert_into(shard, t);
    }

    /// Stores `t` in shard `shard`, overwriting that shard's oldest transition if it is full.
    ///
    /// # Panics
    /// If `shard >= self.shard_count()`.
    pub fn insert_into(&self, shard: usize, t: &Transition<'_>) {
        debug_assert_eq!(
            self.check(t),
            Ok(()),
            "transition does not fit the replay table"
        );
        let shard = &self.shards[shard].0;
        let mut ring = shard.ring.lock();
        ring.push(t);
        shard.inserted.fetch_add(1, Ordering::Relaxed);
    }

    /// Stores every transition of `batch` in shard `shard`, taking the shard's lock once. The
    /// batch must have this table's dimensions (checked by a debug assertion; ingest validates
    /// batches before they get here). It is read in place: a batch in shared memory is copied
    /// only into the ring.
    ///
    /// # Panics
    /// If `shard >= self.shard_count()`.
    pub fn insert_batch_into(&self, shard: usize, batch: BatchRef<'_>) {
        let LevelDims {
            state,
            action,
            goal,
        } = self.dims;
        debug_assert!(
            batch.states.len() == batch.len * state
                && batch.actions.len() == batch.len * action
                && batch.rewards.len() == batch.len
                && batch.next_states.len() == batch.len * state
                && batch.goals.len() == batch.len * goal
                && batch.terminals.len() == batch.len
                && batch.extra.len() == batch.len * self.extra_width,
            "batch does not fit the replay table"
        );
        let e = self.extra_width;
        let shard = &self.shards[shard].0;
        let mut ring = shard.ring.lock();
        for j in 0..batch.len {
            ring.push(&Transition {
                kind: TransitionKind::HindsightAction,
                state: &batch.states[j * state..(j + 1) * state],
                action: &batch.actions[j * action..(j + 1) * action],
                reward: batch.rewards[j],
                next_state: &batch.next_states[j * state..(j + 1) * state],
                goal: &batch.goals[j * goal..(j + 1) * goal],
                terminal: batch.terminals[j] != 0.0,
                extra: &batch.extra[j * e..(j + 1) * e],
            });
        }
        shard
            .inserted
            .fetch_add(batch.len as u64, Ordering::Relaxed);
    }

    /// [`insert`](Self::insert) for untrusted input: rejects a transition whose dimensions do not
    /// match, naming the field.
    pub fn try_insert(&self, t: &Transition<'_>) -> Result<(), DimensionMismatch> {
        self.check(t)?;
        self.insert(t);
        Ok(())
    }

    /// Fills all `batch.len` samples of `batch` with transitions drawn uniformly at random, with
    /// replacement, from everything stored, so each shard contributes in proportion to its fill.
    ///
    /// Two stages keep each shard's lock taken once per call: first the number of samples per
    /// shard (a multinomial draw over the fills), then that many uniform rows from each shard in
    /// turn, copied field by field. Samples therefore come grouped by shard; the losses average
    /// over the batch, so the order does not matter. Under concurrent inserts the split follows
    /// the fills at the start of the call. Deterministic for the same contents and `rng` state;
    /// allocates nothing once the first batch of this size has been drawn.
    ///
    /// `batch` must have this table's dimensions (checked by a debug assertion).
    pub fn sample(&self, rng: &mut Rng, batch: &mut Batch) -> Result<(), SampleError> {
        debug_assert_eq!(
            batch.dims, self.dims,
            "batch dimensions differ from the table's"
        );
        debug_assert_eq!(batch.states.len(), batch.len * self.dims.state);
        debug_assert_eq!(batch.actions.len(), batch.len * self.dims.action);
        debug_assert_eq!(batch.goals.len(), batch.len * self.dims.goal);
        debug_assert_eq!(batch.extra.len(), batch.len * self.extra_width);

        let mut scratch = self.scratch.lock();
        let SampleScratch { ends, counts, rows } = &mut *scratch;
        let mut total = 0;
        for (end, shard) in ends.iter_mut().zip(self.shards.iter()) {
            total += shard.0.len();
            *end = total;
        }
        if total == 0 {
            return Err(SampleError::Empty);
        }

        counts.fill(0);
        for _ in 0..batch.len {
            let row = rng.below(total);
            counts[ends.partition_point(|&end| end <= row)] += 1;
        }

        let mut j = 0;
        for (shard, &count) in self.shards.iter().zip(counts.iter()) {
            if count == 0 {
                continue;
            }
            let ring = shard.0.ring.lock();
            // Non-zero: the shard's fill was positive at the snapshot and rings never shrink.
            let len = ring.len();
            rows.clear();
            rows.extend((0..count).map(|_| rng.below(len)));
            ring.copy_rows(rows, batch, j);
            j += count;
        }
        Ok(())
    }
}

/// Shape and fill only; the rows themselves are far too many to print.
impl fmt::Debug for ReplayTable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ReplayTable")
            .field("dims", &self.dims)
            .field("extra_width", &self.extra_width)
            .field("capacity", &self.capacity)
            .field("shard_lens", &self.shard_lens().collect::<Vec<_>>())
            .field("inserted_total", &self.inserted_total())
            .finish()
    }
}

#[cfg(test)]
impl ReplayTable {
    /// Shard `shard`'s rows, oldest first, as one-sample batches.
    pub(crate) fn rows_oldest_first(&self, shard: usize) -> Vec<Batch> {
        self.shards[shard].0.ring.lock().rows_oldest_first()
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashSet;

    use hac_core::{Rng, TransitionKind};
    use proptest::prelude::*;

    use super::*;

    const DIMS: LevelDims = LevelDims {
        state: 3,
        goal: 2,
        action: 1,
    };

    /// The fields of transition `id`: every value encodes the id, so a row mixing fields of two
    /// transitions is caught. Ids stay far below 2^20, where these values are exact in f32.
    struct Fields {
        state: [f32; 3],
        action: [f32; 1],
        reward: f32,
        next_state: [f32; 3],
        goal: [f32; 2],
        terminal: bool,
    }

    fn fields(id: u32) -> Fields {
        let x = id as f32;
        Fields {
            state: [x, x + 0.25, x + 0.5],
            action: [-x],
            reward: -x - 0.5,
            next_state: [x + 1.0, x + 1.25, x + 1.5],
            goal: [2.0 * x, 2.0 * x + 0.5],
            terminal: id.is_multiple_of(3),
        }
    }

    fn transition(f: &Fields) -> Transition<'_> {
        Transition {
            kind: TransitionKind::HindsightAction,
            state: &f.state,
            action: &f.action,
            reward: f.reward,
            next_state: &f.next_state,
            goal: &f.goal,
            terminal: f.terminal,
            extra: &[],
        }
    }

    /// The id of sample `j` of `batch`, after checking that all its fields belong to that id.
    fn id_of(batch: &Batch, j: usize) -> u32 {
        let id = batch.states[j * 3] as u32;
        let f = fields(id);
        assert_eq!(&batch.states[j * 3..j * 3 + 3], &f.state, "sample {j}");
        assert_eq!(&batch.actions[j..j + 1], &f.action, "sample {j}");
        assert_eq!(batch.rewards[j], f.reward, "sample {j}");
        assert_eq!(
            &batch.next_states[j * 3..j * 3 + 3],
            &f.next_state,
            "sample {j}"
        );
        assert_eq!(&batch.goals[j * 2..j * 2 + 2], &f.goal, "sample {j}");
        assert_eq!(
            batch.terminals[j],
            f32::from(u8::from(f.terminal)),
            "sample {j}"
        );
        id
    }

    fn ids_oldest_first(table: &ReplayTable, shard: usize) -> Vec<u32> {
        table
            .rows_oldest_first(shard)
            .iter()
            .map(|row| id_of(row, 0))
            .collect()
    }

    fn filled(capacity: usize, shards: usize, ids: impl IntoIterator<Item = u32>) -> ReplayTable {
        let table = ReplayTable::new(DIMS, capacity, shards);
        for id in ids {
            table.insert(&transition(&fields(id)));
        }
        table
    }

    #[test]
    fn full_ring_overwrites_oldest_first() {
        let table = filled(4, 1, 0..6);
        assert_eq!(ids_oldest_first(&table, 0), [2, 3, 4, 5]);
        assert_eq!(table.len(), 4);
        assert_eq!(table.inserted_total(), 6);

        table.insert(&transition(&fields(6)));
        assert_eq!(ids_oldest_first(&table, 0), [3, 4, 5, 6]);
    }

    #[test]
    fn batch_insert_stores_rows_in_order_and_wraps() {
        let table = ReplayTable::new(DIMS, 4, 2);
        let mut batch = Batch::zeros(DIMS, 3);
        for (j, id) in (10..13).enumerate() {
            let f = fields(id);
            batch.states[j * 3..j * 3 + 3].copy_from_slice(&f.state);
            batch.actions[j] = f.action[0];
            batch.rewards[j] = f.reward;
            batch.next_states[j * 3..j * 3 + 3].copy_from_slice(&f.next_state);
            batch.goals[j * 2..j * 2 + 2].copy_from_slice(&f.goal);
            batch.terminals[j] = f32::from(u8::from(f.terminal));
        }
        // Shard 1 holds 2 rows: the batch's first row is overwritten by its third.
        table.insert_batch_into(1, batch.view());
        assert_eq!(ids_oldest_first(&table, 1), [11, 12]);
        assert_eq!(table.shard_lens().collect::<Vec<_>>(), [0, 2]);
        assert_eq!(table.inserted_total(), 3);
    }

    #[test]
    fn capacity_splits_across_shards_and_each_shard_is_fifo() {
        // Capacity 5 over 2 shards: 3 + 2. Round robin sends even ids to shard 0, odd to shard 1.
        let table = filled(5, 2, 0..10);
        assert_eq!(table.capacity(), 5);
        assert_eq!(table.shard_lens().collect::<Vec<_>>(), [3, 2]);
        assert_eq!(ids_oldest_first(&table, 0), [4, 6, 8]);
        assert_eq!(ids_oldest_first(&table, 1), [7, 9]);
        assert_eq!(table.len(), 5);
        assert_eq!(table.inserted_total(), 10);
    }

    #[test]
    fn insert_into_routes_to_the_named_shard() {
        let table = ReplayTable::new(DIMS, 8, 4);
        table.insert_into(2, &transition(&fields(7)));
        assert_eq!(table.shard_lens().collect::<Vec<_>>(), [0, 0, 1, 0]);
        assert_eq!(ids_oldest_first(&table, 2), [7]);
    }

    #[test]
    fn try_insert_names_the_wrong_field() {
        let table = ReplayTable::new(DIMS, 8, 2);
        let f = fields(1);
        let long_goal = [0.0; 3];
        let t = Transition {
            goal: &long_goal,
            ..transition(&f)
        };
        let err = table.try_insert(&t).unwrap_err();
        assert_eq!(
            err,
            DimensionMismatch {
                field: "goal",
                expected: 2,
                actual: 3
            }
        );
        assert_eq!(err.to_string(), "transition goal has 3 values, expected 2");
        assert!(table.is_empty());

        table.try_insert(&transition(&f)).unwrap();
        assert_eq!(table.len(), 1);
    }

    #[test]
    fn sampling_an_empty_table_fails() {
        let table = ReplayTable::new(DIMS, 8, 2);
        let mut batch = Batch::zeros(DIMS, 4);
        let err = table.sample(&mut Rng::seed_from(0), &mut batch);
        assert_eq!(err, Err(SampleError::Empty));
    }

    #[test]
    fn samples_are_whole_stored_rows() {
        // 30 inserts into capacity 12: only ids 18..30 are still stored.
        let table = filled(12, 3, 0..30);
        let mut batch = Batch::zeros(DIMS, 500);
        let mut rng = Rng::seed_from(5);
        let mut seen = HashSet::new();
        for _ in 0..4 {
            table.sample(&mut rng, &mut batch).unwrap();
            for j in 0..batch.len {
                let id = id_of(&batch, j);
                assert!((18..30).contains(&id), "sampled overwritten id {id}");
                seen.insert(id);
            }
        }
        assert_eq!(seen.len(), 12, "every stored row shows up in 2000 draws");
    }

    #[test]
    fn sampling_is_deterministic() {
        let table = filled(100, 4, 0..77);
        let (mut a, mut b) = (Batch::zeros(DIMS, 64), Batch::zeros(DIMS, 64));
        table.sample(&mut Rng::seed_from(9), &mut a).unwrap();
        filled(100, 4, 0..77)
            .sample(&mut Rng::seed_from(9), &mut b)
            .unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn shards_are_sampled_in_proportion_to_their_fill() {
        // Shard s holds ids s * 1000 .. s * 1000 + fill[s].
        let fill: [usize; 4] = [100, 300, 600, 0];
        let table = ReplayTable::new(DIMS, 4000, 4);
        for (s, &n) in fill.iter().enumerate() {
            for k in 0..n {
                table.insert_into(s, &transition(&fields((s * 1000 + k) as u32)));
            }
        }

        let mut batch = Batch::zeros(DIMS, 1000);
        let mut rng = Rng::seed_from(2024);
        let mut per_shard = [0usize; 4];
        let mut per_row = vec![0usize; 4000];
        let rounds = 300;
        for _ in 0..rounds {
            table.sample(&mut rng, &mut batch).unwrap();
            for j in 0..batch.len {
                let id = id_of(&batch, j) as usize;
                per_shard[id / 1000] += 1;
                per_row[id] += 1;
            }
        }

        let draws = (rounds * batch.len) as f64;
        for (s, &n) in fill.iter().enumerate() {
            let share = per_shard[s] as f64 / draws;
            let expected = n as f64 / 1000.0;
            assert!(
                (share - expected).abs() < 0.02,
                "shard {s}: share {share}, fill {expected}"
            );
        }
        // Uniform over rows too: 300 expected draws each, a standard deviation of about 17.
        for (s, &n) in fill.iter().enumerate() {
            let rows = &per_row[s * 1000..s * 1000 + n];
            for (k, &draws) in rows.iter().enumerate() {
                assert!(
                    (150..450).contains(&draws),
                    "row {}: {draws} draws",
                    s * 1000 + k
                );
            }
        }
    }

    #[test]
    fn sampling_while_writers_overwrite_sees_only_whole_rows() {
        let table = filled(1000, 3, 0..1000);
        std::thread::scope(|scope| {
            for w in 1..3 {
                let table = &table;
                scope.spawn(move || {
                    for k in 0..20_000 {
                        table.insert_into(w, &transition(&fields(w as u32 * 100_000 + k)));
                    }
                });
            }
            let mut batch = Batch::zeros(DIMS, 256);
            let mut rng = Rng::seed_from(4);
            for _ in 0..200 {
                table.sample(&mut rng, &mut batch).unwrap();
                for j in 0..batch.len {
                    id_of(&batch, j);
                }
            }
        });
        assert_eq!(table.len(), 1000);
        assert_eq!(table.inserted_total(), 41_000);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Concurrent writers, some round robin and some routing themselves: with room for
        /// everything, every transition is stored exactly once and the shard fills add up.
        #[test]
        fn concurrent_inserts_store_everything_once(
            shards in 1usize..6,
            writers in prop::collection::vec((0u32..300, any::<bool>()), 1..5),
            slack in 0usize..10,
        ) {
            let total: usize = writers.iter().map(|&(n, _)| n as usize).sum();
            // Self-routed writers fill shards unevenly, so every shard gets room for everything.
            let table = ReplayTable::new(DIMS, shards * (total + slack + 1), shards);
            std::thread::scope(|scope| {
                for (w, &(n, routed)) in writers.iter().enumerate() {
                    let table = &table;
                    scope.spawn(move || {
                        for k in 0..n {
                            let t = fields(w as u32 * 1000 + k);
                            if routed {
                                table.insert_into((w + k as usize) % shards, &transition(&t));
                            } else {
                                table.insert(&transition(&t));
                            }
                        }
                    });
                }
            });

            prop_assert_eq!(table.len(), total);
            prop_assert_eq!(table.inserted_total(), total as u64);
            prop_assert_eq!(table.shard_lens().sum::<usize>(), total);
            let mut stored: Vec<u32> =
                (0..shards).flat_map(|s| ids_oldest_first(&table, s)).collect();
            stored.sort_unstable();
            let mut expected: Vec<u32> = writers
                .iter()
                .enumerate()
                .flat_map(|(w, &(n, _))| (0..n).map(move |k| w as u32 * 1000 + k))
                .collect();
            expected.sort_unstable();
            prop_assert_eq!(stored, expected);
        }
    }
}
