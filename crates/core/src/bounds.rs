//! Boxes in R^n: primitive-action bounds, subgoal bounds.

use serde::{Deserialize, Serialize};

use crate::Rng;

/// An axis-aligned box `[low_d, high_d]` per dimension.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    pub low: Vec<f32>,
    pub high: Vec<f32>,
}

impl Bounds {
    /// A box from per-dimension limits; panics if they disagree in length or `low > high`.
    pub fn new(low: Vec<f32>, high: Vec<f32>) -> Self {
        assert_eq!(
            low.len(),
            high.len(),
            "bounds: low and high differ in length"
        );
        assert!(
            low.iter().zip(&high).all(|(l, h)| l <= h),
            "bounds: low above high"
        );
        Self { low, high }
    }

    /// The box `[-r_d, r_d]`.
    pub fn symmetric(radius: &[f32]) -> Self {
        Self::new(radius.iter().map(|r| -r).collect(), radius.to_vec())
    }

    pub fn dim(&self) -> usize {
        self.low.len()
    }

    /// A box of no dimensions (an unknown range, where a box is optional).
    pub fn is_empty(&self) -> bool {
        self.low.is_empty()
    }

    /// The smallest box holding both `self` and `other` (of the same dimension).
    pub fn hull(&self, other: &Bounds) -> Bounds {
        debug_assert_eq!(self.dim(), other.dim());
        Bounds {
            low: self
                .low
                .iter()
                .zip(&other.low)
                .map(|(a, b)| a.min(*b))
                .collect(),
            high: self
                .high
                .iter()
                .zip(&other.high)
                .map(|(a, b)| a.max(*b))
                .collect(),
        }
    }

    /// The box widened on each side by `fraction` of each dimension's width plus `absolute`.
    pub fn widened(&self, fraction: f32, absolute: f32) -> Bounds {
        let pad = |d: usize| fraction * (self.high[d] - self.low[d]) + absolute;
        Bounds {
            low: (0..self.dim()).map(|d| self.low[d] - pad(d)).collect(),
            high: (0..self.dim()).map(|d| self.high[d] + pad(d)).collect(),
        }
    }

    /// Centre of dimension `d` (the actor's output offset).
    pub fn offset(&self, d: usize) -> f32 {
        0.5 * (self.low[d] + self.high[d])
    }

    /// Half the width of dimension `d` (the actor's output scale).
    pub fn half_range(&self, d: usize) -> f32 {
        0.5 * (self.high[d] - self.low[d])
    }

    /// Clips `x` into the box in place.
    pub fn clip(&self, x: &mut [f32]) {
        debug_assert_eq!(x.len(), self.dim());
        for ((v, lo), hi) in x.iter_mut().zip(&self.low).zip(&self.high) {
            *v = v.clamp(*lo, *hi);
        }
    }

    /// Whether `x` lies in the box (boundaries included).
    pub fn contains(&self, x: &[f32]) -> bool {
        x.len() == self.dim()
            && x.iter()
                .zip(&self.low)
                .zip(&self.high)
                .all(|((v, lo), hi)| *lo <= *v && *v <= *hi)
    }

    /// Writes a uniform draw from the box into `out`.
    pub fn sample(&self, rng: &mut Rng, out: &mut [f32]) {
        debug_assert_eq!(out.len(), self.dim());
        for (d, o) in out.iter_mut().enumerate() {
            *o = rng.uniform(self.low[d], self.high[d]);
        }
    }
}

/// Whether `achieved` is within `threshold` of `goal` on every dimension (HAC's goal test).
pub fn within(achieved: &[f32], goal: &[f32], threshold: &[f32]) -> bool {
    within_goal(achieved, goal, threshold, &[])
}

/// Like [`within`], but the dimensions flagged in `angles` (radians; empty: none) are compared
/// along the circle: the difference is wrapped to `[-pi, pi]` first, so a goal angle names a
/// direction whatever turn it is written in (`3.0` is within 0.1 of `-3.2`, and `4.0` reaches
/// `4.0 - 2 pi`).
pub fn within_goal(achieved: &[f32], goal: &[f32], threshold: &[f32], angles: &[bool]) -> bool {
    debug_assert_eq!(achieved.len(), goal.len());
    debug_assert_eq!(goal.len(), threshold.len());
    debug_assert!(angles.is_empty() || angles.len() == goal.len());
    achieved
        .iter()
        .zip(goal)
        .zip(threshold)
        .enumerate()
        .all(|(d, ((a, g), t))| {
            let diff = a - g;
            let diff = if angles.get(d).copied().unwrap_or(false) {
                angle_difference(diff)
            } else {
                diff
            };
            diff.abs() <= *t
        })
}

/// `diff` wrapped to `[-pi, pi]`.
pub(crate) fn angle_difference(diff: f32) -> f32 {
    use std::f32::consts::{PI, TAU};
    if (-PI..=PI).contains(&diff) {
        diff
    } else {
        let r = diff.rem_euclid(TAU);
        if r > PI { r - TAU } else { r }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offset_half_range_clip() {
        let b = Bounds::new(vec![-1.0, 0.0], vec![3.0, 2.0]);
        assert_eq!(b.offset(0), 1.0);
        assert_eq!(b.half_range(0), 2.0);
        let mut x = [5.0, -1.0];
        b.clip(&mut x);
        assert_eq!(x, [3.0, 0.0]);
        assert!(b.contains(&x));
        assert!(!b.contains(&[3.1, 1.0]));
    }

    #[test]
    fn within_every_dimension() {
        assert!(within(&[0.0, 1.0], &[0.05, 1.15], &[0.1, 0.2]));
        assert!(!within(&[0.0, 1.0], &[0.1, 1.3], &[0.1, 0.2]));
    }

    #[test]
    fn angle_dimensions_compare_along_the_circle() {
        use std::f32::consts::{PI, TAU};
        let (t, angle) = (&[0.1, 0.1][..], &[true, false][..]);
        // Across the seam at +-pi: 0.08 apart as directions, 6.2 apart as numbers.
        assert!(within_goal(&[3.1, 0.0], &[-3.12, 0.0], t, angle));
        assert!(!within(&[3.1, 0.0], &[-3.12, 0.0], t));
        // A goal written one turn away names the same direction.
        assert!(within_goal(&[-2.0, 0.0], &[-2.0 + TAU, 0.0], t, angle));
        assert!(within_goal(&[2.0, 0.0], &[2.05 - TAU, 0.0], t, angle));
        assert!(!within_goal(&[2.0, 0.0], &[2.2 - TAU, 0.0], t, angle));
        // Only flagged dimensions wrap; the threshold still applies to the wrapped difference.
        assert!(!within_goal(&[0.0, 3.1], &[0.0, -3.12], t, angle));
        assert!(!within_goal(&[0.0, 0.0], &[PI, 0.0], t, angle));
        // No flags: the same as `within`.
        assert!(within_goal(&[0.0, 1.0], &[0.05, 1.05], t, &[]));
    }
}
