//! Matrix kernels on column-major `f32` slices.
//!
//! Products go to [`panel_gemm`], this crate's kernel, wherever the CPU has FMA (AVX2 or
//! AVX-512, chosen at run time): every product of at least 6 in each dimension, and, on a
//! batch, the thin ones with at least [`PANEL_MIN_ROWS`] rows (a first layer of a few inputs
//! and its weight gradient, the output layer's input and weight gradients). Elsewhere the large
//! products go to matrixmultiply's `sgemm`: this crate forbids `unsafe`, so it reaches it
//! through nalgebra's `gemm` on strided views (nalgebra forwards the strides unchanged, which
//! makes transposed operands free, when every dimension is at least 6). What is left (single
//! samples, the one-row output of the output layer, thin products on a CPU without FMA) runs in
//! the vector loops here, written so that the compiler vectorises their inner loop.
//!
//! The build targets the baseline x86-64 (SSE2), so that one binary runs on every machine; the
//! loops that are not products run through [`vectorized`], which compiles them again for AVX2
//! and for AVX-512 and picks the widest this CPU has at run time (pulp's dispatch, safe code).
//! Elementwise results do not depend on the choice: Rust never fuses a multiply and an add on
//! its own, and every sum keeps its order, so each lane computes what the scalar loop would.

use std::sync::LazyLock;

use nalgebra::{DMatrixView, DMatrixViewMut};

/// The widest SIMD extension of this CPU that [`vectorized`] uses, detected once.
static ARCH: LazyLock<pulp::Arch> = LazyLock::new(pulp::Arch::new);

/// Runs `f` compiled for the widest SIMD extension this CPU has (AVX-512, else AVX2 with FMA,
/// else the build's baseline). For `f`'s loops to be compiled so, `f` must be an
/// `#[inline(always)]` closure and every function it calls `#[inline(always)]` too; a call that
/// is not inlined runs at the baseline, correctly but slower.
#[inline(always)]
pub(crate) fn vectorized<R>(f: impl FnOnce() -> R) -> R {
    struct Op<F>(F);
    impl<R, F: FnOnce() -> R> pulp::WithSimd for Op<F> {
        type Output = R;
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) -> R {
            (self.0)()
        }
    }
    ARCH.dispatch(Op(f))
}

/// The name of the SIMD extension [`vectorized`] runs on this CPU: `avx512`, `avx2` or
/// `baseline`.
pub fn simd_extension() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    match *ARCH {
        pulp::Arch::V4(_) => return "avx512",
        pulp::Arch::V3(_) => return "avx2",
        _ => {}
    }
    "baseline"
}

/// The smallest dimension for which nalgebra hands a product to matrixmultiply.
pub(crate) const SGEMM_MIN_DIM: usize = 6;

/// Whether an `m x k` by `k x n` product takes the `sgemm` path.
pub(crate) fn fits_sgemm(m: usize, k: usize, n: usize) -> bool {
    m >= SGEMM_MIN_DIM && k >= SGEMM_MIN_DIM && n >= SGEMM_MIN_DIM
}

/// The fewest rows of `c` for which a product whose other dimensions are thin (a network's
/// first layer of a few inputs, the weight gradient of such a layer, the input gradient of a
/// one-output layer) still goes to [`panel_gemm`]: one AVX-512 vector, two AVX2 ones. Its
/// register blocks hold their accumulators whatever `k` and the column count, where the vector
/// loops below would read and write a column of `c` in memory once per step.
pub(crate) const PANEL_MIN_ROWS: usize = 16;

/// Whether an `m`-row product over a batch of `batch` samples goes to [`sgemm`] even though its
/// other dimensions are thin: where [`panel_gemm`] runs, `m >= PANEL_MIN_ROWS` and the batch is
/// at least [`SGEMM_MIN_DIM`] (a single sample keeps the vector loops). The caller's `a` must
/// have contiguous columns, or go through [`sgemm_via`].
pub(crate) fn fits_panel(m: usize, batch: usize) -> bool {
    m >= PANEL_MIN_ROWS && batch >= SGEMM_MIN_DIM && has_fma_kernel()
}

/// A read-only strided matrix: element `(i, j)` is `data[i * rs + j * cs]`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct MatRef<'a> {
    pub data: &'a [f32],
    pub rows: usize,
    pub cols: usize,
    pub rs: usize,
    pub cs: usize,
}

