//! Continuous mountain car, the task the PyTorch ports of HAC use, with the port's settings as its
//! default hyperparameters so that runs compare side by side.
//!
//! Dynamics (one update per primitive action, in f64 like the Python original):
//!
//! ```text
//! force = clip(a, -1, 1)
//! v = clip(v + 0.0015 force - 0.0025 cos(3 x), -0.07, 0.07)
//! x = clip(x + v, -1.2, 0.6);   if x == -1.2 and v < 0 then v = 0   (an inelastic left wall)
//! ```
//!
//! The episode ends once x >= 0.45. State, end goal and subgoal are all `[x, v]`.

use hac_core::{AgentConfig, Bounds, Env, EnvSpec, Mode, Noise, Rng};

use crate::{StateError, check_physical_state};

const MIN_X: f64 = -1.2;
const MAX_X: f64 = 0.6;
const MAX_SPEED: f64 = 0.07;
const GOAL_X: f64 = 0.45;
const END_GOAL: [f32; 2] = [0.48, 0.04];
const MAX_ACTIONS: usize = 1000;

/// The coefficients of the velocity update a test may want to change.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MountainCarPhysics {
    /// Velocity gained per unit of force per step (0 disconnects the engine).
    pub power: f64,
    /// Scale of the hill's pull, `gravity * cos(3 x)` per step.
    pub gravity: f64,
}

impl Default for MountainCarPhysics {
    fn default() -> Self {
        Self {
            power: 0.0015,
            gravity: 0.0025,
        }
    }
}

/// The continuous mountain car. Until the first `reset` it rests at the valley's start, x = -0.5.
#[derive(Debug, Clone)]
pub struct MountainCar {
    spec: EnvSpec,
    physics: MountainCarPhysics,
    x: f64,
    v: f64,
    /// `[x, v]` as f32, refreshed after every change.
    observation: [f32; 2],
}

impl Default for MountainCar {
    fn default() -> Self {
        Self::new()
    }
}

impl MountainCar {
    /// Registry name.
    pub const NAME: &'static str = "mountain-car";

    /// The task with the standard physics.
    pub fn new() -> Self {
        Self::with_physics(MountainCarPhysics::default())
    }

    /// The task with overridden coefficients (the spec and defaults are unchanged).
    pub fn with_physics(physics: MountainCarPhysics) -> Self {
        let mut env = Self {
            spec: spec(),
            physics,
            x: -0.5,
            v: 0.0,
            observation: [0.0; 2],
        };
        env.observe();
        env
    }

    pub fn physics(&self) -> &MountainCarPhysics {
        &self.physics
    }

    /// `[x, v]` at full precision.
    pub fn physical_state(&self) -> [f64; 2] {
        [self.x, self.v]
    }

    fn observe(&mut self) {
        self.observation = [self.x as f32, self.v as f32];
    }
}

fn spec() -> EnvSpec {
    let thresholds = vec![0.01, 0.02];
    let everywhere = Bounds::new(
        vec![MIN_X as f32, -MAX_SPEED as f32],
        vec![MAX_X as f32, MAX_SPEED as f32],
    );
    EnvSpec {
        name: MountainCar::NAME.to_string(),
        description: "continuous mountain car: rock out of the valley to the flag at x = 0.45 \
                      (PyTorch HAC port's task and settings)"
            .to_string(),
        state_dim: 2,
        action_bounds: Bounds::symmetric(&[1.0]),
        end_goal_dim: 2,
        end_goal_thresholds: thresholds.clone(),
        subgoal_bounds: everywhere.clone(),
        subgoal_thresholds: thresholds,
        end_goal_angles: Vec::new(),
        subgoal_angles: Vec::new(),
        subgoal_wrapped: Vec::new(),
        // The dynamics clip position and speed to these: states, goals and projections alike.
        state_bounds: everywhere.clone(),
        end_goal_bounds: everywhere.clone(),
        achieved_subgoal_bounds: everywhere,
        max_actions: MAX_ACTIONS,
        physics_steps_per_action: 1,
    }
}

