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

    /// The moments `(m, v)` of tensor `i`, for [`StepSizes::apply`].
    pub(crate) fn moments_mut(&mut self, i: usize) -> (&mut [f32], &mut [f32]) {
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

/// The smallest normal `f32`, `2^-126`. Below it a result is subnormal, and on x86-64 an
/// instruction that produces or reads one takes a microcode assist (tens to hundreds of cycles,
/// where an ordinary one takes one). The first moment of a weight whose gradient stays 0 (a dead
/// ReLU unit's) decays by `BETA1` into that range and never leaves it: 0.9 times a few
/// subnormal units rounds back to the same value. With the plain formula `hac bench update`
/// spent 93-104 us per update in the optimiser steps on an Intel Xeon, where 32-49 us do now,
/// and a step over 17,600 such parameters took 300-600 us against 9-14 us for ordinary ones
/// (`cargo bench -p hac-nn --bench update -- adam`).
const MIN_NORMAL: f32 = f32::MIN_POSITIVE;
/// `2^126 = 1 / MIN_NORMAL`, exactly.
const INV_MIN_NORMAL: f32 = 1.0 / MIN_NORMAL;
/// The smallest moment kept as it is: below it `BETA1 * m` (or `BETA2 * v`) would be subnormal
/// (with a factor 2 of margin for rounding), so the moment counts as 0.
const MOMENT_MIN: f32 = 2.0 * MIN_NORMAL / BETA1;
/// The smallest gradient whose term in `m`, `(1 - BETA1) g`, is computed.
const GRAD_M_MIN: f32 = 2.0 * MIN_NORMAL / (1.0 - BETA1);
/// The smallest gradient whose term in `v`, `((1 - BETA2) g) g`, is computed:
/// `sqrt(2 MIN_NORMAL / (1 - BETA2))` (about 4.85e-18) rounded up. Below it the term would be
/// subnormal.
const GRAD_V_MIN: f32 = 4.9e-18;

impl StepSizes {
    /// The step on one tensor: parameters `p`, gradient `g`, moments `m` and `v`.
    ///
    /// Each element is the IEEE float of `m <- b1 m + (1 - b1) g`, `v <- b2 v + ((1 - b2) g) g`,
    /// `p <- p - (step_size m) / (sqrt(v) inv_sqrt_bias2 + eps)`, evaluated in that order, except
    /// that a product or quotient whose result would be subnormal (below about 2.4e-38, with
    /// margin) is taken as 0 instead of being computed (see [`MIN_NORMAL`] for why), and so is a
    /// moment too small to be multiplied by its decay. A term dropped so is below half the
    /// rounding step of any moment or parameter above about 4e-31 in magnitude, so those come
    /// out the same floats as with the plain formula; what changes is that moments this small
    /// read 0 instead of a subnormal (a moment whose two terms cancel can still land there; the
    /// next step reads it as 0). A dropped term moves a parameter's step by under about
    /// 1e-32, so a parameter can differ only where its exact step falls that close to a rounding
    /// boundary. NaN and infinities go through as before (a comparison with NaN is false).
    pub(crate) fn apply(self, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
        debug_assert_eq!(p.len(), g.len());
        debug_assert_eq!(p.len(), m.len());
        debug_assert_eq!(p.len(), v.len());
        let Self {
            step_size,
            inv_sqrt_bias2,
        } = self;
        // `step_size * m` is subnormal below this `|m|` (infinite for a zero step size: then
        // every step is 0, as the plain formula gives).
        let step_m_min = 2.0 * MIN_NORMAL / step_size;
        vectorized(
            #[inline(always)]
            || {
                for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                    // Selects, not branches, so that the loop vectorises.
                    let m_old = if m.abs() < MOMENT_MIN { 0.0 } else { *m };
                    let v_old = if *v < MOMENT_MIN { 0.0 } else { *v };
                    let g_m = if g.abs() < GRAD_M_MIN {
                        0.0
                    } else {
                        (1.0 - BETA1) * g
                    };
                    let g_v = if g.abs() < GRAD_V_MIN {
                        0.0
                    } else {
                        (1.0 - BETA2) * g * g
                    };
                    *m = BETA1 * m_old + g_m;
                    *v = BETA2 * v_old + g_v;
                    let scaled = if m.abs() < step_m_min {
                        0.0
                    } else {
                        step_size * *m
                    };
                    let denominator = v.sqrt() * inv_sqrt_bias2 + EPSILON;
                    // The exact `scaled / denominator` is below `MIN_NORMAL` exactly when this
                    // holds (the scaling by a power of two is exact).
                    *p -= if scaled.abs() * INV_MIN_NORMAL < denominator {
                        0.0
                    } else {
                        scaled / denominator
                    };
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

    /// The plain formula in `f32`, as the step computed it before it avoided subnormals, with the
    /// step sizes `sizes` (from [`Adam::begin_step`]).
    fn plain_step(sizes: StepSizes, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
        for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
            *m = BETA1 * *m + (1.0 - BETA1) * g;
            *v = BETA2 * *v + (1.0 - BETA2) * g * g;
            *p -= sizes.step_size * *m / (v.sqrt() * sizes.inv_sqrt_bias2 + EPSILON);
        }
    }

    #[test]
    fn the_step_keeps_the_plain_formulas_parameters_and_never_stores_a_subnormal() {
        // Gradients from ordinary down to subnormal and zero, then a long run of zeros (a dead
        // unit), which decays the moments through the subnormal range under the plain formula.
        let n = 64;
        let scales = [1.0f32, 1e-3, 1e-12, 3e-18, 1e-20, 1e-37, 1e-40, 0.0];
        let grad = |t: u64, i: usize| -> f32 {
            if t > 40 {
                return 0.0;
            }
            let sign = if (i + t as usize).is_multiple_of(3) {
                -1.0
            } else {
                1.0
            };
            sign * scales[i % scales.len()] * (1.0 + (i as f32) * 0.01)
        };
        let lr = 1e-3;
        let start: Vec<f32> = (0..n).map(|i| (i as f32 - 31.5) * 0.02).collect();
        let mut adam = Adam::new(lr, [n]);
        let mut p = start.clone();
        let (mut p_plain, mut m_plain, mut v_plain) = (start, vec![0.0f32; n], vec![0.0f32; n]);
        // Counts the steps of the plain formula, for its step sizes.
        let mut plain_steps = Adam::new(lr, []);
        let mut saw_subnormal_plain = false;
        for t in 1..=3000u64 {
            let g: Vec<f32> = (0..n).map(|i| grad(t, i)).collect();
            adam.step([(&mut p[..], &g[..])]);
            let sizes = plain_steps.begin_step();
            plain_step(sizes, &mut p_plain, &g, &mut m_plain, &mut v_plain);
            saw_subnormal_plain |= m_plain.iter().chain(&v_plain).any(|x| x.is_subnormal());
            assert_eq!(
                p, p_plain,
                "step {t}: the parameters left the plain formula's"
            );
            let (m, v) = &adam.moments[0];
            assert!(
                !m.iter().chain(v).any(|x| x.is_subnormal()),
                "step {t}: a subnormal moment was stored"
            );
        }
        assert!(
            saw_subnormal_plain,
            "the case no longer reaches subnormal moments"
        );
        assert!(GRAD_V_MIN >= (2.0 * MIN_NORMAL / (1.0 - BETA2)).sqrt());
    }

    #[test]
    fn a_nan_or_infinite_gradient_still_reaches_the_parameters() {
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut p = [0.5f32, -0.5];
            let mut adam = Adam::new(1e-3, [2]);
            adam.step([(&mut p[..], &[bad, 1e-3][..])]);
            assert!(!p[0].is_finite(), "gradient {bad} gave parameter {}", p[0]);
            assert!(p[1].is_finite());
        }
    }
}
