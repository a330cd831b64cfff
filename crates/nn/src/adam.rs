//! The Adam optimiser (Kingma & Ba 2015, Algorithm 1, with bias correction).

use crate::NnError;
use crate::checkpoint::{TensorReader, TensorWriter};
use crate::kernels::vectorized;

/// Decay of the first-moment estimate.
pub const BETA1: f32 = 0.9;
/// Decay of the second-moment estimate.
pub const BETA2: f32 = 0.999;
/// Added to the root of the corrected second moment, against division by zero.
pub const EPSILON: f32 = 1e-8;

/// Adam with `beta1 = 0.9`, `beta2 = 0.999`, `eps = 1e-8`, and one moment pair per parameter
/// tensor. One step with gradient `g` and step count `t` (from 1) does
/// `m <- b1 m + (1 - b1) g`, `v <- b2 v + (1 - b2) g^2`,
/// `p <- p - lr * (m / (1 - b1^t)) / (sqrt(v / (1 - b2^t)) + eps)`.
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    lr: f32,
    steps: u64,
    /// First and second moments, one entry per tensor.
    moments: Vec<(Vec<f32>, Vec<f32>)>,
}

impl Adam {
    /// An optimiser with learning rate `lr` for tensors of the given lengths.
    pub fn new(lr: f32, tensor_lens: impl IntoIterator<Item = usize>) -> Self {
        let moments = tensor_lens
            .into_iter()
            .map(|n| (vec![0.0; n], vec![0.0; n]))
            .collect();
        Self {
            lr,
            steps: 0,
            moments,
        }
    }

    /// The step size `lr`.
    pub fn learning_rate(&self) -> f32 {
        self.lr
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// The step count and both moments of every tensor (m then v, tensor by tensor): what a
    /// step changes, for [`crate::learner::LearnerBackup`].
    pub(crate) fn state_mut(&mut self) -> (&mut u64, impl Iterator<Item = &mut [f32]>) {
        let moments = self
            .moments
            .iter_mut()
            .flat_map(|(m, v)| [m.as_mut_slice(), v.as_mut_slice()]);
        (&mut self.steps, moments)
    }

    /// [`Adam::state_mut`], read-only.
    pub(crate) fn state(&self) -> (u64, impl Iterator<Item = &[f32]>) {
        let moments = self
            .moments
            .iter()
            .flat_map(|(m, v)| [m.as_slice(), v.as_slice()]);
        (self.steps, moments)
    }

    /// One step on every `(parameters, gradient)` pair, in the order given at construction.
    pub fn step<'a>(&mut self, tensors: impl IntoIterator<Item = (&'a mut [f32], &'a [f32])>) {
        let sizes = self.begin_step();
        let mut count = 0;
        for ((p, g), (m, v)) in tensors.into_iter().zip(&mut self.moments) {
            sizes.apply(p, g, m, v);
            count += 1;
        }
        debug_assert_eq!(count, self.moments.len(), "adam: tensor count changed");
    }

    /// Counts a step and returns its step sizes, for a step taken tensor by tensor
    /// ([`StepSizes::apply`] on each tensor and its [`moments`](Self::moments_mut), once each):
    /// the same floats as [`step`](Self::step).
    pub(crate) fn begin_step(&mut self) -> StepSizes {
        self.steps += 1;
        let t = self.steps as f64;
        StepSizes {
            step_size: (f64::from(self.lr) / (1.0 - f64::from(BETA1).powf(t))) as f32,
            inv_sqrt_bias2: (1.0 / (1.0 - f64::from(BETA2).powf(t)).sqrt()) as f32,
        }
    }

    /// The moments `(m, v)` of tensor `i` themselves, to be moved out (to another thread) and
    /// put back with [`std::mem::swap`].
    pub(crate) fn moments_mut(&mut self, i: usize) -> (&mut Vec<f32>, &mut Vec<f32>) {
        let (m, v) = &mut self.moments[i];
        (m, v)
    }

    /// Stores the moments as `{prefix}m.{i}` / `{prefix}v.{i}` and the step count as metadata.
    pub(crate) fn write(&self, prefix: &str, out: &mut TensorWriter) {
        out.meta(format!("{prefix}steps"), self.steps);
        for (i, (m, v)) in self.moments.iter().enumerate() {
            out.add(format!("{prefix}m.{i}"), &[m.len()], m);
            out.add(format!("{prefix}v.{i}"), &[v.len()], v);
        }
    }

    /// Restores what [`Adam::write`] stored into this optimiser, whose tensor lengths must match.
    pub(crate) fn read(&mut self, prefix: &str, file: &TensorReader<'_>) -> Result<(), NnError> {
        self.steps = file.meta(&format!("{prefix}steps"))?;
        for (i, (m, v)) in self.moments.iter_mut().enumerate() {
            file.read_into(&format!("{prefix}m.{i}"), m)?;
            file.read_into(&format!("{prefix}v.{i}"), v)?;
        }
        Ok(())
    }
}

/// The bias-corrected step sizes of one Adam step ([`Adam::begin_step`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct StepSizes {
    step_size: f32,
    inv_sqrt_bias2: f32,
}

impl StepSizes {
    /// The step on one tensor: parameters `p`, gradient `g`, moments `m` and `v`.
    pub(crate) fn apply(self, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
        debug_assert_eq!(p.len(), g.len());
        debug_assert_eq!(p.len(), m.len());
        debug_assert_eq!(p.len(), v.len());
        let Self {
            step_size,
            inv_sqrt_bias2,
        } = self;
        vectorized(
            #[inline(always)]
            || {
                for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                    *m = BETA1 * *m + (1.0 - BETA1) * g;
                    *v = BETA2 * *v + (1.0 - BETA2) * g * g;
                    *p -= step_size * *m / (v.sqrt() * inv_sqrt_bias2 + EPSILON);
                }
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_steps_match_hand_computation() {
        let lr = 0.01;
        let mut p = [1.0f32, -2.0, 0.5];
        let g1 = [0.5f32, -1.0, 0.0];
        let g2 = [0.25f32, 2.0, -3.0];
        let mut adam = Adam::new(lr, [3]);
        adam.step([(&mut p[..], &g1[..])]);
        // By hand: after one step m_hat = g and v_hat = g^2, so each parameter moves by lr against
        // the sign of its gradient, and not at all for a zero gradient.
        for (got, want) in p.iter().zip([0.99, -1.99, 0.5]) {
            assert!((got - want).abs() < 1e-6, "got {got}, want {want}");
        }
        adam.step([(&mut p[..], &g2[..])]);

        // The same two steps in f64, written out from the algorithm's definition.
        let (b1, b2, eps, lr) = (0.9f64, 0.999f64, 1e-8f64, f64::from(lr));
        let want: Vec<f64> = (0..3)
            .map(|i| {
                let (mut p, mut m, mut v) = ([1.0, -2.0, 0.5][i], 0.0, 0.0);
                for (t, g) in [(1, f64::from(g1[i])), (2, f64::from(g2[i]))] {
                    m = b1 * m + (1.0 - b1) * g;
                    v = b2 * v + (1.0 - b2) * g * g;
                    let m_hat = m / (1.0 - b1.powi(t));
                    let v_hat = v / (1.0 - b2.powi(t));
                    p -= lr * m_hat / (v_hat.sqrt() + eps);
                }
                p
            })
            .collect();
        for (got, want) in p.iter().zip(&want) {
            assert!(
                (f64::from(*got) - want).abs() < 1e-6,
                "got {got}, want {want}"
            );
        }
        assert_eq!(adam.steps(), 2);
    }
}