impl Env for MountainCar {
    /// Puts the car at `[x, v]`, which must lie within x in [-1.2, 0.6], v in [-0.07, 0.07].
    fn set_physical_state(&mut self, state: &[f64]) -> Result<(), StateError> {
        let ranges = [(MIN_X, MAX_X), (-MAX_SPEED, MAX_SPEED)];
        check_physical_state(Self::NAME, state, &ranges)?;
        self.x = state[0];
        self.v = state[1];
        self.observe();
        Ok(())
    }

    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn set_max_actions(&mut self, max_actions: usize) {
        self.spec.max_actions = max_actions;
    }

    fn set_subgoal_bounds(&mut self, bounds: Bounds) {
        self.spec.subgoal_bounds = bounds;
    }

    /// The PyTorch port's preset (docs/ENVIRONMENTS.md; the port's `train.py`, `HAC.py`,
    /// `utils.py` and README) at every level count; where it says nothing, the values are ours and
    /// say so.
    fn default_config(&self, levels: usize) -> AgentConfig {
        AgentConfig {
            levels,
            // Port: H = 20 with 2 levels (train.py) and H = 5 with 3 levels (README's results);
            // we keep 5 deeper down. A flat agent gets the whole budget (the run's
            // `max_actions` if it sets one) as its horizon.
            horizon: match levels {
                0 | 1 => self.spec.max_actions,
                2 => 20,
                _ => 5,
            },
            subgoal_test_prob: 0.3,
            // Port: a uniform random action 20% of the time at every level.
            random_action_prob: 0.2,
            // Port: absolute standard deviations.
            action_noise: Noise::Absolute(vec![0.1]),
            subgoal_noise: Noise::Absolute(vec![0.02, 0.01]),
            // Port: a single hindsight goal, the last state reached, relabels every transition.
            num_replay_goals: 1,
            gamma: 0.95,
            // Port: 2 hidden layers of 64 (README).
            hidden_layers: vec![64, 64],
            actor_lr: 1e-3,
            critic_lr: 1e-3,
            // Port: 100 updates of batch 100 after every episode.
            batch_size: 100,
            updates_per_episode: 100,
            // Port: no target networks (README).
            target_tau: None,
            actor_preactivation_l2: 0.0,
            exact_critic_slope: false,
            // Port: PyTorch's float `tanh`, which rounds to +-1 where libm's does (about 9.01),
            // not from TensorFlow's 7.9074 (the HAC paper's code).
            saturating_tanh: false,
            clip_hindsight_actions: false,
            // Ours: 500 episodes keep level 0 of a 2-level agent under the port's per-level
            // buffer of 5e5 transitions, which is the cap.
            episodes_to_store: 500,
            replay_capacity_max: 500_000,
            // Ours: the port trains without test rounds (it saves every 10 episodes); a test
            // round every 10 episodes gives a comparable curve.
            exploration_episodes: 10,
            test_episodes: 100,
        }
    }

    /// x uniform in [-0.6, -0.4], at rest.
    fn reset(&mut self, rng: &mut Rng) {
        self.x = f64::from(rng.uniform(-0.6, -0.4));
        self.v = 0.0;
        self.observe();
    }

    fn state(&self) -> &[f32] {
        &self.observation
    }

    fn step(&mut self, action: &[f32]) {
        let force = f64::from(action[0].clamp(-1.0, 1.0));
        let p = &self.physics;
        self.v = (self.v + force * p.power - p.gravity * (3.0 * self.x).cos())
            .clamp(-MAX_SPEED, MAX_SPEED);
        self.x = (self.x + self.v).clamp(MIN_X, MAX_X);
        if self.x == MIN_X && self.v < 0.0 {
            self.v = 0.0;
        }
        self.observe();
    }

    fn terminated(&self) -> bool {
        self.x >= GOAL_X
    }

    fn project_end_goal(&self, state: &[f32], out: &mut [f32]) {
        self.project_subgoal(state, out);
    }

