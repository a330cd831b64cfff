//! Cart-pole swing-up: swing a hanging pole upright on a cart and hold it still over a goal
//! position, integrated directly from the two-body rigid model.
//!
//! A cart of mass M = 1 kg slides along x (no rail limits, no contacts). A uniform rod of length
//! 1 m and mass m = 0.1 kg is hinged at the cart's origin about the y axis: its centre of mass
//! lies l = 0.5 m from the hinge, its inertia about that centre is I_c = m L^2 / 12 = 1/120
//! kg m^2, so about the hinge J = I_c + m l^2 = 1/30 kg m^2. q is the pole's angle from upright
//! (+z); a positive q tips the top toward +x (right-handed about +y). With the rod's centre at
//! `(x + l sin q, l cos q)`, the Lagrangian
//!
//! ```text
//! T = 1/2 (M + m) xdot^2 + m l cos q xdot qdot + 1/2 J qdot^2,   V = m g l cos q
//! ```
//!
//! gives the equations of motion
//!
//! ```text
//! [ M + m        m l cos q ] [ xddot ]   [ F - b_x xdot + m l sin q qdot^2 ]
//! [ m l cos q    J         ] [ qddot ] = [ m g l sin q - b_q qdot          ]
//!
//! F = 10 clip(control, -1, 1) N,  b_x = 0.05 N s/m (slider),  b_q = 0.01 N m s/rad (hinge),
//! g = 9.81 m/s^2,  det = (M + m) J - (m l cos q)^2 >= 1.1/30 - 0.0025 > 0.
//! ```
//!
//! A push toward +x tips the pole toward -x (the off-diagonal term), and gravity tips it further
//! from upright. Linearised about hanging (q = pi + phi) with no force or damping, the cart's
//! equation gives `(M + m) xddot = m l phiddot`, and the pole's then swings at
//!
//! ```text
//! omega^2 = m g l (M + m) / ((M + m) J - m^2 l^2)   (3.974 rad/s, period 1.581 s),
//! ```
//!
//! faster than on a fixed pivot (`m g l / J`, period 1.638 s) because the cart recoils.
//!
//! Semi-implicit Euler with dt = 0.005 s (both velocities from the current positions first, then
//! the positions from the new velocities), 4 steps per primitive action (0.02 s). Damping is
//! explicit like every other force. The mass matrix depends on q, so this velocity-form Euler is
//! not symplectic: left free the energy is off by O(dt) (the tests check that halving dt halves
//! it). Physics runs in f64; observations and goals are f32.
//!
//! State `[x, cos q, sin q, xdot, qdot]`; end goal `[x, q, qdot]`, subgoal `[x, q, xdot, qdot]`,
//! angles wrapped to (-pi, pi] and compared along the circle in goal checks. Goals clip the
//! velocities (xdot to +-5 m/s, qdot to +-15 rad/s) and leave x as it is: the cart has no rail,
//! so a hindsight subgoal can lie beyond the +-2.5 m the actors propose in.
//!
//! Boxes for admitting actors' transitions (`state_bounds` and the goal boxes): the momentum along
//! x changes only by the force and the slider's damping, so after t seconds |p| <= 10 t; over an
//! episode of 20 s that bounds the cart below about 190 m/s once the pole's share (at most
//! m l |qdot|, with |qdot| below 100 rad/s) is counted. The boxes say 200 m/s, and positions
//! `0.2 + 200 m/s * episode length` (they follow `max_actions`). Random bang-bang control stays
//! far inside them (tested in the crate root).

use std::f32::consts::PI as PI_F32;

use hac_core::{AgentConfig, Bounds, Env, EnvSpec, Mode, Rng};

use crate::{StateError, check_physical_state, stated_horizon, wrap_angle};

/// Mass of the cart, kg.
pub const CART_MASS: f64 = 1.0;
/// Mass of the pole (a uniform rod), kg.
pub const POLE_MASS: f64 = 0.1;
/// Length of the pole, m.
pub const POLE_LENGTH: f64 = 1.0;
/// Distance from the hinge to the pole's centre of mass, m.
pub const HALF_LENGTH: f64 = 0.5 * POLE_LENGTH;
/// The pole's moment of inertia about the hinge: a rod's m L^2 / 12 about its centre plus
/// m l^2, kg m^2.
pub const HINGE_INERTIA: f64 =
    POLE_MASS * POLE_LENGTH * POLE_LENGTH / 12.0 + POLE_MASS * HALF_LENGTH * HALF_LENGTH;