impl<'a> MatRef<'a> {
    /// A contiguous column-major `rows x cols` matrix.
    pub fn col_major(data: &'a [f32], rows: usize, cols: usize) -> Self {
        Self {
            data,
            rows,
            cols,
            rs: 1,
            cs: rows,
        }
    }

    /// The transpose, as a view of the same memory.
    pub fn t(self) -> Self {
        Self {
            data: self.data,
            rows: self.cols,
            cols: self.rows,
            rs: self.cs,
            cs: self.rs,
        }
    }
}

/// `c = a * b`; `c` is contiguous column-major and is overwritten (never read). Callers check
/// [`fits_sgemm`] first: below it nalgebra would fall back to a slow generic loop.
///
/// When `a`'s columns are contiguous and the CPU has FMA (AVX2 or AVX-512), the product runs in
/// [`panel_gemm`], this crate's kernel for the thin shapes of these networks, which needs no
/// packing; otherwise in matrixmultiply's `sgemm`.
pub(crate) fn sgemm(c: &mut [f32], a: MatRef<'_>, b: MatRef<'_>) {
    sgemm_then(c, a, b, Epilogue::Store);
}

/// [`sgemm`], then `epilogue` on the product: in the kernel's registers, before each block is
/// stored, where [`panel_gemm`] runs; as a separate pass over `c` elsewhere. Either way each
/// element is the same float.
pub(crate) fn sgemm_then(c: &mut [f32], a: MatRef<'_>, b: MatRef<'_>, epilogue: Epilogue<'_>) {
    debug_assert!(
        fits_sgemm(a.rows, a.cols, b.cols)
            || (a.rs == 1 && a.rows >= PANEL_MIN_ROWS && has_fma_kernel())
    );
    debug_assert_eq!(a.cols, b.rows);
    if a.rs == 1 && has_fma_kernel() {
        panel_gemm(c, a, b, epilogue);
        return;
    }
    {
        let a = DMatrixView::from_slice_with_strides(a.data, a.rows, a.cols, a.rs, a.cs);
        let b = DMatrixView::from_slice_with_strides(b.data, b.rows, b.cols, b.rs, b.cs);
        let mut c =
            DMatrixViewMut::from_slice(&mut c[..a.nrows() * b.ncols()], a.nrows(), b.ncols());
        c.gemm(1.0, &a, &b, 0.0);
    }
    epilogue.apply(&mut c[..a.rows * b.cols]);
}

/// What happens to a product `c = a * b` (`m x n`, column-major) before it is final: the
/// elementwise step that follows a hidden layer's products, done by [`panel_gemm`] on each block
/// while it is still in registers, so that it costs no pass over memory of its own.
#[derive(Debug)]
pub(crate) enum Epilogue<'a> {
    /// The product as it is.
    Store,
    /// `c[i, j] = relu(c[i, j] + bias[i])`: a hidden layer's forward pass (`bias` has `m`
    /// entries). A NaN becomes 0, as `x > 0` is false for it.
    BiasRelu(&'a [f32]),
    /// `c[i, j] = if h[i, j] > 0 { c[i, j] } else { 0 }`, with `h` (`m x n`, column-major) a
    /// hidden layer's ReLU output: the gradient with respect to its pre-activation. With
    /// `bias_grad` (`m` entries), also its row sums, each summed in column order from 0: the
    /// gradient of the layer's bias.
    ReluMask {
        h: &'a [f32],
        bias_grad: Option<&'a mut [f32]>,
    },
}

