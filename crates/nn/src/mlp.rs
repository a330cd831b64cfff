//! Multi-layer perceptrons evaluated on whole batches: dense layers, ReLU between them, a linear
//! output. Activations are column-major `width x batch` matrices, one sample per column (the
//! layout of [`hac_core::Batch`]), so every layer is one matrix product per pass.

use std::ops::Range;

use hac_core::Rng;

use crate::NnError;
use crate::checkpoint::{TensorReader, TensorWriter};
use crate::kernels::{
    Epilogue, MatRef, SGEMM_MIN_DIM, axpy, dot, fits_panel, fits_sgemm, has_fma_kernel, sgemm,
    sgemm_then, sgemm_via_then, transpose, vectorized,
};

/// Half-width of the output layer's initial weights and biases: small, so that the network
/// starts at the centre of its output activation (DDPG's choice, kept by HAC).
const OUTPUT_INIT: f32 = 3e-3;

/// One dense layer `z = W x + b`, `W` stored `out x inp` column-major. Gradients use the same type.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Dense {
    pub inp: usize,
    pub out: usize,
    pub w: Vec<f32>,
    pub b: Vec<f32>,
}

/// Tensor `i` of `layers` in the order of [`Mlp::tensors`]: layer `i / 2`'s weights for an even
/// `i`, its biases for an odd one.
fn tensor_of(layers: &mut [Dense], i: usize) -> &mut [f32] {
    let layer = &mut layers[i / 2];
    if i.is_multiple_of(2) {
        &mut layer.w
    } else {
        &mut layer.b
    }
}

impl Dense {
    fn zeros(inp: usize, out: usize) -> Self {
        Self {
            inp,
            out,
            w: vec![0.0; inp * out],
            b: vec![0.0; out],
        }
    }

    /// `z = W x` (no bias) for the `n` columns of `x`, then `epilogue` on `z`.
    fn mul(&self, x: &[f32], n: usize, z: &mut [f32], packed: &mut [f32], epilogue: Epilogue<'_>) {
        let (inp, out) = (self.inp, self.out);
        // A first layer of a few inputs too, on a batch (a single sample takes the vector loop).
        if fits_sgemm(out, inp, n) || fits_panel(out, n) {
            sgemm_then(
                z,
                MatRef::col_major(&self.w, out, inp),
                MatRef::col_major(x, inp, n),
                epilogue,
            );
            return;
        } else if out < SGEMM_MIN_DIM && out < inp {
            // Few outputs (the output layer): one dot product per output over a row of W.
            let wt = &mut packed[..inp * out];
            vectorized(
                #[inline(always)]
                || {
                    transpose(&self.w, out, inp, wt);
                    for (zc, xc) in z.chunks_exact_mut(out).zip(x.chunks_exact(inp)) {
                        for (zv, row) in zc.iter_mut().zip(wt.chunks_exact(inp)) {
                            *zv = dot(row, xc);
                        }
                    }
                },
            );
        } else {
            // Few inputs (a first layer) or few samples (`ActorNet::act`): a sum of W's columns.
            vectorized(
                #[inline(always)]
                || {
                    for (zc, xc) in z.chunks_exact_mut(out).zip(x.chunks_exact(inp)) {
                        zc.fill(0.0);
                        for (col, &xv) in self.w.chunks_exact(out).zip(xc) {
                            axpy(zc, xv, col);
                        }
                    }
                },
            );
        }
        epilogue.apply(&mut z[..out * n]);
    }