/// Force on the cart per unit of control, N.
pub const FORCE_GAIN: f64 = 10.0;
/// Integration timestep, s.
pub const TIMESTEP: f64 = 0.005;

const TOTAL_MASS: f64 = CART_MASS + POLE_MASS;
const PHYSICS_STEPS_PER_ACTION: usize = 4;
/// Half ranges of the subgoal space: x, q, xdot, qdot.
const SUBGOAL_LIMITS: [f32; 4] = [2.5, PI_F32, 5.0, 15.0];
const MAX_ACTIONS: usize = 1000;
/// Speeds the admission boxes allow (see the module doc), m/s and rad/s.
const MAX_CART_SPEED: f32 = 200.0;
const MAX_POLE_SPEED: f32 = 100.0;

/// The physical constants a test may want to change; masses and geometry stay fixed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CartPolePhysics {
    /// Viscous damping of the cart on its slider, N s/m.
    pub slider_damping: f64,
    /// Viscous damping of the hinge, N m s/rad.
    pub hinge_damping: f64,
    /// Gravitational acceleration along -z, m/s^2.
    pub gravity: f64,
    /// When false the actuator is disconnected and nothing pushes the cart whatever the action.
    pub actuated: bool,
}

impl Default for CartPolePhysics {
    fn default() -> Self {
        Self {
            slider_damping: 0.05,
            hinge_damping: 0.01,
            gravity: 9.81,
            actuated: true,
        }
    }
}

/// The cart-pole swing-up task. Until the first `reset` it rests at x = 0 with the pole hanging.
#[derive(Debug, Clone)]
pub struct CartPole {
    spec: EnvSpec,
    physics: CartPolePhysics,
    x: f64,
    /// Pole angle from upright, wrapped to (-pi, pi].
    q: f64,
    xdot: f64,
    qdot: f64,
    /// `[x, cos q, sin q, xdot, qdot]`, refreshed after every change of the physical state.
    observation: [f32; 5],
}

impl Default for CartPole {
    fn default() -> Self {
        Self::new()
    }
}

impl CartPole {
    /// Registry name.
    pub const NAME: &'static str = "cartpole";

    /// The task with the standard physics.
    pub fn new() -> Self {
        Self::with_physics(CartPolePhysics::default())
    }

    /// The task with overridden physical constants (the spec and defaults are unchanged).
    pub fn with_physics(physics: CartPolePhysics) -> Self {
        let mut env = Self {
            spec: spec(),
            physics,
            x: 0.0,
            q: std::f64::consts::PI,
            xdot: 0.0,
            qdot: 0.0,
            observation: [0.0; 5],
        };
        env.observe();
        env
    }

    pub fn physics(&self) -> &CartPolePhysics {
        &self.physics
    }

    /// `[x, q, xdot, qdot]` at full precision (the layout `set_physical_state` takes).
    pub fn physical_state(&self) -> [f64; 4] {
        [self.x, self.q, self.xdot, self.qdot]
    }

    /// Mechanical energy: the kinetic energy of cart and rod plus the rod's potential energy
    /// `m g l cos q` (zero with its centre at the hinge's height), J.
    pub fn energy(&self) -> f64 {
        let kinetic = 0.5 * TOTAL_MASS * self.xdot * self.xdot
            + POLE_MASS * HALF_LENGTH * self.q.cos() * self.xdot * self.qdot
            + 0.5 * HINGE_INERTIA * self.qdot * self.qdot;
        kinetic + POLE_MASS * self.physics.gravity * HALF_LENGTH * self.q.cos()
    }

    /// Linear momentum of cart and rod along x, `(M + m) xdot + m l cos q qdot`, kg m/s: only
    /// the actuator and the slider's damping change it (the hinge's damping is internal).
    pub fn momentum(&self) -> f64 {
        TOTAL_MASS * self.xdot + POLE_MASS * HALF_LENGTH * self.q.cos() * self.qdot
    }