impl Epilogue<'_> {
    /// The epilogue as a pass over a finished product `c` (`m x n`, `m` the length of the bias
    /// or bias gradient, or `c.len() / n` for the mask): the same floats as in the kernel.
    pub(crate) fn apply(self, c: &mut [f32]) {
        match self {
            Epilogue::Store => {}
            Epilogue::BiasRelu(bias) => vectorized(
                #[inline(always)]
                || {
                    for col in c.chunks_exact_mut(bias.len()) {
                        for (v, b) in col.iter_mut().zip(bias) {
                            *v = relu(*v + b);
                        }
                    }
                },
            ),
            Epilogue::ReluMask { h, bias_grad } => vectorized(
                #[inline(always)]
                || match bias_grad {
                    Some(bg) => {
                        bg.fill(0.0);
                        let width = bg.len();
                        for (gc, hc) in c.chunks_exact_mut(width).zip(h.chunks_exact(width)) {
                            for ((gv, &hv), b) in gc.iter_mut().zip(hc).zip(bg.iter_mut()) {
                                *gv = if hv > 0.0 { *gv } else { 0.0 };
                                *b += *gv;
                            }
                        }
                    }
                    None => {
                        // A select rather than a conditional store, so that the loop vectorises.
                        for (gv, &hv) in c.iter_mut().zip(h) {
                            *gv = if hv > 0.0 { *gv } else { 0.0 };
                        }
                    }
                },
            ),
        }
    }
}

/// `max(x, 0)`, with a NaN sent to 0.
#[inline(always)]
fn relu(x: f32) -> f32 {
    if x > 0.0 { x } else { 0.0 }
}

/// Whether [`panel_gemm`] runs here: on x86-64 with AVX2 and FMA, or AVX-512.
pub(crate) fn has_fma_kernel() -> bool {
    #[cfg(target_arch = "x86_64")]
    if matches!(*ARCH, pulp::Arch::V4(_) | pulp::Arch::V3(_)) {
        return true;
    }
    false
}

/// [`sgemm`] for any `a`: where [`panel_gemm`] runs and `a`'s columns are not contiguous (a
/// transposed view, as in an input gradient `W^T dz`), `a` is first copied column-major into
/// `scratch` (at least `a.rows * a.cols` long), so that the kernel reads its columns in place.
pub(crate) fn sgemm_via(c: &mut [f32], a: MatRef<'_>, b: MatRef<'_>, scratch: &mut [f32]) {
    sgemm_via_then(c, a, b, scratch, Epilogue::Store);
}

/// [`sgemm_via`] followed by `epilogue` (see [`sgemm_then`]).
pub(crate) fn sgemm_via_then(
    c: &mut [f32],
    a: MatRef<'_>,
    b: MatRef<'_>,
    scratch: &mut [f32],
    epilogue: Epilogue<'_>,
) {
    if a.rs == 1 || !has_fma_kernel() {
        sgemm_then(c, a, b, epilogue);
        return;
    }
    let copy = &mut scratch[..a.rows * a.cols];
    vectorized(
        #[inline(always)]
        || {
            for (p, column) in copy.chunks_exact_mut(a.rows).enumerate() {
                for (i, value) in column.iter_mut().enumerate() {
                    *value = a.data[i * a.rs + p * a.cs];
                }
            }
        },
    );
    sgemm_then(c, MatRef::col_major(copy, a.rows, a.cols), b, epilogue);
}

/// Rows of `c` per block of [`panel_gemm`], in SIMD vectors: 4 with 16 lanes (AVX-512, 64 rows,
/// a hidden layer of 64 in one block), 2 with 8 (AVX2, whose 16 registers would not hold 4 x 4
/// accumulators and their operands).
const fn block_vectors(lanes: usize) -> usize {
    if lanes >= 16 { 4 } else { 2 }
}

/// Columns of `c` per block of [`panel_gemm`] for SIMD vectors of `lanes` floats: 4 with 16
/// lanes (AVX-512: 4 x 4 accumulators), 6 with 8 (AVX2: 2 x 6 accumulators, the two vectors of
/// `a` and the broadcast of `b` fill the 16 registers). Fused multiply-adds take 4-5 cycles on
/// two ports, so a block needs at least 8-10 independent accumulators to keep both busy: 2 x 4
/// on AVX2 left them waiting on their own results.
const fn block_columns(lanes: usize) -> usize {
    if lanes >= 16 { 4 } else { 6 }
}

/// The most columns of any block (AVX2's): the size of the copy of `b` a strided block reads.
const BLOCK_COLUMNS: usize = block_columns(8);

