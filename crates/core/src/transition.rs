//! Transitions as the rollout produces them, and batches as the learner consumes them.

use serde::{Deserialize, Serialize};

use crate::LevelDims;

/// Which of HAC's three rules produced a transition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TransitionKind {
    /// The action actually achieved (or the subgoal, if the level below reached it).
    HindsightAction,
    /// A copy of a hindsight action transition relabelled with an achieved goal (HER).
    HindsightGoal,
    /// A tested subgoal that the level below missed: reward -H, terminal.
    SubgoalPenalty,
}

/// One transition `[state, action, reward, next_state, goal, terminal]`, borrowed from the
/// rollout's buffers; `terminal` means the target does not bootstrap (discount 0). `extra` is
/// what an algorithm stores beside it at a fixed width per level: empty for every level of HAC;
/// HIRO's high level stores its low-level steps there ([`crate::hiro::LowLevelSteps::pack`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transition<'a> {
    pub kind: TransitionKind,
    pub state: &'a [f32],
    pub action: &'a [f32],
    pub reward: f32,
    pub next_state: &'a [f32],
    pub goal: &'a [f32],
    pub terminal: bool,
    pub extra: &'a [f32],
}

/// Receives every transition the rollout creates, tagged with the level it belongs to.
pub trait TransitionSink {
    fn push(&mut self, level: usize, transition: &Transition<'_>);
}

/// Discards everything (test episodes, benchmarks).
#[derive(Debug, Default, Clone, Copy)]
pub struct NullSink;

impl TransitionSink for NullSink {
    fn push(&mut self, _level: usize, _transition: &Transition<'_>) {}
}

/// An owned transition, for tests and tools that keep what they receive.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OwnedTransition {
    pub level: usize,
    pub kind: TransitionKind,
    pub state: Vec<f32>,
    pub action: Vec<f32>,
    pub reward: f32,
    pub next_state: Vec<f32>,
    pub goal: Vec<f32>,
    pub terminal: bool,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub extra: Vec<f32>,
}

/// Keeps every transition it receives, in order.
impl TransitionSink for Vec<OwnedTransition> {
    fn push(&mut self, level: usize, t: &Transition<'_>) {
        self.push(OwnedTransition {
            level,
            kind: t.kind,
            state: t.state.to_vec(),
            action: t.action.to_vec(),
            reward: t.reward,
            next_state: t.next_state.to_vec(),
            goal: t.goal.to_vec(),
            terminal: t.terminal,
            extra: t.extra.to_vec(),
        });
    }
}

/// A minibatch for one level in structure-of-arrays layout. Sample `j` occupies
/// `states[j * dims.state .. (j + 1) * dims.state]`, and so on: read as a column-major matrix,
/// each field is `dim x len` with one sample per column. `terminals` holds 1.0 or 0.0. `extra`
/// holds each sample's [`Transition::extra`], `extra_width` values each (0 for HAC's levels).
#[derive(Debug, Clone, PartialEq)]
pub struct Batch {
    pub dims: LevelDims,
    pub len: usize,
    pub states: Vec<f32>,
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    pub next_states: Vec<f32>,
    pub goals: Vec<f32>,
    pub terminals: Vec<f32>,
    pub extra_width: usize,
    pub extra: Vec<f32>,
}

impl Batch {
    /// A zero-filled batch of `len` samples, allocated once and refilled by samplers.
    pub fn zeros(dims: LevelDims, len: usize) -> Self {
        Self::zeros_with_extra(dims, 0, len)
    }

    /// [`zeros`](Self::zeros) for a level that stores `extra_width` extra values per sample.
    pub fn zeros_with_extra(dims: LevelDims, extra_width: usize, len: usize) -> Self {
        Self {
            dims,
            len,
            states: vec![0.0; dims.state * len],
            actions: vec![0.0; dims.action * len],
            rewards: vec![0.0; len],
            next_states: vec![0.0; dims.state * len],
            goals: vec![0.0; dims.goal * len],
            terminals: vec![0.0; len],
            extra_width,
            extra: vec![0.0; extra_width * len],
        }
    }

    /// The batch as borrowed slices.
    pub fn view(&self) -> BatchRef<'_> {
        BatchRef {
            len: self.len,
            states: &self.states,
            actions: &self.actions,
            rewards: &self.rewards,
            next_states: &self.next_states,
            goals: &self.goals,
            terminals: &self.terminals,
            extra: &self.extra,
        }
    }
}

/// A [`Batch`] borrowed from wherever it lives (a `Batch`, a shared-memory message): the same
/// structure-of-arrays layout, so that ingest reads transitions in place, without a copy. It
/// carries no dimensions: whoever reads it knows the level's (ingest checks the lengths against
/// them first).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BatchRef<'a> {
    pub len: usize,
    pub states: &'a [f32],
    pub actions: &'a [f32],
    pub rewards: &'a [f32],
    pub next_states: &'a [f32],
    pub goals: &'a [f32],
    pub terminals: &'a [f32],
    /// `len` samples' extra values, one after another (empty for HAC's levels).
    pub extra: &'a [f32],
}