    /// One semi-implicit Euler step of `dt` under cart force `force`.
    fn integrate(&mut self, force: f64, dt: f64) {
        let CartPolePhysics {
            slider_damping,
            hinge_damping,
            gravity,
            ..
        } = self.physics;
        let (sin, cos) = self.q.sin_cos();
        let ml = POLE_MASS * HALF_LENGTH;
        let coupling = ml * cos;
        let rhs_x = force - slider_damping * self.xdot + ml * sin * self.qdot * self.qdot;
        let rhs_q = ml * gravity * sin - hinge_damping * self.qdot;
        // Cramer's rule on the 2x2 mass matrix.
        let det = TOTAL_MASS * HINGE_INERTIA - coupling * coupling;
        let xddot = (HINGE_INERTIA * rhs_x - coupling * rhs_q) / det;
        let qddot = (TOTAL_MASS * rhs_q - coupling * rhs_x) / det;
        self.xdot += dt * xddot;
        self.qdot += dt * qddot;
        self.x += dt * self.xdot;
        self.q = wrap_angle(self.q + dt * self.qdot);
    }

    fn observe(&mut self) {
        let (sin, cos) = self.q.sin_cos();
        self.observation = [
            self.x as f32,
            cos as f32,
            sin as f32,
            self.xdot as f32,
            self.qdot as f32,
        ];
    }
}

fn spec() -> EnvSpec {
    let angle_threshold = 10f32.to_radians();
    let mut spec = EnvSpec {
        name: CartPole::NAME.to_string(),
        description: "cart-pole swing-up: swing the pole up and hold it still over a goal \
                      position on the rail"
            .to_string(),
        state_dim: 5,
        action_bounds: Bounds::symmetric(&[1.0]),
        end_goal_dim: 3,
        end_goal_thresholds: vec![0.1, angle_threshold, 1.0],
        subgoal_bounds: Bounds::symmetric(&SUBGOAL_LIMITS),
        subgoal_thresholds: vec![0.1, angle_threshold, 0.5, 1.0],
        // The pole angle is compared along the circle, positions and speeds as numbers.
        end_goal_angles: vec![false, true, false],
        subgoal_angles: vec![false, true, false, false],
        subgoal_wrapped: Vec::new(),
        state_bounds: Bounds::symmetric(&[0.0, 1.0, 1.0, MAX_CART_SPEED, MAX_POLE_SPEED]),
        end_goal_bounds: Bounds::symmetric(&[0.0, PI_F32, SUBGOAL_LIMITS[3]]),
        achieved_subgoal_bounds: Bounds::symmetric(&[
            0.0,
            PI_F32,
            SUBGOAL_LIMITS[2],
            SUBGOAL_LIMITS[3],
        ]),
        max_actions: MAX_ACTIONS,
        physics_steps_per_action: PHYSICS_STEPS_PER_ACTION,
    };
    set_position_bounds(&mut spec);
    spec
}

/// Sets the position range of the admission boxes for the spec's episode budget: the cart
/// starts within 0.2 m and moves slower than [`MAX_CART_SPEED`].
fn set_position_bounds(spec: &mut EnvSpec) {
    let seconds = spec.max_actions as f64 * PHYSICS_STEPS_PER_ACTION as f64 * TIMESTEP;
    let reach = (0.2 + f64::from(MAX_CART_SPEED) * seconds) as f32;
    for bounds in [
        &mut spec.state_bounds,
        &mut spec.end_goal_bounds,
        &mut spec.achieved_subgoal_bounds,
    ] {
        bounds.low[0] = -reach;
        bounds.high[0] = reach;
    }
}

/// The pole angle of an observation, in (-pi, pi] like the state's.
fn observed_angle(state: &[f32]) -> f32 {
    let q = state[2].atan2(state[1]);
    // atan2 can return -pi (for sin q = -0).
    if q <= -PI_F32 { PI_F32 } else { q }
}

impl Env for CartPole {
    /// Puts the cart-pole at `[x, q, xdot, qdot]` (m, radians from upright, wrapped; m/s, rad/s;
    /// all finite).
    fn set_physical_state(&mut self, state: &[f64]) -> Result<(), StateError> {
        check_physical_state(Self::NAME, state, &[(f64::MIN, f64::MAX); 4])?;
        self.x = state[0];
        self.q = wrap_angle(state[1]);
        self.xdot = state[2];
        self.qdot = state[3];
        self.observe();
        Ok(())
    }

    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn set_max_actions(&mut self, max_actions: usize) {
        self.spec.max_actions = max_actions;
        set_position_bounds(&mut self.spec);
    }