/// `c = a * b` for `a` with contiguous columns (`a.rs == 1`), by register blocks of
/// `block_vectors` SIMD vectors of rows by `block_columns` columns: for each `p`, the block's
/// rows of column `p` of `a` are loaded once and multiplied by `b[p, j]` of each of the block's
/// columns, accumulating with fused multiply-adds. `a`'s columns are read in place, and so are
/// `b`'s columns or rows where they are contiguous; only a `b` with neither is copied, a few
/// rows at a time ([`PANEL_STEPS`]).
///
/// Every element of `c` is the chain `fma(a[i, k-1], b[k-1, j], ... fma(a[i, 0], b[0, j], 0))`
/// in order of `p`, whatever the SIMD width and the block it falls in (the rows left over at the
/// edge use the same chain in scalar fused multiply-adds), so the result is the same on AVX2 and
/// AVX-512. The `epilogue` is applied to each block in registers, with the same floats as
/// [`Epilogue::apply`] (a bias gradient is summed over the columns in order: the panels go
/// through the columns in order, and each adds its columns in order).
fn panel_gemm(c: &mut [f32], a: MatRef<'_>, b: MatRef<'_>, epilogue: Epilogue<'_>) {
    struct Op<'a> {
        c: &'a mut [f32],
        a: MatRef<'a>,
        b: MatRef<'a>,
        epilogue: Epilogue<'a>,
    }
    impl pulp::WithSimd for Op<'_> {
        type Output = ();
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, simd: S) {
            let Op {
                c,
                a,
                b,
                mut epilogue,
            } = self;
            let m = a.rows;
            let c = &mut c[..m * b.cols];
            if let Epilogue::ReluMask {
                bias_grad: Some(bg),
                ..
            } = &mut epilogue
            {
                bg.fill(0.0);
            }
            let mut b_panel = [0.0f32; PANEL_STEPS * BLOCK_COLUMNS];
            let mut j = 0;
            if block_columns(S::F32_LANES) == 6 {
                while j + 6 <= b.cols {
                    panel::<S, 6>(simd, c, a, b, j, &mut b_panel, &mut epilogue);
                    j += 6;
                }
            }
            while j + 4 <= b.cols {
                panel::<S, 4>(simd, c, a, b, j, &mut b_panel, &mut epilogue);
                j += 4;
            }
            while j < b.cols {
                panel::<S, 1>(simd, c, a, b, j, &mut b_panel, &mut epilogue);
                j += 1;
            }
        }
    }
    debug_assert_eq!(a.rs, 1);
    ARCH.dispatch(Op { c, a, b, epilogue });
}

/// Columns `j..j + N` of `c = a * b` (see [`panel_gemm`]).
#[inline(always)]
fn panel<S: pulp::Simd, const N: usize>(
    simd: S,
    c: &mut [f32],
    a: MatRef<'_>,
    b: MatRef<'_>,
    j: usize,
    b_panel: &mut [f32; PANEL_STEPS * BLOCK_COLUMNS],
    epilogue: &mut Epilogue<'_>,
) {
    let lanes = S::F32_LANES;
    let m = a.rows;
    let rows = block_vectors(lanes) * lanes;
    let mut i = 0;
    while i + rows <= m {
        if block_vectors(lanes) == 4 {
            block::<S, 4, N>(simd, c, a, b, i, j, b_panel, epilogue);
        } else {
            block::<S, 2, N>(simd, c, a, b, i, j, b_panel, epilogue);
        }
        i += rows;
    }
    while i + lanes <= m {
        block::<S, 1, N>(simd, c, a, b, i, j, b_panel, epilogue);
        i += lanes;
    }
    for i in i..m {
        for jj in j..j + N {
            let mut acc = 0.0f32;
            for p in 0..a.cols {
                acc = a.data[i + p * a.cs].mul_add(b.data[p * b.rs + jj * b.cs], acc);
            }
            let at = i + jj * m;
            c[at] = match epilogue {
                Epilogue::Store => acc,
                Epilogue::BiasRelu(bias) => relu(acc + bias[i]),
                Epilogue::ReluMask { h, bias_grad } => {
                    let g = if h[at] > 0.0 { acc } else { 0.0 };
                    if let Some(bg) = bias_grad {
                        bg[i] += g;
                    }
                    g
                }
            };
        }
    }
}

/// Steps of `p` whose elements of `b` [`block`] copies into a small array at a time, so that its
/// inner loop reads them without bounds checks, whatever `b`'s strides.
const PANEL_STEPS: usize = 128;

