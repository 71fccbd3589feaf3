//! Loops over a field's cells on both cores, where that pays. Each value is made as one thread
//! would make it, so the bits do not depend on how the work was split (the default mission's
//! files are the same with one core or many).

use faer::linalg::matmul::matmul;
use faer::traits::ComplexField;
use faer::{c64, Accum, Mat, MatRef, Par};
use rayon::prelude::*;

/// Work (cells times the operations per cell, in units of a few flops) below which a loop
/// stays on the calling thread: handing it to rayon's pool costs tens of microseconds, about
/// what a 48 x 96 field's pass takes (4,608 cells).
pub const MIN_WORK: usize = 1 << 20;

/// Whether `n` items of `weight` each are work enough to share with the pool.
fn worth_sharing(n: usize, weight: usize) -> bool {
    n.saturating_mul(weight.max(1)) >= MIN_WORK
}

/// How many items a task takes so that it holds at least half of [`MIN_WORK`].
fn per_task(weight: usize) -> usize {
    (MIN_WORK / 2 / weight.max(1)).max(1)
}

/// How many of `n` rows a block of a blocked kernel holds ([`chunks_mut`] with this width):
/// all of them when the work is too small to share, else a task's worth.
pub fn block_rows(n: usize, weight: usize) -> usize {
    match worth_sharing(n, weight) {
        true => per_task(weight),
        false => n.max(1),
    }
}

/// `f(i)` for every `i < n`, in order; `weight` is the work of one item.
pub fn map<T: Send>(n: usize, weight: usize, f: impl Fn(usize) -> T + Sync + Send) -> Vec<T> {
    if !worth_sharing(n, weight) {
        return (0..n).map(f).collect();
    }
    (0..n).into_par_iter().with_min_len(per_task(weight)).map(f).collect()
}

/// `f(k, chunk)` over `out` cut into chunks of `width` values (a grid's rows); `weight` is the
/// work of one value.
pub fn chunks_mut<T: Send>(out: &mut [T], width: usize, weight: usize, f: impl Fn(usize, &mut [T]) + Sync + Send) {
    let width = width.max(1);
    if !worth_sharing(out.len(), weight) {
        out.chunks_mut(width).enumerate().for_each(|(k, c)| f(k, c));
        return;
    }
    let rows = (per_task(weight) / width).max(1);
    out.par_chunks_mut(width)
        .enumerate()
        .with_min_len(rows)
        .for_each(|(k, c)| f(k, c));
}

/// The product `a b` of a tall `a` (a field's cells by a few columns) and a small `b`, a block
/// of `a`'s rows at a time on every core: each block's rows as the whole product makes them.
pub fn product<T: ComplexField>(a: MatRef<'_, T>, b: MatRef<'_, T>) -> Mat<T> {
    let (n, m) = (a.nrows(), b.ncols());
    let weight = a.ncols() * m;
    let mut out = Mat::<T>::zeros(n, m);
    if !worth_sharing(n, weight) || m == 0 {
        matmul(out.as_mut(), Accum::Replace, a, b, T::one_impl(), Par::Seq);
        return out;
    }
    let rows = per_task(weight);
    out.as_mut()
        .par_row_chunks_mut(rows)
        .enumerate()
        .for_each(|(k, block)| {
            let a = a.subrows(k * rows, block.nrows());
            matmul(block, Accum::Replace, a, b, T::one_impl(), Par::Seq);
        });
    out
}

/// `dst + alpha a b` into `dst` (`alpha` 1 or -1: the same bits as adding or subtracting
/// [`product`]'s result, without a second field-sized matrix or a pass to add it), a block of
/// rows at a time on every core.
pub fn product_add(mut dst: faer::MatMut<'_, f64>, a: MatRef<'_, f64>, b: MatRef<'_, f64>, alpha: f64) {
    let (n, m) = (a.nrows(), b.ncols());
    let weight = a.ncols() * m;
    if !worth_sharing(n, weight) || m == 0 {
        matmul(dst.as_mut(), Accum::Add, a, b, alpha, Par::Seq);
        return;
    }
    let rows = per_task(weight);
    dst.par_row_chunks_mut(rows).enumerate().for_each(|(k, block)| {
        let a = a.subrows(k * rows, block.nrows());
        matmul(block, Accum::Add, a, b, alpha, Par::Seq);
    });
}

