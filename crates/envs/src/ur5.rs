//! UR5 reacher (the paper's task): move the first three joints of a UR5 arm to target angles,
//! integrated directly from the rigid-body model the reference simulated in MuJoCo.
//!
//! The chain, its inertias and the dynamics algorithms live in [`arm`]; this module is the task:
//! velocity-servo actuators, integration, spaces, goal distributions and defaults
//! (docs/ENVIRONMENTS.md).
//!
//! Physics per step of dt = 0.002 s (15 per primitive action), in f64:
//!
//! ```text
//! tau   = clip(10 control - 10 qdot, -150, 150)           velocity servos, control ranges
//!                                                         [-3.15, 3.15], [-5, 5], [-3.15, 3.15]
//! M(q) qddot = tau - C(q, qdot) qdot - g(q) - 10 qdot     joint damping 10 N m s/rad, explicit
//! qdot += dt qddot;   q = wrap(q + dt qdot)               semi-implicit Euler
//! ```
//!
//! Servo and damping together make a joint settle at half its commanded speed when nothing else
//! loads it. MuJoCo's Euler would treat the joint damping implicitly; explicit damping is stable
//! as long as `dt * 20 / lambda_min(M) < 2` for damping plus servo, and M's smallest eigenvalue
//! over all q is about 0.038 kg m^2, which gives 1.05: the stiffest mode decays within a step or
//! two either way, but its per-step damping differs from MuJoCo's by up to half.
//!
//! This velocity-form Euler is MuJoCo's, and with a mass matrix that depends on q it is not
//! symplectic: left free (no damping, no servos) the arm loses energy at a rate proportional to
//! dt, about 0.1% of its kinetic energy per second in a gentle swing, while the model itself
//! conserves energy (tests integrate it with RK4). Against the 20 N m s/rad of damping plus
//! servo that every joint sees in the task, that numerical loss is negligible.
//!
//! Angles: every task wraps its angles to (-pi, pi], and so does this one, in the state, the
//! projections and the goals. The reference leaves MuJoCo's joint positions unwrapped and folds
//! them into (-2pi, 2pi) only when projecting, hence its subgoal bounds of +-2pi, which this task
//! keeps (they also set the subgoal noise scale, a fraction of the half range). Goal checks
//! compare the joint angles along the circle (`EnvSpec::end_goal_angles` / `subgoal_angles`):
//! a subgoal angle names a direction, so every point of the +-2pi box is a reachable subgoal
//! (`4.0` is reached at `4.0 - 2pi`), and a goal near +-pi is reached from either side of the
//! seam. Compared as plain numbers, as before, the seven eighths of the box with an angle beyond
//! +-pi could never be reached, and a subgoal there could only be penalised.
//! Since every direction is then in the box twice, a run can bound the subgoal angles by one turn
//! instead (`subgoal_bounds` in the run config; docs/RESULTS.md measures it).
//! Wrapping is exact for the physics (M, C and g depend on q only through sines and cosines).

pub mod arm;

use std::f32::consts::{FRAC_PI_4, PI as PI_F32, TAU as TAU_F32};

use hac_core::{AgentConfig, Bounds, Env, EnvSpec, Mode, Noise, Rng};
use nalgebra::Vector3;

pub use arm::{JOINTS, Pose, Ur5Arm, WRIST_IN_FOREARM};

use crate::{StateError, check_physical_state, stated_horizon, wrap_angle};

/// Integration timestep, s.
pub const TIMESTEP: f64 = 0.002;
/// Velocity-servo gain: torque per rad/s of commanded speed and of joint speed, N m s/rad.
pub const SERVO_GAIN: f64 = 10.0;
/// Actuator torque limit on every joint, N m.
pub const MAX_JOINT_TORQUE: f64 = 150.0;
/// Control ranges (commanded joint speeds), rad/s.
pub const CONTROL_LIMITS: [f32; JOINTS] = [3.15, 5.0, 3.15];
/// The fixed part of the initial state: shoulder-lift and elbow angles, rad.
pub const INITIAL_LIFT_AND_ELBOW: [f64; 2] = [0.00322757851, -0.127944547];

