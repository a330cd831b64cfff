//! The critic `Q(s, g, a)`: an MLP on `[state, goal, action]` whose output is bounded to
//! `[-H, 0]` as `-H * sigmoid(x + q_offset)`.
//!
//! Every reward is -1 or 0 and a level gets at most `H` attempts, so a value outside `[-H, 0]`
//! cannot be right. `q_offset = -ln(H / 0.067 - 1)` makes the untrained critic (whose `x` is about
//! 0) answer about -0.067: optimistic, which drives exploration.

use std::ops::Range;

use hac_core::{LevelDims, Rng};

use crate::checkpoint::{TensorReader, TensorWriter};
use crate::kernels::copy_rows;
use crate::mlp::MlpTransposed;
use crate::{Mlp, MlpGrads, MlpWorkspace, NnError};

/// Minus the critic's value at `x = 0`, whatever the horizon.
pub const INITIAL_Q: f32 = 0.067;

/// A level's action-value function.
#[derive(Debug, Clone)]
pub struct CriticNet {
    dims: LevelDims,
    mlp: Mlp,
    horizon: f32,
    q_offset: f32,
}

impl CriticNet {
    /// A freshly initialised critic for a level with `dims` and horizon `horizon` (H), with
    /// hidden layers of the given widths.
    ///
    /// Panics unless `horizon > 0.067` (the offset is undefined otherwise).
    pub fn new(dims: LevelDims, horizon: f32, hidden: &[usize], rng: &mut Rng) -> Self {
        let sizes: Vec<usize> = std::iter::once(dims.state + dims.goal + dims.action)
            .chain(hidden.iter().copied())
            .chain(std::iter::once(1))
            .collect();
        Self::from_parts(dims, Mlp::new(&sizes, rng), horizon)
    }

    fn from_parts(dims: LevelDims, mlp: Mlp, horizon: f32) -> Self {
        assert!(
            horizon > INITIAL_Q,
            "critic: horizon must exceed {INITIAL_Q}, got {horizon}"
        );
        let q_offset = -(f64::from(horizon) / f64::from(INITIAL_Q) - 1.0).ln() as f32;
        Self {
            dims,
            mlp,
            horizon,
            q_offset,
        }
    }

    /// The level's state, goal and action widths.
    pub fn dims(&self) -> LevelDims {
        self.dims
    }

    /// The network before the output bounding.
    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    /// H: the bound of the output range `[-H, 0]`.
    pub fn horizon(&self) -> f32 {
        self.horizon
    }

    /// The constant added before the sigmoid, `-ln(H / 0.067 - 1)`.
    pub fn q_offset(&self) -> f32 {
        self.q_offset
    }

    pub(crate) fn mlp_mut(&mut self) -> &mut Mlp {
        &mut self.mlp
    }

    /// The input rows holding the action.
    pub(crate) fn action_rows(&self) -> Range<usize> {
        let start = self.dims.state + self.dims.goal;
        start..start + self.dims.action
    }

    /// Fills the state and goal rows of `ws`'s input with the batch columns.
    pub(crate) fn fill_state_goal(&self, ws: &mut MlpWorkspace, states: &[f32], goals: &[f32]) {
        let LevelDims { state, goal, .. } = self.dims;
        let rows = self.mlp.input_dim();
        copy_rows(ws.input_mut(), rows, 0, states, state);
        copy_rows(ws.input_mut(), rows, state, goals, goal);
    }

    /// Fills the action rows of `ws`'s input with the batch columns.
    pub(crate) fn fill_actions(&self, ws: &mut MlpWorkspace, actions: &[f32]) {
        let rows = self.mlp.input_dim();
        let start = self.action_rows().start;
        copy_rows(ws.input_mut(), rows, start, actions, self.dims.action);
    }

