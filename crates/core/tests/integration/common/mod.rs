//! Small environments and scripted collaborators for rollout tests.
#![allow(dead_code)] // each test binary uses its own part of this module

use std::collections::VecDeque;

use hac_core::{AgentConfig, Bounds, Env, EnvSpec, Exploration, Mode, Policy, Rng};

/// A point on a line or in a box: `x += action`, clipped to `[-extent, extent]^d`.
/// The state, end goal and subgoal spaces are all the position itself.
#[derive(Debug, Clone)]
pub struct PointEnv {
    pub spec: EnvSpec,
    pub x: Vec<f32>,
    pub extent: f32,
    pub start: Option<Vec<f32>>,
    /// The episode terminates once the first coordinate reaches this value.
    pub terminate_at: Option<f32>,
    /// The end goal of every episode (drawn at random when `None`).
    pub end_goal: Option<Vec<f32>>,
}

impl PointEnv {
    pub fn new(dim: usize, max_step: f32, extent: f32, threshold: f32, max_actions: usize) -> Self {
        let spec = EnvSpec {
            name: "point".into(),
            description: "a point moved by bounded displacements".into(),
            state_dim: dim,
            action_bounds: Bounds::symmetric(&vec![max_step; dim]),
            end_goal_dim: dim,
            end_goal_thresholds: vec![threshold; dim],
            subgoal_bounds: Bounds::symmetric(&vec![extent; dim]),
            subgoal_thresholds: vec![threshold; dim],
            end_goal_angles: Vec::new(),
            subgoal_angles: Vec::new(),
            subgoal_wrapped: Vec::new(),
            state_bounds: Bounds::default(),
            end_goal_bounds: Bounds::default(),
            achieved_subgoal_bounds: Bounds::default(),
            max_actions,
            physics_steps_per_action: 1,
        };
        Self {
            spec,
            x: vec![0.0; dim],
            extent,
            start: None,
            terminate_at: None,
            end_goal: None,
        }
    }
}

impl Env for PointEnv {
    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn set_max_actions(&mut self, max_actions: usize) {
        self.spec.max_actions = max_actions;
    }

    fn set_subgoal_bounds(&mut self, bounds: Bounds) {
        self.spec.subgoal_bounds = bounds;
    }

    fn default_config(&self, levels: usize) -> AgentConfig {
        agent_config(levels, 5)
    }

    fn reset(&mut self, rng: &mut Rng) {
        match &self.start {
            Some(s) => self.x.copy_from_slice(s),
            None => {
                let half = self.extent / 2.0;
                for x in &mut self.x {
                    *x = rng.uniform(-half, half);
                }
            }
        }
    }

    fn state(&self) -> &[f32] {
        &self.x
    }

    fn step(&mut self, action: &[f32]) {
        for (x, a) in self.x.iter_mut().zip(action) {
            *x = (*x + a).clamp(-self.extent, self.extent);
        }
    }

    fn terminated(&self) -> bool {
        self.terminate_at.is_some_and(|t| self.x[0] >= t)
    }

    fn project_end_goal(&self, state: &[f32], out: &mut [f32]) {
        out.copy_from_slice(state);
    }

    fn project_subgoal(&self, state: &[f32], out: &mut [f32]) {
        out.copy_from_slice(state);
        self.spec.subgoal_bounds.clip(out);
    }

    fn sample_end_goal(&self, rng: &mut Rng, _mode: Mode, out: &mut [f32]) {
        if let Some(goal) = &self.end_goal {
            out.copy_from_slice(goal);
            return;
        }
        let half = self.extent / 2.0;
        for g in out {
            *g = rng.uniform(-half, half);
        }
    }
}

pub fn agent_config(levels: usize, horizon: usize) -> AgentConfig {
    AgentConfig::reference(levels, horizon)
}

/// A policy that replays scripted outputs per level (cycling through each level's list).
#[derive(Debug, Default)]
pub struct ScriptedPolicy {
    pub outputs: Vec<VecDeque<Vec<f32>>>,
}

impl Policy for ScriptedPolicy {
    fn act(&mut self, level: usize, _state: &[f32], _goal: &[f32], action: &mut [f32]) {
        let q = &mut self.outputs[level];
        let next = q.pop_front().expect("scripted policy ran out of outputs");
        action.copy_from_slice(&next);
        q.push_back(next);
    }
}

/// Exploration whose every decision is scripted.
#[derive(Debug, Default)]
pub struct ScriptedExploration {
    /// Added to the greedy output of each level.
    pub perturbation: Vec<Vec<f32>>,
    /// Test decisions of each level, in order.
    pub tests: Vec<VecDeque<bool>>,
    /// Random hindsight-goal indices, in order of request.
    pub replay_indices: VecDeque<usize>,
}

impl Exploration for ScriptedExploration {
    fn explore(&mut self, level: usize, _state: &[f32], _bounds: &Bounds, action: &mut [f32]) {
        for (a, p) in action.iter_mut().zip(&self.perturbation[level]) {
            *a += p;
        }
    }

    fn test_subgoal(&mut self, level: usize) -> bool {
        self.tests[level]
            .pop_front()
            .expect("unscripted subgoal test")
    }

    fn replay_goal_index(&mut self, _level: usize, n: usize) -> usize {
        let i = self
            .replay_indices
            .pop_front()
            .expect("unscripted replay goal index");
        assert!(
            i < n,
            "scripted replay index {i} out of range for {n} attempts"
        );
        i
    }
}

/// A policy that outputs uniform random values in a box wider than the bounds (so clipping is
/// exercised), per level.
#[derive(Debug)]
pub struct RandomPolicy {
    pub rng: Rng,
    pub bounds: Vec<Bounds>,
}

impl Policy for RandomPolicy {
    fn act(&mut self, level: usize, _state: &[f32], _goal: &[f32], action: &mut [f32]) {
        let b = &self.bounds[level];
        for (d, a) in action.iter_mut().enumerate() {
            let (lo, hi) = (b.low[d], b.high[d]);
            let pad = 0.2 * (hi - lo);
            *a = self.rng.uniform(lo - pad, hi + pad);
        }
    }
}