    /// `dx = W[:, rows]^T dz`: the gradient with respect to the input rows `rows`, then
    /// `epilogue` on `dx`. `wt`, if given, is `W^T` (`inp x out`, column-major, as
    /// [`MlpTransposed`] keeps it): the kernel then reads its columns in place instead of a copy
    /// made for this call, with the same floats.
    #[allow(clippy::too_many_arguments)] // the layer's product, its operands and scratch
    fn mul_transposed(
        &self,
        dz: &[f32],
        n: usize,
        rows: Range<usize>,
        dx: &mut [f32],
        packed: &mut [f32],
        wt: Option<&[f32]>,
        epilogue: Epilogue<'_>,
    ) {
        let (inp, out, r) = (self.inp, self.out, rows.len());
        // Columns `rows` of W: an `out x r` column-major block.
        let w_cols = &self.w[rows.start * out..rows.end * out];
        // The input gradient of a layer of a few outputs too (the output layer), on a batch.
        if fits_sgemm(r, out, n) || fits_panel(r, n) {
            if let Some(wt) = wt.filter(|_| has_fma_kernel()) {
                // Rows `rows` of W^T: contiguous columns, `inp` apart.
                let a = MatRef {
                    data: &wt[rows.start..],
                    rows: r,
                    cols: out,
                    rs: 1,
                    cs: inp,
                };
                sgemm_then(dx, a, MatRef::col_major(dz, out, n), epilogue);
                return;
            }
            sgemm_via_then(
                dx,
                MatRef::col_major(w_cols, out, r).t(),
                MatRef::col_major(dz, out, n),
                packed,
                epilogue,
            );
            return;
        } else if r <= out {
            vectorized(
                #[inline(always)]
                || {
                    for (dxc, dzc) in dx.chunks_exact_mut(r).zip(dz.chunks_exact(out)) {
                        for (v, col) in dxc.iter_mut().zip(w_cols.chunks_exact(out)) {
                            *v = dot(col, dzc);
                        }
                    }
                },
            );
        } else {
            // Few outputs: a sum of W's rows, made contiguous first.
            let wt = &mut packed[..inp * out];
            vectorized(
                #[inline(always)]
                || {
                    transpose(&self.w, out, inp, wt);
                    for (dxc, dzc) in dx.chunks_exact_mut(r).zip(dz.chunks_exact(out)) {
                        dxc.fill(0.0);
                        for (row, &d) in wt.chunks_exact(inp).zip(dzc) {
                            axpy(dxc, d, &row[rows.clone()]);
                        }
                    }
                },
            );
        }
        epilogue.apply(&mut dx[..r * n]);
    }

    /// Sets this gradient layer's weights to `dz x^T`, summed over the `n` samples.
    fn set_weight_grad(&mut self, dz: &[f32], x: &[f32], n: usize, packed: &mut [f32]) {
        let (inp, out) = (self.inp, self.out);
        // The weight gradient of a first layer of a few inputs too.
        if fits_sgemm(out, n, inp) || fits_panel(out, n) {
            sgemm(
                &mut self.w,
                MatRef::col_major(dz, out, n),
                MatRef::col_major(x, inp, n).t(),
            );
        } else if out < inp && fits_panel(inp, n) {
            // Few outputs (the output layer): `W^T = x dz^T` in the kernel, transposed once.
            let gt = &mut packed[..inp * out];
            sgemm(
                gt,
                MatRef::col_major(x, inp, n),
                MatRef::col_major(dz, out, n).t(),
            );
            let w = &mut self.w;
            vectorized(
                #[inline(always)]
                || transpose(gt, inp, out, w),
            );
        } else if inp <= out {
            let w = &mut self.w;
            vectorized(
                #[inline(always)]
                || {
                    w.fill(0.0);
                    for (dzc, xc) in dz.chunks_exact(out).zip(x.chunks_exact(inp)) {
                        for (gc, &xv) in w.chunks_exact_mut(out).zip(xc) {
                            axpy(gc, xv, dzc);
                        }
                    }
                },
            );
        } else {
            // Few outputs: accumulate W^T, whose columns are then contiguous, and transpose once.
            let (gt, w) = (&mut packed[..inp * out], &mut self.w);
            vectorized(
                #[inline(always)]
                || {
                    gt.fill(0.0);
                    for (dzc, xc) in dz.chunks_exact(out).zip(x.chunks_exact(inp)) {
                        for (gr, &d) in gt.chunks_exact_mut(inp).zip(dzc) {
                            axpy(gr, d, xc);
                        }
                    }
                    transpose(gt, inp, out, w);
                },
            );
        }
    }
}

/// A dense network: ReLU after every layer but the last, whose output is linear.
///
/// Hidden layers start uniform in `+-1/sqrt(fan_in)` (weights and biases), the output layer uniform
/// in `+-3e-3`, all drawn from the given [`Rng`] in layer order, weights before biases.
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    layers: Vec<Dense>,
}