    fn set_subgoal_bounds(&mut self, bounds: Bounds) {
        self.spec.subgoal_bounds = bounds;
    }

    /// The pendulum's H per level count (1000 / 32 / 10 for 1 / 2 / 3 levels) and the reference
    /// values for everything else.
    fn default_config(&self, levels: usize) -> AgentConfig {
        let horizon = stated_horizon(levels, self.spec.max_actions, [32, 10]);
        // Noise 0.1 and 0.1 of the half range, 200 episodes stored, 50 training episodes between
        // test rounds, no target networks.
        AgentConfig::reference(levels, horizon)
    }

    /// x uniform in [-0.2, 0.2] m, the pole hanging within 0.2 rad of straight down, at rest.
    fn reset(&mut self, rng: &mut Rng) {
        self.x = f64::from(rng.uniform(-0.2, 0.2));
        self.q = wrap_angle(f64::from(rng.uniform(PI_F32 - 0.2, PI_F32 + 0.2)));
        self.xdot = 0.0;
        self.qdot = 0.0;
        self.observe();
    }

    fn state(&self) -> &[f32] {
        &self.observation
    }

    fn step(&mut self, action: &[f32]) {
        let force = if self.physics.actuated {
            FORCE_GAIN * f64::from(action[0].clamp(-1.0, 1.0))
        } else {
            0.0
        };
        for _ in 0..PHYSICS_STEPS_PER_ACTION {
            self.integrate(force, TIMESTEP);
        }
        self.observe();
    }

    /// `[x, q, qdot clipped to +-15]`.
    fn project_end_goal(&self, state: &[f32], out: &mut [f32]) {
        out[0] = state[0];
        out[1] = observed_angle(state);
        out[2] = state[4].clamp(-SUBGOAL_LIMITS[3], SUBGOAL_LIMITS[3]);
    }

    /// `[x, q, xdot, qdot]`, the velocities clipped to the subgoal bounds.
    fn project_subgoal(&self, state: &[f32], out: &mut [f32]) {
        out[0] = state[0];
        out[1] = observed_angle(state);
        out[2] = state[3].clamp(-SUBGOAL_LIMITS[2], SUBGOAL_LIMITS[2]);
        out[3] = state[4].clamp(-SUBGOAL_LIMITS[3], SUBGOAL_LIMITS[3]);
    }

