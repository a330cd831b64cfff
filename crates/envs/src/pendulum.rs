//! Inverted-pendulum swing-up (the paper's task), integrated directly from its rigid-body model.
//!
//! A hinge about the horizontal y axis carries a massless pole of length L = 0.5 m with a solid
//! sphere (m = 1 kg, r = 0.05 m) centred at its end; q is the pole's angle from upright. The
//! sphere's height above the hinge is `L cos q`, so gravity's torque about the hinge is
//! `m g L sin q` (it pushes the pole away from upright), and the equation of motion is
//!
//! ```text
//! I qddot = m g L sin q - b qdot + tau,   I = m L^2 + 2/5 m r^2 = 0.251 kg m^2,
//!                                          m g L = 4.905 N m,  b = 0.1 N m s/rad,
//!                                          tau = clip(control, -2, 2) N m.
//! ```
//!
//! Semi-implicit Euler with dt = 0.002 s (velocity from the current angle first, then the angle
//! from the new velocity), 10 steps per primitive action (docs/ENVIRONMENTS.md). Damping is
//! explicit like every other force; MuJoCo's Euler would treat it implicitly, which changes the
//! damping term by about dt b / I = 8e-4 of itself per step. Physics runs in f64; observations and
//! goals are f32.

use std::f32::consts::PI as PI_F32;

use hac_core::{AgentConfig, Bounds, Env, EnvSpec, Mode, Rng};

use crate::{StateError, check_physical_state, stated_horizon, wrap_angle};

/// Distance from the hinge to the sphere's centre, m.
pub const POLE_LENGTH: f64 = 0.5;
/// Mass of the sphere (the pole is massless), kg.
pub const BOB_MASS: f64 = 1.0;
/// Radius of the sphere, m.
pub const BOB_RADIUS: f64 = 0.05;
/// Moment of inertia about the hinge: the sphere as a point at L plus its own 2/5 m r^2.
pub const INERTIA: f64 = BOB_MASS * (POLE_LENGTH * POLE_LENGTH + 0.4 * BOB_RADIUS * BOB_RADIUS);
/// Integration timestep, s.
pub const TIMESTEP: f64 = 0.002;

const PHYSICS_STEPS_PER_ACTION: usize = 10;
const MAX_TORQUE: f32 = 2.0;
/// Bound of the angular velocity in goals (velocities are clipped to it before comparing).
const GOAL_SPEED_LIMIT: f32 = 15.0;
const MAX_ACTIONS: usize = 1000;
/// A bound on |qdot| that no episode can pass (the spec's `state_bounds`). Above
/// `(m g L + max torque) / b` = 69.05 rad/s, damping takes more energy than gravity and the motor
/// can add, so the speed falls; one semi-implicit step maps `|qdot| <= V` into itself for that
/// `V`, since `qdot' = qdot (1 - dt b / I) + dt (m g L sin q + tau) / I`. Episodes start at
/// |qdot| <= 0.05.
const MAX_SPEED: f32 = 70.0;

/// The physical constants a test may want to change; the geometry stays fixed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PendulumPhysics {
    /// Joint damping, N m s/rad.
    pub damping: f64,
    /// Gravitational acceleration along -z, m/s^2.
    pub gravity: f64,
    /// When false the actuator is disconnected and the pole swings freely whatever the action.
    pub actuated: bool,
}

impl Default for PendulumPhysics {
    fn default() -> Self {
        Self {
            damping: 0.1,
            gravity: 9.81,
            actuated: true,
        }
    }
}

impl PendulumPhysics {
    /// m g L: gravity's torque about the hinge with the pole horizontal, N m.
    pub fn mgl(&self) -> f64 {
        BOB_MASS * self.gravity * POLE_LENGTH
    }
}

/// The pendulum swing-up task. Until the first `reset` it hangs at rest (q = pi).
#[derive(Debug, Clone)]
pub struct Pendulum {
    spec: EnvSpec,
    physics: PendulumPhysics,
    /// Angle from upright, wrapped to (-pi, pi].
    q: f64,
    qdot: f64,
    /// `[cos q, sin q, qdot]`, refreshed after every change of `q` or `qdot`.
    observation: [f32; 3],
}

impl Default for Pendulum {
    fn default() -> Self {
        Self::new()
    }
}