impl Mlp {
    /// A freshly initialised network with layer widths `sizes = [input, hidden.., output]`.
    ///
    /// Panics if `sizes` has fewer than two entries or a zero width.
    pub fn new(sizes: &[usize], rng: &mut Rng) -> Self {
        assert!(
            sizes.len() >= 2 && !sizes.contains(&0),
            "mlp: needs an input and an output width, all positive (got {sizes:?})"
        );
        let last = sizes.len() - 2;
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(l, io)| {
                let bound = if l == last {
                    OUTPUT_INIT
                } else {
                    1.0 / (io[0] as f32).sqrt()
                };
                let mut layer = Dense::zeros(io[0], io[1]);
                for v in layer.w.iter_mut().chain(&mut layer.b) {
                    *v = rng.uniform(-bound, bound);
                }
                layer
            })
            .collect();
        Self { layers }
    }

    /// Layer widths `[input, hidden.., output]`.
    pub fn sizes(&self) -> Vec<usize> {
        std::iter::once(self.input_dim())
            .chain(self.layers.iter().map(|l| l.out))
            .collect()
    }

    /// Width of the input.
    pub fn input_dim(&self) -> usize {
        self.layers[0].inp
    }

    /// Width of the output.
    pub fn output_dim(&self) -> usize {
        self.layers[self.layers.len() - 1].out
    }

    /// Number of trainable parameters.
    pub fn param_count(&self) -> usize {
        self.tensors().map(<[f32]>::len).sum()
    }

    /// The parameter tensors in a fixed order: layer 0's weights (`out x in`, column-major), its
    /// biases, then layer 1's, and so on. [`MlpGrads::tensors`] and the optimiser use this order.
    pub fn tensors(&self) -> impl Iterator<Item = &[f32]> {
        self.layers
            .iter()
            .flat_map(|l| [l.w.as_slice(), l.b.as_slice()])
    }

    /// The parameter tensors, mutably, in the order of [`Mlp::tensors`].
    pub fn tensors_mut(&mut self) -> impl Iterator<Item = &mut [f32]> {
        self.layers
            .iter_mut()
            .flat_map(|l| [l.w.as_mut_slice(), l.b.as_mut_slice()])
    }

    /// Number of parameter tensors (a weight matrix and a bias vector per layer).
    pub(crate) fn tensor_count(&self) -> usize {
        2 * self.layers.len()
    }

    /// Parameter tensor `i` (in the order of [`Mlp::tensors`]), to change.
    pub(crate) fn tensor_mut(&mut self, i: usize) -> &mut [f32] {
        tensor_of(&mut self.layers, i)
    }

    /// `(out, inp)` of tensor `i` if it is a weight matrix; `None` for a bias vector.
    pub(crate) fn weight_shape(&self, i: usize) -> Option<(usize, usize)> {
        let layer = &self.layers[i / 2];
        i.is_multiple_of(2).then_some((layer.out, layer.inp))
    }

    /// Evaluates the network on the `ws.batch()` columns of `ws.input_mut()`; the linear output is
    /// then in `ws.output()`, and `ws` holds what [`Mlp::backward`] needs.
    pub fn forward(&self, ws: &mut MlpWorkspace) {
        debug_assert!(ws.is_for(self), "workspace built for another network");
        let n = ws.batch;
        let last = self.layers.len() - 1;
        for (l, layer) in self.layers.iter().enumerate() {
            let (below, above) = ws.acts.split_at_mut(l + 1);
            let x = &below[l][..layer.inp * n];
            let z = &mut above[0][..layer.out * n];
            if l == last {
                layer.mul(x, n, z, &mut ws.packed, Epilogue::Store);
                add_bias(z, &layer.b);
            } else {
                layer.mul(x, n, z, &mut ws.packed, Epilogue::BiasRelu(&layer.b));
            }
        }
    }

    /// Back-propagates `ws.output_grad_mut()` (the loss gradient with respect to the output of the
    /// last [`Mlp::forward`] on `ws`).
    ///
    /// With `grads`, sets it to the parameter gradient. With a non-empty `input_rows`, leaves the
    /// gradient with respect to those input rows in `ws.input_grad()` (`input_rows.len() x batch`).
    /// Gradients that are not asked for are not computed.
    pub fn backward(
        &self,
        ws: &mut MlpWorkspace,
        grads: Option<&mut MlpGrads>,
        input_rows: Range<usize>,
    ) {
        self.backward_with(ws, grads, input_rows, None);
    }

    /// [`backward`](Self::backward), reading the input gradients' transposed weights from
    /// `transposed` (which must be up to date with this network's weights) where it is given,
    /// instead of transposing them for this call: the same floats, without a copy of each
    /// hidden layer's weights per call.
    pub(crate) fn backward_with(
        &self,
        ws: &mut MlpWorkspace,
        mut grads: Option<&mut MlpGrads>,
        input_rows: Range<usize>,
        transposed: Option<&MlpTransposed>,
    ) {
        debug_assert!(ws.is_for(self), "workspace built for another network");
        debug_assert!(
            transposed.is_none_or(|t| t.is_up_to_date(self)),
            "mlp: transposed weights older than the weights"
        );
        assert!(
            input_rows.end <= self.input_dim(),
            "mlp: input rows {input_rows:?} out of range"
        );
        let n = ws.batch;
        let MlpWorkspace {
            acts,
            out_grad,
            deltas: [even, odd],
            in_grad,
            in_grad_rows,
            packed,
            ..
        } = ws;
        let last = self.layers.len() - 1;
        if let Some(g) = grads.as_deref_mut() {
            debug_assert_eq!(g.layers.len(), self.layers.len());
            row_sums(&out_grad[..self.output_dim() * n], &mut g.layers[last].b);
        }
        for (l, layer) in self.layers.iter().enumerate().rev() {
            // Hidden layer h's gradient lives in buffer h % 2, so the one being read and the one
            // being written are always different.
            let (this, below) = if l % 2 == 0 {
                (&*even, &mut *odd)
            } else {
                (&*odd, &mut *even)
            };
            let dz = if l == last {
                &out_grad[..layer.out * n]
            } else {
                &this[..layer.out * n]
            };
            let x = &acts[l][..layer.inp * n];
            if let Some(g) = grads.as_deref_mut() {
                g.layers[l].set_weight_grad(dz, x, n, packed);
            }
            let wt = transposed.and_then(|t| t.layer(l));
            if l > 0 {
                // Through the ReLU of the layer below, whose output is this layer's input.
                let dx = &mut below[..layer.inp * n];
                let bias_grad = grads
                    .as_deref_mut()
                    .map(|g| g.layers[l - 1].b.as_mut_slice());
                let relu = Epilogue::ReluMask { h: x, bias_grad };
                layer.mul_transposed(dz, n, 0..layer.inp, dx, packed, wt, relu);
            } else if !input_rows.is_empty() {
                let dx = &mut in_grad[..input_rows.len() * n];
                let rows = input_rows.clone();
                layer.mul_transposed(dz, n, rows, dx, packed, wt, Epilogue::Store);
            }
        }
        *in_grad_rows = input_rows.len();
    }

    pub(crate) fn layers(&self) -> &[Dense] {
        &self.layers
    }

    /// `self <- tau * source + (1 - tau) * self` (Polyak averaging of target networks).
    pub(crate) fn polyak_toward(&mut self, source: &Mlp, tau: f32) {
        for (t, s) in self.tensors_mut().zip(source.tensors()) {
            vectorized(
                #[inline(always)]
                || {
                    for (t, s) in t.iter_mut().zip(s) {
                        *t += tau * (s - *t);
                    }
                },
            );
        }
    }

    /// Stores the layers as `{prefix}{l}.weight` (`[out, in]`, row-major as is usual in
    /// safetensors files) and `{prefix}{l}.bias` (`[out]`).
    pub(crate) fn write(&self, prefix: &str, out: &mut TensorWriter) {
        for (l, layer) in self.layers.iter().enumerate() {
            let mut row_major = vec![0.0; layer.w.len()];
            transpose(&layer.w, layer.out, layer.inp, &mut row_major);
            out.add(
                format!("{prefix}{l}.weight"),
                &[layer.out, layer.inp],
                &row_major,
            );
            out.add(format!("{prefix}{l}.bias"), &[layer.out], &layer.b);
        }
    }

    /// Reads what [`Mlp::write`] stored, taking the architecture from the tensor shapes.
    pub(crate) fn read(prefix: &str, file: &TensorReader<'_>) -> Result<Self, NnError> {
        let mut layers: Vec<Dense> = Vec::new();
        while let Some(shape) = file.shape(&format!("{prefix}{}.weight", layers.len())) {
            let name = format!("{prefix}{}.weight", layers.len());
            let [out, inp] = shape[..] else {
                return Err(NnError::Shape {
                    name,
                    expected: "[out, in]".into(),
                    found: shape,
                });
            };
            if out == 0 || inp == 0 {
                return Err(NnError::Shape {
                    name,
                    expected: "positive widths".into(),
                    found: shape,
                });
            }
            if let Some(prev) = layers.last()
                && inp != prev.out
            {
                return Err(NnError::Shape {
                    name,
                    expected: format!("[_, {}] (the previous layer's width)", prev.out),
                    found: shape,
                });
            }
            let mut layer = Dense::zeros(inp, out);
            let row_major = file.read(&name, &[out, inp])?;
            transpose(&row_major, inp, out, &mut layer.w);
            layer.b = file.read(&format!("{prefix}{}.bias", layers.len()), &[out])?;
            layers.push(layer);
        }
        if layers.is_empty() {
            return Err(NnError::MissingTensor(format!("{prefix}0.weight")));
        }
        Ok(Self { layers })
    }
}