/// Rows `i..i + V * lanes` by columns `j..j + N` of `c = a * b`, with the epilogue applied (see
/// [`panel_gemm`]).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // `p` indexes `a`'s columns and `b`'s together
#[allow(clippy::too_many_arguments)] // the block's place in `c`, its operands and scratch
fn block<S: pulp::Simd, const V: usize, const N: usize>(
    simd: S,
    c: &mut [f32],
    a: MatRef<'_>,
    b: MatRef<'_>,
    i: usize,
    j: usize,
    b_panel: &mut [f32; PANEL_STEPS * BLOCK_COLUMNS],
    epilogue: &mut Epilogue<'_>,
) {
    let lanes = S::F32_LANES;
    let m = a.rows;
    let mut acc = [[simd.splat_f32s(0.0); N]; V];
    let k = a.cols;
    if b.rs == 1 {
        // `b`'s columns are contiguous (a forward pass, an input gradient): read them in place.
        let b_columns: [&[f32]; N] = std::array::from_fn(|jj| &b.data[(j + jj) * b.cs..][..k]);
        for p in 0..k {
            fma_step(simd, &mut acc, &a.data[i + p * a.cs..], |jj| {
                b_columns[jj][p]
            });
        }
    } else if b.cs == 1 {
        // `b`'s rows are contiguous (a weight gradient, `b` a transposed view): the block's
        // columns are `N` neighbours in row `p`.
        let b_rows = b.data[j..].chunks(b.rs);
        for (column, b_row) in a.data[i..].chunks(a.cs).zip(b_rows).take(k) {
            let b_row = &b_row[..N];
            fma_step(simd, &mut acc, column, |jj| b_row[jj]);
        }
    } else {
        block_strided::<S, V, N>(simd, &mut acc, a, b, i, j, b_panel);
    }
    let load = |from: &[f32]| -> S::f32s {
        pulp::bytemuck::pod_read_unaligned(pulp::bytemuck::cast_slice(&from[..lanes]))
    };
    let store = |to: &mut [f32], value: &S::f32s| {
        pulp::bytemuck::cast_slice_mut::<f32, u8>(&mut to[..lanes])
            .copy_from_slice(pulp::bytemuck::bytes_of(value));
    };
    let zero = simd.splat_f32s(0.0);
    match epilogue {
        Epilogue::Store => {}
        Epilogue::BiasRelu(bias) => {
            for (v, row_acc) in acc.iter_mut().enumerate() {
                let bv = load(&bias[i + v * lanes..]);
                for value in row_acc.iter_mut() {
                    let x = simd.add_f32s(*value, bv);
                    *value = simd.select_f32s(simd.greater_than_f32s(x, zero), x, zero);
                }
            }
        }
        Epilogue::ReluMask { h, bias_grad } => {
            for (v, row_acc) in acc.iter_mut().enumerate() {
                for (jj, value) in row_acc.iter_mut().enumerate() {
                    let hv = load(&h[i + v * lanes + (j + jj) * m..]);
                    *value = simd.select_f32s(simd.greater_than_f32s(hv, zero), *value, zero);
                }
                if let Some(bg) = bias_grad {
                    // The block's columns in order, onto the sums of the columns before them.
                    let at = i + v * lanes;
                    let mut sum = load(&bg[at..]);
                    for value in row_acc.iter() {
                        sum = simd.add_f32s(sum, *value);
                    }
                    store(&mut bg[at..], &sum);
                }
            }
        }
    }
    for (v, row_acc) in acc.iter().enumerate() {
        for (jj, value) in row_acc.iter().enumerate() {
            store(&mut c[i + v * lanes + (j + jj) * m..], value);
        }
    }
}

/// One step `p` of [`block`]: `acc[v][jj] <- fma(a[rows v, p], b_row(jj), acc[v][jj])`, with
/// `column` the block's rows of column `p` of `a` (and possibly more after them) and `b_row(jj)`
/// the element `b[p, j + jj]`.
#[inline(always)]
#[allow(clippy::needless_range_loop)] // `jj` and `v` index the register block in two dimensions
fn fma_step<S: pulp::Simd, const V: usize, const N: usize>(
    simd: S,
    acc: &mut [[S::f32s; N]; V],
    column: &[f32],
    b_row: impl Fn(usize) -> f32,
) {
    let lanes = S::F32_LANES;
    let column = &column[..V * lanes];
    let av: [S::f32s; V] = std::array::from_fn(|v| {
        pulp::bytemuck::pod_read_unaligned(pulp::bytemuck::cast_slice(
            &column[v * lanes..(v + 1) * lanes],
        ))
    });
    for jj in 0..N {
        let bv = simd.splat_f32s(b_row(jj));
        for v in 0..V {
            acc[v][jj] = simd.mul_add_f32s(av[v], bv, acc[v][jj]);
        }
    }
}

