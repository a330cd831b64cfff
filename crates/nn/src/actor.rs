//! The actor `pi(s, g)`: an MLP on `[state, goal]` whose output is squashed into the level's
//! action (or subgoal) bounds as `tanh(x) * half_range + offset`, per dimension.
//!
//! The `tanh` is libm's, or, with [`ActorNet::with_saturating_tanh`], one that reads exactly
//! `+-1` from `|x| >= 7.9074` on, as TensorFlow's float `tanh` (Eigen's rational approximation,
//! clamped; the HAC reference code's arithmetic) does; libm's only rounds to `+-1` from `|x|` of
//! about 9.01, so between the two an output at its bound keeps a gradient `1 - tanh^2` of about
//! `5e-7` instead of none. Inside, the two differ by at most `3.5e-7`; this one is libm's there.

use hac_core::{Bounds, LevelDims, Rng};

use crate::checkpoint::{TensorReader, TensorWriter};
use crate::kernels::copy_rows;
use crate::mlp::MlpTransposed;
use crate::{Mlp, MlpGrads, MlpWorkspace, NnError};

/// Value of the `format` metadata entry of an actor file.
const FORMAT: &str = "hac-nn/actor";

/// `|x|` from which the saturating `tanh` reads exactly `+-1`: the smallest `f32` at which
/// TensorFlow's `tanh` (2.21, on x86-64) returns 1.
pub const TANH_SATURATION: f32 = 7.907_389_6;

/// `tanh(x)`, exactly `+-1` from `|x| >= TANH_SATURATION` on when `saturating`.
#[inline]
fn squash(x: f32, saturating: bool) -> f32 {
    if saturating && x.abs() >= TANH_SATURATION {
        1.0f32.copysign(x)
    } else {
        x.tanh()
    }
}

/// A level's deterministic policy. Cheap to clone and `Send`, so rollouts and remote actors can
/// hold their own copy; [`ActorNet::act`] allocates nothing.
#[derive(Debug, Clone)]
pub struct ActorNet {
    dims: LevelDims,
    mlp: Mlp,
    scale: Vec<f32>,
    offset: Vec<f32>,
    /// The `tanh` reads exactly `+-1` from `|x| >= TANH_SATURATION` on.
    saturating_tanh: bool,
    /// Buffers of the single-sample forward pass.
    single: MlpWorkspace,
}

impl ActorNet {
    /// A freshly initialised actor for a level with `dims`, acting within `bounds`, with hidden
    /// layers of the given widths.
    ///
    /// Panics if `bounds` does not have `dims.action` dimensions.
    pub fn new(dims: LevelDims, bounds: &Bounds, hidden: &[usize], rng: &mut Rng) -> Self {
        assert_eq!(
            bounds.dim(),
            dims.action,
            "actor: bounds have {} dimensions, the action {}",
            bounds.dim(),
            dims.action
        );
        let sizes: Vec<usize> = std::iter::once(dims.state + dims.goal)
            .chain(hidden.iter().copied())
            .chain(std::iter::once(dims.action))
            .collect();
        let mlp = Mlp::new(&sizes, rng);
        let scale = (0..dims.action).map(|d| bounds.half_range(d)).collect();
        let offset = (0..dims.action).map(|d| bounds.offset(d)).collect();
        Self::from_parts(dims, mlp, scale, offset)
    }

    fn from_parts(dims: LevelDims, mlp: Mlp, scale: Vec<f32>, offset: Vec<f32>) -> Self {
        let single = MlpWorkspace::new(&mlp, 1);
        Self {
            dims,
            mlp,
            scale,
            offset,
            saturating_tanh: false,
            single,
        }
    }

    /// The actor with the saturating `tanh` (exactly `+-1` from `|x| >= 7.9074` on, as in
    /// TensorFlow) when `on`, libm's otherwise (the default).
    pub fn with_saturating_tanh(mut self, on: bool) -> Self {
        self.saturating_tanh = on;
        self
    }

    /// Whether the output `tanh` saturates at `|x| >= 7.9074` (see
    /// [`ActorNet::with_saturating_tanh`]).
    pub fn saturating_tanh(&self) -> bool {
        self.saturating_tanh
    }

