//! HIRO's off-policy correction ([`hac_core::hiro::OffPolicyCorrection`]) for a whole minibatch
//! of high-level transitions, with the low-level policy evaluated in batched forward passes
//! instead of one [`ActorNet::act`] per candidate and step.
//!
//! For each transition the candidates are the ones [`OffPolicyCorrection::candidates`] lists,
//! drawn from the random stream in the order that calling
//! [`OffPolicyCorrection::relabel`] on the transitions one after another would draw them; the
//! chosen candidate maximises the same score, `-1/2 sum_i ||a_i - mu(s_i, g~_i)||^2` with
//! `g~_i = goal_transition(p(s_0), candidate, p(s_i))`, summed over the steps in the same
//! order, with ties to the earlier candidate. Only the policy's outputs can differ from
//! `relabel`'s with [`ActorNet::act`], by the rounding of another matrix-product path, so the
//! choice can differ only where two candidates' scores nearly tie.

use hac_core::Rng;
use hac_core::hiro::{LowLevelSteps, OffPolicyCorrection, goal_transition};

use crate::{ActorNet, MlpWorkspace};

/// The most policy inputs one forward pass evaluates: the columns (one per candidate and step)
/// are evaluated in blocks of this many, so that a block's activations stay in cache and the
/// workspace stays small however large the minibatch.
pub const FORWARD_COLUMNS: usize = 1024;

/// HIRO's off-policy correction of a minibatch of high-level transitions in batched forward
/// passes of the low-level actor. Owns every buffer it needs: after the first call at a given
/// size (transitions, candidates, steps), a call allocates nothing.
#[derive(Debug, Clone)]
pub struct BatchedCorrection {
    /// Lists each transition's candidates (and holds the random candidate count).
    correction: OffPolicyCorrection,
    /// Half range of the relative goals' box per goal dimension.
    half_range: Vec<f32>,
    /// Goal dimensions that are angles (radians), compared along the circle; empty: none.
    angles: Vec<bool>,
    /// Every transition's candidates, transition after transition (`candidates x goal_dim`
    /// values each).
    candidates: Vec<f32>,
    /// Per transition: its number `k` of low-level steps.
    step_counts: Vec<usize>,
    /// The policy's input for every (transition, candidate, step), in that nesting order: a
    /// column-major `(state_dim + goal_dim) x columns` matrix, each column `[s_i; g~_i]`.
    inputs: Vec<f32>,
    /// The actions taken at every step, transition after transition (`action_dim` each).
    taken: Vec<f32>,
    /// The policy's actions `mu(s_i, g~_i)` at every column (`action_dim x columns`).
    actions: Vec<f32>,
    /// The forward pass's buffers, for the actor of the last call.
    ws: Option<MlpWorkspace>,
    /// Per transition of the last call: the index of the chosen candidate (0: the stored goal).
    chosen: Vec<usize>,
}

impl BatchedCorrection {
    /// A correction drawing `random` Gaussian candidates per transition beside the stored goal
    /// and the achieved displacement (HIRO: 8), for relative goals in the box
    /// `[-half_range, half_range]` (one half range per goal dimension, in the goal's units),
    /// with the dimensions flagged in `angles` (radians; empty: none) compared along the circle.
    ///
    /// Panics if `angles` is neither empty nor one flag per goal dimension.
    pub fn new(random: usize, half_range: Vec<f32>, angles: Vec<bool>) -> Self {
        assert!(
            angles.is_empty() || angles.len() == half_range.len(),
            "batched correction: {} angle flags for {} goal dimensions",
            angles.len(),
            half_range.len()
        );
        Self {
            correction: OffPolicyCorrection::new(random),
            half_range,
            angles,
            candidates: Vec::new(),
            step_counts: Vec::new(),
            inputs: Vec::new(),
            taken: Vec::new(),
            actions: Vec::new(),
            ws: None,
            chosen: Vec::new(),
        }
    }

    /// Candidates per transition: the stored goal, the achieved displacement and the random
    /// ones.
    pub fn candidates_per_transition(&self) -> usize {
        2 + self.correction.random()
    }