/// [`block`]'s accumulation for a `b` with neither contiguous columns nor contiguous rows:
/// `b`'s elements are first copied, [`PANEL_STEPS`] rows at a time, into `b_panel`.
#[inline(always)]
fn block_strided<S: pulp::Simd, const V: usize, const N: usize>(
    simd: S,
    acc: &mut [[S::f32s; N]; V],
    a: MatRef<'_>,
    b: MatRef<'_>,
    i: usize,
    j: usize,
    b_panel: &mut [f32; PANEL_STEPS * BLOCK_COLUMNS],
) {
    let mut p0 = 0;
    while p0 < a.cols {
        let steps = PANEL_STEPS.min(a.cols - p0);
        for (q, row) in b_panel[..steps * N].chunks_exact_mut(N).enumerate() {
            for (jj, value) in row.iter_mut().enumerate() {
                *value = b.data[(p0 + q) * b.rs + (j + jj) * b.cs];
            }
        }
        let columns = a.data[i + p0 * a.cs..].chunks(a.cs);
        for (column, b_row) in columns.zip(b_panel[..steps * N].chunks_exact(N)) {
            fma_step(simd, acc, column, |jj| b_row[jj]);
        }
        p0 += steps;
    }
}

/// Single-core GFLOP/s of this crate's `sgemm` path on the three products a hidden
/// `width x width` layer does on `batch` samples (forward `W x`, input gradient `W^T dz`, weight
/// gradient `dz x^T`), one after the other, repeated on the calling thread for at least
/// `min_seconds`: the peak an update of such layers could reach on one core.
///
/// Panics if `width` or `batch` is below the `sgemm` path's smallest dimension (6).
pub fn hidden_layer_sgemm_gflops(width: usize, batch: usize, min_seconds: f64) -> f64 {
    assert!(
        fits_sgemm(width, width, batch),
        "sgemm peak: width {width} and batch {batch} must be at least {SGEMM_MIN_DIM}"
    );
    let fill = |len: usize| -> Vec<f32> { (0..len).map(|i| (i % 17) as f32 * 0.01).collect() };
    let (w, x, dz) = (
        fill(width * width),
        fill(width * batch),
        fill(width * batch),
    );
    let (mut out, mut grad) = (vec![0.0; width * batch], vec![0.0; width * width]);
    let mut wt = vec![0.0; width * width];
    let mut round = || {
        let w = MatRef::col_major(&w, width, width);
        sgemm(&mut out, w, MatRef::col_major(&x, width, batch));
        sgemm_via(
            &mut out,
            w.t(),
            MatRef::col_major(&dz, width, batch),
            &mut wt,
        );
        sgemm(
            &mut grad,
            MatRef::col_major(&dz, width, batch),
            MatRef::col_major(&x, width, batch).t(),
        );
    };
    round();
    let start = std::time::Instant::now();
    let mut rounds = 0u64;
    while rounds == 0 || start.elapsed().as_secs_f64() < min_seconds {
        round();
        rounds += 1;
    }
    let flops = 3.0 * 2.0 * (width * width * batch) as f64 * rounds as f64;
    std::hint::black_box((&out, &grad));
    flops / start.elapsed().as_secs_f64() / 1e9
}

/// `y += s * x`.
#[inline(always)]
pub(crate) fn axpy(y: &mut [f32], s: f32, x: &[f32]) {
    debug_assert_eq!(y.len(), x.len());
    for (y, x) in y.iter_mut().zip(x) {
        *y += s * x;
    }
}