    /// Training and test alike: x uniform in [-1, 1] m, the pole upright and still.
    fn sample_end_goal(&self, rng: &mut Rng, _mode: Mode, out: &mut [f32]) {
        out[0] = rng.uniform(-1.0, 1.0);
        out[1] = 0.0;
        out[2] = 0.0;
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;

    use super::*;

    fn free() -> CartPole {
        CartPole::with_physics(CartPolePhysics {
            slider_damping: 0.0,
            hinge_damping: 0.0,
            actuated: false,
            ..CartPolePhysics::default()
        })
    }

    /// Energy above the hanging rest position, the scale of a swing's own energy.
    fn swing_energy(env: &CartPole) -> f64 {
        env.energy() + POLE_MASS * env.physics().gravity * HALF_LENGTH
    }

    /// The worst relative error of the swing energy over `seconds` of free motion from a large
    /// swing with a moving cart, integrated with timestep `dt`.
    fn worst_energy_error(dt: f64, seconds: f64) -> f64 {
        let mut env = free();
        env.set_physical_state(&[0.0, 2.0, 0.3, 1.0]).unwrap();
        let e0 = swing_energy(&env);
        let mut worst = 0.0f64;
        for _ in 0..(seconds / dt).round() as usize {
            env.integrate(0.0, dt);
            worst = worst.max(((swing_energy(&env) - e0) / e0).abs());
        }
        worst
    }

    fn worst_momentum_error(dt: f64, seconds: f64) -> (f64, f64) {
        let mut env = CartPole::with_physics(CartPolePhysics {
            slider_damping: 0.0,
            actuated: false,
            ..CartPolePhysics::default()
        });
        env.set_physical_state(&[0.0, 2.0, 0.3, 1.0]).unwrap();
        let p0 = env.momentum();
        let mut worst = 0.0f64;
        for _ in 0..(seconds / dt).round() as usize {
            env.integrate(0.0, dt);
            worst = worst.max((env.momentum() - p0).abs());
        }
        (worst, p0)
    }

    fn deviation_from_bottom(env: &CartPole) -> f64 {
        wrap_angle(env.physical_state()[1] - PI)
    }

    #[test]
    fn constants_match_the_model() {
        assert!((HINGE_INERTIA - 1.0 / 30.0).abs() < 1e-15);
        assert!(
            (HINGE_INERTIA - POLE_MASS * HALF_LENGTH * HALF_LENGTH - 1.0 / 120.0).abs() < 1e-15
        );
        assert_eq!(TOTAL_MASS, 1.1);
        let p = CartPolePhysics::default();
        assert_eq!(
            (p.slider_damping, p.hinge_damping, p.gravity, p.actuated),
            (0.05, 0.01, 9.81, true)
        );
    }

    #[test]
    fn spec_matches_the_task() {
        let env = CartPole::new();
        let s = env.spec();
        assert_eq!(s.name, "cartpole");
        assert_eq!(s.state_dim, 5);
        assert_eq!(s.action_bounds, Bounds::new(vec![-1.0], vec![1.0]));
        assert_eq!(s.end_goal_dim, 3);
        assert_eq!(s.end_goal_thresholds, vec![0.1, 10f32.to_radians(), 1.0]);
        assert_eq!(s.subgoal_dim(), 4);
        assert_eq!(
            s.subgoal_bounds,
            Bounds::new(
                vec![-2.5, -PI_F32, -5.0, -15.0],
                vec![2.5, PI_F32, 5.0, 15.0]
            )
        );
        assert_eq!(
            s.subgoal_thresholds,
            vec![0.1, 10f32.to_radians(), 0.5, 1.0]
        );
        assert_eq!(s.end_goal_angles, vec![false, true, false]);
        assert_eq!(s.subgoal_angles, vec![false, true, false, false]);
        assert_eq!(s.max_actions, 1000);
        assert_eq!(s.physics_steps_per_action, 4);
        assert_eq!(TIMESTEP * s.physics_steps_per_action as f64, 0.02);
    }

    #[test]
    fn default_horizons_and_noise() {
        let env = CartPole::new();
        let h: Vec<usize> = (1..=5).map(|k| env.default_config(k).horizon).collect();
        assert_eq!(h, [1000, 32, 10, 6, 4]);
        let c = env.default_config(2);
        assert_eq!(c, CartPole::new().default_config(2));
        assert_eq!(c.action_noise, hac_core::Noise::Relative(0.1));
        assert_eq!(c.subgoal_noise, hac_core::Noise::Relative(0.1));
        assert_eq!(c.episodes_to_store, 200);
        assert_eq!(c.exploration_episodes, 50);
        assert_eq!(c, crate::Pendulum::new().default_config(2));
    }

    /// With the mass matrix depending on q, velocity-form Euler is first order in energy: over
    /// 10 s of a large swing with a moving cart (several swings) the energy is off by at most
    /// 1.45% at dt, and halving dt halves that (measured ratio 1.99), so the error is the
    /// integrator's O(dt) and not a modelling mistake (which would not shrink with dt).
    #[test]
    fn free_motion_conserves_energy_to_first_order() {
        let coarse = worst_energy_error(TIMESTEP, 10.0);
        let fine = worst_energy_error(TIMESTEP / 2.0, 10.0);
        assert!(coarse < 1.6e-2, "energy relative error {coarse}");
        let ratio = coarse / fine;
        assert!((1.8..2.2).contains(&ratio), "halving dt: ratio {ratio}");
    }

    /// No force and no slider damping: nothing outside pushes along x, so the momentum of cart
    /// plus rod is constant (the hinge's damping is internal and stays on). Discretely it is off
    /// by O(dt): 2.5e-3 kg m/s at dt from 0.31 over 10 s, half that at dt / 2.
    #[test]
    fn momentum_along_x_is_conserved_without_force_or_slider_damping() {
        let (coarse, p0) = worst_momentum_error(TIMESTEP, 10.0);
        let (fine, _) = worst_momentum_error(TIMESTEP / 2.0, 10.0);
        assert!(p0 > 0.3, "{p0}");
        assert!(coarse < 3e-3, "momentum error {coarse}");
        let ratio = coarse / fine;
        assert!((1.8..2.2).contains(&ratio), "halving dt: ratio {ratio}");
        // The slider's damping does change it: the cart slows.
        let mut damped = CartPole::with_physics(CartPolePhysics {
            actuated: false,
            ..CartPolePhysics::default()
        });
        damped.set_physical_state(&[0.0, PI, 1.0, 0.0]).unwrap();
        let before = damped.momentum();
        for _ in 0..50 {
            damped.step(&[0.0]);
        }
        assert!(damped.momentum() < 0.96 * before, "{}", damped.momentum());
    }

    /// Linearised about hanging with a free cart: omega^2 = m g l (M + m) / ((M + m) J - m^2 l^2)
    /// (see the module doc), not the fixed pivot's m g l / J.
    #[test]
    fn small_swing_period_matches_the_free_cart_analysis() {
        let mut env = free();
        env.set_physical_state(&[0.0, PI - 0.01, 0.0, 0.0]).unwrap();
        let ml = POLE_MASS * HALF_LENGTH;
        // (M + m) times the x of the centre of mass of cart and rod.
        let centre = |env: &CartPole| {
            let [x, q, ..] = env.physical_state();
            TOTAL_MASS * x + ml * q.sin()
        };
        let c0 = centre(&env);
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
        let mgl = POLE_MASS * env.physics().gravity * HALF_LENGTH;
        let omega2 = mgl * TOTAL_MASS / (TOTAL_MASS * HINGE_INERTIA - ml * ml);
        let expected = 2.0 * PI / omega2.sqrt();
        assert!((expected - 1.5811).abs() < 1e-4, "{expected}");
        let rel = (measured - expected).abs() / expected;
        // Semi-implicit Euler on the linearised system runs fast by (omega dt)^2 / 24 = 1.6e-5;
        // the 0.01 rad amplitude slows it by a few 1e-6 (measured 8e-6 in all).
        assert!(rel < 2e-5, "period {measured} vs {expected} (rel {rel})");
        let fixed_pivot = 2.0 * PI * (HINGE_INERTIA / mgl).sqrt();
        assert!(
            (measured - fixed_pivot) / fixed_pivot < -0.03,
            "{measured} vs {fixed_pivot}"
        );
        // The cart recoils against the swing and keeps the centre of mass still.
        let drift = (centre(&env) - c0).abs();
        assert!(
            drift < 1e-3 * c0,
            "centre of mass moved by {drift} from {c0}"
        );
    }

    #[test]
    fn a_push_tips_the_pole_back_and_gravity_tips_it_over() {
        // Upright at rest, pushed toward +x: the cart moves right, the pole tips toward -x.
        let mut env = CartPole::new();
        env.set_physical_state(&[0.0, 0.0, 0.0, 0.0]).unwrap();
        env.step(&[1.0]);
        let [x, q, xdot, qdot] = env.physical_state();
        assert!(x > 0.0 && xdot > 0.0, "{x} {xdot}");
        assert!(q < 0.0 && qdot < 0.0, "{q} {qdot}");
        // The first physics step's accelerations are the model's: with sin q = 0 and no speed,
        // det = (M + m) J - m^2 l^2, xddot = J F / det, qddot = -m l F / det.
        let mut env = CartPole::new();
        env.set_physical_state(&[0.0, 0.0, 0.0, 0.0]).unwrap();
        env.integrate(FORCE_GAIN, TIMESTEP);
        let ml = POLE_MASS * HALF_LENGTH;
        let det = TOTAL_MASS * HINGE_INERTIA - ml * ml;
        let [_, _, xdot, qdot] = env.physical_state();
        assert!((xdot - TIMESTEP * HINGE_INERTIA * FORCE_GAIN / det).abs() < 1e-15);
        assert!((qdot + TIMESTEP * ml * FORCE_GAIN / det).abs() < 1e-15);
        // Slightly right of upright, no force: gravity tips it further right, and the cart
        // recoils left.
        let mut env = free();
        env.set_physical_state(&[0.0, 0.1, 0.0, 0.0]).unwrap();
        env.step(&[0.0]);
        let [x, q, xdot, qdot] = env.physical_state();
        assert!(q > 0.1 && qdot > 0.0, "{q} {qdot}");
        assert!(x < 0.0 && xdot < 0.0, "{x} {xdot}");
    }

    #[test]
    fn hanging_at_rest_stays() {
        let mut env = CartPole::new();
        env.set_physical_state(&[0.5, PI, 0.0, 0.0]).unwrap();
        for _ in 0..1000 {
            env.step(&[0.0]);
            // sin(PI) is 1.2e-16, not 0: the pole may sway by rounding, no more.
            assert!(deviation_from_bottom(&env).abs() < 1e-12);
            assert!((env.physical_state()[0] - 0.5).abs() < 1e-12);
        }
        let s = env.state();
        assert!((s[0] - 0.5).abs() < 1e-7 && (s[1] + 1.0).abs() < 1e-7 && s[2].abs() < 1e-7);
    }

    #[test]
    fn force_is_clipped_and_ignored_when_unactuated() {
        let mut a = CartPole::new();
        let mut b = CartPole::new();
        a.step(&[1.0]);
        b.step(&[50.0]);
        assert_eq!(a.physical_state(), b.physical_state());
        assert!(a.physical_state()[2] > 0.0);
        let mut c = free();
        let mut d = free();
        c.step(&[1.0]);
        d.step(&[-1.0]);
        assert_eq!(c.physical_state(), d.physical_state());
    }

    #[test]
    fn same_seed_same_trajectory() {
        let run = |seed| {
            let mut env = CartPole::new();
            let mut rng = Rng::seed_from(seed);
            env.reset(&mut rng);
            let mut trace = Vec::new();
            for _ in 0..500 {
                env.step(&[rng.uniform(-1.0, 1.0)]);
                trace.extend(env.state().iter().map(|x| x.to_bits()));
            }
            trace
        };
        assert_eq!(run(5), run(5));
        assert_ne!(run(5), run(6));
    }

    #[test]
    fn initial_states_follow_their_distribution() {
        let mut env = CartPole::new();
        let mut rng = Rng::seed_from(3);
        let (mut left, mut right) = (0, 0);
        for _ in 0..1000 {
            env.reset(&mut rng);
            let [x, q, xdot, qdot] = env.physical_state();
            assert!(x.abs() <= 0.2, "{x}");
            assert!(q > -PI && q <= PI, "{q}");
            assert!(deviation_from_bottom(&env).abs() <= 0.2 + 1e-6, "{q}");
            assert_eq!((xdot, qdot), (0.0, 0.0));
            // Hanging either side of straight down wraps to opposite ends of (-pi, pi].
            if q < 0.0 {
                left += 1;
            } else {
                right += 1;
            }
        }
        assert!(left > 400 && right > 400, "{left} {right}");
    }

    #[test]
    fn end_goals_are_upright_and_still_over_a_uniform_x() {
        let env = CartPole::new();
        let mut rng = Rng::seed_from(11);
        let mut g = [0.0f32; 3];
        for mode in [Mode::Train, Mode::Test] {
            let (mut low, mut high) = (f32::MAX, f32::MIN);
            for _ in 0..1000 {
                env.sample_end_goal(&mut rng, mode, &mut g);
                assert!(g[0].abs() <= 1.0, "{g:?}");
                assert_eq!((g[1], g[2]), (0.0, 0.0));
                low = low.min(g[0]);
                high = high.max(g[0]);
            }
            assert!(low < -0.95 && high > 0.95, "{mode:?}: {low} {high}");
        }
    }

    #[test]
    fn set_physical_state_round_trips_and_refuses_bad_input() {
        let mut env = CartPole::new();
        env.set_physical_state(&[0.3, 7.0, -1.5, 2.0]).unwrap();
        let [x, q, xdot, qdot] = env.physical_state();
        assert_eq!((x, xdot, qdot), (0.3, -1.5, 2.0));
        assert!((q - (7.0 - 2.0 * PI)).abs() < 1e-12, "{q}");
        let s = env.state();
        let expected = [0.3, q.cos() as f32, q.sin() as f32, -1.5, 2.0];
        assert_eq!(s, expected);
        env.set_physical_state(&[-4.0, -PI, 0.0, 0.0]).unwrap();
        assert_eq!(env.physical_state()[1], PI);
        for wrong in [&[0.0; 3][..], &[0.0; 5][..], &[]] {
            assert!(matches!(
                env.set_physical_state(wrong),
                Err(StateError::WrongLength { expected: 4, .. })
            ));
        }
        for index in 0..4 {
            for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                let mut state = [0.0; 4];
                state[index] = bad;
                assert!(matches!(
                    env.set_physical_state(&state),
                    Err(StateError::OutOfRange { index: i, .. }) if i == index
                ));
            }
        }
        // A refused state leaves the environment where it was.
        assert_eq!(env.physical_state(), [-4.0, PI, 0.0, 0.0]);
    }