    /// Forward pass on a batch; leaves `Q` in `ws.output()` and `dQ/dx` for
    /// [`CriticNet::backward_batch`] in `ws`.
    ///
    /// The slope is `-H s (1 - s)` with `s = sigmoid(x + q_offset)`. The reference computes it
    /// from the output, as `Q (1 + Q / H)` (TensorFlow's `y (1 - y)`); in f32 `s` rounds to 1
    /// from `x + q_offset` of about 17, and there the slope is exactly zero: a critic that reads
    /// `-H` on a sample cannot learn that sample again, however wrong, and gives an actor there
    /// no gradient. With `exact_slope` it is computed from `x` (see [`sigmoid_and_complement`]),
    /// exact until `exp` underflows near `x + q_offset = 100`.
    pub(crate) fn forward_batch(&self, ws: &mut MlpWorkspace, exact_slope: bool) {
        self.mlp.forward(ws);
        let (h, off) = (self.horizon, self.q_offset);
        let (out, slope) = ws.output_and_slope_mut();
        let pairs = out.iter_mut().zip(slope);
        if exact_slope {
            for (v, d) in pairs {
                let (s, one_minus_s) = sigmoid_and_complement(*v + off);
                *v = -h * s;
                *d = -h * s * one_minus_s;
            }
        } else {
            let inv_h = 1.0 / h;
            for (v, d) in pairs {
                let q = -h / (1.0 + (-(*v + off)).exp());
                *v = q;
                *d = q * (1.0 + q * inv_h);
            }
        }
    }

    /// Back-propagates the loss gradient with respect to `Q`, given in `ws.output_grad_mut()`
    /// (consumed). With `grads`, sets it to the parameter gradient; with `action_grad`, leaves the
    /// gradient with respect to the action in `ws.input_grad()` (`action x batch`). `transposed`:
    /// the network's transposed weights, if kept (see [`Mlp::backward_with`]).
    pub(crate) fn backward_batch(
        &self,
        ws: &mut MlpWorkspace,
        grads: Option<&mut MlpGrads>,
        action_grad: bool,
        transposed: Option<&MlpTransposed>,
    ) {
        let (g, slope) = ws.grad_and_slope_mut();
        for (g, d) in g.iter_mut().zip(slope) {
            *g *= d;
        }
        let rows = if action_grad {
            self.action_rows()
        } else {
            0..0
        };
        self.mlp.backward_with(ws, grads, rows, transposed);
    }

    pub(crate) fn write(&self, prefix: &str, out: &mut TensorWriter) {
        self.mlp.write(&format!("{prefix}layers."), out);
        out.meta(format!("{prefix}state_dim"), self.dims.state);
        out.meta(format!("{prefix}goal_dim"), self.dims.goal);
        out.meta(format!("{prefix}horizon"), self.horizon);
    }

    pub(crate) fn read(prefix: &str, file: &TensorReader<'_>) -> Result<Self, NnError> {
        let mlp = Mlp::read(&format!("{prefix}layers."), file)?;
        let state: usize = file.meta(&format!("{prefix}state_dim"))?;
        let goal: usize = file.meta(&format!("{prefix}goal_dim"))?;
        let horizon: f32 = file.meta(&format!("{prefix}horizon"))?;
        if horizon.is_nan() || horizon <= INITIAL_Q {
            return Err(NnError::Metadata {
                key: format!("{prefix}horizon"),
                reason: format!("must exceed {INITIAL_Q}, got {horizon}"),
            });
        }
        let layers = mlp.layers();
        let (first, last) = (&layers[0], &layers[layers.len() - 1]);
        if first.inp <= state + goal {
            return Err(NnError::Shape {
                name: format!("{prefix}layers.0.weight"),
                expected: format!("[_, more than state_dim + goal_dim = {}]", state + goal),
                found: vec![first.out, first.inp],
            });
        }
        if last.out != 1 {
            return Err(NnError::Shape {
                name: format!("{prefix}layers.{}.weight", layers.len() - 1),
                expected: "[1, _]".into(),
                found: vec![last.out, last.inp],
            });
        }
        let dims = LevelDims {
            state,
            goal,
            action: mlp.input_dim() - state - goal,
        };
        Ok(Self::from_parts(dims, mlp, horizon))
    }
}