    /// The level's state, goal and action widths.
    pub fn dims(&self) -> LevelDims {
        self.dims
    }

    /// The network before the output squashing.
    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    /// Per-dimension output scale (the bounds' half range).
    pub fn output_scale(&self) -> &[f32] {
        &self.scale
    }

    /// Per-dimension output offset (the bounds' centre).
    pub fn output_offset(&self) -> &[f32] {
        &self.offset
    }

    /// Writes the greedy action `pi(state, goal)` into `out`.
    ///
    /// Panics if a slice's length does not match the actor's dimensions.
    pub fn act(&mut self, state: &[f32], goal: &[f32], out: &mut [f32]) {
        let LevelDims {
            state: s,
            goal: g,
            action: a,
        } = self.dims;
        assert!(
            state.len() == s && goal.len() == g && out.len() == a,
            "actor: expects state {s}, goal {g}, action {a} values"
        );
        let input = self.single.input_mut();
        input[..s].copy_from_slice(state);
        input[s..].copy_from_slice(goal);
        self.mlp.forward(&mut self.single);
        for (((o, &x), s), c) in out
            .iter_mut()
            .zip(self.single.output())
            .zip(&self.scale)
            .zip(&self.offset)
        {
            *o = squash(x, self.saturating_tanh) * s + c;
        }
    }

    /// The actor as a safetensors file: layers `layers.{l}.weight` (`[out, in]`) and
    /// `layers.{l}.bias`, `output_scale`, `output_offset`; metadata `format`, `state_dim`,
    /// `goal_dim`, and `saturating_tanh = true` when it is on (absent: libm's `tanh`).
    pub fn to_safetensors(&self) -> Vec<u8> {
        let mut out = TensorWriter::default();
        out.meta("format".into(), FORMAT);
        self.write("", &mut out);
        out.finish()
    }

    /// Reads what [`ActorNet::to_safetensors`] wrote; the architecture comes from the tensor
    /// shapes, which must be consistent with each other and with the metadata.
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self, NnError> {
        let file = TensorReader::new(bytes)?;
        file.expect_format(FORMAT)?;
        Self::read("", &file)
    }

    pub(crate) fn write(&self, prefix: &str, out: &mut TensorWriter) {
        self.mlp.write(&format!("{prefix}layers."), out);
        out.add(
            format!("{prefix}output_scale"),
            &[self.dims.action],
            &self.scale,
        );
        out.add(
            format!("{prefix}output_offset"),
            &[self.dims.action],
            &self.offset,
        );
        out.meta(format!("{prefix}state_dim"), self.dims.state);
        out.meta(format!("{prefix}goal_dim"), self.dims.goal);
        if self.saturating_tanh {
            out.meta(format!("{prefix}saturating_tanh"), true);
        }
    }

    pub(crate) fn read(prefix: &str, file: &TensorReader<'_>) -> Result<Self, NnError> {
        let mlp = Mlp::read(&format!("{prefix}layers."), file)?;
        let state: usize = file.meta(&format!("{prefix}state_dim"))?;
        let goal: usize = file.meta(&format!("{prefix}goal_dim"))?;
        if mlp.input_dim() != state + goal {
            return Err(NnError::Shape {
                name: format!("{prefix}layers.0.weight"),
                expected: format!("[_, {}] (state_dim + goal_dim)", state + goal),
                found: vec![mlp.layers()[0].out, mlp.input_dim()],
            });
        }
        let action = mlp.output_dim();
        let scale = file.read(&format!("{prefix}output_scale"), &[action])?;
        let offset = file.read(&format!("{prefix}output_offset"), &[action])?;
        let dims = LevelDims {
            state,
            goal,
            action,
        };
        let saturating_key = format!("{prefix}saturating_tanh");
        let saturating = if file.metadata().contains_key(&saturating_key) {
            file.meta(&saturating_key)?
        } else {
            false
        };
        Ok(Self::from_parts(dims, mlp, scale, offset).with_saturating_tanh(saturating))
    }

    pub(crate) fn mlp_mut(&mut self) -> &mut Mlp {
        &mut self.mlp
    }