impl Pendulum {
    /// Registry name.
    pub const NAME: &'static str = "pendulum";

    /// The task with the standard physics.
    pub fn new() -> Self {
        Self::with_physics(PendulumPhysics::default())
    }

    /// The task with overridden physical constants (the spec and defaults are unchanged).
    pub fn with_physics(physics: PendulumPhysics) -> Self {
        let mut env = Self {
            spec: spec(),
            physics,
            q: std::f64::consts::PI,
            qdot: 0.0,
            observation: [0.0; 3],
        };
        env.observe();
        env
    }

    pub fn physics(&self) -> &PendulumPhysics {
        &self.physics
    }

    /// `[q, qdot]` at full precision.
    pub fn physical_state(&self) -> [f64; 2] {
        [self.q, self.qdot]
    }

    /// Mechanical energy: kinetic `1/2 I qdot^2` plus potential `m g L cos q` (zero at the
    /// hinge's height), J.
    pub fn energy(&self) -> f64 {
        0.5 * INERTIA * self.qdot * self.qdot + self.physics.mgl() * self.q.cos()
    }

    fn observe(&mut self) {
        let (sin, cos) = self.q.sin_cos();
        self.observation = [cos as f32, sin as f32, self.qdot as f32];
    }
}

fn spec() -> EnvSpec {
    let thresholds = vec![9.5f32.to_radians(), 0.6];
    EnvSpec {
        name: Pendulum::NAME.to_string(),
        description: "inverted pendulum swing-up: bring the pole upright and nearly still \
                      (paper task)"
            .to_string(),
        state_dim: 3,
        action_bounds: Bounds::symmetric(&[MAX_TORQUE]),
        end_goal_dim: 2,
        end_goal_thresholds: thresholds.clone(),
        subgoal_bounds: Bounds::symmetric(&[PI_F32, GOAL_SPEED_LIMIT]),
        subgoal_thresholds: thresholds,
        // The goal tests compare the angle as a plain number, as the reference's do (goals
        // near the bottom are missed across the seam; the end goals are near the top, where
        // it makes no difference). HIRO's relative goals, differences of two wrapped angles,
        // take it along the circle.
        end_goal_angles: Vec::new(),
        subgoal_angles: Vec::new(),
        subgoal_wrapped: vec![true, false],
        state_bounds: Bounds::symmetric(&[1.0, 1.0, MAX_SPEED]),
        end_goal_bounds: Bounds::symmetric(&[PI_F32, GOAL_SPEED_LIMIT]),
        achieved_subgoal_bounds: Bounds::symmetric(&[PI_F32, GOAL_SPEED_LIMIT]),
        max_actions: MAX_ACTIONS,
        physics_steps_per_action: PHYSICS_STEPS_PER_ACTION,
    }
}

/// End goals and subgoals share one projection: `[q, qdot clipped]`, with q recovered from the
/// observation (the state is all a projection sees).
fn project(state: &[f32], out: &mut [f32]) {
    let q = state[1].atan2(state[0]);
    // atan2 can return -pi (for sin q = -0); goals use (-pi, pi] like the state.
    out[0] = if q <= -PI_F32 { PI_F32 } else { q };
    out[1] = state[2].clamp(-GOAL_SPEED_LIMIT, GOAL_SPEED_LIMIT);
}