    #[test]
    fn projections_recover_the_angle_and_clip_the_velocities() {
        let mut env = CartPole::new();
        let mut end = [0.0f32; 3];
        let mut sub = [0.0f32; 4];
        env.set_physical_state(&[0.7, -2.5, 1.0, -3.0]).unwrap();
        env.project_end_goal(env.state(), &mut end);
        env.project_subgoal(env.state(), &mut sub);
        assert!((end[1] + 2.5).abs() < 1e-6 && (sub[1] + 2.5).abs() < 1e-6);
        assert_eq!((end[0], end[2]), (0.7, -3.0));
        assert_eq!((sub[0], sub[2], sub[3]), (0.7, 1.0, -3.0));
        env.set_physical_state(&[-9.0, 0.5, 8.0, 20.0]).unwrap();
        env.project_end_goal(env.state(), &mut end);
        env.project_subgoal(env.state(), &mut sub);
        assert_eq!((end[0], end[2]), (-9.0, 15.0));
        assert_eq!((sub[0], sub[2], sub[3]), (-9.0, 5.0, 15.0));
        // A state with sin q = -0 projects to +pi, not -pi.
        env.project_end_goal(&[0.0, -1.0, -0.0, 0.0, 0.0], &mut end);
        assert_eq!(end[1], PI_F32);
        // Random rollouts and edge states stay inside the achieved-subgoal box (x beyond the
        // subgoal bounds included).
        let bounds = env.spec().achieved_subgoal_bounds.clone();
        for edge in [[30.0, PI, -30.0, 100.0], [-30.0, -PI + 1e-9, 30.0, -100.0]] {
            env.set_physical_state(&edge).unwrap();
            env.project_subgoal(env.state(), &mut sub);
            assert!(bounds.contains(&sub), "{sub:?}");
        }
        let mut rng = Rng::seed_from(7);
        for _ in 0..10 {
            env.reset(&mut rng);
            for _ in 0..200 {
                env.step(&[rng.uniform(-1.0, 1.0)]);
                env.project_subgoal(env.state(), &mut sub);
                assert!(bounds.contains(&sub), "{sub:?}");
            }
        }
    }