    /// Fills `ws`'s input with the batch columns `[states; goals]`.
    pub(crate) fn fill_input(&self, ws: &mut MlpWorkspace, states: &[f32], goals: &[f32]) {
        let LevelDims { state, goal, .. } = self.dims;
        copy_rows(ws.input_mut(), state + goal, 0, states, state);
        copy_rows(ws.input_mut(), state + goal, state, goals, goal);
    }

    /// Forward pass on a batch; leaves `tanh(x)` (not yet scaled) in `ws.output()`, which
    /// [`ActorNet::write_actions`] and [`ActorNet::backward_batch`] use.
    pub(crate) fn forward_batch(&self, ws: &mut MlpWorkspace) {
        self.mlp.forward(ws);
        self.squash_output(ws);
    }

    /// Replaces the pre-activations in `ws.output()` by their `tanh`.
    fn squash_output(&self, ws: &mut MlpWorkspace) {
        let saturating = self.saturating_tanh;
        for v in ws.output_mut() {
            *v = squash(*v, saturating);
        }
    }

    /// [`ActorNet::forward_batch`] that also copies the pre-activations `x` (before `tanh`) into
    /// `pre` (resized to `action x batch`), for [`ActorNet::backward_batch`]'s penalty: at
    /// saturation `tanh(x)` rounds to 1 and cannot give `x` back.
    pub(crate) fn forward_batch_keeping_pre(&self, ws: &mut MlpWorkspace, pre: &mut Vec<f32>) {
        self.mlp.forward(ws);
        pre.clear();
        pre.extend_from_slice(ws.output());
        self.squash_output(ws);
    }

    /// Writes the actions of the last [`ActorNet::forward_batch`] into rows `row..row + action` of
    /// the column-major `dst_rows x batch` matrix `dst`.
    pub(crate) fn write_actions(
        &self,
        ws: &MlpWorkspace,
        dst: &mut [f32],
        dst_rows: usize,
        row: usize,
    ) {
        let a = self.dims.action;
        for (d, t) in dst
            .chunks_exact_mut(dst_rows)
            .zip(ws.output().chunks_exact(a))
        {
            for (((d, t), s), c) in d[row..row + a]
                .iter_mut()
                .zip(t)
                .zip(&self.scale)
                .zip(&self.offset)
            {
                *d = t * s + c;
            }
        }
    }