const PHYSICS_STEPS_PER_ACTION: usize = 15;
/// Bound of the joint speeds in subgoals (speeds are clipped to it before comparing).
const GOAL_SPEED_LIMIT: f32 = 4.0;
const MAX_ACTIONS: usize = 600;
/// A bound on every joint speed for the spec's `state_bounds`, far above what the arm reaches:
/// the servos command at most 5 rad/s and damp every joint (10 N m s/rad from the servo's gain
/// plus 10 from the joint), and gravity's torque is below 40 N m, so the speeds settle near the
/// command; random bang-bang control stays below 15 rad/s (tested).
const MAX_SPEED: f32 = 50.0;
/// Goal rule (docs/ENVIRONMENTS.md): minimum heights of the elbow and the wrist point, m.
const MIN_ELBOW_HEIGHT: f64 = 0.05;
const MIN_WRIST_HEIGHT: f64 = 0.15;

/// The physical constants a test may want to change; the chain's geometry and inertias stay.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ur5Physics {
    /// Damping of every joint, N m s/rad.
    pub damping: f64,
    /// Gravitational acceleration along -z, m/s^2.
    pub gravity: f64,
    /// When false the servos are disconnected and the arm moves freely whatever the action.
    pub actuated: bool,
}

impl Default for Ur5Physics {
    fn default() -> Self {
        Self {
            damping: 10.0,
            gravity: 9.81,
            actuated: true,
        }
    }
}

/// The UR5 reacher task. Until the first `reset` the arm rests at the initial lift and elbow
/// angles with the pan at 0.
#[derive(Debug, Clone)]
pub struct Ur5Reacher {
    spec: EnvSpec,
    physics: Ur5Physics,
    arm: Ur5Arm,
    /// Joint angles, each wrapped to (-pi, pi].
    q: Vector3<f64>,
    qd: Vector3<f64>,
    /// `[q, qdot]` as f32, refreshed after every change of `q` or `qd`.
    observation: [f32; 2 * JOINTS],
}

impl Default for Ur5Reacher {
    fn default() -> Self {
        Self::new()
    }
}

impl Ur5Reacher {
    /// Registry name.
    pub const NAME: &'static str = "ur5-reacher";

    /// The task with the standard physics.
    pub fn new() -> Self {
        Self::with_physics(Ur5Physics::default())
    }

    /// The task with overridden physical constants (the spec and defaults are unchanged).
    pub fn with_physics(physics: Ur5Physics) -> Self {
        let [lift, elbow] = INITIAL_LIFT_AND_ELBOW;
        let mut env = Self {
            spec: spec(),
            physics,
            arm: Ur5Arm::new(physics.gravity),
            q: Vector3::new(0.0, lift, elbow),
            qd: Vector3::zeros(),
            observation: [0.0; 2 * JOINTS],
        };
        env.observe();
        env
    }

    pub fn physics(&self) -> &Ur5Physics {
        &self.physics
    }

    /// The rigid-body model (kinematics, mass matrix, inverse dynamics).
    pub fn arm(&self) -> &Ur5Arm {
        &self.arm
    }

    /// The arm's current pose.
    pub fn pose(&self) -> Pose {
        self.arm.pose(&self.q)
    }

    /// `[q1, q2, q3, qdot1, qdot2, qdot3]` at full precision.
    pub fn physical_state(&self) -> [f64; 2 * JOINTS] {
        let (q, qd) = (&self.q, &self.qd);
        [q[0], q[1], q[2], qd[0], qd[1], qd[2]]
    }

    /// Mechanical energy: kinetic `1/2 qdot^T M qdot` plus the centres of mass' potential
    /// (zero at the base's height), J.
    pub fn energy(&self) -> f64 {
        let pose = self.pose();
        self.arm.kinetic_energy(&pose, &self.qd) + self.arm.potential_energy(&pose)
    }

    /// Whether joint angles `goal` pass the redraw rule: the pan more than pi/4 from zero
    /// either way, the elbow higher than 0.05 m and the wrist point higher than 0.15 m.
    pub fn is_valid_end_goal(&self, goal: &[f32]) -> bool {
        let q = Vector3::from_fn(|i, _| f64::from(goal[i]));
        let pose = self.arm.pose(&q);
        q[0].abs() > std::f64::consts::FRAC_PI_4
            && pose.elbow_height() > MIN_ELBOW_HEIGHT
            && pose.wrist_height() > MIN_WRIST_HEIGHT
    }

    /// One integration step under actuator torques `applied` (damping and gravity are added
    /// here). Tests drive it directly with torques the servos could not produce.
    fn physics_step(&mut self, applied: &Vector3<f64>, dt: f64) {
        let pose = self.arm.pose(&self.q);
        let tau = applied - self.physics.damping * self.qd;
        let qdd = self.arm.forward_dynamics(&pose, &self.qd, &tau);
        self.qd += dt * qdd;
        self.q += dt * self.qd;
        self.q.apply(|a| *a = wrap_angle(*a));
    }