impl Env for Pendulum {
    /// Puts the pendulum at `[q, qdot]` (q in radians from upright, wrapped; both finite).
    fn set_physical_state(&mut self, state: &[f64]) -> Result<(), StateError> {
        check_physical_state(Self::NAME, state, &[(f64::MIN, f64::MAX); 2])?;
        self.q = wrap_angle(state[0]);
        self.qdot = state[1];
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

    /// The paper's reference values, with the pendulum's own H, noise, storage and schedule
    /// (docs/ENVIRONMENTS.md).
    fn default_config(&self, levels: usize) -> AgentConfig {
        // The covering rule of `stated_horizon` reproduces 1000, 32 and 10 here.
        let horizon = stated_horizon(levels, self.spec.max_actions, [32, 10]);
        // Everything else is the reference's: noise 0.1 and 0.1 of the half range, 200 episodes
        // stored, 50 training episodes between test rounds, no target networks.
        AgentConfig::reference(levels, horizon)
    }

    /// q uniform in [pi/4, 7pi/4] (anywhere but near upright), qdot uniform in [-0.05, 0.05].
    fn reset(&mut self, rng: &mut Rng) {
        let q = rng.uniform(PI_F32 / 4.0, 7.0 * PI_F32 / 4.0);
        self.q = wrap_angle(f64::from(q));
        self.qdot = f64::from(rng.uniform(-0.05, 0.05));
        self.observe();
    }

    fn state(&self) -> &[f32] {
        &self.observation
    }

    fn step(&mut self, action: &[f32]) {
        let torque = if self.physics.actuated {
            f64::from(action[0].clamp(-MAX_TORQUE, MAX_TORQUE))
        } else {
            0.0
        };
        let mgl = self.physics.mgl();
        let damping = self.physics.damping;
        for _ in 0..PHYSICS_STEPS_PER_ACTION {
            let qddot = (mgl * self.q.sin() - damping * self.qdot + torque) / INERTIA;
            self.qdot += TIMESTEP * qddot;
            self.q = wrap_angle(self.q + TIMESTEP * self.qdot);
        }
        self.observe();
    }

    fn project_end_goal(&self, state: &[f32], out: &mut [f32]) {
        project(state, out);
    }

    fn project_subgoal(&self, state: &[f32], out: &mut [f32]) {
        project(state, out);
    }

    /// Training: uniform in [-16 deg, 16 deg] x [-0.6, 0.6]; test: exactly upright and still.
    fn sample_end_goal(&self, rng: &mut Rng, mode: Mode, out: &mut [f32]) {
        match mode {
            Mode::Train => {
                let max_angle = 16f32.to_radians();
                out[0] = rng.uniform(-max_angle, max_angle);
                out[1] = rng.uniform(-0.6, 0.6);
            }
            Mode::Test => {
                out[0] = 0.0;
                out[1] = 0.0;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;

    use super::*;

    /// No damping, no actuator: a conservative system.
    fn free() -> Pendulum {
        Pendulum::with_physics(PendulumPhysics {
            damping: 0.0,
            actuated: false,
            ..PendulumPhysics::default()
        })
    }

    fn deviation_from_bottom(env: &Pendulum) -> f64 {
        wrap_angle(env.physical_state()[0] - PI)
    }

    #[test]
    fn constants_match_the_model() {
        assert!((INERTIA - 0.251).abs() < 1e-15);
        assert!((PendulumPhysics::default().mgl() - 4.905).abs() < 1e-12);
    }

    #[test]
    fn spec_matches_envs_md() {
        let env = Pendulum::new();
        let s = env.spec();
        assert_eq!(s.state_dim, 3);
        assert_eq!(s.action_bounds, Bounds::new(vec![-2.0], vec![2.0]));
        assert_eq!(s.end_goal_dim, 2);
        assert_eq!(
            s.subgoal_bounds,
            Bounds::new(vec![-PI_F32, -15.0], vec![PI_F32, 15.0])
        );
        assert_eq!(s.end_goal_thresholds, vec![9.5f32.to_radians(), 0.6]);
        assert_eq!(s.subgoal_thresholds, s.end_goal_thresholds);
        assert_eq!(s.max_actions, 1000);
        assert_eq!(s.physics_steps_per_action, 10);
    }

    #[test]
    fn default_horizons() {
        let env = Pendulum::new();
        let h: Vec<usize> = (1..=5).map(|k| env.default_config(k).horizon).collect();
        assert_eq!(h, [1000, 32, 10, 6, 4]);
        let c = env.default_config(2);
        assert_eq!(c.action_noise, hac_core::Noise::Relative(0.1));
        assert_eq!(c.subgoal_noise, hac_core::Noise::Relative(0.1));
        assert_eq!(c.episodes_to_store, 200);
        assert_eq!(c.exploration_episodes, 50);
    }

    /// Semi-implicit Euler is symplectic: the energy oscillates at O(dt) but does not drift, and
    /// its modified energy `H + dt/2 * qdot * m g L sin q` is conserved to O(dt^2).
    #[test]
    fn free_swing_conserves_energy() {
        let mut env = free();
        env.set_physical_state(&[1.0, 0.0]).unwrap();
        let mgl = env.physics().mgl();
        // Measured from the hanging rest position so the scale is the swing's own energy.
        let energy = |e: &Pendulum| e.energy() + mgl;
        let modified = |e: &Pendulum| {
            let [q, qdot] = e.physical_state();
            energy(e) + 0.5 * TIMESTEP * qdot * mgl * q.sin()
        };
        let (e0, m0) = (energy(&env), modified(&env));
        let (mut worst_e, mut worst_m) = (0.0f64, 0.0f64);
        // 10_000 actions = 100_000 physics steps = 200 s, about 100 swings.
        for _ in 0..10_000 {
            env.step(&[2.0]);
            worst_e = worst_e.max(((energy(&env) - e0) / e0).abs());
            worst_m = worst_m.max(((modified(&env) - m0) / m0).abs());
        }
        assert!(worst_e < 5e-3, "energy relative error {worst_e}");
        // Observed ~1e-5, a quarter of that at half the timestep: O(dt^2), no drift.
        assert!(worst_m < 2e-5, "modified energy relative error {worst_m}");
    }

    #[test]
    fn small_swing_period_about_the_bottom() {
        let mut env = free();
        env.set_physical_state(&[PI - 0.01, 0.0]).unwrap();
        let dt = TIMESTEP * PHYSICS_STEPS_PER_ACTION as f64;
        // Upward zero crossings of the deviation from the bottom, linearly interpolated.
        let mut crossings = Vec::new();
        let mut prev = deviation_from_bottom(&env);
        for i in 1..=1000 {
            env.step(&[0.0]);
            let now = deviation_from_bottom(&env);
            if prev < 0.0 && now >= 0.0 {
                crossings.push(dt * (f64::from(i) - now / (now - prev)));
            }
            prev = now;
        }
        assert!(crossings.len() >= 11, "{} crossings", crossings.len());
        let periods = (crossings.len() - 1) as f64;
        let measured = (crossings[crossings.len() - 1] - crossings[0]) / periods;
        let expected = 2.0 * PI * (INERTIA / env.physics().mgl()).sqrt();
        let rel = (measured - expected).abs() / expected;
        // Symplectic Euler runs fast by (omega dt)^2 / 24 = 3e-6; the amplitude adds 6e-6.
        assert!(rel < 2e-5, "period {measured} vs {expected} (rel {rel})");
    }

    #[test]
    fn hanging_at_rest_stays() {
        let mut env = Pendulum::new();
        env.set_physical_state(&[PI, 0.0]).unwrap();
        for _ in 0..1000 {
            env.step(&[0.0]);
            // sin(PI) is 1.2e-16, not 0: the pole may sway by rounding, no more.
            assert!(deviation_from_bottom(&env).abs() < 1e-12);
            assert!(env.physical_state()[1].abs() < 1e-12);
        }
        let s = env.state();
        assert!((s[0] + 1.0).abs() < 1e-7 && s[1].abs() < 1e-7 && s[2].abs() < 1e-7);
    }

    #[test]
    fn constant_torque_accelerates_at_tau_over_inertia() {
        let tau = 1.5;
        let accel = tau / INERTIA;
        let n = PHYSICS_STEPS_PER_ACTION as f64;
        // Without gravity and damping the discrete update is exact: qdot = n dt a and, velocity
        // first, q = dt^2 a (1 + 2 + ... + n).
        let mut env = Pendulum::with_physics(PendulumPhysics {
            gravity: 0.0,
            damping: 0.0,
            actuated: true,
        });
        env.set_physical_state(&[0.0, 0.0]).unwrap();
        env.step(&[tau as f32]);
        let [q, qdot] = env.physical_state();
        assert!((qdot - n * TIMESTEP * accel).abs() < 1e-12, "{qdot}");
        assert!(
            (q - TIMESTEP * TIMESTEP * accel * n * (n + 1.0) / 2.0).abs() < 1e-12,
            "{q}"
        );
        // With the real physics, hanging at rest, gravity and damping start at zero: the first
        // action's acceleration is tau / I to within a fraction of a percent.
        let mut env = Pendulum::new();
        env.set_physical_state(&[PI, 0.0]).unwrap();
        env.step(&[tau as f32]);
        let measured = env.physical_state()[1] / (n * TIMESTEP);
        assert!(
            (measured / accel - 1.0).abs() < 5e-3,
            "{measured} vs {accel}"
        );
    }

    #[test]
    fn torque_is_clipped_and_ignored_when_unactuated() {
        let mut a = Pendulum::new();
        let mut b = Pendulum::new();
        a.step(&[2.0]);
        b.step(&[50.0]);
        assert_eq!(a.physical_state(), b.physical_state());
        let mut c = free();
        let mut d = free();
        c.step(&[2.0]);
        d.step(&[-2.0]);
        assert_eq!(c.physical_state(), d.physical_state());
    }

    #[test]
    fn projections_land_inside_subgoal_bounds() {
        let mut env = Pendulum::new();
        let bounds = env.spec().subgoal_bounds.clone();
        let mut out = [0.0f32; 2];
        let mut check = |env: &Pendulum| {
            env.project_subgoal(env.state(), &mut out);
            assert!(bounds.contains(&out), "{out:?}");
            env.project_end_goal(env.state(), &mut out);
            assert!(bounds.contains(&out), "{out:?}");
        };
        for edge in [
            [PI, 0.0],
            [-PI, 100.0],
            [PI - 1e-9, 15.0],
            [-PI + 1e-9, -15.0],
            [0.0, -100.0],
        ] {
            env.set_physical_state(&edge).unwrap();
            check(&env);
        }
        let mut rng = Rng::seed_from(7);
        for _ in 0..20 {
            env.reset(&mut rng);
            for _ in 0..200 {
                env.step(&[rng.uniform(-2.0, 2.0)]);
                check(&env);
            }
        }
    }

    #[test]
    fn projection_recovers_angle_and_clips_speed() {
        let mut env = Pendulum::new();
        let mut out = [0.0f32; 2];
        env.set_physical_state(&[0.5, 20.0]).unwrap();
        env.project_subgoal(env.state(), &mut out);
        assert!((out[0] - 0.5).abs() < 1e-6);
        assert_eq!(out[1], 15.0);
        env.set_physical_state(&[-2.5, -3.0]).unwrap();
        env.project_end_goal(env.state(), &mut out);
        assert!((out[0] + 2.5).abs() < 1e-6);
        assert_eq!(out[1], -3.0);
        // A state with sin q = -0 projects to +pi, not -pi.
        env.project_end_goal(&[-1.0, -0.0, 0.0], &mut out);
        assert_eq!(out[0], PI_F32);
    }

    #[test]
    fn initial_states_follow_their_distribution() {
        let mut env = Pendulum::new();
        let mut rng = Rng::seed_from(3);
        for _ in 0..1000 {
            env.reset(&mut rng);
            let [q, qdot] = env.physical_state();
            // Angle from upright at least pi/4 either way.
            assert!(q.abs() >= PI / 4.0 - 1e-6 && q <= PI, "{q}");
            assert!(qdot.abs() <= 0.05, "{qdot}");
        }
    }

    #[test]
    fn end_goal_samples() {
        let env = Pendulum::new();
        let mut rng = Rng::seed_from(11);
        let mut g = [0.0f32; 2];
        let max_angle = 16f32.to_radians();
        for _ in 0..1000 {
            env.sample_end_goal(&mut rng, Mode::Train, &mut g);
            assert!(g[0].abs() <= max_angle && g[1].abs() <= 0.6, "{g:?}");
        }
        env.sample_end_goal(&mut rng, Mode::Test, &mut g);
        assert_eq!(g, [0.0, 0.0]);
    }

    #[test]
    fn same_seed_same_trajectory() {
        let run = |seed| {
            let mut env = Pendulum::new();
            let mut rng = Rng::seed_from(seed);
            env.reset(&mut rng);
            let mut trace = Vec::new();
            for _ in 0..500 {
                env.step(&[rng.uniform(-2.0, 2.0)]);
                trace.extend(env.state().iter().map(|x| x.to_bits()));
            }
            trace
        };
        assert_eq!(run(5), run(5));
        assert_ne!(run(5), run(6));
    }

    #[test]
    fn set_physical_state_rejects_bad_input() {
        let mut env = Pendulum::new();
        assert!(matches!(
            env.set_physical_state(&[0.0, 0.0, 0.0]),
            Err(StateError::WrongLength {
                expected: 2,
                got: 3,
                ..
            })
        ));
        assert!(env.set_physical_state(&[f64::NAN, 0.0]).is_err());
        assert!(env.set_physical_state(&[0.0, f64::INFINITY]).is_err());
        env.set_physical_state(&[7.0, 1.0]).unwrap();
        assert!((env.physical_state()[0] - (7.0 - 2.0 * PI)).abs() < 1e-12);
    }

    #[test]
    fn goal_tests_compare_plain_numbers_but_relative_goals_wrap_the_angle() {
        let spec = Pendulum::new().spec().clone();
        assert!(spec.end_goal_angles.is_empty() && spec.subgoal_angles.is_empty());
        assert_eq!(spec.relative_goal_angles(), [true, false]);
        // Tasks that flag their angles for the goal test use the same flags; others none.
        let ur5 = crate::make("ur5-reacher").unwrap().spec().clone();
        assert_eq!(ur5.relative_goal_angles(), ur5.subgoal_angles);
        let car = crate::make("mountain-car").unwrap().spec().clone();
        assert!(car.relative_goal_angles().is_empty());
    }

    /// HIRO's low level on the pendulum: relative goals are differences of angles that the
    /// projection wraps to (-pi, pi], so the goal transition and the intrinsic reward must take
    /// them along the circle, or a pole swinging through the bottom (where q jumps from pi to
    /// -pi) earns a reward of about -2 pi for a step of a few hundredths of a radian.
    #[test]
    fn hiro_takes_the_angle_along_the_circle_through_the_bottom() {
        use hac_core::hiro::{HighTransition, HiroRollout, HiroSink};
        use hac_core::{Exploration, Policy, Transition};

        /// Level 1 proposes "stay where you are" (a zero offset); level 0 pushes at full torque.
        struct Scripted;
        impl Policy for Scripted {
            fn act(&mut self, level: usize, _: &[f32], _: &[f32], action: &mut [f32]) {
                action.fill(if level == 0 { MAX_TORQUE } else { 0.0 });
            }
        }
        struct Greedy;
        impl Exploration for Greedy {
            fn explore(&mut self, _: usize, _: &[f32], _: &Bounds, _: &mut [f32]) {}
            fn test_subgoal(&mut self, _: usize) -> bool {
                false
            }
            fn replay_goal_index(&mut self, _: usize, _: usize) -> usize {
                0
            }
        }
        /// One low-level step: p(s), g, r, p(s').
        type Step = ([f32; 2], [f32; 2], f32, [f32; 2]);
        #[derive(Default)]
        struct Steps(Vec<Step>);
        impl HiroSink for Steps {
            fn push_low(&mut self, t: &Transition<'_>) {
                let (mut p, mut next) = ([0.0; 2], [0.0; 2]);
                project(t.state, &mut p);
                project(t.next_state, &mut next);
                self.0.push((p, [t.goal[0], t.goal[1]], t.reward, next));
            }
            fn push_high(&mut self, _: &HighTransition<'_>) {}
        }

        let mut env = Pendulum::new();
        env.set_max_actions(300);
        let c = 10;
        let mut rollout = HiroRollout::new(&env.spec().clone(), c);
        let mut steps = Steps::default();
        rollout.run_episode(
            &mut env,
            &mut Scripted,
            &mut Greedy,
            Mode::Train,
            &mut Rng::seed_from(5),
            &mut steps,
        );
        let wrap = |x: f32| wrap_angle(f64::from(x)) as f32;
        let mut crossings = 0;
        for (i, (p, goal, reward, next)) in steps.0.iter().enumerate() {
            // The goal names p(s_k) of the segment's first step k: its angle is the short turn
            // back there, and the reward the distance to it from p(s') along the circle.
            let start = &steps.0[i - i % c].0;
            assert!(
                (goal[0] - wrap(start[0] - p[0])).abs() < 1e-4,
                "step {i}: goal angle {} from {} to {}",
                goal[0],
                p[0],
                start[0]
            );
            let miss = [wrap(p[0] + goal[0] - next[0]), p[1] + goal[1] - next[1]];
            let want = -(miss[0] * miss[0] + miss[1] * miss[1]).sqrt();
            assert!((reward - want).abs() < 1e-4, "step {i}: {reward} vs {want}");
            crossings +=
                usize::from(p[0].abs() > 3.0 && next[0].abs() > 3.0 && p[0] * next[0] < 0.0);
        }
        assert!(
            crossings >= 2,
            "the pole crossed the bottom {crossings} times"
        );
    }
}