    /// The state itself, clipped into the subgoal bounds in case f32 rounding leaves them.
    fn project_subgoal(&self, state: &[f32], out: &mut [f32]) {
        out.copy_from_slice(state);
        self.spec.subgoal_bounds.clip(out);
    }

    /// The flag at full speed, [0.48, 0.04], in training and in tests alike.
    fn sample_end_goal(&self, _rng: &mut Rng, _mode: Mode, out: &mut [f32]) {
        out.copy_from_slice(&END_GOAL);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(x: f64, v: f64) -> MountainCar {
        let mut env = MountainCar::new();
        env.set_physical_state(&[x, v]).unwrap();
        env
    }

    #[test]
    fn spec_matches_envs_md() {
        let env = MountainCar::new();
        let s = env.spec();
        assert_eq!(s.state_dim, 2);
        assert_eq!(s.action_bounds, Bounds::new(vec![-1.0], vec![1.0]));
        assert_eq!(
            s.subgoal_bounds,
            Bounds::new(vec![-1.2, -0.07], vec![0.6, 0.07])
        );
        assert_eq!(s.end_goal_thresholds, vec![0.01, 0.02]);
        assert_eq!(s.subgoal_thresholds, vec![0.01, 0.02]);
        assert_eq!(s.max_actions, 1000);
        assert_eq!(s.physics_steps_per_action, 1);
    }

    #[test]
    fn default_config_is_the_port_preset() {
        let env = MountainCar::new();
        let c = env.default_config(2);
        assert_eq!(c.horizon, 20);
        assert_eq!(c.gamma, 0.95);
        assert_eq!((c.batch_size, c.updates_per_episode), (100, 100));
        assert_eq!(c.action_noise, Noise::Absolute(vec![0.1]));
        assert_eq!(c.subgoal_noise, Noise::Absolute(vec![0.02, 0.01]));
        assert_eq!(c.hidden_layers, vec![64, 64]);
        assert_eq!(env.default_config(1).horizon, 1000);
        assert_eq!(env.default_config(3).horizon, 5);
        assert!(c.replay_capacity(0) <= 500_000);
    }

    /// Three updates from x = -0.5 at rest, against values worked out by hand (in f64):
    /// v1 = 0.0015 - 0.0025 cos(-1.5) = 0.0013231569958307428, x1 = -0.5 + v1, and so on; the
    /// third action (2.0) is clipped to 1. Actions are exact in f32, so nothing is lost on the way.
    #[test]
    fn update_matches_hand_computation() {
        let mut env = at(-0.5, 0.0);
        let expected = [
            (-0.49867684300416926, 0.0013231569958307428),
            (-0.4979154264118068, 0.0007614165923624283),
            (-0.49584644440167047, 0.0020689820101363397),
        ];
        for (a, (x, v)) in [1.0, -0.25, 2.0].into_iter().zip(expected) {
            env.step(&[a]);
            let [ex, ev] = env.physical_state();
            assert!(
                (ex - x).abs() < 1e-15 && (ev - v).abs() < 1e-15,
                "{ex} {ev}"
            );
            assert_eq!(env.state(), [x as f32, v as f32]);
        }
    }

    #[test]
    fn speed_is_clipped() {
        // Near full speed on the downhill side, pushing: v would exceed 0.07.
        let mut env = at(-0.5, 0.0699);
        env.step(&[1.0]);
        assert_eq!(env.physical_state()[1], MAX_SPEED);
        let mut env = at(0.0, -0.0699);
        env.step(&[-1.0]);
        assert_eq!(env.physical_state()[1], -MAX_SPEED);
    }

    #[test]
    fn left_wall_stops_the_car() {
        let mut env = at(-1.19, -0.05);
        env.step(&[-1.0]);
        assert_eq!(env.physical_state(), [MIN_X, 0.0]);
        // Leaving the wall is allowed: the hill pushes right from there.
        env.step(&[0.0]);
        let [x, v] = env.physical_state();
        assert!(v > 0.0 && x > MIN_X, "{x} {v}");
    }

    #[test]
    fn right_edge_clips_position_only() {
        let mut env = at(0.59, 0.05);
        env.step(&[1.0]);
        let [x, v] = env.physical_state();
        assert_eq!(x, MAX_X);
        assert!(v > 0.0);
    }

    #[test]
    fn terminates_at_the_flag() {
        assert!(!at(0.449, 0.0).terminated());
        assert!(at(0.45, 0.0).terminated());
        assert!(at(0.45, -0.01).terminated());
        let mut env = at(0.44, 0.02);
        assert!(!env.terminated());
        env.step(&[1.0]);
        assert!(env.terminated());
        assert!(!MountainCar::new().terminated());
    }

    /// Pushing in the direction of motion pumps energy in: the classic bang-bang solution.
    #[test]
    fn bang_bang_reaches_the_flag() {
        let mut env = MountainCar::new();
        let mut rng = Rng::seed_from(0);
        for _ in 0..20 {
            env.reset(&mut rng);
            let steps = (1..=1000).find(|_| {
                let push = if env.physical_state()[1] < 0.0 {
                    -1.0
                } else {
                    1.0
                };
                env.step(&[push]);
                env.terminated()
            });
            assert!(steps.is_some(), "did not reach x >= 0.45");
        }
    }

    #[test]
    fn engine_off_ignores_the_action() {
        let mut env = MountainCar::with_physics(MountainCarPhysics {
            power: 0.0,
            ..MountainCarPhysics::default()
        });
        env.set_physical_state(&[-0.5, 0.0]).unwrap();
        let mut reference = at(-0.5, 0.0);
        env.step(&[1.0]);
        reference.step(&[0.0]);
        assert_eq!(env.physical_state(), reference.physical_state());
    }

    #[test]
    fn reset_distribution_and_determinism() {
        let mut env = MountainCar::new();
        let mut rng = Rng::seed_from(9);
        for _ in 0..1000 {
            env.reset(&mut rng);
            let [x, v] = env.physical_state();
            assert!((-0.6..=-0.4).contains(&x) && v == 0.0, "{x} {v}");
        }
        let run = |seed| {
            let mut env = MountainCar::new();
            let mut rng = Rng::seed_from(seed);
            env.reset(&mut rng);
            (0..300)
                .map(|_| {
                    env.step(&[rng.uniform(-1.0, 1.0)]);
                    env.physical_state().map(f64::to_bits)
                })
                .collect::<Vec<_>>()
        };
        assert_eq!(run(4), run(4));
        assert_ne!(run(4), run(5));
    }

    #[test]
    fn projections_and_goals() {
        let mut env = MountainCar::new();
        let bounds = env.spec().subgoal_bounds.clone();
        let mut rng = Rng::seed_from(2);
        let mut out = [0.0f32; 2];
        env.reset(&mut rng);
        for _ in 0..2000 {
            env.step(&[rng.uniform(-1.0, 1.0)]);
            env.project_subgoal(env.state(), &mut out);
            assert_eq!(out, env.state());
            assert!(bounds.contains(&out));
            env.project_end_goal(env.state(), &mut out);
            assert_eq!(out, env.state());
        }
        env.project_subgoal(&[0.7, -0.1], &mut out);
        assert_eq!(out, [0.6, -0.07]);
        for mode in [Mode::Train, Mode::Test] {
            env.sample_end_goal(&mut rng, mode, &mut out);
            assert_eq!(out, [0.48, 0.04]);
        }
    }

    #[test]
    fn set_physical_state_rejects_bad_input() {
        let mut env = MountainCar::new();
        assert!(matches!(
            env.set_physical_state(&[0.0]),
            Err(StateError::WrongLength {
                expected: 2,
                got: 1,
                ..
            })
        ));
        assert!(env.set_physical_state(&[-1.3, 0.0]).is_err());
        assert!(env.set_physical_state(&[0.0, 0.08]).is_err());
        assert!(env.set_physical_state(&[f64::NAN, 0.0]).is_err());
        env.set_physical_state(&[-1.2, 0.07]).unwrap();
        assert_eq!(env.physical_state(), [MIN_X, MAX_SPEED]);
    }
}