/// The transposes `W^T` of an [`Mlp`]'s weight matrices, kept beside it so that the input
/// gradients of its backward passes ([`Mlp::backward_with`]) read them in place: the kernel needs
/// `W^T`'s columns contiguous, and without these each pass would copy every layer's weights
/// transposed (for a 64 x 64 layer about 3 us, 15% of the product it feeds). Worth it where the
/// weights change less often than they are read: a learner's update reads each network's from
/// every chunk and changes them once. The owner brings them up to date after each change
/// ([`refresh`](Self::refresh)); debug builds check it at each use.
#[derive(Debug, Clone)]
pub(crate) struct MlpTransposed {
    /// Layer by layer, `W^T` (`inp x out`, column-major); empty for a layer of one output,
    /// whose `W^T` is its `W`.
    layers: Vec<Vec<f32>>,
}

impl MlpTransposed {
    /// The transposes of `mlp`'s weights as they are now.
    pub(crate) fn new(mlp: &Mlp) -> Self {
        let layers = mlp
            .layers
            .iter()
            .map(|l| {
                if l.out > 1 {
                    vec![0.0; l.w.len()]
                } else {
                    Vec::new()
                }
            })
            .collect();
        let mut t = Self { layers };
        t.refresh(mlp);
        t
    }

    /// Brings the transposes up to date with `mlp`'s weights (the network they were made for).
    pub(crate) fn refresh(&mut self, mlp: &Mlp) {
        debug_assert_eq!(self.layers.len(), mlp.layers.len());
        for (wt, layer) in self.layers.iter_mut().zip(&mlp.layers) {
            if !wt.is_empty() {
                transpose_weights(&layer.w, (layer.out, layer.inp), wt);
            }
        }
    }