    fn observe(&mut self) {
        for i in 0..JOINTS {
            self.observation[i] = self.q[i] as f32;
            self.observation[JOINTS + i] = self.qd[i] as f32;
        }
    }
}

/// The velocity servos' torques for commanded speeds `control` at joint speeds `qd`.
fn servo_torque(control: &Vector3<f64>, qd: &Vector3<f64>) -> Vector3<f64> {
    (SERVO_GAIN * (control - qd)).map(|t| t.clamp(-MAX_JOINT_TORQUE, MAX_JOINT_TORQUE))
}

fn spec() -> EnvSpec {
    let angle_threshold = 10f32.to_radians();
    let mut subgoal_thresholds = vec![angle_threshold; JOINTS];
    subgoal_thresholds.extend([2.0; JOINTS]);
    let mut subgoal_radius = vec![TAU_F32; JOINTS];
    subgoal_radius.extend([GOAL_SPEED_LIMIT; JOINTS]);
    EnvSpec {
        name: Ur5Reacher::NAME.to_string(),
        description: "UR5 reacher: bring the arm's first three joints to target angles \
                      (paper task)"
            .to_string(),
        state_dim: 2 * JOINTS,
        action_bounds: Bounds::symmetric(&CONTROL_LIMITS),
        end_goal_dim: JOINTS,
        end_goal_thresholds: vec![angle_threshold; JOINTS],
        subgoal_bounds: Bounds::symmetric(&subgoal_radius),
        subgoal_thresholds,
        // Joint angles are compared along the circle, velocities as numbers.
        end_goal_angles: vec![true; JOINTS],
        subgoal_angles: [[true; JOINTS], [false; JOINTS]].concat(),
        subgoal_wrapped: Vec::new(),
        state_bounds: Bounds::symmetric(&[PI_F32, PI_F32, PI_F32, MAX_SPEED, MAX_SPEED, MAX_SPEED]),
        end_goal_bounds: Bounds::symmetric(&[PI_F32; JOINTS]),
        achieved_subgoal_bounds: Bounds::symmetric(&[
            PI_F32,
            PI_F32,
            PI_F32,
            GOAL_SPEED_LIMIT,
            GOAL_SPEED_LIMIT,
            GOAL_SPEED_LIMIT,
        ]),
        max_actions: MAX_ACTIONS,
        physics_steps_per_action: PHYSICS_STEPS_PER_ACTION,
    }
}

/// An observed angle in (-pi, pi]. The state's own angles pass unchanged (f32 rounding can put
/// pi at `PI_F32`, a hair above, which must not flip to -pi); anything else is wrapped.
fn wrap_observed(a: f32) -> f32 {
    if (-PI_F32..=PI_F32).contains(&a) {
        a
    } else {
        wrap_angle(f64::from(a)) as f32
    }
}