    /// The pole angle is compared along the circle: hanging just left of straight down reaches
    /// a goal just right of it, across the seam at +-pi.
    #[test]
    fn goal_test_compares_the_angle_along_the_circle() {
        let mut env = CartPole::new();
        let mut end = [0.0f32; 3];
        let mut sub = [0.0f32; 4];
        let spec = env.spec().clone();
        env.set_physical_state(&[0.0, PI - 0.05, 0.0, 0.0]).unwrap();
        env.project_end_goal(env.state(), &mut end);
        env.project_subgoal(env.state(), &mut sub);
        let (thresholds, angles) = spec.goal_test(true);
        let across = [0.05, -PI_F32 + 0.05, 0.5];
        assert!(hac_core::within_goal(&end, &across, thresholds, angles));
        assert!(
            !hac_core::within(&end, &across, thresholds),
            "plain numbers differ"
        );
        let (thresholds, angles) = spec.goal_test(false);
        let across = [0.05, -PI_F32 + 0.05, 0.4, -0.9];
        assert!(hac_core::within_goal(&sub, &across, thresholds, angles));
        assert!(!hac_core::within(&sub, &across, thresholds));
        // Upright within 10 degrees either side of 0, and not beyond.
        let (thresholds, angles) = spec.goal_test(true);
        for (q, reached) in [(0.17, true), (-0.17, true), (0.18, false), (-0.18, false)] {
            env.set_physical_state(&[0.0, q, 0.0, 0.0]).unwrap();
            env.project_end_goal(env.state(), &mut end);
            let ok = hac_core::within_goal(&end, &[0.0, 0.0, 0.0], thresholds, angles);
            assert_eq!(ok, reached, "q = {q}");
        }
    }
}
