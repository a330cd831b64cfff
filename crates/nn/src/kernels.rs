//! Matrix kernels on column-major `f32` slices.
//!
//! Every large product goes to matrixmultiply's `sgemm` (AVX2/FMA, chosen at run time). This crate
//! forbids `unsafe`, so it reaches `sgemm` through nalgebra's `gemm` on strided views: nalgebra
//! forwards the views' strides unchanged, which makes transposed operands free. nalgebra only does
//! so when every dimension is at least 6; the thin products below that (the first layer of a
//! low-dimensional input, the output layer, single samples) use the vector loops here, written so
//! that the compiler vectorises their inner loop.

use nalgebra::{DMatrixView, DMatrixViewMut};

/// The smallest dimension for which nalgebra hands a product to matrixmultiply.
pub(crate) const SGEMM_MIN_DIM: usize = 6;

/// Whether an `m x k` by `k x n` product takes the `sgemm` path.
pub(crate) fn fits_sgemm(m: usize, k: usize, n: usize) -> bool {
    m >= SGEMM_MIN_DIM && k >= SGEMM_MIN_DIM && n >= SGEMM_MIN_DIM
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

/// `c = a * b` through matrixmultiply's `sgemm`; `c` is contiguous column-major and is
/// overwritten (never read). Callers check [`fits_sgemm`] first: below it nalgebra would fall back
/// to a slow generic loop.
pub(crate) fn sgemm(c: &mut [f32], a: MatRef<'_>, b: MatRef<'_>) {
    debug_assert!(fits_sgemm(a.rows, a.cols, b.cols));
    debug_assert_eq!(a.cols, b.rows);
    let a = DMatrixView::from_slice_with_strides(a.data, a.rows, a.cols, a.rs, a.cs);
    let b = DMatrixView::from_slice_with_strides(b.data, b.rows, b.cols, b.rs, b.cs);
    let mut c = DMatrixViewMut::from_slice(&mut c[..a.nrows() * b.ncols()], a.nrows(), b.ncols());
    c.gemm(1.0, &a, &b, 0.0);
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
    let mut round = || {
        let w = MatRef::col_major(&w, width, width);
        sgemm(&mut out, w, MatRef::col_major(&x, width, batch));
        sgemm(&mut out, w.t(), MatRef::col_major(&dz, width, batch));
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
#[inline]
pub(crate) fn axpy(y: &mut [f32], s: f32, x: &[f32]) {
    debug_assert_eq!(y.len(), x.len());
    for (y, x) in y.iter_mut().zip(x) {
        *y += s * x;
    }
}

/// Dot product with eight independent partial sums, so that it vectorises (floating-point addition
/// is not associative, so the compiler will not reorder a single running sum).
#[inline]
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

    #[test]
    fn dot_matches_sequential_sum_on_integers() {
        let a: Vec<f32> = (0..21).map(|i| i as f32).collect();
        let b: Vec<f32> = (0..21).map(|i| (i % 3) as f32).collect();
        let want: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        assert_eq!(dot(&a, &b), want);
    }
}