    /// The kept transpose of weight tensor `i` (in the order of [`Mlp::tensors`]), to refresh:
    /// empty where none is kept.
    pub(crate) fn tensor_mut(&mut self, i: usize) -> &mut [f32] {
        debug_assert_eq!(i % 2, 0, "only weights have transposes");
        &mut self.layers[i / 2]
    }

    /// Layer `l`'s `W^T`, if it is kept.
    fn layer(&self, l: usize) -> Option<&[f32]> {
        Some(self.layers[l].as_slice()).filter(|wt| !wt.is_empty())
    }

    /// Whether these are the transposes of `mlp`'s weights as they are now.
    fn is_up_to_date(&self, mlp: &Mlp) -> bool {
        let bits = |v: &Vec<f32>| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let now = Self::new(mlp);
        self.layers.iter().map(bits).eq(now.layers.iter().map(bits))
    }
}

/// Writes `W^T` of the `(out, inp)` weights `w` into `wt`, as [`MlpTransposed`] keeps it.
pub(crate) fn transpose_weights(w: &[f32], (out, inp): (usize, usize), wt: &mut [f32]) {
    vectorized(
        #[inline(always)]
        || transpose(w, out, inp, wt),
    );
}

/// Parameter gradients of an [`Mlp`], shaped like it.
#[derive(Debug, Clone, PartialEq)]
pub struct MlpGrads {
    layers: Vec<Dense>,
}

impl MlpGrads {
    /// Zero gradients for `mlp`.
    pub fn new(mlp: &Mlp) -> Self {
        Self {
            layers: mlp
                .layers
                .iter()
                .map(|l| Dense::zeros(l.inp, l.out))
                .collect(),
        }
    }

    /// The gradient tensors, in the order of [`Mlp::tensors`].
    pub fn tensors(&self) -> impl Iterator<Item = &[f32]> {
        self.layers
            .iter()
            .flat_map(|l| [l.w.as_slice(), l.b.as_slice()])
    }

    /// Gradient tensor `i` (in the order of [`Mlp::tensors`]).
    pub(crate) fn tensor(&self, i: usize) -> &[f32] {
        let layer = &self.layers[i / 2];
        if i.is_multiple_of(2) {
            &layer.w
        } else {
            &layer.b
        }
    }

    /// Gradient tensor `i`, to change.
    pub(crate) fn tensor_mut(&mut self, i: usize) -> &mut [f32] {
        tensor_of(&mut self.layers, i)
    }

    /// `self <- self + other`, element by element (gradients of the same network).
    #[cfg(test)]
    pub(crate) fn add(&mut self, other: &MlpGrads) {
        for i in 0..2 * self.layers.len() {
            add_assign(tensor_of(&mut self.layers, i), other.tensor(i));
        }
    }
}