/// `(sigmoid(x), 1 - sigmoid(x))`, each to full relative precision: `1 - s` stays the true, tiny,
/// value where `s` rounds to 1, and so does the slope made from it, which Adam's step scaling can
/// still act on.
fn sigmoid_and_complement(x: f32) -> (f32, f32) {
    if x >= 0.0 {
        let e = (-x).exp();
        (1.0 / (1.0 + e), e / (1.0 + e))
    } else {
        let e = x.exp();
        (e / (1.0 + e), 1.0 / (1.0 + e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{
        assert_grad_close, fd_gradient, fd_param_gradients, params_f64, reference_forward,
        uniform_vec, widen,
    };

    const DIMS: LevelDims = LevelDims {
        state: 3,
        goal: 2,
        action: 2,
    };

    /// Fills the input of `ws` with random `(s, g, a)`; returns it (`7 x n`).
    fn random_input(
        critic: &CriticNet,
        ws: &mut MlpWorkspace,
        rng: &mut Rng,
        scale: f32,
    ) -> Vec<f32> {
        let n = ws.batch();
        let states = uniform_vec(rng, DIMS.state * n, scale);
        let goals = uniform_vec(rng, DIMS.goal * n, scale);
        let actions = uniform_vec(rng, DIMS.action * n, scale);
        critic.fill_state_goal(ws, &states, &goals);
        critic.fill_actions(ws, &actions);
        ws.input_mut().to_vec()
    }

    #[test]
    fn backward_matches_finite_differences_for_parameters_and_action() {
        backward_matches_finite_differences(false);
        backward_matches_finite_differences(true);
    }

    fn backward_matches_finite_differences(exact_slope: bool) {
        let mut rng = Rng::seed_from(21);
        let horizon = 10.0;
        let mut critic = CriticNet::new(DIMS, horizon, &[8, 6], &mut rng);
        // Weights far from the small initial output layer, and an output bias that cancels the
        // offset, so that the sigmoid is far from linear.
        let q_offset = critic.q_offset();
        for t in critic.mlp_mut().tensors_mut() {
            t.copy_from_slice(&uniform_vec(&mut rng, t.len(), 0.7));
        }
        if let Some(bias) = critic.mlp_mut().tensors_mut().last() {
            bias[0] = -q_offset;
        }
        let n = 10;
        let mut ws = MlpWorkspace::new(critic.mlp(), n);
        let x = random_input(&critic, &mut ws, &mut rng, 1.0);
        let r = uniform_vec(&mut rng, n, 1.0);
        critic.forward_batch(&mut ws, exact_slope);
        ws.output_grad_mut().copy_from_slice(&r);
        let mut grads = MlpGrads::new(critic.mlp());
        critic.backward_batch(&mut ws, Some(&mut grads), true, None);

        // The loss sum(R * Q) on the f64 reference network.
        let sizes = critic.mlp().sizes();
        let (h, off, r) = (f64::from(horizon), f64::from(critic.q_offset()), widen(&r));
        let loss = |p: &[Vec<f64>], x: &[f64]| {
            let z = reference_forward(&sizes, p, x, n);
            z.iter()
                .zip(&r)
                .map(|(z, r)| r * -h / (1.0 + (-(z + off)).exp()))
                .sum::<f64>()
        };
        let mut x64 = widen(&x);
        let fd = fd_param_gradients(&mut params_f64(critic.mlp()), |p| loss(p, &x64));
        for (t, (got, want)) in grads.tensors().zip(&fd).enumerate() {
            assert_grad_close(got, want, &format!("critic tensor {t}"));
        }

        let p64 = params_f64(critic.mlp());
        let fd_x = fd_gradient(&mut x64, |x| loss(&p64, x));
        let want: Vec<f64> = (0..n)
            .flat_map(|j| critic.action_rows().map(move |i| i + j * 7))
            .map(|i| fd_x[i])
            .collect();
        assert_grad_close(ws.input_grad(), &want, "critic action gradient");
    }

    #[test]
    fn the_gradient_survives_where_the_output_rounds_to_minus_h() {
        let mut rng = Rng::seed_from(23);
        let horizon = 20.0;
        let mut critic = CriticNet::new(DIMS, horizon, &[8, 6], &mut rng);
        // An output bias that puts x + q_offset at about 25 (30 and 40 below): sigmoid rounds to
        // 1 in f32, as in a critic that rates everything at -H.
        let n = 16;
        let mut ws = MlpWorkspace::new(critic.mlp(), n);
        let x = random_input(&critic, &mut ws, &mut rng, 1.0);
        let q_offset = critic.q_offset();
        for lift in [25.0, 30.0, 40.0] {
            if let Some(bias) = critic.mlp_mut().tensors_mut().last() {
                bias[0] = lift - q_offset;
            }
            ws.input_mut().copy_from_slice(&x);
            critic.forward_batch(&mut ws, true);
            assert!(
                ws.output().iter().all(|&q| q == -horizon),
                "{:?}",
                ws.output()
            );
            ws.output_grad_mut().fill(1.0);
            let mut grads = MlpGrads::new(critic.mlp());
            critic.backward_batch(&mut ws, Some(&mut grads), true, None);

            // The output bias's gradient is the sum of dQ/dx = -H s (1 - s), here in f64 as
            // -H e / (1 + e)^2 with e = exp(-x) (1 - s itself rounds to 0 in f64 from x = 37).
            let z = reference_forward(
                &critic.mlp().sizes(),
                &params_f64(critic.mlp()),
                &widen(&x),
                n,
            );
            let want: f64 = z
                .iter()
                .map(|z| {
                    let e = (-(z + f64::from(q_offset))).exp();
                    -f64::from(horizon) * e / ((1.0 + e) * (1.0 + e))
                })
                .sum();
            let got = f64::from(grads.tensors().last().unwrap()[0]);
            assert!(want < 0.0);
            assert!(
                ((got - want) / want).abs() < 1e-4,
                "x + q_offset near {lift}: bias gradient {got}, want {want}"
            );
            // The action gradient is there too: the actor is not stuck either.
            assert!(ws.input_grad().iter().any(|&g| g != 0.0));

            // The reference's slope, from Q, is exactly zero here.
            critic.forward_batch(&mut ws, false);
            ws.output_grad_mut().fill(1.0);
            critic.backward_batch(&mut ws, Some(&mut grads), true, None);
            assert_eq!(grads.tensors().last().unwrap()[0], 0.0);
        }
    }

    #[test]
    fn starts_near_the_optimistic_value_and_stays_in_range() {
        let mut rng = Rng::seed_from(22);
        let n = 256;
        for horizon in [5.0, 10.0, 25.0] {
            let mut critic = CriticNet::new(DIMS, horizon, &[64, 64, 64], &mut rng);
            assert!((critic.q_offset() + (horizon / INITIAL_Q - 1.0).ln()).abs() < 1e-5);
            let mut ws = MlpWorkspace::new(critic.mlp(), n);
            random_input(&critic, &mut ws, &mut rng, 1.0);
            critic.forward_batch(&mut ws, false);
            for &q in ws.output() {
                assert!((q + INITIAL_Q).abs() < 0.01, "H {horizon}: initial Q {q}");
            }

            // Blown-up weights and inputs saturate the sigmoid at both ends.
            for t in critic.mlp_mut().tensors_mut() {
                t.iter_mut().for_each(|v| *v *= 30.0);
            }
            random_input(&critic, &mut ws, &mut rng, 100.0);
            critic.forward_batch(&mut ws, false);
            let q = ws.output();
            assert!(
                q.iter().all(|q| (-horizon..=0.0).contains(q)),
                "Q outside [-H, 0]"
            );
            assert!(q.iter().any(|&q| q < -0.99 * horizon) && q.iter().any(|&q| q > -0.01));
        }
    }
}
