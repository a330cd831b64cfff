//! Test support: an independent f64 evaluation of an [`Mlp`] and central-difference gradients.
//!
//! Finite differences in f32 are too noisy to check gradients tightly, so the reference gradient
//! is taken on an f64 copy of the network (same parameters, widened), where a step of 1e-6 leaves
//! an error around 1e-9: far below the f32 rounding of the analytic gradient being checked.

use hac_core::Rng;

use crate::Mlp;

/// Step of the central differences.
const FD_STEP: f64 = 1e-6;

/// The network's parameter tensors, widened to f64, in the order of [`Mlp::tensors`].
pub fn params_f64(mlp: &Mlp) -> Vec<Vec<f64>> {
    mlp.tensors()
        .map(|t| t.iter().map(|&v| f64::from(v)).collect())
        .collect()
}

/// The linear output (`output x n`, column-major) of a network with layer widths `sizes` and
/// parameters `params` on the column-major input `x`, computed sample by sample in f64.
pub fn reference_forward(sizes: &[usize], params: &[Vec<f64>], x: &[f64], n: usize) -> Vec<f64> {
    let layers = sizes.len() - 1;
    let mut out = Vec::new();
    for j in 0..n {
        let mut a: Vec<f64> = x[j * sizes[0]..(j + 1) * sizes[0]].to_vec();
        for l in 0..layers {
            let (inp, width) = (sizes[l], sizes[l + 1]);
            let (w, b) = (&params[2 * l], &params[2 * l + 1]);
            let mut z: Vec<f64> = (0..width)
                .map(|i| b[i] + (0..inp).map(|k| w[i + k * width] * a[k]).sum::<f64>())
                .collect();
            if l + 1 < layers {
                z.iter_mut().for_each(|v| *v = v.max(0.0));
            }
            a = z;
        }
        out.extend(a);
    }
    out
}

/// Central-difference gradient of `f` with respect to every entry of `x`.
pub fn fd_gradient(x: &mut [f64], mut f: impl FnMut(&[f64]) -> f64) -> Vec<f64> {
    (0..x.len())
        .map(|i| {
            let keep = x[i];
            x[i] = keep + FD_STEP;
            let up = f(x);
            x[i] = keep - FD_STEP;
            let down = f(x);
            x[i] = keep;
            (up - down) / (2.0 * FD_STEP)
        })
        .collect()
}

/// Central-difference gradients of `f` with respect to every entry of every tensor of `params`.
pub fn fd_param_gradients(
    params: &mut [Vec<f64>],
    mut f: impl FnMut(&[Vec<f64>]) -> f64,
) -> Vec<Vec<f64>> {
    (0..params.len())
        .map(|t| {
            (0..params[t].len())
                .map(|i| {
                    let keep = params[t][i];
                    params[t][i] = keep + FD_STEP;
                    let up = f(params);
                    params[t][i] = keep - FD_STEP;
                    let down = f(params);
                    params[t][i] = keep;
                    (up - down) / (2.0 * FD_STEP)
                })
                .collect()
        })
        .collect()
}

/// Asserts that `analytic` matches `reference` to a relative 1e-4 of the largest reference
/// entry: loose enough for f32 sums over a batch, tight enough to catch any wrong term.
pub fn assert_grad_close(analytic: &[f32], reference: &[f64], what: &str) {
    assert_eq!(analytic.len(), reference.len(), "{what}: length");
    let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(scale > 0.0, "{what}: reference gradient is zero");
    for (i, (&a, &r)) in analytic.iter().zip(reference).enumerate() {
        let err = (f64::from(a) - r).abs();
        assert!(
            err <= 1e-4 * scale,
            "{what}[{i}]: analytic {a}, finite differences {r} (scale {scale})"
        );
    }
}

/// `len` draws uniform in `[-scale, scale)`.
pub fn uniform_vec(rng: &mut Rng, len: usize, scale: f32) -> Vec<f32> {
    (0..len).map(|_| rng.uniform(-scale, scale)).collect()
}

pub fn widen(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}