/// Dot product with eight independent partial sums, so that it vectorises (floating-point addition
/// is not associative, so the compiler will not reorder a single running sum).
#[inline(always)]
pub(crate) fn dot(a: &[f32], b: &[f32]) -> f32 {
    debug_assert_eq!(a.len(), b.len());
    let mut acc = [0.0f32; 8];
    let (a8, b8) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = a8
        .remainder()
        .iter()
        .zip(b8.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in a8.zip(b8) {
        for l in 0..8 {
            acc[l] += x[l] * y[l];
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// Writes the transpose of the column-major `rows x cols` matrix `a` into `out` (`cols x rows`).
#[inline(always)]
pub(crate) fn transpose(a: &[f32], rows: usize, cols: usize, out: &mut [f32]) {
    debug_assert_eq!(a.len(), rows * cols);
    for (i, out_col) in out[..rows * cols].chunks_exact_mut(cols).enumerate() {
        for (j, o) in out_col.iter_mut().enumerate() {
            *o = a[i + j * rows];
        }
    }
}

/// Copies the column-major `src_rows x n` matrix `src` into rows `row..row + src_rows` of the
/// column-major `dst_rows x n` matrix `dst` (building a network input from a batch's fields).
pub(crate) fn copy_rows(
    dst: &mut [f32],
    dst_rows: usize,
    row: usize,
    src: &[f32],
    src_rows: usize,
) {
    if src_rows == 0 {
        return;
    }
    debug_assert!(row + src_rows <= dst_rows);
    debug_assert_eq!(dst.len() / dst_rows, src.len() / src_rows);
    for (d, s) in dst
        .chunks_exact_mut(dst_rows)
        .zip(src.chunks_exact(src_rows))
    {
        d[row..row + src_rows].copy_from_slice(s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive(a: MatRef<'_>, b: MatRef<'_>) -> Vec<f32> {
        let mut c = vec![0.0; a.rows * b.cols];
        for j in 0..b.cols {
            for i in 0..a.rows {
                c[i + j * a.rows] = (0..a.cols)
                    .map(|p| a.data[i * a.rs + p * a.cs] * b.data[p * b.rs + j * b.cs])
                    .sum();
            }
        }
        c
    }

    #[test]
    fn sgemm_honours_transposed_views() {
        let (m, k, n) = (7, 9, 11);
        let a: Vec<f32> = (0..m * k).map(|i| (i % 5) as f32 - 2.0).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i % 7) as f32 * 0.5).collect();
        // a stored as its transpose (k x m), b stored as its transpose (n x k).
        let at = {
            let mut t = vec![0.0; m * k];
            transpose(&a, m, k, &mut t);
            t
        };
        let bt = {
            let mut t = vec![0.0; k * n];
            transpose(&b, k, n, &mut t);
            t
        };
        let a_view = MatRef::col_major(&at, k, m).t();
        let b_view = MatRef::col_major(&bt, n, k).t();
        let mut c = vec![f32::NAN; m * n];
        sgemm(&mut c, a_view, b_view);
        let want = naive(MatRef::col_major(&a, m, k), MatRef::col_major(&b, k, n));
        assert_eq!(c, want);
    }

    /// What [`panel_gemm`] promises for every element: the fused multiply-add chain in order of
    /// `p`, starting from 0.
    fn fused_chain(a: MatRef<'_>, b: MatRef<'_>) -> Vec<f32> {
        let mut c = vec![0.0; a.rows * b.cols];
        for j in 0..b.cols {
            for i in 0..a.rows {
                let mut acc = 0.0f32;
                for p in 0..a.cols {
                    acc = a.data[i * a.rs + p * a.cs].mul_add(b.data[p * b.rs + j * b.cs], acc);
                }
                c[i + j * a.rows] = acc;
            }
        }
        c
    }

    #[test]
    fn panel_gemm_computes_each_element_as_the_fused_chain() {
        if !has_fma_kernel() {
            eprintln!("no AVX2/FMA on this CPU: panel_gemm does not run here, nothing to check");
            return;
        }
        let mut rng = hac_core::Rng::seed_from(7);
        // Full blocks, leftover vectors, leftover scalar rows and columns, long reductions (more
        // than one panel of the strided path).
        let shapes = [
            (64, 64, 256),
            (64, 5, 9),
            (7, 9, 11),
            (37, 13, 6),
            (100, 20, 17),
            (16, 64, 4),
            (64, 300, 64),
            (8, 3, 1),
        ];
        for (m, k, n) in shapes {
            // `a` as the rows 2..2 + m of a taller column-major matrix (columns contiguous, with a
            // stride beyond m), `b` both column-major and as the transpose of a stored matrix.
            let lda = m + 3;
            let a_data: Vec<f32> = (0..lda * k).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let a = MatRef {
                data: &a_data[2..],
                rows: m,
                cols: k,
                rs: 1,
                cs: lda,
            };
            let b_data: Vec<f32> = (0..2 * k * n).map(|_| rng.uniform(-1.0, 1.0)).collect();
            // Every other element of a column-major `2k x n` matrix: neither strides 1.
            let b_strided = MatRef {
                data: &b_data,
                rows: k,
                cols: n,
                rs: 2,
                cs: 2 * k,
            };
            for b in [
                MatRef::col_major(&b_data[..k * n], k, n),
                MatRef::col_major(&b_data[..k * n], n, k).t(),
                b_strided,
            ] {
                let mut c = vec![f32::NAN; m * n];
                panel_gemm(&mut c, a, b, Epilogue::Store);
                let want = fused_chain(a, b);
                assert!(
                    c.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits()),
                    "{m}x{k} by {k}x{n} (b strides {} {}): not the fused chain",
                    b.rs,
                    b.cs
                );
            }
        }
    }

    /// The epilogues in the kernel's registers give the same floats as the separate pass over the
    /// product, bias gradients included, for shapes with leftover vectors, rows and columns.
    #[test]
    fn epilogues_in_the_kernel_match_the_separate_pass() {
        if !has_fma_kernel() {
            eprintln!("no AVX2/FMA on this CPU: panel_gemm does not run here, nothing to check");
            return;
        }
        let mut rng = hac_core::Rng::seed_from(8);
        let mut uniform =
            |len: usize| -> Vec<f32> { (0..len).map(|_| rng.uniform(-1.0, 1.0)).collect() };
        for (m, k, n) in [
            (64, 64, 256),
            (64, 5, 9),
            (37, 13, 6),
            (100, 20, 17),
            (16, 64, 1),
        ] {
            let (a_data, b_data) = (uniform(m * k), uniform(k * n));
            let (a, b) = (
                MatRef::col_major(&a_data, m, k),
                MatRef::col_major(&b_data, k, n),
            );
            let mut bias = uniform(m);
            // A NaN in a pre-activation becomes 0, in the kernel as in the pass.
            bias[m / 2] = f32::NAN;
            // About half the ReLU outputs are 0.
            let h: Vec<f32> = uniform(m * n).iter().map(|v| v.max(0.0)).collect();
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();

            let mut plain = vec![0.0; m * n];
            panel_gemm(&mut plain, a, b, Epilogue::Store);

            let mut want = plain.clone();
            Epilogue::BiasRelu(&bias).apply(&mut want);
            let mut got = vec![f32::NAN; m * n];
            panel_gemm(&mut got, a, b, Epilogue::BiasRelu(&bias));
            assert_eq!(bits(&got), bits(&want), "bias + ReLU, {m}x{k} by {k}x{n}");
            assert!(got.iter().all(|v| *v >= 0.0));

            for with_bias_grad in [false, true] {
                let (mut want_bg, mut got_bg) = (vec![f32::NAN; m], vec![f32::NAN; m]);
                let mut want = plain.clone();
                Epilogue::ReluMask {
                    h: &h,
                    bias_grad: with_bias_grad.then_some(&mut want_bg[..]),
                }
                .apply(&mut want);
                let mut got = vec![f32::NAN; m * n];
                panel_gemm(
                    &mut got,
                    a,
                    b,
                    Epilogue::ReluMask {
                        h: &h,
                        bias_grad: with_bias_grad.then_some(&mut got_bg[..]),
                    },
                );
                assert_eq!(bits(&got), bits(&want), "ReLU mask, {m}x{k} by {k}x{n}");
                assert_eq!(
                    bits(&got_bg),
                    bits(&want_bg),
                    "bias gradient, {m}x{k} by {k}x{n}"
                );
            }
        }
    }

    #[test]
    fn dot_matches_sequential_sum_on_integers() {
        let a: Vec<f32> = (0..21).map(|i| i as f32).collect();
        let b: Vec<f32> = (0..21).map(|i| (i % 3) as f32).collect();
        let want: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        assert_eq!(dot(&a, &b), want);
    }
}