/// The product `a b` of a tall real `a` and a small complex `b` (the modes `F C` from their
/// factors), as two real products `a Re(b)` and `a Im(b)`, a block of rows at a time on every
/// core. A complex copy of `a` times `b` held a second field-sized complex matrix at the refit
/// (47 MB at 384 x 768, the server's peak) and spent half its flops multiplying by zeros.
pub fn real_times_complex(a: MatRef<'_, f64>, b: MatRef<'_, c64>) -> Mat<c64> {
    let (n, m) = (a.nrows(), b.ncols());
    let (b_re, b_im) = (
        Mat::<f64>::from_fn(b.nrows(), m, |i, j| b[(i, j)].re),
        Mat::<f64>::from_fn(b.nrows(), m, |i, j| b[(i, j)].im),
    );
    let mut out = Mat::<c64>::zeros(n, m);
    let block = |k: usize, rows: usize, mut block: faer::MatMut<'_, c64>| {
        let a = a.subrows(k * rows, block.nrows());
        let (mut re, mut im) = (Mat::<f64>::zeros(a.nrows(), m), Mat::<f64>::zeros(a.nrows(), m));
        matmul(re.as_mut(), Accum::Replace, a, b_re.as_ref(), 1.0, Par::Seq);
        matmul(im.as_mut(), Accum::Replace, a, b_im.as_ref(), 1.0, Par::Seq);
        for j in 0..m {
            for i in 0..a.nrows() {
                block[(i, j)] = c64::new(re[(i, j)], im[(i, j)]);
            }
        }
    };
    if !worth_sharing(n, 2 * a.ncols() * m) || m == 0 {
        block(0, n, out.as_mut());
        return out;
    }
    let rows = per_task(2 * a.ncols() * m);
    out.as_mut()
        .par_row_chunks_mut(rows)
        .enumerate()
        .for_each(|(k, b)| block(k, rows, b));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_split_gives_the_one_thread_result_in_order() {
        for n in [0, 1, 100, MIN_WORK - 1, MIN_WORK, 3 * MIN_WORK + 7] {
            let want: Vec<f64> = (0..n).map(|i| (i as f64).sqrt() * 0.1).collect();
            assert_eq!(map(n, 1, |i| (i as f64).sqrt() * 0.1), want);
            let mut out = vec![0.0; n];
            chunks_mut(&mut out, 37, 1, |k, c| {
                c.iter_mut()
                    .enumerate()
                    .for_each(|(j, x)| *x = ((k * 37 + j) as f64).sqrt() * 0.1)
            });
            assert_eq!(out, want);
        }
    }

    #[test]
    fn a_tall_product_is_the_whole_product_to_the_bit() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for (n, k, m) in [(5, 3, 2), (3 * MIN_WORK + 17, 13, 11), (MIN_WORK / 2 + 1, 24, 24)] {
            let a = Mat::<f64>::from_fn(n, k, |_, _| rng.random::<f64>() - 0.5);
            let b = Mat::<f64>::from_fn(k, m, |_, _| rng.random::<f64>() - 0.5);
            assert!(product(a.as_ref(), b.as_ref()) == &a * &b, "{n} x {k} x {m}");
            let c = faer::Mat::<faer::c64>::from_fn(n, k, |i, j| faer::c64::new(a[(i, j)], a[(i, j)] * 0.5));
            let d = faer::Mat::<faer::c64>::from_fn(k, m, |i, j| faer::c64::new(b[(i, j)], -b[(i, j)]));
            assert!(product(c.as_ref(), d.as_ref()) == &c * &d, "complex {n} x {k} x {m}");
        }
    }

    /// Adding or subtracting a product in place gives the bits of the product made apart and
    /// then added or subtracted (what the DMD update did, with a field-sized matrix more).
    #[test]
    fn a_product_added_in_place_is_the_product_added() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for (n, k, m) in [
            (5, 3, 2),
            (3 * MIN_WORK / 20 + 17, 10, 10),
            (3 * MIN_WORK / 50 + 3, 5, 10),
            (7, 4, 0),
        ] {
            let a = Mat::<f64>::from_fn(n, k, |_, _| rng.random::<f64>() - 0.5);
            let b = Mat::<f64>::from_fn(k, m, |_, _| rng.random::<f64>() - 0.5);
            let c = Mat::<f64>::from_fn(n, m, |_, _| rng.random::<f64>() - 0.5);
            for alpha in [1.0, -1.0] {
                let mut got = c.clone();
                product_add(got.as_mut(), a.as_ref(), b.as_ref(), alpha);
                let p = product(a.as_ref(), b.as_ref());
                let want = if alpha > 0.0 { &c + &p } else { &c - &p };
                assert!(got == want, "{n} x {k} x {m}, {alpha}");
            }
        }
    }

    /// The real-by-complex product is the two real products `a Re(b)`, `a Im(b)` of the whole
    /// matrix to the bit, however its rows were split, and the complex product of `a`'s complex
    /// copy within a few ulps of the entries' scale (each part is a sum of the same k products;
    /// the complex kernel may add them in another order).
    #[test]
    fn a_real_times_complex_product_is_the_complex_product() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for (n, k, m) in [(5, 3, 2), (3 * MIN_WORK / 20 + 17, 10, 10), (7, 4, 0)] {
            let a = Mat::<f64>::from_fn(n, k, |_, _| rng.random::<f64>() - 0.5);
            let b = Mat::<c64>::from_fn(k, m, |_, _| {
                c64::new(rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5)
            });
            let got = real_times_complex(a.as_ref(), b.as_ref());
            let re = &a * Mat::<f64>::from_fn(k, m, |i, j| b[(i, j)].re);
            let im = &a * Mat::<f64>::from_fn(k, m, |i, j| b[(i, j)].im);
            assert_eq!((got.nrows(), got.ncols()), (n, m));
            let cells = || (0..m).flat_map(|j| (0..n).map(move |i| (i, j)));
            assert!(
                cells().all(|(i, j)| got[(i, j)] == c64::new(re[(i, j)], im[(i, j)])),
                "{n} x {k} x {m}"
            );
            let want = crate::dmd::linalg::to_complex(a.as_ref()) * &b;
            let worst = cells()
                .map(|(i, j)| (got[(i, j)] - want[(i, j)]).norm())
                .fold(0.0, f64::max);
            assert!(worst <= 16.0 * f64::EPSILON * k as f64, "{n} x {k} x {m}: {worst:e}");
        }
    }
}