    /// Sets `grads` to the parameter gradient, given the loss gradient with respect to the actions
    /// in `ws.output_grad_mut()` (consumed).
    ///
    /// With `penalty = Some((pre, c, samples))` (`pre` from
    /// [`ActorNet::forward_batch_keeping_pre`]) the loss also holds `c sum(x^2) / (action x
    /// samples)`, the pre-activations' mean square over a minibatch of `samples` (of which `ws`
    /// may hold a part), whose gradient `2 c x / (action x samples)` still pulls a saturated
    /// output back where the action gradient through `tanh` has vanished.
    ///
    /// `transposed`: the network's transposed weights, if kept (see [`Mlp::backward_with`]).
    pub(crate) fn backward_batch(
        &self,
        ws: &mut MlpWorkspace,
        grads: &mut MlpGrads,
        penalty: Option<(&[f32], f32, usize)>,
        transposed: Option<&MlpTransposed>,
    ) {
        let a = self.dims.action;
        let (t, g) = ws.output_and_grad_mut();
        for (gc, tc) in g.chunks_exact_mut(a).zip(t.chunks_exact(a)) {
            for ((g, t), s) in gc.iter_mut().zip(tc).zip(&self.scale) {
                *g *= s * (1.0 - t * t);
            }
        }
        if let Some((pre, c, samples)) = penalty {
            assert_eq!(
                pre.len(),
                g.len(),
                "actor: pre-activations of another batch"
            );
            let k = 2.0 * c / (a * samples) as f32;
            for (g, x) in g.iter_mut().zip(pre) {
                *g += k * x;
            }
        }
        self.mlp.backward_with(ws, Some(grads), 0..0, transposed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{
        assert_grad_close, fd_param_gradients, params_f64, reference_forward, uniform_vec, widen,
    };

    const DIMS: LevelDims = LevelDims {
        state: 3,
        goal: 3,
        action: 2,
    };

    fn bounds() -> Bounds {
        Bounds::new(vec![-2.0, 1.0], vec![0.5, 3.0])
    }

    fn actor(seed: u64) -> ActorNet {
        ActorNet::new(DIMS, &bounds(), &[7, 8], &mut Rng::seed_from(seed))
    }

    /// Runs the batched forward pass and returns the actions, `action x n`.
    fn batch_actions(
        actor: &ActorNet,
        ws: &mut MlpWorkspace,
        states: &[f32],
        goals: &[f32],
    ) -> Vec<f32> {
        actor.fill_input(ws, states, goals);
        actor.forward_batch(ws);
        let mut a = vec![0.0; DIMS.action * ws.batch()];
        actor.write_actions(ws, &mut a, DIMS.action, 0);
        a
    }

    /// Checks [`ActorNet::backward_batch`] against finite differences of the loss
    /// `sum(R * action) + c mean(x^2)` (`x` the pre-activations; `c` 0 without a penalty) on the
    /// f64 reference network, with weights far from the small initial output layer so that tanh
    /// is far from linear.
    fn check_backward_against_finite_differences(seed: u64, penalty: Option<f32>) {
        let mut rng = Rng::seed_from(seed);
        let mut actor = actor(seed + 1);
        for t in actor.mlp_mut().tensors_mut() {
            t.copy_from_slice(&uniform_vec(&mut rng, t.len(), 0.7));
        }
        let n = 9;
        let states = uniform_vec(&mut rng, DIMS.state * n, 2.0);
        let goals = uniform_vec(&mut rng, DIMS.goal * n, 2.0);
        let r = uniform_vec(&mut rng, DIMS.action * n, 1.0);
        let mut ws = MlpWorkspace::new(actor.mlp(), n);
        let mut pre = Vec::new();
        actor.fill_input(&mut ws, &states, &goals);
        if penalty.is_some() {
            actor.forward_batch_keeping_pre(&mut ws, &mut pre);
            let tanh_of_pre: Vec<f32> = pre.iter().map(|x| x.tanh()).collect();
            assert_eq!(ws.output(), tanh_of_pre.as_slice());
        } else {
            actor.forward_batch(&mut ws);
        }
        ws.output_grad_mut().copy_from_slice(&r);
        let mut grads = MlpGrads::new(actor.mlp());
        actor.backward_batch(
            &mut ws,
            &mut grads,
            penalty.map(|c| (pre.as_slice(), c, n)),
            None,
        );

        let sizes = actor.mlp().sizes();
        let mut x = vec![0.0; (DIMS.state + DIMS.goal) * n];
        copy_rows(&mut x, 6, 0, &states, 3);
        copy_rows(&mut x, 6, 3, &goals, 3);
        let (x, r) = (widen(&x), widen(&r));
        let (scale, offset) = (widen(actor.output_scale()), widen(actor.output_offset()));
        let c = f64::from(penalty.unwrap_or(0.0));
        let loss = |p: &[Vec<f64>]| {
            let u = reference_forward(&sizes, p, &x, n);
            let actions: f64 = (0..u.len())
                .map(|i| r[i] * (u[i].tanh() * scale[i % 2] + offset[i % 2]))
                .sum();
            actions + c * u.iter().map(|u| u * u).sum::<f64>() / u.len() as f64
        };
        let fd = fd_param_gradients(&mut params_f64(actor.mlp()), loss);
        for (t, (got, want)) in grads.tensors().zip(&fd).enumerate() {
            assert_grad_close(got, want, &format!("actor tensor {t}"));
        }
    }

    #[test]
    fn backward_through_tanh_scaling_matches_finite_differences() {
        check_backward_against_finite_differences(10, None);
    }

    #[test]
    fn the_preactivation_penalty_adds_its_exact_gradient() {
        check_backward_against_finite_differences(14, Some(0.3));
    }

    #[test]
    fn act_matches_batch_and_stays_in_bounds() {
        let mut rng = Rng::seed_from(12);
        let mut actor = actor(13);
        // Large weights and inputs saturate the tanh: outputs must still be within bounds.
        for t in actor.mlp_mut().tensors_mut() {
            t.iter_mut().for_each(|v| *v *= 50.0);
        }
        let n = 16;
        let states = uniform_vec(&mut rng, DIMS.state * n, 100.0);
        let goals = uniform_vec(&mut rng, DIMS.goal * n, 100.0);
        let mut ws = MlpWorkspace::new(actor.mlp(), n);
        let batch = batch_actions(&actor, &mut ws, &states, &goals);
        let mut out = [0.0; 2];
        for j in 0..n {
            actor.act(
                &states[3 * j..3 * j + 3],
                &goals[3 * j..3 * j + 3],
                &mut out,
            );
            assert!(bounds().contains(&out), "{out:?} outside the bounds");
            for (a, b) in out.iter().zip(&batch[2 * j..2 * j + 2]) {
                assert!(
                    (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
                    "act {a} vs batch {b}"
                );
            }
        }
    }

    #[test]
    fn the_saturating_tanh_reads_exactly_one_from_its_edge_on() {
        assert_eq!(TANH_SATURATION.to_bits(), 0x40fd_0956, "7.9073896408081055");
        let below = f32::from_bits(TANH_SATURATION.to_bits() - 1);
        // libm's tanh is still below 1 from the edge up to about 9.01: what the switch changes.
        for x in [below, TANH_SATURATION, 8.0, 8.5, 9.0] {
            assert!(x.tanh() < 1.0, "libm tanh({x}) = {}", x.tanh());
            assert_eq!(squash(x, false), x.tanh());
            assert_eq!(squash(-x, false), (-x).tanh());
        }
        assert_eq!(9.5f32.tanh(), 1.0);
        assert_eq!(squash(below, true), below.tanh(), "libm's below the edge");
        assert!(squash(below, true) < 1.0);
        for x in [TANH_SATURATION, 8.0, 8.5, 9.0, 1e30, f32::INFINITY] {
            assert_eq!(squash(x, true), 1.0, "at {x}");
            assert_eq!(squash(-x, true), -1.0, "at -{x}");
        }
        assert!(squash(f32::NAN, true).is_nan());
    }

    /// An actor whose pre-activations are `pre` for every input: zero output weights.
    fn constant_actor(pre: f32, saturating: bool) -> ActorNet {
        let mut actor = actor(20).with_saturating_tanh(saturating);
        let mut tensors: Vec<&mut [f32]> = actor.mlp_mut().tensors_mut().collect();
        let n = tensors.len();
        tensors[n - 2].fill(0.0);
        tensors[n - 1].fill(pre);
        actor
    }

    #[test]
    fn a_saturating_actor_sits_on_its_bounds_with_no_gradient() {
        let (states, goals) = ([0.1, 0.2, 0.3], [0.4, 0.5, 0.6]);
        let upper = [0.5, 3.0];
        for (saturating, on_bounds) in [(true, true), (false, false)] {
            let mut actor = constant_actor(8.5, saturating);
            let mut out = [0.0; 2];
            actor.act(&states, &goals, &mut out);
            assert_eq!(
                out == upper,
                on_bounds,
                "act {out:?}, saturating {saturating}"
            );
            let mut ws = MlpWorkspace::new(actor.mlp(), 1);
            assert_eq!(batch_actions(&actor, &mut ws, &states, &goals), out);
            ws.output_grad_mut().fill(1.0);
            let mut grads = MlpGrads::new(actor.mlp());
            actor.backward_batch(&mut ws, &mut grads, None, None);
            let output_bias = grads.tensors().last().unwrap();
            assert_eq!(
                output_bias.iter().all(|&g| g == 0.0),
                saturating,
                "output bias gradient {output_bias:?}, saturating {saturating}"
            );
        }
    }

    #[test]
    fn the_saturating_tanh_travels_with_the_file() {
        let plain = actor(21).to_safetensors();
        let (_, header) = safetensors::SafeTensors::read_metadata(&plain).unwrap();
        assert!(
            !header
                .metadata()
                .as_ref()
                .unwrap()
                .contains_key("saturating_tanh")
        );
        assert!(
            !ActorNet::from_safetensors(&plain)
                .unwrap()
                .saturating_tanh()
        );

        let mut a = constant_actor(8.5, true);
        let bytes = a.to_safetensors();
        let mut b = ActorNet::from_safetensors(&bytes).unwrap();
        assert!(b.saturating_tanh());
        assert_eq!(b.to_safetensors(), bytes);
        let (mut out_a, mut out_b) = ([0.0; 2], [0.0; 2]);
        a.act(&[0.0; 3], &[0.0; 3], &mut out_a);
        b.act(&[0.0; 3], &[0.0; 3], &mut out_b);
        assert_eq!(out_a.map(f32::to_bits), out_b.map(f32::to_bits));

        let mut file = TensorWriter::default();
        file.meta("format".into(), FORMAT);
        a.write("", &mut file);
        file.meta("saturating_tanh".into(), "yes");
        assert!(matches!(
            ActorNet::from_safetensors(&file.finish()),
            Err(NnError::Metadata { key, .. }) if key == "saturating_tanh"
        ));
    }

    #[test]
    fn actor_is_clone_and_send() {
        fn check<T: Clone + Send + 'static>() {}
        check::<ActorNet>();
    }

    #[test]
    fn safetensors_round_trip_is_exact() {
        let mut a = actor(14);
        let bytes = a.to_safetensors();
        let mut b = ActorNet::from_safetensors(&bytes).expect("round trip");
        assert_eq!(a.mlp(), b.mlp());
        assert_eq!(a.dims(), b.dims());
        assert_eq!(b.to_safetensors(), bytes);
        let (mut out_a, mut out_b) = ([0.0; 2], [0.0; 2]);
        a.act(&[0.1, 0.2, 0.3], &[0.4, 0.5, 0.6], &mut out_a);
        b.act(&[0.1, 0.2, 0.3], &[0.4, 0.5, 0.6], &mut out_b);
        assert_eq!(out_a.map(f32::to_bits), out_b.map(f32::to_bits));
    }

    #[test]
    fn truncated_or_mis_shaped_files_are_rejected() {
        let bytes = actor(15).to_safetensors();
        for len in [0, 7, 100, bytes.len() - 1] {
            assert!(
                matches!(
                    ActorNet::from_safetensors(&bytes[..len]),
                    Err(NnError::Format(_))
                ),
                "truncated to {len} bytes"
            );
        }

        let file = |edit: &dyn Fn(&mut TensorWriter)| {
            let mut out = TensorWriter::default();
            out.meta("format".into(), FORMAT);
            out.meta("state_dim".into(), 2);
            out.meta("goal_dim".into(), 1);
            edit(&mut out);
            out.finish()
        };
        let layer = |out: &mut TensorWriter, l: usize, o: usize, i: usize| {
            out.add(format!("layers.{l}.weight"), &[o, i], &vec![0.5; o * i]);
            out.add(format!("layers.{l}.bias"), &[o], &vec![0.5; o]);
        };
        let head = |out: &mut TensorWriter, a: usize| {
            out.add("output_scale".into(), &[a], &vec![1.0; a]);
            out.add("output_offset".into(), &[a], &vec![0.0; a]);
        };
        let good = file(&|out| {
            layer(out, 0, 4, 3);
            layer(out, 1, 2, 4);
            head(out, 2);
        });
        assert_eq!(ActorNet::from_safetensors(&good).unwrap().dims().action, 2);

        let chained_wrong = file(&|out| {
            layer(out, 0, 4, 3);
            layer(out, 1, 2, 5);
            head(out, 2);
        });
        let input_wrong = file(&|out| {
            layer(out, 0, 4, 6);
            layer(out, 1, 2, 4);
            head(out, 2);
        });
        let head_wrong = file(&|out| {
            layer(out, 0, 4, 3);
            layer(out, 1, 2, 4);
            head(out, 3);
        });
        let bias_wrong = file(&|out| {
            out.add("layers.0.weight".into(), &[4, 3], &[0.5; 12]);
            out.add("layers.0.bias".into(), &[3], &[0.5; 3]);
            head(out, 4);
        });
        for (what, bytes) in [
            ("chaining", chained_wrong),
            ("input width", input_wrong),
            ("output scale", head_wrong),
            ("bias", bias_wrong),
        ] {
            let err = ActorNet::from_safetensors(&bytes).expect_err(what);
            assert!(matches!(err, NnError::Shape { .. }), "{what}: {err}");
        }
        let no_layers = file(&|out| head(out, 2));
        assert!(matches!(
            ActorNet::from_safetensors(&no_layers),
            Err(NnError::MissingTensor(_))
        ));
    }
}
