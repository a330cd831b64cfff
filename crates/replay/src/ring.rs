//! One shard's storage: a fixed-capacity FIFO ring of transitions in structure-of-arrays layout.

use hac_core::{Batch, LevelDims, Transition};

/// Row `i` occupies `states[i * dims.state .. (i + 1) * dims.state]` (and likewise for the other
/// fields), the same layout as [`Batch`], so sampling copies contiguous slices.
pub(crate) struct Ring {
    dims: LevelDims,
    /// Extra values per row ([`Transition::extra`]), 0 for HAC's levels.
    extra_width: usize,
    capacity: usize,
    len: usize,
    /// The row the next push writes; once the ring is full this is also the oldest row.
    next: usize,
    states: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    next_states: Vec<f32>,
    goals: Vec<f32>,
    terminals: Vec<f32>,
    extra: Vec<f32>,
}

impl Ring {
    /// Reserves the whole capacity up front so that pushes never reallocate (a multi-gigabyte copy
    /// in the middle of ingest); the OS commits the pages only as rows are written.
    pub(crate) fn new(dims: LevelDims, extra_width: usize, capacity: usize) -> Self {
        Self {
            dims,
            extra_width,
            capacity,
            len: 0,
            next: 0,
            states: Vec::with_capacity(dims.state * capacity),
            actions: Vec::with_capacity(dims.action * capacity),
            rewards: Vec::with_capacity(capacity),
            next_states: Vec::with_capacity(dims.state * capacity),
            goals: Vec::with_capacity(dims.goal * capacity),
            terminals: Vec::with_capacity(capacity),
            extra: Vec::with_capacity(extra_width * capacity),
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// The row the next push writes.
    pub(crate) fn next(&self) -> usize {
        self.next
    }

    /// Moves the write position of a full ring (restoring a snapshot).
    pub(crate) fn set_next(&mut self, next: usize) {
        assert!(
            next < self.capacity && (self.len == self.capacity || next == self.len),
            "ring write position {next} with {} of {} rows",
            self.len,
            self.capacity
        );
        self.next = next;
    }

    /// Appends `t`, overwriting the oldest row once the ring is full. The caller has checked the
    /// dimensions.
    pub(crate) fn push(&mut self, t: &Transition<'_>) {
        let terminal = if t.terminal { 1.0 } else { 0.0 };
        if self.len < self.capacity {
            self.states.extend_from_slice(t.state);
            self.actions.extend_from_slice(t.action);
            self.rewards.push(t.reward);
            self.next_states.extend_from_slice(t.next_state);
            self.goals.extend_from_slice(t.goal);
            self.terminals.push(terminal);
            self.extra.extend_from_slice(t.extra);
            self.len += 1;
        } else {
            let i = self.next;
            let LevelDims {
                state,
                action,
                goal,
            } = self.dims;
            self.states[i * state..(i + 1) * state].copy_from_slice(t.state);
            self.actions[i * action..(i + 1) * action].copy_from_slice(t.action);
            self.rewards[i] = t.reward;
            self.next_states[i * state..(i + 1) * state].copy_from_slice(t.next_state);
            self.goals[i * goal..(i + 1) * goal].copy_from_slice(t.goal);
            self.terminals[i] = terminal;
            let e = self.extra_width;
            self.extra[i * e..(i + 1) * e].copy_from_slice(t.extra);
        }
        self.next = (self.next + 1) % self.capacity;
    }

    /// Every field as `(name, values, width)`, in [`Batch`]'s order; `extra` last.
    pub(crate) fn fields(&self) -> [(&'static str, &[f32], usize); 7] {
        let LevelDims {
            state,
            action,
            goal,
        } = self.dims;
        [
            ("states", &self.states, state),
            ("actions", &self.actions, action),
            ("rewards", &self.rewards, 1),
            ("next_states", &self.next_states, state),
            ("goals", &self.goals, goal),
            ("terminals", &self.terminals, 1),
            ("extra", &self.extra, self.extra_width),
        ]
    }

    /// Copies rows `rows` into samples `first..first + rows.len()` of `batch`, one field at a
    /// time: each pass is a run of independent loads from one array, which the CPU overlaps.
    pub(crate) fn copy_rows(&self, rows: &[usize], batch: &mut Batch, first: usize) {
        let LevelDims {
            state,
            action,
            goal,
        } = self.dims;
        let end = first + rows.len();
        gather(
            &self.states,
            state,
            rows,
            &mut batch.states[first * state..end * state],
        );
        gather(
            &self.actions,
            action,
            rows,
            &mut batch.actions[first * action..end * action],
        );
        gather(&self.rewards, 1, rows, &mut batch.rewards[first..end]);
        gather(
            &self.next_states,
            state,
            rows,
            &mut batch.next_states[first * state..end * state],
        );
        gather(
            &self.goals,
            goal,
            rows,
            &mut batch.goals[first * goal..end * goal],
        );
        gather(&self.terminals, 1, rows, &mut batch.terminals[first..end]);
        let e = self.extra_width;
        if e > 0 {
            gather(&self.extra, e, rows, &mut batch.extra[first * e..end * e]);
        }
    }
}

#[cfg(test)]
impl Ring {
    /// The stored rows, oldest first, copied out as one-sample batches.
    pub(crate) fn rows_oldest_first(&self) -> Vec<Batch> {
        let start = if self.len < self.capacity {
            0
        } else {
            self.next
        };
        (0..self.len)
            .map(|k| {
                let mut row = Batch::zeros_with_extra(self.dims, self.extra_width, 1);
                self.copy_rows(&[(start + k) % self.capacity], &mut row, 0);
                row
            })
            .collect()
    }
}

/// Copies row `rows[k]` of the `dim`-wide field `src` into the `k`-th `dim`-wide slot of `dst`.
fn gather(src: &[f32], dim: usize, rows: &[usize], dst: &mut [f32]) {
    for (out, &row) in dst.chunks_exact_mut(dim).zip(rows) {
        out.copy_from_slice(&src[row * dim..(row + 1) * dim]);
    }
}