    /// The goal width (the relative goals' dimensions).
    pub fn goal_dim(&self) -> usize {
        self.half_range.len()
    }

    /// Per transition of the last [`relabel`](Self::relabel), the index of the chosen candidate
    /// in [`OffPolicyCorrection::candidates`]' order (0: the stored goal kept).
    pub fn chosen(&self) -> &[usize] {
        &self.chosen
    }

    /// Corrects the goals of `n` high-level transitions: `goals` holds their stored relative
    /// goals (`n x goal_dim`, one transition after another) and receives the chosen ones;
    /// `steps` yields each transition's low-level steps, in the same order (each may have its
    /// own count `k >= 1`). `actor` is the current low-level policy `mu`, whose state, goal and
    /// action widths the steps must have. Random candidates are drawn from `rng` transition
    /// after transition, as [`OffPolicyCorrection::relabel`] called on each in turn would.
    /// Returns how many goals were changed (a candidate other than the stored goal chosen);
    /// [`chosen`](Self::chosen) has the indices.
    ///
    /// Panics if `goals` is not a whole number of goals, `steps` yields another number of
    /// transitions than `goals` holds, a transition has no step or steps of other widths than
    /// the actor's, or the actor's goal width is not [`goal_dim`](Self::goal_dim).
    pub fn relabel<'a>(
        &mut self,
        actor: &ActorNet,
        goals: &mut [f32],
        steps: impl IntoIterator<Item = LowLevelSteps<'a>>,
        rng: &mut Rng,
    ) -> usize {
        let dims = actor.dims();
        let dim = self.goal_dim();
        assert_eq!(
            dims.goal, dim,
            "batched correction: the actor's goal width differs from the goal box's"
        );
        assert!(
            dim > 0 && goals.len().is_multiple_of(dim),
            "batched correction: {} goal values are not a whole number of {dim}-wide goals",
            goals.len()
        );
        let n = goals.len() / dim;
        let per = self.candidates_per_transition();
        let rows = dims.state + dim;
        self.candidates.clear();
        self.step_counts.clear();
        self.inputs.clear();
        self.taken.clear();
        let mut count = 0;
        for (t, s) in steps.into_iter().enumerate() {
            assert!(
                t < n,
                "batched correction: more transitions' steps than goals ({n})"
            );
            let k = (s.achieved.len() / dim).saturating_sub(1);
            assert!(
                k > 0
                    && s.achieved.len() == (k + 1) * dim
                    && s.states.len() == k * dims.state
                    && s.actions.len() == k * dims.action,
                "batched correction: transition {t}'s steps have {} state, {} projection and {} \
                 action values, not k states of {}, k + 1 projections of {dim} and k actions of \
                 {} for some k >= 1",
                s.states.len(),
                s.achieved.len(),
                s.actions.len(),
                dims.state,
                dims.action
            );
            let stored = &goals[t * dim..(t + 1) * dim];
            let first = &s.achieved[..dim];
            let last = &s.achieved[k * dim..];
            let candidates = self.correction.candidates(
                stored,
                first,
                last,
                &self.half_range,
                &self.angles,
                rng,
            );
            debug_assert_eq!(candidates.len(), per * dim);
            self.candidates.extend_from_slice(candidates);
            self.step_counts.push(k);
            self.taken.extend_from_slice(s.actions);
            let start = self.inputs.len();
            self.inputs.resize(start + per * k * rows, 0.0);
            let columns = self.inputs[start..].chunks_exact_mut(rows);
            let candidates = &self.candidates[t * per * dim..(t + 1) * per * dim];
            let column_sources = candidates
                .chunks_exact(dim)
                .flat_map(|c| (0..k).map(move |i| (c, i)));
            for (column, (candidate, i)) in columns.zip(column_sources) {
                let (state, goal) = column.split_at_mut(dims.state);
                state.copy_from_slice(&s.states[i * dims.state..(i + 1) * dims.state]);
                let achieved = &s.achieved[i * dim..(i + 1) * dim];
                goal_transition(first, candidate, achieved, &self.angles, goal);
            }
            count = t + 1;
        }
        assert_eq!(
            count, n,
            "batched correction: steps of {count} transitions for {n} goals"
        );
        self.evaluate(actor);
        self.choose(dims.action, dim, goals)
    }

    /// Sets `self.actions` to the actor's actions at every column of `self.inputs`, a block of
    /// at most [`FORWARD_COLUMNS`] columns per forward pass.
    fn evaluate(&mut self, actor: &ActorNet) {
        let dims = actor.dims();
        let rows = dims.state + dims.goal;
        let columns = self.inputs.len() / rows;
        self.actions.resize(columns * dims.action, 0.0);
        if columns == 0 {
            return;
        }
        let ws = match &mut self.ws {
            Some(ws) if ws.is_for(actor.mlp()) => ws,
            slot => slot.insert(MlpWorkspace::new(actor.mlp(), 0)),
        };
        for (input, actions) in self
            .inputs
            .chunks(FORWARD_COLUMNS * rows)
            .zip(self.actions.chunks_mut(FORWARD_COLUMNS * dims.action))
        {
            ws.set_batch(input.len() / rows);
            ws.input_mut().copy_from_slice(input);
            actor.forward_batch(ws);
            actor.write_actions(ws, actions, dims.action, 0);
        }
    }

    /// Scores every candidate from `self.actions`, writes each transition's best into `goals`
    /// and its index into `self.chosen`; returns how many are not the stored goal.
    fn choose(&mut self, action_dim: usize, dim: usize, goals: &mut [f32]) -> usize {
        let per = self.candidates_per_transition();
        self.chosen.clear();
        let (mut column, mut step) = (0, 0);
        for (t, &k) in self.step_counts.iter().enumerate() {
            let taken = &self.taken[step * action_dim..(step + k) * action_dim];
            let (mut best, mut best_log_likelihood) = (0, f32::NEG_INFINITY);
            for candidate in 0..per {
                let actions = &self.actions[column * action_dim..(column + k) * action_dim];
                let mut log_likelihood = 0.0f32;
                for (a, t) in actions
                    .chunks_exact(action_dim)
                    .zip(taken.chunks_exact(action_dim))
                {
                    log_likelihood -=
                        0.5 * a.iter().zip(t).map(|(a, t)| (a - t) * (a - t)).sum::<f32>();
                }
                if log_likelihood > best_log_likelihood {
                    (best, best_log_likelihood) = (candidate, log_likelihood);
                }
                column += k;
            }
            let from = (t * per + best) * dim;
            goals[t * dim..(t + 1) * dim].copy_from_slice(&self.candidates[from..from + dim]);
            self.chosen.push(best);
            step += k;
        }
        self.chosen.iter().filter(|&&i| i != 0).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::uniform_vec;
    use hac_core::{Bounds, LevelDims};

    /// A low-level actor whose actions depend strongly on the goal: random weights of magnitude
    /// up to `scale`, so that tanh is far from linear.
    fn actor(dims: LevelDims, hidden: &[usize], scale: f32, rng: &mut Rng) -> ActorNet {
        let bounds = Bounds::symmetric(&vec![2.0; dims.action]);
        let mut actor = ActorNet::new(dims, &bounds, hidden, rng);
        for t in actor.mlp_mut().tensors_mut() {
            t.copy_from_slice(&uniform_vec(rng, t.len(), scale));
        }
        actor
    }

    /// One transition's steps, owned: states, projections `p(s_0) .. p(s_k)`, actions.
    struct Owned {
        states: Vec<f32>,
        achieved: Vec<f32>,
        actions: Vec<f32>,
    }

    impl Owned {
        fn steps(&self) -> LowLevelSteps<'_> {
            LowLevelSteps {
                states: &self.states,
                achieved: &self.achieved,
                actions: &self.actions,
            }
        }
    }

    /// `-1/2 sum_i ||a_i - mu(s_i, g~_i)||^2` of `candidate`, with [`ActorNet::act`].
    fn score(actor: &mut ActorNet, s: &Owned, candidate: &[f32], angles: &[bool]) -> f32 {
        let d = actor.dims();
        let k = s.states.len() / d.state;
        let (mut goal, mut action) = (vec![0.0; d.goal], vec![0.0; d.action]);
        let mut log_likelihood = 0.0f32;
        for i in 0..k {
            let achieved = &s.achieved[i * d.goal..(i + 1) * d.goal];
            goal_transition(
                &s.achieved[..d.goal],
                candidate,
                achieved,
                angles,
                &mut goal,
            );
            actor.act(
                &s.states[i * d.state..(i + 1) * d.state],
                &goal,
                &mut action,
            );
            let taken = &s.actions[i * d.action..(i + 1) * d.action];
            log_likelihood -= 0.5
                * action
                    .iter()
                    .zip(taken)
                    .map(|(a, t)| (a - t) * (a - t))
                    .sum::<f32>();
        }
        log_likelihood
    }

    #[test]
    fn batched_choices_equal_per_sample_relabel_but_for_near_ties() {
        let dims = LevelDims {
            state: 3,
            goal: 2,
            action: 2,
        };
        let (half_range, angles) = (vec![1.0, 0.5], vec![true, false]);
        let mut rng = Rng::seed_from(21);
        let mut mu = actor(dims, &[16, 16], 0.8, &mut rng);
        let mut near_ties = 0;
        let mut batched = BatchedCorrection::new(8, half_range.clone(), angles.clone());
        // Two rounds: the second reuses the buffers at other step counts; more than
        // FORWARD_COLUMNS columns in all, so the forward pass runs in blocks.
        for (round, n) in [(0, 40), (1, 25)] {
            let transitions: Vec<Owned> = (0..n)
                .map(|_| {
                    let k = 1 + (rng.unit() * 10.0) as usize % 10;
                    Owned {
                        states: uniform_vec(&mut rng, k * dims.state, 1.5),
                        achieved: uniform_vec(&mut rng, (k + 1) * dims.goal, 1.0),
                        actions: uniform_vec(&mut rng, k * dims.action, 2.0),
                    }
                })
                .collect();
            let stored = uniform_vec(&mut rng, n * dims.goal, 0.5);

            let mut batched_rng = rng.clone();
            let mut goals = stored.clone();
            let changed = batched.relabel(
                &mu,
                &mut goals,
                transitions.iter().map(Owned::steps),
                &mut batched_rng,
            );
            assert_eq!(batched.chosen().len(), n);
            if round == 0 {
                let columns: usize = transitions.iter().map(|t| 10 * t.actions.len() / 2).sum();
                assert!(columns > FORWARD_COLUMNS, "{columns} columns");
            }

            let mut single = OffPolicyCorrection::new(8);
            let mut policy_actor = mu.clone();
            let mut policy = |s: &[f32], g: &[f32], a: &mut [f32]| policy_actor.act(s, g, a);
            let mut per_sample_changed = 0;
            for (t, tr) in transitions.iter().enumerate() {
                let stored = &stored[t * 2..(t + 1) * 2];
                let candidates = single
                    .candidates(
                        stored,
                        &tr.achieved[..2],
                        &tr.achieved[tr.achieved.len() - 2..],
                        &half_range,
                        &angles,
                        &mut rng.clone(),
                    )
                    .to_vec();
                let mut out = [0.0; 2];
                let index = single.relabel(
                    stored,
                    tr.steps(),
                    &half_range,
                    &angles,
                    &mut rng,
                    &mut policy,
                    &mut out,
                );
                per_sample_changed += usize::from(index != 0);
                let got = batched.chosen()[t];
                let candidate = |i: usize| &candidates[i * 2..(i + 1) * 2];
                assert_eq!(&goals[t * 2..(t + 1) * 2], candidate(got), "transition {t}");
                if got != index {
                    let (a, b) = (
                        score(&mut mu, tr, candidate(got), &angles),
                        score(&mut mu, tr, candidate(index), &angles),
                    );
                    assert!(
                        (a - b).abs() <= 1e-4 * a.abs().max(b.abs()),
                        "transition {t}: batched chose {got} ({a}), per sample {index} ({b})"
                    );
                    near_ties += 1;
                }
            }
            if near_ties == 0 {
                assert_eq!(changed, per_sample_changed);
            }
            assert!(changed > 0, "{changed} of {n} changed");
            // Both drew the same random numbers.
            assert_eq!(batched_rng.unit(), rng.unit());
        }
        assert!(near_ties <= 2, "{near_ties} near ties");
    }

    /// Transitions whose actions the actor took for a known relative goal: `p(s) = s`, the
    /// states moving along a random line; the actions are `mu(s_i, g~_i)` for the known goal.
    fn explained(
        mu: &mut ActorNet,
        n: usize,
        true_goal: impl Fn(&[f32], &[f32]) -> Vec<f32>,
        rng: &mut Rng,
    ) -> (Vec<Owned>, Vec<f32>) {
        let d = mu.dims();
        let mut goals = Vec::new();
        let transitions = (0..n)
            .map(|j| {
                let k = 3 + j % 8;
                let start = uniform_vec(rng, d.state, 1.0);
                let velocity = uniform_vec(rng, d.state, 0.08);
                let achieved: Vec<f32> = (0..=k)
                    .flat_map(|i| {
                        start
                            .iter()
                            .zip(&velocity)
                            .map(move |(s, v)| s + v * i as f32)
                    })
                    .collect();
                let goal = true_goal(&achieved[..d.goal], &achieved[k * d.goal..]);
                let mut actions = vec![0.0; k * d.action];
                let mut g = vec![0.0; d.goal];
                for i in 0..k {
                    let here = &achieved[i * d.goal..(i + 1) * d.goal];
                    goal_transition(&achieved[..d.goal], &goal, here, &[], &mut g);
                    mu.act(here, &g, &mut actions[i * d.action..(i + 1) * d.action]);
                }
                goals.extend_from_slice(&goal);
                Owned {
                    states: achieved[..k * d.state].to_vec(),
                    achieved,
                    actions,
                }
            })
            .collect();
        (transitions, goals)
    }

    #[test]
    fn picks_the_candidate_that_explains_the_actions() {
        let dims = LevelDims {
            state: 2,
            goal: 2,
            action: 1,
        };
        let mut rng = Rng::seed_from(22);
        let mut mu = actor(dims, &[32, 32], 0.8, &mut rng);
        let mut correction = BatchedCorrection::new(8, vec![1.0, 1.0], Vec::new());
        let n = 30;

        // The low level was given the displacement it achieved; the stored goals are stale.
        let displacement = |first: &[f32], last: &[f32]| -> Vec<f32> {
            first.iter().zip(last).map(|(f, l)| l - f).collect()
        };
        let (transitions, truth) = explained(&mut mu, n, displacement, &mut rng);
        let mut goals = uniform_vec(&mut rng, n * 2, 1.0);
        let changed = correction.relabel(
            &mu,
            &mut goals,
            transitions.iter().map(Owned::steps),
            &mut rng,
        );
        assert_eq!(changed, n);
        assert!(
            correction.chosen().iter().all(|&i| i == 1),
            "{:?}",
            correction.chosen()
        );
        assert_eq!(goals, truth);

        // The low level was given a goal elsewhere in the box, and it is the one stored: kept.
        let elsewhere = |_: &[f32], _: &[f32]| -> Vec<f32> { vec![-0.7, 0.6] };
        let (transitions, truth) = explained(&mut mu, n, elsewhere, &mut rng);
        let mut goals = truth.clone();
        let changed = correction.relabel(
            &mu,
            &mut goals,
            transitions.iter().map(Owned::steps),
            &mut rng,
        );
        assert_eq!((changed, goals), (0, truth));
    }

    #[test]
    #[should_panic(expected = "steps of 2 transitions for 3 goals")]
    fn fewer_steps_than_goals_are_refused() {
        let dims = LevelDims {
            state: 2,
            goal: 2,
            action: 1,
        };
        let mut rng = Rng::seed_from(23);
        let mu = actor(dims, &[8], 0.5, &mut rng);
        let step = Owned {
            states: vec![0.0; 2],
            achieved: vec![0.0; 4],
            actions: vec![0.0],
        };
        let mut goals = vec![0.0; 6];
        BatchedCorrection::new(8, vec![1.0, 1.0], Vec::new()).relabel(
            &mu,
            &mut goals,
            [step.steps(), step.steps()],
            &mut rng,
        );
    }
}