/// `t <- t + o`, element by element.
pub(crate) fn add_assign(t: &mut [f32], o: &[f32]) {
    debug_assert_eq!(t.len(), o.len());
    vectorized(
        #[inline(always)]
        || {
            for (t, o) in t.iter_mut().zip(o) {
                *t += o;
            }
        },
    );
}

/// Buffers for evaluating and differentiating one [`Mlp`] on a batch. They are sized on the first
/// use at a batch size and reused after, so steady-state passes allocate nothing.
#[derive(Debug, Clone)]
pub struct MlpWorkspace {
    sizes: Vec<usize>,
    batch: usize,
    /// `acts[0]` is the input; `acts[l + 1]` the output of layer `l` (after ReLU when hidden).
    acts: Vec<Vec<f32>>,
    out_grad: Vec<f32>,
    /// The derivative of an output activation applied in place after [`Mlp::forward`], for an
    /// activation whose derivative cannot be recovered accurately from its value (see
    /// [`MlpWorkspace::output_and_slope_mut`]).
    out_slope: Vec<f32>,
    /// Gradients with respect to hidden pre-activations, alternating between layers.
    deltas: [Vec<f32>; 2],
    in_grad: Vec<f32>,
    in_grad_rows: usize,
    /// Room for one transposed weight or weight-gradient matrix (the thin-layer kernels).
    packed: Vec<f32>,
}

impl MlpWorkspace {
    /// Buffers for `mlp` at `batch` samples.
    pub fn new(mlp: &Mlp, batch: usize) -> Self {
        let sizes = mlp.sizes();
        let packed = mlp.layers.iter().map(|l| l.inp * l.out).max().unwrap_or(0);
        let mut ws = Self {
            acts: vec![Vec::new(); sizes.len()],
            sizes,
            batch: 0,
            out_grad: Vec::new(),
            out_slope: Vec::new(),
            deltas: [Vec::new(), Vec::new()],
            in_grad: Vec::new(),
            in_grad_rows: 0,
            packed: vec![0.0; packed],
        };
        ws.set_batch(batch);
        ws
    }

    /// Resizes the buffers for `batch` samples; allocates only when growing past an earlier size.
    pub fn set_batch(&mut self, batch: usize) {
        if batch == self.batch {
            return;
        }
        self.batch = batch;
        for (a, width) in self.acts.iter_mut().zip(&self.sizes) {
            a.resize(width * batch, 0.0);
        }
        let hidden = &self.sizes[1..self.sizes.len() - 1];
        let widest_hidden = hidden.iter().copied().max().unwrap_or(0);
        for d in &mut self.deltas {
            d.resize(widest_hidden * batch, 0.0);
        }
        let outputs = self.sizes[self.sizes.len() - 1] * batch;
        self.out_grad.resize(outputs, 0.0);
        self.out_slope.resize(outputs, 0.0);
        self.in_grad.resize(self.sizes[0] * batch, 0.0);
    }

    /// The number of samples the buffers are sized for.
    pub fn batch(&self) -> usize {
        self.batch
    }

    /// Whether these buffers have the layer widths of `mlp`.
    pub(crate) fn is_for(&self, mlp: &Mlp) -> bool {
        self.sizes.len() == mlp.layers.len() + 1
            && self.sizes[0] == mlp.input_dim()
            && mlp
                .layers
                .iter()
                .zip(&self.sizes[1..])
                .all(|(l, &w)| l.out == w)
    }

    /// The input, `input_dim x batch` column-major, to fill before [`Mlp::forward`].
    pub fn input_mut(&mut self) -> &mut [f32] {
        &mut self.acts[0]
    }

    /// The output of the last forward pass, `output_dim x batch`.
    pub fn output(&self) -> &[f32] {
        &self.acts[self.acts.len() - 1]
    }

    /// The output, mutably, for in-place output activations.
    pub fn output_mut(&mut self) -> &mut [f32] {
        let last = self.acts.len() - 1;
        &mut self.acts[last]
    }

    /// The loss gradient with respect to the output, to fill before [`Mlp::backward`].
    pub fn output_grad_mut(&mut self) -> &mut [f32] {
        &mut self.out_grad
    }

    /// The output (read) together with its gradient (written): for output activations whose
    /// derivative is a function of their value.
    pub(crate) fn output_and_grad_mut(&mut self) -> (&[f32], &mut [f32]) {
        (&self.acts[self.acts.len() - 1], &mut self.out_grad)
    }

    /// The output (to transform in place) with room for the transform's derivative at each
    /// output, which a later backward pass reads with [`MlpWorkspace::grad_and_slope_mut`].
    pub(crate) fn output_and_slope_mut(&mut self) -> (&mut [f32], &mut [f32]) {
        let last = self.acts.len() - 1;
        (&mut self.acts[last], &mut self.out_slope)
    }

