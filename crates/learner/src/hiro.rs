//! What a HIRO level's trainer does to a sampled minibatch before its TD3 update
//! (docs/ALGORITHM.md, "HIRO").
//!
//! - Level 0 learns on `(s, g, a, r, s', g')` where `g' = p(s) + g - p(s')` (the goal
//!   transition). The actor stores no `g'`: it follows from the transition, so it is computed
//!   here with the environment's projection `p`, and a batch cannot smuggle in a `g'` of its
//!   own.
//! - Level 1's stored goals (its actions) are corrected when sampled: each becomes the candidate
//!   under which the current low-level policy most likely took the stored low-level actions.
//!   "Current" is the level-0 actor of the latest snapshot that covered more episodes than the
//!   one before (not of weights published in between, at moments timing decides): with one
//!   lockstep actor, the policy of the episode just played, so a seed gives the same run.

use hac_core::hiro::{LowLevelSteps, StepsShape, goal_radius, goal_transition};
use hac_core::{Batch, Env, EnvSpec, Rng};
use hac_nn::{ActorNet, BatchedCorrection};
use hac_proto::{Published, WeightsSnapshot};

/// The preparation of one HIRO level's minibatches.
pub(crate) enum HiroPrep {
    Low(LowPrep),
    High(Box<HighPrep>),
}

pub(crate) struct LowPrep {
    /// For its projection `p` only.
    env: Box<dyn Env>,
    angles: Vec<bool>,
    achieved: Vec<f32>,
    next_achieved: Vec<f32>,
    next_goals: Vec<f32>,
}

pub(crate) struct HighPrep {
    shape: StepsShape,
    correction: BatchedCorrection,
    /// The low level's actor and the weights version it is from.
    low: Option<(u64, ActorNet)>,
}

impl HiroPrep {
    /// Level `level`'s preparation; `env` is a fresh instance of the run's environment, `c` and
    /// `candidates` HIRO's settings.
    pub(crate) fn new(level: usize, env: Box<dyn Env>, c: usize, candidates: usize) -> Self {
        let spec: EnvSpec = env.spec().clone();
        let g = spec.subgoal_dim();
        if level == 0 {
            Self::Low(LowPrep {
                env,
                angles: spec.relative_goal_angles(),
                achieved: vec![0.0; g],
                next_achieved: vec![0.0; g],
                next_goals: Vec::new(),
            })
        } else {
            Self::High(Box::new(HighPrep {
                shape: StepsShape::of(&spec, c),
                correction: BatchedCorrection::new(
                    candidates,
                    goal_radius(&spec),
                    spec.relative_goal_angles(),
                ),
                low: None,
            }))
        }
    }

    /// Prepares `batch` in place; returns the next goals level 0's update bootstraps from
    /// (`None` at level 1, whose goal is the end goal, unchanged).
    pub(crate) fn prepare(
        &mut self,
        batch: &mut Batch,
        weights: &Published<WeightsSnapshot>,
        rng: &mut Rng,
    ) -> Option<&[f32]> {
        match self {
            Self::Low(low) => Some(low.next_goals(batch)),
            Self::High(high) => {
                high.correct(batch, weights, rng);
                None
            }
        }
    }
}

impl LowPrep {
    fn next_goals(&mut self, batch: &Batch) -> &[f32] {
        let (sd, gd) = (batch.dims.state, batch.dims.goal);
        self.next_goals.resize(batch.len * gd, 0.0);
        for j in 0..batch.len {
            let state = &batch.states[j * sd..(j + 1) * sd];
            let next_state = &batch.next_states[j * sd..(j + 1) * sd];
            self.env.project_subgoal(state, &mut self.achieved);
            self.env
                .project_subgoal(next_state, &mut self.next_achieved);
            goal_transition(
                &self.achieved,
                &batch.goals[j * gd..(j + 1) * gd],
                &self.next_achieved,
                &self.angles,
                &mut self.next_goals[j * gd..(j + 1) * gd],
            );
        }
        &self.next_goals
    }
}

impl HighPrep {
    fn correct(&mut self, batch: &mut Batch, weights: &Published<WeightsSnapshot>, rng: &mut Rng) {
        let Some(snapshot) = weights.latest() else {
            return;
        };
        if self
            .low
            .as_ref()
            .is_none_or(|(v, _)| *v != snapshot.version)
        {
            // The learner published these weights itself: they decode.
            let actor = ActorNet::from_safetensors(&snapshot.levels[0])
                .expect("the learner's own level-0 weights decode");
            self.low = Some((snapshot.version, actor));
        }
        let (_, actor) = self.low.as_ref().expect("set above");
        let (width, shape) = (batch.extra_width, self.shape);
        // Ingest checked every stored transition's steps (`TransitionLimits::for_hiro_level`).
        let steps = batch.extra.chunks_exact(width).map(|packed| {
            LowLevelSteps::unpack(packed, shape).expect("stored steps were checked at ingest")
        });
        self.correction
            .relabel(actor, &mut batch.actions, steps, rng);
    }
}