impl Env for Ur5Reacher {
    /// Puts the arm at `[q1, q2, q3, qdot1, qdot2, qdot3]` (radians, wrapped; rad/s; all finite).
    fn set_physical_state(&mut self, state: &[f64]) -> Result<(), StateError> {
        check_physical_state(Self::NAME, state, &[(f64::MIN, f64::MAX); 2 * JOINTS])?;
        self.q = Vector3::from_fn(|i, _| wrap_angle(state[i]));
        self.qd = Vector3::from_fn(|i, _| state[JOINTS + i]);
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

    /// The paper's reference values, with the UR5's own H, noise, storage and schedule
    /// (docs/ENVIRONMENTS.md).
    fn default_config(&self, levels: usize) -> AgentConfig {
        // The covering rule of `stated_horizon` would give 9, not 10, for 3 levels here.
        let horizon = stated_horizon(levels, self.spec.max_actions, [25, 10]);
        AgentConfig {
            // The reference's: primitive 0.1 and subgoal 0.03, as fractions of the half range.
            subgoal_noise: Noise::Relative(0.03),
            episodes_to_store: 500,
            ..AgentConfig::reference(levels, horizon)
        }
    }

    /// Pan uniform in [-pi/8, pi/8], lift and elbow at the reference's fixed angles, at rest.
    fn reset(&mut self, rng: &mut Rng) {
        let pan = rng.uniform(-PI_F32 / 8.0, PI_F32 / 8.0);
        let [lift, elbow] = INITIAL_LIFT_AND_ELBOW;
        self.q = Vector3::new(f64::from(pan), lift, elbow);
        self.qd = Vector3::zeros();
        self.observe();
    }

    fn state(&self) -> &[f32] {
        &self.observation
    }

    fn step(&mut self, action: &[f32]) {
        let control = Vector3::from_fn(|i, _| {
            f64::from(action[i].clamp(-CONTROL_LIMITS[i], CONTROL_LIMITS[i]))
        });
        for _ in 0..PHYSICS_STEPS_PER_ACTION {
            let applied = if self.physics.actuated {
                servo_torque(&control, &self.qd)
            } else {
                Vector3::zeros()
            };
            self.physics_step(&applied, TIMESTEP);
        }
        self.observe();
    }

    /// The three joint angles.
    fn project_end_goal(&self, state: &[f32], out: &mut [f32]) {
        for i in 0..JOINTS {
            out[i] = wrap_observed(state[i]);
        }
    }

    /// The three joint angles and the three joint speeds clipped to +-4 rad/s.
    fn project_subgoal(&self, state: &[f32], out: &mut [f32]) {
        for i in 0..JOINTS {
            out[i] = wrap_observed(state[i]);
            out[JOINTS + i] = state[JOINTS + i].clamp(-GOAL_SPEED_LIMIT, GOAL_SPEED_LIMIT);
        }
    }

    /// Training and test alike: pan in [-pi, pi], lift in [-pi/4, 0], elbow in [-pi/4, pi/4],
    /// all three redrawn until [`Ur5Reacher::is_valid_end_goal`] holds (about 6 draws in 10
    /// pass).
    fn sample_end_goal(&self, rng: &mut Rng, _mode: Mode, out: &mut [f32]) {
        loop {
            out[0] = rng.uniform(-PI_F32, PI_F32);
            out[1] = rng.uniform(-FRAC_PI_4, 0.0);
            out[2] = rng.uniform(-FRAC_PI_4, FRAC_PI_4);
            if self.is_valid_end_goal(out) {
                return;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::{FRAC_PI_4, FRAC_PI_8, PI, TAU};

    use super::*;

    /// No damping, no actuator: a conservative system.
    fn free(gravity: f64) -> Ur5Reacher {
        Ur5Reacher::with_physics(Ur5Physics {
            damping: 0.0,
            gravity,
            actuated: false,
        })
    }

    /// The largest |x| over the run of `f` for `n` physics steps under `torque(env)`.
    fn run_max(
        env: &mut Ur5Reacher,
        n: usize,
        dt: f64,
        torque: impl Fn(&Ur5Reacher) -> Vector3<f64>,
        f: impl Fn(&Ur5Reacher) -> f64,
    ) -> f64 {
        let mut worst = 0.0f64;
        for _ in 0..n {
            let tau = torque(env);
            env.physics_step(&tau, dt);
            worst = worst.max(f(env).abs());
        }
        worst
    }

    fn gravity_compensation(env: &Ur5Reacher) -> Vector3<f64> {
        env.arm.gravity_torque(&env.pose())
    }

    #[test]
    fn spec_matches_envs_md() {
        let env = Ur5Reacher::new();
        let s = env.spec();
        assert_eq!(s.name, "ur5-reacher");
        assert_eq!(s.state_dim, 6);
        assert_eq!(
            s.action_bounds,
            Bounds::new(vec![-3.15, -5.0, -3.15], vec![3.15, 5.0, 3.15])
        );
        assert_eq!(s.end_goal_dim, 3);
        let deg10 = 10f32.to_radians();
        assert_eq!(s.end_goal_thresholds, vec![deg10; 3]);
        let two_pi = 2.0 * PI_F32;
        assert_eq!(
            s.subgoal_bounds,
            Bounds::new(
                vec![-two_pi, -two_pi, -two_pi, -4.0, -4.0, -4.0],
                vec![two_pi, two_pi, two_pi, 4.0, 4.0, 4.0]
            )
        );
        assert_eq!(
            s.subgoal_thresholds,
            vec![deg10, deg10, deg10, 2.0, 2.0, 2.0]
        );
        assert_eq!(s.max_actions, 600);
        assert_eq!(s.physics_steps_per_action, 15);
        let p = Ur5Physics::default();
        assert_eq!((p.damping, p.gravity, p.actuated), (10.0, 9.81, true));
    }

    #[test]
    fn default_config_per_level_count() {
        let env = Ur5Reacher::new();
        let h: Vec<usize> = (1..=6).map(|k| env.default_config(k).horizon).collect();
        // 5^4 = 625 and 4^5 = 1024 cover 600; 4^4 = 256 and 3^5 = 243 do not.
        assert_eq!(h, [600, 25, 10, 5, 4, 3]);
        let c = env.default_config(3);
        assert_eq!(c.action_noise, Noise::Relative(0.1));
        assert_eq!(c.subgoal_noise, Noise::Relative(0.03));
        assert_eq!(c.episodes_to_store, 500);
        assert_eq!(c.exploration_episodes, 50);
        assert_eq!(c.test_episodes, 100);
        assert_eq!(c.target_tau, None);
        c.validate(3, 6).unwrap();
    }

    /// Semi-implicit Euler in MuJoCo's velocity form is not symplectic once the mass matrix
    /// depends on q (the velocity update uses M(q) and the Coriolis terms from before the step),
    /// so unlike the pendulum's it does not conserve a modified energy: the free arm slowly
    /// loses energy, at a rate proportional to dt, while the continuous model conserves it (see
    /// `arm`'s RK4 test). Here: a gentle swing of the hanging arm for 60 s (30_000 steps).
    #[test]
    fn free_motion_energy_error_is_first_order_and_never_a_gain() {
        // Upper arm hanging straight down, lift swinging at 0.5 rad/s: 0.25 J of kinetic energy.
        let start = [0.0, PI / 2.0, 0.0, 0.0, 0.5, 0.0];
        let run = |dt: f64| {
            let mut env = free(9.81);
            env.set_physical_state(&start).unwrap();
            let e0 = env.energy();
            let n = (60.0 / dt).round() as usize;
            let (mut gain, mut tail) = (0.0f64, 0.0);
            for k in 0..n {
                env.physics_step(&Vector3::zeros(), dt);
                let error = env.energy() - e0;
                gain = gain.max(error);
                if k >= n - n / 10 {
                    tail += error / (n / 10) as f64;
                }
            }
            (gain, tail)
        };
        let (gain, loss) = run(TIMESTEP);
        let (half_gain, half_loss) = run(TIMESTEP / 2.0);
        // Observed: the energy rises at most 7.6e-4 J above its start (the O(dt) oscillation)
        // and ends 1.9e-2 J (8% of the kinetic energy) below it; both halve with dt.
        assert!(gain < 1e-3, "energy gain {gain}");
        assert!((-3e-2..-1e-2).contains(&loss), "energy change {loss}");
        let (gain_ratio, loss_ratio) = (gain / half_gain, loss / half_loss);
        assert!((1.8..2.2).contains(&gain_ratio), "{gain_ratio}");
        assert!((1.8..2.2).contains(&loss_ratio), "{loss_ratio}");
    }

    /// A violent tumble under gravity (up to 59 J of kinetic energy) stays bounded: the integrator
    /// dissipates, it never pumps energy in beyond its O(dt) oscillation.
    #[test]
    fn free_tumble_never_gains_energy() {
        let mut env = free(9.81);
        env.set_physical_state(&[0.3, -0.6, 0.9, 1.0, -2.0, 1.5])
            .unwrap();
        let e0 = env.energy();
        // 150_000 steps, 300 s.
        let gain = run_max(
            &mut env,
            150_000,
            TIMESTEP,
            |_| Vector3::zeros(),
            |e| (e.energy() - e0).max(0.0),
        );
        assert!(gain < 3.0, "energy gain {gain} J");
        assert!(env.energy() < e0);
    }

    /// With the arm stretched out level (q2 = q3 = 0) every centre of mass is at the height of
    /// the lift and elbow axes, so neither turning the pan nor its spin loads those joints: the
    /// pan alone spins up as a rigid body with `qddot = tau / I_zz`, and semi-implicit Euler
    /// integrates that exactly.
    #[test]
    fn pan_spins_up_at_torque_over_inertia() {
        // Moment of inertia about the vertical pan axis, by hand from the model's figures: the
        // shoulder's own z moment, then each link's moment about its centre of mass about the world
        // z axis (the link's x axis once the 90 degree quaternion has turned it) plus m d^2 for the
        // horizontal distance of its centre of mass from the axis.
        let upper = 0.226891 + 8.393 * (0.28f64.powi(2) + 0.13585f64.powi(2));
        let fore = 0.0494433 + 2.275 * (0.675f64.powi(2) + (0.13585f64 - 0.1197).powi(2));
        let izz = 0.00666 + upper + fore;
        let tau = 40.0;
        let n = 1500;
        for gravity in [0.0, 9.81] {
            let mut env = free(gravity);
            env.set_physical_state(&[0.0; 6]).unwrap();
            // Gravity compensation keeps the lift and elbow loaded exactly as without gravity.
            let worst_still = run_max(
                &mut env,
                n,
                TIMESTEP,
                |e| gravity_compensation(e) + Vector3::new(tau, 0.0, 0.0),
                |e| e.qd[1].abs().max(e.qd[2].abs()),
            );
            assert!(worst_still < 1e-9, "lift/elbow speed {worst_still}");
            let a = tau / izz;
            let steps = n as f64;
            let qd = env.qd[0];
            assert!((qd / (steps * TIMESTEP * a) - 1.0).abs() < 1e-9, "{qd}");
            let turned = TIMESTEP * TIMESTEP * a * steps * (steps + 1.0) / 2.0;
            let q = env.q[0];
            assert!((wrap_angle(turned) - q).abs() < 1e-9, "{q} vs {turned}");
        }
    }

    #[test]
    fn gravity_compensation_holds_the_arm_still() {
        let mut env = Ur5Reacher::new();
        let mut rng = Rng::seed_from(9);
        let mut goal = [0.0f32; 3];
        for _ in 0..20 {
            env.sample_end_goal(&mut rng, Mode::Train, &mut goal);
            let q = goal.map(f64::from);
            env.set_physical_state(&[q[0], q[1], q[2], 0.0, 0.0, 0.0])
                .unwrap();
            let start = env.q;
            let drift = run_max(&mut env, 3000, TIMESTEP, gravity_compensation, |e| {
                (e.q - start).norm() + e.qd.norm()
            });
            assert!(drift < 1e-10, "drift {drift} from {start}");
            // Without it the arm sags.
            let sag = run_max(
                &mut env,
                100,
                TIMESTEP,
                |_| Vector3::zeros(),
                |e| (e.q - start).norm(),
            );
            assert!(sag > 1e-3, "{sag}");
        }
    }

    /// Against the pan's damping 10 the servo's torque `10 (u - qdot)` balances at
    /// `qdot = u / 2`; with the arm level and no gravity nothing else loads the pan.
    #[test]
    fn servo_settles_at_half_the_commanded_speed() {
        let mut env = Ur5Reacher::with_physics(Ur5Physics {
            gravity: 0.0,
            ..Ur5Physics::default()
        });
        env.set_physical_state(&[0.0; 6]).unwrap();
        for _ in 0..300 {
            env.step(&[2.0, 0.0, 0.0]);
        }
        let s = env.physical_state();
        assert!((s[3] - 1.0).abs() < 1e-9, "{s:?}");
        assert!(s[4].abs() < 1e-9 && s[5].abs() < 1e-9, "{s:?}");
    }

    /// Left alone with its servos holding zero speed, the arm sags under gravity and comes to
    /// rest hanging down, losing energy on every action: the explicit damping is stable even
    /// from violent starts.
    #[test]
    fn damped_arm_comes_to_rest_from_anywhere() {
        let mut env = Ur5Reacher::new();
        let mut rng = Rng::seed_from(13);
        for _ in 0..20 {
            let state: Vec<f64> = (0..6)
                .map(|i| {
                    let scale = if i < JOINTS { PI } else { 10.0 };
                    (rng.unit_f64() * 2.0 - 1.0) * scale
                })
                .collect();
            env.set_physical_state(&state).unwrap();
            let mut energy = env.energy();
            // 60 s: the overdamped elbow creeps down with a time constant of about 4 s.
            for _ in 0..2000 {
                env.step(&[0.0; 3]);
                let now = env.energy();
                assert!(now <= energy + 1e-9, "energy rose from {energy} to {now}");
                energy = now;
            }
            let s = env.physical_state();
            assert!(
                s[3..].iter().all(|v| v.abs() < 1e-3),
                "{s:?} from {state:?}"
            );
            // Upper arm and forearm straight down: both centres of mass at their lowest.
            let pose = env.pose();
            assert!(pose.com(1).z < pose.origin(1).z - 0.27, "{s:?}");
            assert!(pose.com(2).z < pose.origin(2).z - 0.24, "{s:?}");
        }
    }

    #[test]
    fn servo_torque_is_clipped() {
        let t = servo_torque(
            &Vector3::new(3.0, -5.0, 1.0),
            &Vector3::new(-20.0, 30.0, 0.5),
        );
        assert_eq!(t, Vector3::new(150.0, -150.0, 5.0));
    }

    #[test]
    fn controls_are_clipped_and_ignored_when_unactuated() {
        let (mut a, mut b) = (Ur5Reacher::new(), Ur5Reacher::new());
        a.step(&[3.15, -5.0, 3.15]);
        b.step(&[9.0, -9.0, 9.0]);
        assert_eq!(a.physical_state(), b.physical_state());
        let (mut c, mut d) = (free(9.81), free(9.81));
        c.step(&[3.0, 5.0, 3.0]);
        d.step(&[-3.0, -5.0, -3.0]);
        assert_eq!(c.physical_state(), d.physical_state());
    }

    #[test]
    fn projections_land_inside_subgoal_bounds() {
        let mut env = Ur5Reacher::new();
        let bounds = env.spec().subgoal_bounds.clone();
        let mut sub = [0.0f32; 6];
        let mut end = [0.0f32; 3];
        let mut check = |env: &Ur5Reacher, state: &[f32]| {
            env.project_subgoal(state, &mut sub);
            assert!(bounds.contains(&sub), "{sub:?}");
            env.project_end_goal(state, &mut end);
            assert_eq!(end, sub[..3]);
        };
        for edge in [
            [PI, -PI, PI, 100.0, -100.0, 4.0],
            [PI - 1e-9, -PI + 1e-9, 0.0, -4.0, 0.0, 1e9],
            [7.0, -20.0, 1e6, 0.0, 0.0, 0.0],
        ] {
            env.set_physical_state(&edge).unwrap();
            check(&env, env.state());
        }
        // States from elsewhere (not wrapped by this environment) are wrapped by the projection.
        check(&env, &[10.0, -7.0, 3.2, 5.0, -5.0, 0.0]);
        let mut rng = Rng::seed_from(7);
        for _ in 0..10 {
            env.reset(&mut rng);
            for _ in 0..300 {
                let action: Vec<f32> = CONTROL_LIMITS.iter().map(|&c| rng.uniform(-c, c)).collect();
                env.step(&action);
                check(&env, env.state());
            }
        }
    }

    #[test]
    fn projection_keeps_angles_and_clips_speeds() {
        let mut env = Ur5Reacher::new();
        env.set_physical_state(&[0.5, -2.5, PI, 6.0, -1.5, -9.0])
            .unwrap();
        let mut sub = [0.0f32; 6];
        env.project_subgoal(env.state(), &mut sub);
        assert_eq!(sub, [0.5, -2.5, PI_F32, 4.0, -1.5, -4.0]);
        let mut end = [0.0f32; 3];
        env.project_end_goal(&[-PI_F32, 3.5, 0.0, 0.0, 0.0, 0.0], &mut end);
        assert_eq!(end[0], -PI_F32);
        assert!((end[1] - (3.5 - TAU_F32)).abs() < 1e-6, "{end:?}");
    }

    #[test]
    fn subgoal_angles_anywhere_in_the_bounds_are_reached_along_the_circle() {
        let mut env = Ur5Reacher::new();
        let spec = env.spec().clone();
        assert_eq!(spec.end_goal_angles, [true; 3]);
        assert_eq!(spec.subgoal_angles, [true, true, true, false, false, false]);
        let reached = |env: &Ur5Reacher, goal: &[f32]| {
            let mut sub = [0.0f32; 6];
            env.project_subgoal(env.state(), &mut sub);
            hac_core::within_goal(&sub, goal, &spec.subgoal_thresholds, &spec.subgoal_angles)
        };
        // The arm at (-2.28, 2.5, 0.2) rad, the pan turning at 1 rad/s.
        env.set_physical_state(&[4.0 - TAU, 2.5, 0.2, 1.0, 0.0, 0.0])
            .unwrap();
        // A subgoal of 4.0 rad (inside the +-2pi bounds) names the pan's direction; so does a lift
        // of 2.5 - 2pi. Within 10 degrees and 2 rad/s on every dimension.
        assert!(reached(&env, &[4.0, 2.5, 0.2, 1.0, 0.0, 0.0]));
        assert!(reached(&env, &[4.1, 2.5 - TAU_F32, 0.3, 2.5, -1.5, 1.9]));
        // Still 10 degrees: 0.2 rad off the pan is missed, and speeds do not wrap.
        assert!(!reached(&env, &[4.2, 2.5, 0.2, 1.0, 0.0, 0.0]));
        assert!(!reached(&env, &[4.0, 2.5, 0.2, 1.0 + TAU_F32, 0.0, 0.0]));
        // Across the seam: an end goal at 3.1 rad is reached by a pan at -3.12 rad.
        env.set_physical_state(&[-3.12, 0.0, 0.0, 0.0, 0.0, 0.0])
            .unwrap();
        let mut end = [0.0f32; 3];
        env.project_end_goal(env.state(), &mut end);
        let goal = [3.1, 0.0, 0.0];
        assert!(hac_core::within_goal(
            &end,
            &goal,
            &spec.end_goal_thresholds,
            &spec.end_goal_angles
        ));
    }

    #[test]
    fn initial_states_follow_their_distribution() {
        let mut env = Ur5Reacher::new();
        let mut rng = Rng::seed_from(3);
        let (mut low, mut high) = (0.0f64, 0.0f64);
        for _ in 0..1000 {
            env.reset(&mut rng);
            let s = env.physical_state();
            assert!(s[0].abs() <= FRAC_PI_8 + 1e-6, "{s:?}");
            assert_eq!(s[1..], [0.00322757851, -0.127944547, 0.0, 0.0, 0.0]);
            (low, high) = (low.min(s[0]), high.max(s[0]));
        }
        assert!(low < -0.9 * FRAC_PI_8 && high > 0.9 * FRAC_PI_8);
    }

    /// Goal samples obey the redraw rule, checked with the reference's closed-form heights rather
    /// than this environment's kinematics; and the rule does reject part of the box.
    #[test]
    fn end_goal_samples_satisfy_the_redraw_rules() {
        let env = Ur5Reacher::new();
        let elbow = |g: &[f32]| 0.089159 - 0.425 * f64::from(g[1]).sin();
        let wrist = |g: &[f32]| elbow(g) - 0.39225 * f64::from(g[1] + g[2]).sin();
        let mut rng = Rng::seed_from(11);
        let mut g = [0.0f32; 3];
        let (mut negative_pan, mut positive_pan) = (0, 0);
        for mode in [Mode::Train, Mode::Test] {
            for _ in 0..2000 {
                env.sample_end_goal(&mut rng, mode, &mut g);
                let pan = f64::from(g[0]);
                assert!(pan.abs() > FRAC_PI_4 && pan.abs() <= PI + 1e-6, "{g:?}");
                assert!((-FRAC_PI_4 as f32..=0.0).contains(&g[1]), "{g:?}");
                assert!(g[2].abs() <= FRAC_PI_4 as f32, "{g:?}");
                assert!(elbow(&g) > 0.05 && wrist(&g) > 0.15, "{g:?}");
                if pan < 0.0 {
                    negative_pan += 1;
                } else {
                    positive_pan += 1;
                }
            }
        }
        assert!(negative_pan > 1500 && positive_pan > 1500);
        // Lift level and elbow bent down: the wrist dips to -0.19 m.
        assert!(!env.is_valid_end_goal(&[2.0, 0.0, FRAC_PI_4 as f32]));
        assert!(!env.is_valid_end_goal(&[0.5, -0.5, 0.0]));
        assert!(env.is_valid_end_goal(&[2.0, -0.5, 0.0]));
    }

    #[test]
    fn same_seed_same_trajectory() {
        let run = |seed| {
            let mut env = Ur5Reacher::new();
            let mut rng = Rng::seed_from(seed);
            env.reset(&mut rng);
            let mut goal = [0.0f32; 3];
            env.sample_end_goal(&mut rng, Mode::Train, &mut goal);
            let mut trace: Vec<u32> = goal.iter().map(|x| x.to_bits()).collect();
            for _ in 0..200 {
                let action = [
                    rng.uniform(-3.15, 3.15),
                    rng.uniform(-5.0, 5.0),
                    rng.uniform(-3.15, 3.15),
                ];
                env.step(&action);
                trace.extend(env.state().iter().map(|x| x.to_bits()));
            }
            trace
        };
        assert_eq!(run(5), run(5));
        assert_ne!(run(5), run(6));
    }

    #[test]
    fn set_physical_state_rejects_bad_input() {
        let mut env = Ur5Reacher::new();
        assert!(matches!(
            env.set_physical_state(&[0.0; 3]),
            Err(StateError::WrongLength {
                expected: 6,
                got: 3,
                ..
            })
        ));
        assert!(matches!(
            env.set_physical_state(&[0.0; 7]),
            Err(StateError::WrongLength { got: 7, .. })
        ));
        assert!(
            env.set_physical_state(&[0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0])
                .is_err()
        );
        assert!(
            env.set_physical_state(&[0.0, 0.0, 0.0, 0.0, 0.0, f64::INFINITY])
                .is_err()
        );
        env.set_physical_state(&[7.0, -4.0, 0.5, 1.0, 2.0, 3.0])
            .unwrap();
        let s = env.physical_state();
        assert!((s[0] - (7.0 - 2.0 * PI)).abs() < 1e-12);
        assert!((s[1] - (2.0 * PI - 4.0)).abs() < 1e-12);
        assert_eq!(s[2..], [0.5, 1.0, 2.0, 3.0]);
        assert_eq!(env.state()[3..], [1.0, 2.0, 3.0]);
    }
}
