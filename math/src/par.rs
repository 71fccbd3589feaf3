//! Loops over a field's cells on both cores, where that pays. Each value is made as one thread
//! would make it, so the bits do not depend on how the work was split (the default mission's
//! files are the same with one core or many).

use faer::linalg::matmul::matmul;
use faer::traits::ComplexField;
use faer::{Accum, Mat, MatRef, Par};
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
}