    /// The output gradient (written) with the derivatives kept by the forward pass (read).
    pub(crate) fn grad_and_slope_mut(&mut self) -> (&mut [f32], &[f32]) {
        (&mut self.out_grad, &self.out_slope)
    }

    /// The gradient with respect to the input rows asked of the last [`Mlp::backward`],
    /// `rows x batch` column-major.
    pub fn input_grad(&self) -> &[f32] {
        &self.in_grad[..self.in_grad_rows * self.batch]
    }
}

fn add_bias(z: &mut [f32], b: &[f32]) {
    vectorized(
        #[inline(always)]
        || {
            for col in z.chunks_exact_mut(b.len()) {
                for (v, b) in col.iter_mut().zip(b) {
                    *v += b;
                }
            }
        },
    );
}

/// `out[i] = sum_j g[i, j]` for the column-major `out.len() x n` matrix `g`.
fn row_sums(g: &[f32], out: &mut [f32]) {
    vectorized(
        #[inline(always)]
        || {
            out.fill(0.0);
            for col in g.chunks_exact(out.len()) {
                for (o, v) in out.iter_mut().zip(col) {
                    *o += v;
                }
            }
        },
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{
        assert_grad_close, fd_gradient, fd_param_gradients, params_f64, reference_forward,
        uniform_vec, widen,
    };

    /// Checks forward, parameter gradients and input-row gradients of a network with widths
    /// `sizes` on `n` samples against the f64 reference, for the loss `sum(R * output)`.
    fn check_gradients(sizes: &[usize], n: usize, rows: Range<usize>, seed: u64) {
        let mut rng = Rng::seed_from(seed);
        let mlp = Mlp::new(sizes, &mut rng);
        let x = uniform_vec(&mut rng, sizes[0] * n, 1.0);
        let r = uniform_vec(&mut rng, sizes[sizes.len() - 1] * n, 1.0);

        let mut ws = MlpWorkspace::new(&mlp, n);
        ws.input_mut().copy_from_slice(&x);
        mlp.forward(&mut ws);
        let mut params = params_f64(&mlp);
        let want = reference_forward(sizes, &params, &widen(&x), n);
        for (got, want) in ws.output().iter().zip(&want) {
            assert!(
                (f64::from(*got) - want).abs() < 1e-5,
                "forward {got} vs {want}"
            );
        }

        ws.output_grad_mut().copy_from_slice(&r);
        let mut grads = MlpGrads::new(&mlp);
        mlp.backward(&mut ws, Some(&mut grads), rows.clone());

        let r64 = widen(&r);
        let loss = |y: Vec<f64>| y.iter().zip(&r64).map(|(y, r)| y * r).sum::<f64>();
        let x64 = widen(&x);
        let fd = fd_param_gradients(&mut params, |p| loss(reference_forward(sizes, p, &x64, n)));
        for (t, (got, want)) in grads.tensors().zip(&fd).enumerate() {
            assert_grad_close(got, want, &format!("{sizes:?} tensor {t}"));
        }

        let p64 = params_f64(&mlp);
        let mut x64 = x64;
        let fd_x = fd_gradient(&mut x64, |x| loss(reference_forward(sizes, &p64, x, n)));
        let want: Vec<f64> = (0..n)
            .flat_map(|j| rows.clone().map(move |i| (i, j)))
            .map(|(i, j)| fd_x[i + j * sizes[0]])
            .collect();
        assert_grad_close(
            ws.input_grad(),
            &want,
            &format!("{sizes:?} input rows {rows:?}"),
        );
    }

    #[test]
    fn gradients_through_sgemm_layers() {
        // Every product of the first two layers is large enough for sgemm.
        check_gradients(&[7, 8, 9, 2], 10, 0..7, 1);
    }

    #[test]
    fn gradients_through_thin_layers() {
        // Few inputs, few outputs, small batch: every product takes the vector loops.
        check_gradients(&[5, 6, 1], 3, 1..4, 2);
        // Wide input, narrow layers: the transposed-weight paths.
        check_gradients(&[9, 3, 4], 7, 0..9, 3);
        // One sample, as in `ActorNet::act`.
        check_gradients(&[4, 6, 6, 2], 1, 2..4, 4);
    }

    #[test]
    fn gradients_through_thin_layers_in_the_kernel() {
        // A batch through a first layer of 3 inputs and an output layer of 1 output, 20 and 17
        // wide: where the CPU has FMA, the first layer's product and weight gradient and the
        // output layer's input and weight gradients go to the kernel (at least `PANEL_MIN_ROWS`
        // rows; 20 and 17 leave rows over a whole vector), elsewhere to the vector loops.
        check_gradients(&[3, 20, 17, 1], 9, 0..3, 5);
        check_gradients(&[2, 33, 2], 6, 1..2, 6);
    }

    #[test]
    fn skipping_gradients_changes_nothing_else() {
        let mut rng = Rng::seed_from(5);
        let mlp = Mlp::new(&[6, 16, 16, 2], &mut rng);
        let n = 12;
        let x = uniform_vec(&mut rng, 6 * n, 1.0);
        let r = uniform_vec(&mut rng, 2 * n, 1.0);
        let mut ws = MlpWorkspace::new(&mlp, n);
        let mut input_grads = Vec::new();
        for grads in [Some(MlpGrads::new(&mlp)), None] {
            ws.input_mut().copy_from_slice(&x);
            mlp.forward(&mut ws);
            ws.output_grad_mut().copy_from_slice(&r);
            let mut grads = grads;
            mlp.backward(&mut ws, grads.as_mut(), 4..6);
            input_grads.push(ws.input_grad().to_vec());
        }
        assert_eq!(input_grads[0], input_grads[1]);
    }

    #[test]
    fn kept_transposes_give_the_same_bits_as_a_copy_per_call() {
        // Layers the kernel runs (20 x 40, 40 x 20 and the 20-row input gradients of a 40 x 3
        // layer, with rows over a whole vector), the thin ones beside them, a range of input rows
        // of more than one row (the kernel, reading rows of a kept W^T) and of one (the vector
        // loops); a batch of a few samples and one of a single sample.
        let mut rng = Rng::seed_from(7);
        let mlp = Mlp::new(&[40, 20, 40, 3, 1], &mut rng);
        let transposed = MlpTransposed::new(&mlp);
        for (n, rows) in [(37, 2..39), (37, 5..6), (1, 0..40)] {
            let x = uniform_vec(&mut rng, 40 * n, 1.0);
            let r = uniform_vec(&mut rng, n, 1.0);
            let mut ws = MlpWorkspace::new(&mlp, n);
            let mut results = Vec::new();
            for t in [None, Some(&transposed)] {
                ws.input_mut().copy_from_slice(&x);
                mlp.forward(&mut ws);
                ws.output_grad_mut().copy_from_slice(&r);
                let mut grads = MlpGrads::new(&mlp);
                mlp.backward_with(&mut ws, Some(&mut grads), rows.clone(), t);
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                let grads: Vec<Vec<u32>> = grads.tensors().map(bits).collect();
                results.push((grads, bits(ws.input_grad())));
            }
            assert_eq!(results[0], results[1], "batch {n}, input rows {rows:?}");
        }
    }

    #[test]
    fn transposes_follow_the_weights_only_when_refreshed() {
        let mut rng = Rng::seed_from(8);
        let mut mlp = Mlp::new(&[4, 16, 8, 1], &mut rng);
        let mut transposed = MlpTransposed::new(&mlp);
        assert!(transposed.is_up_to_date(&mlp));
        // A layer of one output keeps no copy: its W^T is its W.
        assert!(transposed.layer(2).is_none() && transposed.layer(1).is_some());
        mlp.tensors_mut().nth(2).unwrap()[5] += 1.0;
        assert!(!transposed.is_up_to_date(&mlp));
        transposed.refresh(&mlp);
        assert!(transposed.is_up_to_date(&mlp));
    }

    #[test]
    fn init_follows_fan_in_and_output_scale() {
        let mut rng = Rng::seed_from(6);
        let mlp = Mlp::new(&[5, 64, 64, 1], &mut rng);
        let tensors: Vec<&[f32]> = mlp.tensors().collect();
        let max_abs = |t: &[f32]| t.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(max_abs(tensors[0]) <= 1.0 / 5f32.sqrt());
        assert!(max_abs(tensors[0]) > 0.9 / 5f32.sqrt());
        assert!(max_abs(tensors[2]) <= 1.0 / 8.0 && max_abs(tensors[3]) <= 1.0 / 8.0);
        assert!(max_abs(tensors[4]) <= 3e-3 && max_abs(tensors[5]) <= 3e-3);
        assert_eq!(mlp, Mlp::new(&[5, 64, 64, 1], &mut Rng::seed_from(6)));
        assert_eq!(mlp.param_count(), 5 * 64 + 64 + 64 * 64 + 64 + 64 + 1);
    }
}
