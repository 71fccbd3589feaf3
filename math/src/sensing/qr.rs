//! Greedy pivoted-QR sensor selection: points (paper Alg. 1) and disks of radius k (Alg. 2),
//! plus a greedy D-optimal (log-det) disk selector for comparison.
//!
//! Column `p` of `Phi Phi^T` is represented by `c_p = R phi_p^T` (r numbers, `Phi = Q R`), so a
//! column norm costs O(r) and a Householder deflation of all columns O(r N).
//!
//! Block QR reading (DESIGN.md "open points"): a disk's weight is the sum of its columns' norms
//! (`W_i`); after a pick, ONE direction is removed from every column, the chosen block's
//! leading left singular vector (removing the block's whole span would exhaust rank r after one
//! disk of more than r cells). The per-disk share `w` is the chosen weight over the sum of all
//! column norms at that step. Once the r directions are used up (every remaining weight below
//! 1e-12 of the first), the remaining disks are chosen by the undeflated weights, so boats
//! beyond the rank still go where the modes have energy.

use super::{Room, SensingError};
use crate::grid::{Cell, Grid};
use faer::{Mat, MatRef};
use serde::Serialize;

/// One chosen sensing disk.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Disk {
    pub centre: Cell,
    /// Flat indices of the cells it covers (clipped at the borders).
    pub cells: Vec<usize>,
    /// Cumulative weight `W` of the disk when it was chosen.
    pub weight: f64,
    /// Its share `w` of the total weight at that step.
    pub share: f64,
}

/// `c_p = R phi_p^T` for every cell `p` (`Phi = Q R`), stored as `r` rows of `N` values so
/// the passes over all cells run along contiguous memory (and vectorise across cells).
///
/// Deflation is lazy: the chosen directions `q_1..q_k` are orthonormal, so the residual of
/// `c_p` after removing them has `q_{k+1} . residual = q_{k+1} . c_p`, and its squared norm
/// drops by exactly that dot squared. A pick therefore costs one pass over the original
/// columns; a norm that has lost more than half its digits to cancellation is recomputed from
/// the explicit residual (LAPACK's pivoted QR does the same).
struct Coords {
    r: usize,
    n: usize,
    rows: Vec<f64>,
    /// Directions removed so far (orthonormal, length r each).
    removed: Vec<Vec<f64>>,
    /// Squared residual norms, and the originals (for the cancellation test).
    n2: Vec<f64>,
    n2_orig: Vec<f64>,
}

/// An upper-triangular `R` with `R^T R = Phi^T Phi` (so `|R phi_p^T|` are the column norms of
/// `Phi Phi^T`): the Cholesky factor of the small Gram matrix, or the QR's `R` when the Gram
/// matrix is too ill-conditioned for Cholesky to be accurate.
fn triangular_factor(phi: MatRef<'_, f64>) -> Mat<f64> {
    match crate::dmd::linalg::gram_cholesky(phi) {
        Some(l) => l.transpose().to_owned(),
        None => phi.qr().thin_R().to_owned(),
    }
}

impl Coords {
    /// Each row `i` of `R Phi^T` and each cell's squared norm made on the cores as one thread
    /// makes it (the same bits: a row's terms in `k` order, a cell's in `i` order), reading
    /// the basis's columns where they are (a copy of the basis was 24 MB at 384 x 768).
    fn new(phi: MatRef<'_, f64>) -> Self {
        let (n, r) = (phi.nrows(), phi.ncols());
        let rm = triangular_factor(phi);
        let owned;
        let phi = match phi.col(0).try_as_col_major() {
            Some(_) => phi,
            None => {
                owned = phi.to_owned();
                owned.as_ref()
            }
        };
        let col = |k: usize| phi.col(k).try_as_col_major().expect("contiguous columns").as_slice();
        let mut rows = vec![0.0; n * r];
        // Row i of R Phi^T = sum_k R[i, k] Phi[:, k]^T (R upper triangular).
        crate::par::chunks_mut(&mut rows, n.max(1), r, |i, row| {
            for k in i..r {
                let a = rm[(i, k)];
                for (x, v) in row.iter_mut().zip(col(k)) {
                    *x += a * v;
                }
            }
        });
        let mut n2 = vec![0.0; n];
        let block = crate::par::block_rows(n, r);
        crate::par::chunks_mut(&mut n2, block, r, |b, out| {
            for row in rows.chunks_exact(n) {
                for (s, v) in out.iter_mut().zip(&row[b * block..]) {
                    *s += v * v;
                }
            }
        });
        Self {
            r,
            n,
            rows,
            removed: vec![],
            n2_orig: n2.clone(),
            n2,
        }
    }

    /// Current residual norms (recomputing the ones cancellation has made unreliable). Near
    /// the rank's end that is most cells: recomputed [`STALE_AT_ONCE`] at a time
    /// ([`residual_norms`]), the blocks of cells on the cores.
    fn norms(&mut self) -> Vec<f64> {
        self.refresh();
        self.n2.iter().map(|v| v.max(0.0).sqrt()).collect()
    }

    /// Recompute the squared norms cancellation has made unreliable ([`Self::norms`]).
    fn refresh(&mut self) {
        if !self.removed.is_empty() {
            use rayon::prelude::*;
            let (n, r, rows, removed) = (self.n, self.r, &self.rows, &self.removed);
            let block = crate::par::block_rows(n, r * removed.len());
            let recompute = |b: usize, (n2, orig): (&mut [f64], &mut [f64])| {
                let stale: Vec<usize> = (0..n2.len()).filter(|&i| n2[i] < 1e-8 * orig[i]).collect();
                for cells in stale.chunks(STALE_AT_ONCE) {
                    let fresh = residual_norms((rows, n, removed), cells.iter().map(|&i| b * block + i));
                    for (&i, v) in cells.iter().zip(fresh) {
                        // Exact from here on: compare future cancellation with this value.
                        (n2[i], orig[i]) = (v, v);
                    }
                }
            };
            let (n2, orig) = (&mut self.n2, &mut self.n2_orig);
            // One block stays on this thread: a parallel iterator of one item still hands it
            // to the pool and waits (a wake-up of tens of microseconds at each of r picks).
            match block >= n {
                true => recompute(0, (n2, orig)),
                false => {
                    let pairs = n2.par_chunks_mut(block).zip(orig.par_chunks_mut(block));
                    pairs.enumerate().for_each(|(b, pair)| recompute(b, pair));
                }
            }
        }
    }

    /// The cell of largest residual norm not yet `chosen` (the lowest index on ties, the norms
    /// compared as [`Self::norms`] gives them), and that norm; `None` when every cell is chosen.
    fn largest(&mut self, chosen: &[bool]) -> Option<(usize, f64)> {
        self.refresh();
        let (mut p, mut np) = (usize::MAX, f64::NEG_INFINITY);
        for (j, v) in self.n2.iter().enumerate() {
            let v = v.max(0.0).sqrt();
            if v > np && !chosen[j] {
                (p, np) = (j, v);
            }
        }
        (p != usize::MAX).then_some((p, np))
    }

    /// The residual of column `p` after the removed directions (twice, for orthogonality).
    fn residual(&self, p: usize) -> Vec<f64> {
        let mut c: Vec<f64> = (0..self.r).map(|i| self.rows[i * self.n + p]).collect();
        for _ in 0..2 {
            project_out(&mut c, &self.removed);
        }
        c
    }

    /// Remove direction `q` (length r) from every column.
    fn deflate(&mut self, q: &[f64]) {
        let mut q = q.to_vec();
        for _ in 0..2 {
            project_out(&mut q, &self.removed);
        }
        let nq = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !(nq > 1e-12) {
            return;
        }
        q.iter_mut().for_each(|v| *v /= nq);
        // Per cell, q . c_p in `i` order and the norm's drop, a block of cells on each core.
        let (n, rows) = (self.n, &self.rows);
        let block = crate::par::block_rows(n, self.r);
        crate::par::chunks_mut(&mut self.n2, block, self.r, |b, n2| {
            let mut dots = vec![0.0; n2.len()];
            for (row, &qi) in rows.chunks_exact(n).zip(&q) {
                for (d, v) in dots.iter_mut().zip(&row[b * block..]) {
                    *d += qi * v;
                }
            }
            for (n2, d) in n2.iter_mut().zip(&dots) {
                *n2 -= d * d;
            }
        });
        self.removed.push(q);
    }

    /// The leading left singular vector of the block of residual columns `cells` (the
    /// eigenvector of its r x r Gram matrix with the largest eigenvalue), or `None` for a zero
    /// block.
    fn leading_direction(&self, cells: &[usize]) -> Result<Option<Vec<f64>>, SensingError> {
        let r = self.r;
        let mut gram = Mat::<f64>::zeros(r, r);
        for &p in cells {
            let c = self.residual(p);
            for j in 0..r {
                for i in j..r {
                    gram[(i, j)] += c[i] * c[j];
                }
            }
        }
        let eig = gram
            .self_adjoint_eigen(faer::Side::Lower)
            .map_err(|e| SensingError::Numerical(format!("{e:?}")))?;
        let s = eig.S().column_vector();
        // Eigenvalues come in ascending order.
        Ok((s[r - 1] > 0.0).then(|| eig.U().col(r - 1).iter().copied().collect()))
    }
}

/// How many cells [`residual_norms`] takes at once: their coordinates (r values each) and dots
/// stay in the first-level cache.
const STALE_AT_ONCE: usize = 64;

/// The squared norms of the residuals of `cells` ([`Coords::residual`]), the cells side by
/// side: each cell's arithmetic is [`Coords::residual`]'s and the sum of its squares, term by
/// term in the same order from the same start (`Iterator::sum`'s `-0.0`), so the same bits;
/// the loops run across the cells, many at once, where one cell's dot is a chain of r
/// dependent additions (the norms of 32 boats' picks were a tenth of the epoch at 192 x 384),
/// four at a time where the CPU has AVX2 ([`residuals_here`]).
fn residual_norms((rows, n, removed): (&[f64], usize, &[Vec<f64>]), cells: impl Iterator<Item = usize>) -> Vec<f64> {
    let cells: Vec<usize> = cells.collect();
    let (w, r) = (cells.len(), rows.len() / n.max(1));
    // c[i * w + t]: coordinate i of cell t.
    let mut c: Vec<f64> = (0..r)
        .flat_map(|i| cells.iter().map(move |&p| rows[i * n + p]))
        .collect();
    let mut n2 = vec![-0.0; w];
    residuals_here(&mut c, removed, &mut n2);
    n2
}

/// [`residual_norms`]' arithmetic: `c` holds the cells' coordinates (`c[i * w + t]`, `w` the
/// length of `n2`), made their residuals; `n2` gets each one's squared norm.
#[inline(always)]
fn residuals_side_by_side(c: &mut [f64], removed: &[Vec<f64>], n2: &mut [f64]) {
    let w = n2.len().max(1);
    let mut d = vec![0.0; n2.len()];
    for _ in 0..2 {
        for q in removed {
            d.fill(-0.0);
            for (&qi, ci) in q.iter().zip(c.chunks_exact(w)) {
                d.iter_mut().zip(ci).for_each(|(d, &x)| *d += qi * x);
            }
            for (&qi, ci) in q.iter().zip(c.chunks_exact_mut(w)) {
                ci.iter_mut().zip(&d).for_each(|(x, &d)| *x -= d * qi);
            }
        }
    }
    for ci in c.chunks_exact(w) {
        n2.iter_mut().zip(ci).for_each(|(s, &x)| *s += x * x);
    }
}

crate::simd::on_avx2! {
    /// [`residuals_side_by_side`] as this CPU runs it fastest.
    fn residuals_here(c: &mut [f64], removed: &[Vec<f64>], n2: &mut [f64]) = residuals_side_by_side;
}

/// `c -= sum_j q_j (q_j . c)` for orthonormal `q_j`.
fn project_out(c: &mut [f64], qs: &[Vec<f64>]) {
    for q in qs {
        let d: f64 = q.iter().zip(c.iter()).map(|(a, b)| a * b).sum();
        c.iter_mut().zip(q).for_each(|(x, qi)| *x -= d * qi);
    }
}

/// Greedy pivoted QR (Alg. 1): up to `k` cells, each the column of largest residual norm,
/// whose direction is then removed from all columns. Stops early when the basis is exhausted
/// (a rank-r basis has at most r meaningful pivots). Returns the cells and their `|R_ii|`.
pub fn point_qr(phi: MatRef<'_, f64>, k: usize) -> (Vec<usize>, Vec<f64>) {
    let mut c = Coords::new(phi);
    let first = c.norms().into_iter().fold(0.0, f64::max);
    let mut chosen: Vec<usize> = vec![];
    let mut taken = vec![false; phi.nrows()];
    let mut rdiag = vec![];
    for _ in 0..k.min(phi.nrows()) {
        let Some((p, np)) = c.largest(&taken).filter(|&(_, np)| np > 1e-12 * first) else {
            break;
        };
        chosen.push(p);
        taken[p] = true;
        rdiag.push(np);
        let q = c.residual(p);
        c.deflate(&q);
    }
    (chosen, rdiag)
}

/// Per-row prefix sums of a field, for O(2k+1) sums over disks of one radius.
///
/// Each row's sums are padded by the disk's reach on both sides with their edge values (0 on
/// the left, the row's total on the right), so a disk clipped by an edge reads the same two
/// numbers the clipped segment would, without a test: every row offset is one branch-free,
/// vectorised pass over a row of centres.
struct DiskSums {
    grid: Grid,
    /// rows x `width`: `prefix[r * width + pad + c]` is the sum of row `r`'s first `c` values
    /// (`c` clamped to `0..=cols`).
    prefix: Vec<f64>,
    width: usize,
    pad: usize,
    /// Half-width in columns of the disk's row at each row offset `-reach..=reach`.
    half: Vec<i64>,
    /// Whether every value is >= 0 (a square's sum then bounds its disk's).
    nonnegative: bool,
    /// Whether every value is 0 (nothing taken yet: every disk sum is 0).
    zero: bool,
    /// Per row, whether its values are all `>= 0` and all 0 (the two flags above of a row,
    /// kept so that renewing a few rows need not look at the others).
    row_flags: Vec<(bool, bool)>,
    /// Centres no disk may have (land), each adding 1 to its own disk's sum: empty for none.
    /// Only the overlap test's sums have them ([`Self::barring`]).
    barred: Vec<bool>,
}

impl DiskSums {
    fn new(grid: Grid, v: &[f64], k: f64) -> Self {
        let k = k.max(0.0);
        let reach = k.floor() as i64;
        let half: Vec<i64> = (-reach..=reach)
            .map(|dr| ((k * k + 1e-9 - (dr * dr) as f64).max(0.0)).sqrt().floor() as i64)
            .collect();
        let pad = half.iter().copied().max().unwrap_or(0).max(0) as usize;
        let width = grid.cols + 1 + 2 * pad;
        let mut sums = Self {
            grid,
            prefix: vec![0.0; grid.rows * width],
            width,
            pad,
            half,
            nonnegative: true,
            zero: true,
            row_flags: vec![(true, true); grid.rows],
            barred: vec![],
        };
        sums.renew_rows(v, 0..grid.rows);
        sums
    }

    /// The overlap test's sums: of `covered` (0/1 weights), and 1 more at every centre that is
    /// `dry`, so a disk centred on land reads as touching what is taken.
    fn barring(grid: Grid, covered: &[f64], k: f64, dry: &[bool]) -> Self {
        let mut sums = Self::new(grid, covered, k);
        if dry.iter().any(|&d| d) {
            sums.barred = dry.to_vec();
            sums.zero = false;
        }
        sums
    }

    /// The prefix sums of `rows` made again from `v` (the values of the other rows unchanged
    /// since they were made): a disk taken changes only the rows it spans.
    fn renew_rows(&mut self, v: &[f64], rows: std::ops::Range<usize>) {
        let (cols, pad) = (self.grid.cols, self.pad);
        for r in rows.start..rows.end.min(self.grid.rows) {
            let row = &mut self.prefix[r * self.width..(r + 1) * self.width];
            let mut sum = 0.0;
            for c in 0..cols {
                sum += v[r * cols + c];
                row[pad + c + 1] = sum;
            }
            row[pad + cols + 1..].fill(sum);
            let values = &v[r * cols..(r + 1) * cols];
            self.row_flags[r] = (values.iter().all(|&x| x >= 0.0), values.iter().all(|&x| x == 0.0));
        }
        self.nonnegative = self.row_flags.iter().all(|f| f.0);
        self.zero = self.row_flags.iter().all(|f| f.1) && self.barred.is_empty();
    }

    /// Sum over the disk centred on `cell` (same cells as [`Grid::disk`]).
    fn disk_sum(&self, cell: Cell) -> f64 {
        let reach = (self.half.len() / 2) as i64;
        let mut s = 0.0;
        for (dr, &hw) in (-reach..=reach).zip(&self.half) {
            let row = cell.row as i64 + dr;
            if row < 0 || row >= self.grid.rows as i64 {
                continue;
            }
            let base = row as usize * self.width + self.pad + cell.col;
            let hw = hw as usize;
            s += self.prefix[base + hw + 1] - self.prefix[base - hw];
        }
        if self.barred.get(self.grid.index(cell)).copied().unwrap_or(false) {
            s += 1.0;
        }
        s
    }

    /// Per row of centres, a bound on its largest disk sum: the largest sum over the square
    /// that holds each disk (of side `2 reach + 1`, clipped to the grid), from the prefix sums
    /// summed down the columns, widened by `1e-9` of the field's total for the rounding of
    /// that other order. A bound only for values >= 0 (squared norms, 0/1 weights).
    fn row_bounds(&self) -> Vec<f64> {
        let (rows, cols, width) = (self.grid.rows, self.grid.cols, self.width);
        let reach = self.half.len() / 2;
        // down[r * width + j]: the sum of the first r rows' prefix sums at column j.
        let mut down = vec![0.0; (rows + 1) * width];
        for r in 0..rows {
            let (above, below) = down.split_at_mut((r + 1) * width);
            let (prev, next) = (&above[r * width..], &mut below[..width]);
            let row = &self.prefix[r * width..(r + 1) * width];
            next.iter_mut().zip(prev).zip(row).for_each(|((n, p), x)| *n = p + x);
        }
        let total = down[rows * width + self.pad + cols];
        let slack = 1e-9 * total.abs();
        (0..rows)
            .map(|r| {
                let (top, bottom) = (r.saturating_sub(reach), (r + reach + 1).min(rows));
                let band = |j: usize| down[bottom * width + j] - down[top * width + j];
                (0..cols)
                    .map(|c| band(self.pad + c + reach + 1) - band(self.pad + c - reach))
                    .fold(f64::NEG_INFINITY, f64::max)
                    + slack
            })
            .collect()
    }

    /// [`Self::disk_sum`] of every cell of `row`, into `out` (a value per column): each sum
    /// added up over the same row offsets in the same order, so the values are the same to the
    /// bit; the inner loop runs along a row's contiguous prefix sums.
    fn row_sums(&self, row: usize, out: &mut [f64]) {
        let (rows, cols) = (self.grid.rows as i64, self.grid.cols);
        let reach = (self.half.len() / 2) as i64;
        out.fill(0.0);
        for (dr, &hw) in (-reach..=reach).zip(&self.half) {
            let r = row as i64 + dr;
            if r < 0 || r >= rows {
                continue;
            }
            let p = &self.prefix[r as usize * self.width..(r as usize + 1) * self.width];
            let hw = hw as usize;
            let (hi, lo) = (&p[self.pad + hw + 1..], &p[self.pad - hw..]);
            for ((s, a), b) in out[..cols].iter_mut().zip(hi).zip(lo) {
                *s += a - b;
            }
        }
        if !self.barred.is_empty() {
            let barred = &self.barred[row * cols..(row + 1) * cols];
            out[..cols]
                .iter_mut()
                .zip(barred)
                .filter(|(_, b)| **b)
                .for_each(|(s, _)| *s += 1.0);
        }
    }
}

/// Cells no disk may touch (beyond the fence), as the 0/1 weights the overlap test sums.
pub(crate) fn blocked(grid: &Grid, room: Room<'_>) -> Result<Vec<f64>, SensingError> {
    room.check(grid)?;
    Ok((0..grid.len())
        .map(|i| if room.is_outside(i) { 1.0 } else { 0.0 })
        .collect())
}

/// The overlap test's weights for the disks' first pass, in open water ([`Room`]): the cells
/// beyond the fence and the land taken.
fn open_water(grid: &Grid, room: Room<'_>) -> Result<Vec<f64>, SensingError> {
    let mut covered = blocked(grid, room)?;
    (0..grid.len())
        .filter(|&i| room.is_dry(i))
        .for_each(|i| covered[i] = 1.0);
    Ok(covered)
}

/// The second pass, reaching the coast: the land no longer taken in `covered` (no disk took a
/// dry cell: a disk holds only its wet ones), its centres barred instead.
fn to_coast(grid: Grid, covered: &mut [f64], radius: f64, room: Room<'_>) -> DiskSums {
    (0..covered.len())
        .filter(|&i| room.is_dry(i))
        .for_each(|i| covered[i] = 0.0);
    DiskSums::barring(grid, covered, radius, room.dry)
}

fn check(phi: MatRef<'_, f64>, grid: &Grid, m: usize, radius: f64) -> Result<(), SensingError> {
    if phi.nrows() != grid.len() {
        return Err(SensingError::Input(format!(
            "basis has {} rows, the grid {} cells",
            phi.nrows(),
            grid.len()
        )));
    }
    if phi.ncols() == 0 {
        return Err(SensingError::Input("empty basis".into()));
    }
    if !(radius.is_finite() && radius >= 0.0) {
        return Err(SensingError::Input(format!(
            "radius must be finite and >= 0, got {radius}"
        )));
    }
    if m == 0 {
        return Err(SensingError::Input("at least one disk must be asked for".into()));
    }
    Ok(())
}

/// Pick the best valid candidate by `score`; `taken` marks covered cells (a candidate is
/// valid when its disk covers none of them).
fn best_candidate(grid: &Grid, taken: &DiskSums, score: impl Fn(Cell) -> f64) -> Option<(Cell, f64)> {
    let mut best: Option<(Cell, f64)> = None;
    for i in 0..grid.len() {
        let cell = grid.cell(i);
        let s = score(cell);
        // The overlap test only for a candidate that would win (most do not).
        if best.is_none_or(|(_, b)| s > b) && taken.disk_sum(cell) < 0.5 {
            best = Some((cell, s));
        }
    }
    best
}

/// [`best_candidate`] scored by disk sums, a row of centres at a time ([`DiskSums::row_sums`]):
/// the same pick from the same sums, without a call and its bounds tests per cell and row offset.
/// Rows are summed in the order of a bound on their best disk ([`DiskSums::row_bounds`]) until
/// no row left can beat the best valid centre found: at 192 x 384 the sums of every row were
/// the largest part of the placement (a disk of radius 40 adds 81 row segments a centre).
fn best_disk(grid: &Grid, taken: &DiskSums, sums: &DiskSums) -> Option<(Cell, f64)> {
    let bounds = sums.row_bounds();
    if !sums.nonnegative || bounds.iter().any(|b| !b.is_finite()) {
        return best_disk_of_all(grid, taken, sums);
    }
    let order = rows_by_bound(&bounds);
    // The rows' scores a batch at a time on the cores, then taken in the same order with the
    // same stop as one at a time: the same pick, a few rows past the stop summed for nothing.
    // A row's overlap with the disks taken is summed (on the cores too) only when one of its
    // scores reaches the best at the batch's start: no other centre of it can win.
    // Enough rows that a batch is work enough to share (fewer stayed on one core).
    let batch = crate::par::MIN_WORK.div_ceil(row_work(grid, sums)).max(2);
    best_disk_in_batches(grid, taken, sums, (&bounds, &order), batch)
}

/// The rows of centres, the highest bound first (the lower row on a tie).
fn rows_by_bound(bounds: &[f64]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..bounds.len()).collect();
    order.sort_by(|&a, &b| bounds[b].total_cmp(&bounds[a]).then(a.cmp(&b)));
    order
}

/// The work of one row of disk sums: a segment per row offset for every centre.
fn row_work(grid: &Grid, sums: &DiskSums) -> usize {
    (grid.cols * sums.half.len()).max(1)
}

/// [`best_disk`] with the rows in `order` summed `batch` at a time.
fn best_disk_in_batches(
    grid: &Grid,
    taken: &DiskSums,
    sums: &DiskSums,
    (bounds, order): (&[f64], &[usize]),
    batch: usize,
) -> Option<(Cell, f64)> {
    let (cols, weight) = (grid.cols, row_work(grid, sums));
    let mut best: Option<(usize, f64)> = None;
    let none_taken = vec![0.0; if taken.zero { cols } else { 0 }];
    for rows in order.chunks(batch) {
        let live = rows
            .iter()
            .take_while(|&&r| !best.is_some_and(|(_, b)| bounds[r] < b))
            .count();
        if live == 0 {
            break;
        }
        let row_sums = |of: &DiskSums, r: usize| {
            let mut out = vec![0.0; cols];
            of.row_sums(r, &mut out);
            out
        };
        let scored = crate::par::map(live, weight, |j| row_sums(sums, rows[j]));
        let floor = best.map(|(_, b)| b);
        let overlaps = crate::par::map(live, weight, |j| {
            let reaches = floor.is_none_or(|b| scored[j].iter().any(|&s| s >= b));
            (reaches && !taken.zero).then(|| row_sums(taken, rows[j]))
        });
        for ((&r, scores), overlap) in rows.iter().zip(&scored).zip(&overlaps) {
            if best.is_some_and(|(_, b)| bounds[r] < b) {
                return best.map(|(i, s)| (grid.cell(i), s));
            }
            let overlap = overlap.as_deref().unwrap_or(&none_taken);
            if !overlap.is_empty() {
                best = best_in_row(r * cols, scores, overlap, best);
            }
        }
    }
    best.map(|(i, s)| (grid.cell(i), s))
}

/// The scan's pick through a row of centres (the first at cell `first`) given their scores
/// and their disks' overlap with what is taken: the largest score, the first cell of it,
/// among the centres whose disk touches nothing taken.
fn best_in_row(first: usize, scores: &[f64], overlap: &[f64], mut best: Option<(usize, f64)>) -> Option<(usize, f64)> {
    for (c, (&s, &o)) in scores.iter().zip(overlap).enumerate() {
        let i = first + c;
        if best.is_none_or(|(j, b)| s > b || (s == b && i < j)) && o < 0.5 {
            best = Some((i, s));
        }
    }
    best
}

/// [`best_disk`] by summing every row first: the scan of every centre in order, for scores a
/// bound cannot be put on (not finite, or from values below 0).
fn best_disk_of_all(grid: &Grid, taken: &DiskSums, sums: &DiskSums) -> Option<(Cell, f64)> {
    // The overlap is summed a row of centres at a time, for the rows that hold a centre that
    // would win: once disks are taken, those centres are mostly beside them, and testing them
    // one by one cost more than the scores (7 ms of the fifth pick at 192 x 384).
    let scores = all_row_sums(grid, sums);
    let mut overlap: Vec<Option<Vec<f64>>> = vec![None; grid.rows];
    let mut best: Option<(usize, f64)> = None;
    for (i, &s) in scores.iter().enumerate() {
        if best.is_none_or(|(_, b)| s > b) {
            let (r, c) = (i / grid.cols, i % grid.cols);
            let row = overlap[r].get_or_insert_with(|| {
                let mut row = vec![0.0; grid.cols];
                taken.row_sums(r, &mut row);
                row
            });
            if row[c] < 0.5 {
                best = Some((i, s));
            }
        }
    }
    best.map(|(i, s)| (grid.cell(i), s))
}

/// [`DiskSums::row_sums`] of every row, made on every core (each row's as one thread makes
/// it: the same bits).
fn all_row_sums(grid: &Grid, sums: &DiskSums) -> Vec<f64> {
    use rayon::prelude::*;
    let mut all = vec![0.0; grid.len()];
    all.par_chunks_mut(grid.cols.max(1))
        .enumerate()
        .with_min_len(8)
        .for_each(|(r, row)| sums.row_sums(r, row));
    all
}

/// The centres by their disk sums, for the picks once the directions are used up: those
/// picks score by the undeflated weights, which no pick changes, so the centres are ranked
/// once (a heap, made in O(N)) and each pick takes the first whose disk touches nothing taken.
/// A centre found touching stays so (cells are only ever taken), so it is dropped for good.
/// The same pick as [`best_disk`]: the largest score, the first centre of a tie, among the
/// valid; the scores are [`DiskSums::row_sums`]'s, the same bits (with 32 boats at rank 10,
/// 22 of the 32 picks summed rows of the same scores again, deeper each time).
struct Ranked(std::collections::BinaryHeap<Ranking>);

/// A centre's place in [`Ranked`]: a larger score first, then the lower cell.
#[derive(Debug, PartialEq)]
struct Ranking {
    score: f64,
    cell: usize,
}

impl Eq for Ranking {}

impl Ord for Ranking {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.score.total_cmp(&other.score).then(other.cell.cmp(&self.cell))
    }
}

impl PartialOrd for Ranking {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ranked {
    /// `None` where [`best_disk`] scans every centre instead (scores not finite or from values
    /// below 0: there `total_cmp`'s order is not the scan's).
    fn new(grid: &Grid, sums: &DiskSums) -> Option<Self> {
        let scores = all_row_sums(grid, sums);
        if !sums.nonnegative || scores.iter().any(|s| !s.is_finite()) {
            return None;
        }
        // `+ 0.0` makes a -0.0 (which `total_cmp` puts below 0.0, the scan not) a 0.0.
        let ranks = scores
            .into_iter()
            .enumerate()
            .map(|(cell, s)| Ranking { score: s + 0.0, cell });
        Some(Self(ranks.collect()))
    }

    fn best_valid(&mut self, grid: &Grid, taken: &DiskSums) -> Option<(Cell, f64)> {
        while let Some(top) = self.0.peek() {
            if taken.disk_sum(grid.cell(top.cell)) < 0.5 {
                return Some((grid.cell(top.cell), top.score));
            }
            self.0.pop();
        }
        None
    }
}

/// Block pivoted QR with sensing radius (Alg. 2): up to `m` non-overlapping disks of radius
/// `radius` cells. Fewer are returned only when no non-overlapping disk is left.
pub fn block_qr(phi: MatRef<'_, f64>, grid: &Grid, m: usize, radius: f64) -> Result<Vec<Disk>, SensingError> {
    block_qr_within(phi, grid, m, radius, Room::OPEN)
}

/// [`block_qr`] in the `room` the site leaves: no disk beyond its fence, none centred on land,
/// each disk its wet cells.
pub fn block_qr_within(
    phi: MatRef<'_, f64>,
    grid: &Grid,
    m: usize,
    radius: f64,
    room: Room<'_>,
) -> Result<Vec<Disk>, SensingError> {
    check(phi, grid, m, radius)?;
    let mut c = Coords::new(phi);
    let mut norms = c.norms();
    let original = DiskSums::new(*grid, &norms, radius);
    let mut covered = open_water(grid, room)?;
    let mut coast = false;
    let mut taken = DiskSums::new(*grid, &covered, radius);
    let mut total: f64 = norms.iter().sum();
    let first = total;
    let mut ranked: Option<Option<Ranked>> = None;
    let mut out = vec![];
    while out.len() < m {
        let exhausted = !(total > 1e-12 * first);
        let pick = match exhausted {
            false => best_disk(grid, &taken, &DiskSums::new(*grid, &norms, radius)),
            true => match ranked.get_or_insert_with(|| Ranked::new(grid, &original)) {
                Some(r) => r.best_valid(grid, &taken),
                None => best_disk(grid, &taken, &original),
            },
        };
        let Some((centre, _)) = pick else {
            if coast || !room.has_land() {
                break;
            }
            // No open water left for a disk: the rest reach the coast (centres found touching
            // land in open water may be valid now, so they are ranked again).
            (coast, ranked) = (true, None);
            taken = to_coast(*grid, &mut covered, radius, room);
            continue;
        };
        let cells = room.wet(grid.disk(centre, radius));
        let weight: f64 = cells.iter().map(|&p| norms[p]).sum();
        for &p in &cells {
            covered[p] = 1.0;
        }
        let reach = radius.max(0.0).floor() as usize;
        taken.renew_rows(&covered, centre.row.saturating_sub(reach)..centre.row + reach + 1);
        let share = if total > 0.0 { weight / total } else { 0.0 };
        if !exhausted {
            // Deflate by the block's leading left singular vector.
            if let Some(q) = c.leading_direction(&cells)? {
                c.deflate(&q);
                norms = c.norms();
                total = norms.iter().sum();
            }
        }
        out.push(Disk {
            centre,
            cells,
            weight,
            share,
        });
    }
    Ok(out)
}

/// Greedy D-optimal disks: each pick maximises the gain in `log det` of the information matrix
/// `sum_{p in L} phi_p^T phi_p + eps I` (eps = 1e-9 of the mean diagonal, so the first pick is
/// defined). Uses the rows of `Phi` only (r x r matrices), never `Phi Phi^T`.
pub fn block_dopt(phi: MatRef<'_, f64>, grid: &Grid, m: usize, radius: f64) -> Result<Vec<Disk>, SensingError> {
    block_dopt_within(phi, grid, m, radius, Room::OPEN)
}

/// [`block_dopt`] in the `room` the site leaves ([`block_qr_within`]).
pub fn block_dopt_within(
    phi: MatRef<'_, f64>,
    grid: &Grid,
    m: usize,
    radius: f64,
    room: Room<'_>,
) -> Result<Vec<Disk>, SensingError> {
    check(phi, grid, m, radius)?;
    let (n, r) = (phi.nrows(), phi.ncols());
    let trace: f64 = (0..r).map(|j| phi.col(j).squared_norm_l2()).sum();
    let eps = 1e-9 * trace / r as f64;
    let mut info = Mat::<f64>::identity(r, r) * faer::Scale(eps);
    let mut covered = open_water(grid, room)?;
    let mut coast = false;
    let mut out = vec![];
    let packed: Vec<(usize, usize)> = (0..r).flat_map(|a| (a..r).map(move |b| (a, b))).collect();
    while out.len() < m {
        // Whiten the rows by the current information: g_p = L^-1 phi_p^T.
        let llt = info
            .llt(faer::Side::Lower)
            .map_err(|e| SensingError::Numerical(format!("{e:?}")))?;
        let mut g = phi.transpose().to_owned();
        faer::linalg::triangular_solve::solve_lower_triangular_in_place(llt.L(), g.as_mut(), faer::Par::Seq);
        // Disk sums of every entry of g_p g_p^T.
        let sums: Vec<DiskSums> = packed
            .iter()
            .map(|&(a, b)| {
                DiskSums::new(
                    *grid,
                    &(0..n).map(|p| g[(a, p)] * g[(b, p)]).collect::<Vec<_>>(),
                    radius,
                )
            })
            .collect();
        let taken = match coast {
            true => DiskSums::barring(*grid, &covered, radius, room.dry),
            false => DiskSums::new(*grid, &covered, radius),
        };
        let gain = |cell: Cell| -> f64 {
            let mut b = Mat::<f64>::identity(r, r);
            for (k, &(i, j)) in packed.iter().enumerate() {
                let v = sums[k].disk_sum(cell);
                b[(i, j)] += v;
                if i != j {
                    b[(j, i)] += v;
                }
            }
            match b.llt(faer::Side::Lower) {
                Ok(l) => (0..r).map(|i| 2.0 * l.L()[(i, i)].ln()).sum(),
                Err(_) => f64::NEG_INFINITY,
            }
        };
        let Some((centre, g_best)) = best_candidate(grid, &taken, gain) else {
            if coast || !room.has_land() {
                break;
            }
            coast = true; // no open water left for a disk: the rest reach the coast
            (0..covered.len())
                .filter(|&i| room.is_dry(i))
                .for_each(|i| covered[i] = 0.0);
            continue;
        };
        let cells = room.wet(grid.disk(centre, radius));
        for &p in &cells {
            covered[p] = 1.0;
            for i in 0..r {
                for j in 0..r {
                    info[(i, j)] += phi[(p, i)] * phi[(p, j)];
                }
            }
        }
        out.push(Disk {
            centre,
            cells,
            weight: g_best,
            share: 0.0,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod row_sum_tests {
    use super::*;

    /// The coordinates `R Phi^T`, their squared norms and a deflation's new norms, made a block
    /// of cells at a time on the cores, are what one thread makes, to the bit: at a size whose
    /// work is shared ([`crate::par::MIN_WORK`]), and on a basis that is a view, not a `Mat`.
    #[test]
    fn the_coordinates_made_on_the_cores_are_one_threads_to_the_bit() {
        let (n, r) = (150_001, 7);
        assert!(
            n * r >= crate::par::MIN_WORK,
            "the work must be shared for the test to test it"
        );
        let value = |i: usize, k: usize| ((i * 7919 + k * 104_729) % 1009) as f64 / 1009.0 - 0.5;
        let (tall, across) = (Mat::from_fn(n, r, value), Mat::from_fn(r, n, |k, i| value(i, k)));
        for phi in [tall.as_ref(), across.as_ref().transpose()] {
            let n = phi.nrows();
            let rm = triangular_factor(phi);
            let mut rows = vec![0.0; n * r];
            let mut n2 = vec![0.0; n];
            for i in 0..r {
                for k in i..r {
                    (0..n).for_each(|p| rows[i * n + p] += rm[(i, k)] * phi[(p, k)]);
                }
                (0..n).for_each(|p| n2[p] += rows[i * n + p] * rows[i * n + p]);
            }
            let mut c = Coords::new(phi);
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&c.rows), bits(&rows));
            assert_eq!(bits(&c.n2), bits(&n2));
            let raw: Vec<f64> = (0..r).map(|i| 1.0 + i as f64).collect();
            let norm = raw.iter().map(|v| v * v).sum::<f64>().sqrt();
            let q: Vec<f64> = raw.iter().map(|v| v / norm).collect();
            for (p, n2) in n2.iter_mut().enumerate() {
                let d = (0..r).fold(0.0, |d, i| d + q[i] * rows[i * n + p]);
                *n2 -= d * d;
            }
            c.deflate(&raw);
            assert_eq!(bits(&c.n2), bits(&n2));
        }
    }

    /// Every centre's row sum is its disk sum to the bit, on grids narrower than the disk,
    /// as wide, and wider, with radii from 0 to past the grid.
    #[test]
    fn row_sums_are_the_disk_sums_to_the_bit_and_the_disks_cells() {
        for (rows, cols) in [(1, 1), (3, 7), (9, 4), (12, 31)] {
            let grid = Grid::new(rows, cols, 1.0).unwrap();
            let v: Vec<f64> = (0..grid.len()).map(|i| ((i * 7919) % 97) as f64 / 13.0 - 3.0).collect();
            for radius in [0.0, 0.5, 1.0, 2.5, 3.0, 6.2, 40.0] {
                let sums = DiskSums::new(grid, &v, radius);
                let mut row = vec![f64::NAN; cols];
                for r in 0..rows {
                    sums.row_sums(r, &mut row);
                    for (c, s) in row.iter().enumerate() {
                        let want = sums.disk_sum(Cell::new(r, c));
                        // The padded prefix sums read the disk's own cells, clipped at the
                        // edges: a difference of prefix sums of at most 12 x 31 values of
                        // size <= 5 loses a few ulps of ~2000 (1e-9 is millions of them).
                        let cells: f64 = grid.disk(Cell::new(r, c), radius).iter().map(|&i| v[i]).sum();
                        assert!(
                            (want - cells).abs() < 1e-9,
                            "{rows}x{cols} radius {radius} at ({r}, {c})"
                        );
                        assert_eq!(
                            s.to_bits(),
                            want.to_bits(),
                            "{rows}x{cols} radius {radius} at ({r}, {c})"
                        );
                    }
                }
            }
        }
    }

    /// The residual norms made side by side are each cell's own, to the bit, after one, a few
    /// and every direction removed (where cancellation leaves rounding only), for any cells in
    /// any order (repeats too), and nothing for no cells.
    #[test]
    fn the_residual_norms_side_by_side_are_each_cells_own() {
        let (n, r) = (301, 6);
        let phi = Mat::from_fn(n, r, |i, j| ((i * (j + 3)) as f64 * 0.173).sin() + 0.01 * j as f64);
        let mut c = Coords::new(phi.as_ref());
        for k in 0..r {
            let q: Vec<f64> = (0..r).map(|i| ((i + 2 * k) as f64 * 0.71).cos()).collect();
            c.deflate(&q);
            let cells: Vec<usize> = (0..n).rev().step_by(k + 1).chain([7, 7, 0]).collect();
            let got = residual_norms((&c.rows, c.n, &c.removed), cells.iter().copied());
            for (&p, g) in cells.iter().zip(&got) {
                let want: f64 = c.residual(p).iter().map(|v| v * v).sum();
                assert_eq!(g.to_bits(), want.to_bits(), "cell {p} after {} directions", k + 1);
            }
        }
        assert!(residual_norms((&c.rows, c.n, &c.removed), std::iter::empty()).is_empty());
    }

    /// Sums renewed in the rows a disk spans are the sums made afresh, to the bit, disk after
    /// disk (at the borders too), and so are their flags.
    #[test]
    fn sums_renewed_where_a_disk_was_taken_are_made_afresh() {
        let grid = Grid::new(19, 27, 1.0).unwrap();
        for radius in [0.0, 2.5, 6.0] {
            let mut covered = vec![0.0; grid.len()];
            let mut taken = DiskSums::new(grid, &covered, radius);
            for centre in [Cell::new(0, 0), Cell::new(9, 13), Cell::new(18, 26), Cell::new(3, 20)] {
                grid.disk(centre, radius).into_iter().for_each(|p| covered[p] = 1.0);
                let reach = radius.floor() as usize;
                taken.renew_rows(&covered, centre.row.saturating_sub(reach)..centre.row + reach + 1);
                let fresh = DiskSums::new(grid, &covered, radius);
                let bits = |d: &DiskSums| d.prefix.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&taken), bits(&fresh), "radius {radius}, centre {centre:?}");
                assert_eq!((taken.zero, taken.nonnegative), (fresh.zero, fresh.nonnegative));
            }
        }
    }

    /// The ranked centres pick, disk after disk, what the scan of every centre picks, on the
    /// fields of the test below (ties of every kind, a flat field, an empty one), with cells
    /// excluded from the start, until no valid centre is left; on a field with values below 0
    /// there is no ranking (the scan stays).
    #[test]
    fn the_ranked_centres_pick_what_the_scan_picks() {
        let grid = Grid::new(17, 29, 1.0).unwrap();
        let fields: Vec<Vec<f64>> = vec![
            (0..grid.len()).map(|i| ((i * 7919) % 97) as f64 / 97.0).collect(),
            vec![1.0; grid.len()],
            (0..grid.len()).map(|i| if i % 29 < 11 { 2.0 } else { 1.0 }).collect(),
            vec![0.0; grid.len()],
        ];
        for v in &fields {
            for radius in [0.0, 1.5, 4.0, 12.0] {
                let sums = DiskSums::new(grid, v, radius);
                let mut ranked = Ranked::new(&grid, &sums).expect("scores >= 0");
                let mut covered: Vec<f64> = (0..grid.len()).map(|i| f64::from(i % 13 == 5)).collect();
                loop {
                    let taken = DiskSums::new(grid, &covered, radius);
                    let want = best_disk_of_all(&grid, &taken, &sums);
                    assert_eq!(ranked.best_valid(&grid, &taken), want, "radius {radius}");
                    let Some((centre, _)) = want else { break };
                    grid.disk(centre, radius).into_iter().for_each(|p| covered[p] = 1.0);
                }
            }
        }
        let below: Vec<f64> = (0..grid.len()).map(|i| ((i * 31) % 17) as f64 - 8.0).collect();
        assert!(Ranked::new(&grid, &DiskSums::new(grid, &below, 2.0)).is_none());
    }

    /// The rows summed in the order of their bound pick what the scan of every centre picks:
    /// the largest valid score, the first centre of a tie. On fields with one peak, many,
    /// none (flat: every centre ties) and steps (plateaus of ties), with disks taken, and
    /// every row bound at or above its row's largest disk sum; on a field with values below 0
    /// (where a square's sum bounds nothing) by the scan itself.
    #[test]
    fn the_bounded_rows_pick_what_the_scan_of_every_centre_picks() {
        let grid = Grid::new(23, 41, 1.0).unwrap();
        let at = |i: usize| ((i / 41) as f64, (i % 41) as f64);
        let fields: Vec<Vec<f64>> = vec![
            (0..grid.len())
                .map(|i| {
                    let (r, c) = at(i);
                    (-((r - 7.0).powi(2) + (c - 30.0).powi(2)) / 20.0).exp()
                })
                .collect(),
            (0..grid.len()).map(|i| ((i * 7919) % 97) as f64 / 97.0).collect(),
            vec![1.0; grid.len()],
            (0..grid.len())
                .map(|i| if at(i).1 < 20.0 { 2.0 } else { 1.0 })
                .collect(),
            vec![0.0; grid.len()],
            (0..grid.len()).map(|i| ((i * 31) % 17) as f64 - 8.0).collect(),
        ];
        for v in &fields {
            for radius in [0.0, 1.5, 4.0, 9.0, 30.0] {
                let sums = DiskSums::new(grid, v, radius);
                let bounds = sums.row_bounds();
                let mut row = vec![0.0; grid.cols];
                for (r, bound) in bounds.iter().enumerate().filter(|_| sums.nonnegative) {
                    sums.row_sums(r, &mut row);
                    assert!(row.iter().all(|s| s <= bound), "row {r} radius {radius}");
                }
                let mut covered = vec![0.0; grid.len()];
                for _ in 0..4 {
                    let taken = DiskSums::new(grid, &covered, radius);
                    let want = best_disk_of_all(&grid, &taken, &sums);
                    assert_eq!(best_disk(&grid, &taken, &sums), want, "radius {radius}");
                    if sums.nonnegative {
                        // Batches of rows: the overlap summed only for rows that reach the best.
                        let order = rows_by_bound(&bounds);
                        for batch in [1, 2, 5] {
                            let got = best_disk_in_batches(&grid, &taken, &sums, (&bounds, &order), batch);
                            assert_eq!(got, want, "radius {radius}, batches of {batch}");
                        }
                    }
                    let Some((centre, _)) = want else { break };
                    grid.disk(centre, radius).into_iter().for_each(|p| covered[p] = 1.0);
                }
            }
        }
    }

    /// Channels one cell wide (rows 1 and 3 land, rows 0, 2 and 4 water): a disk of radius 2
    /// reaches land wherever it is centred, so there is no open water. Every disk is then
    /// centred on water, holds only wet cells, shares none with another and touches no cell
    /// beyond the fence; and they go where the modes are (the middle channel). Before disks
    /// could reach land, such a field got no disk at all.
    #[test]
    fn disks_reach_the_coast_centred_on_water_where_no_open_water_is_left() {
        let grid = Grid::new(5, 30, 1.0).unwrap();
        let dry: Vec<bool> = (0..grid.len()).map(|i| matches!(grid.cell(i).row, 1 | 3)).collect();
        let outside: Vec<bool> = (0..grid.len()).map(|i| grid.cell(i).col >= 28).collect();
        let phi = Mat::from_fn(grid.len(), 2, |i, j| {
            let (r, c) = (grid.cell(i).row, grid.cell(i).col as f64);
            match (dry[i], r) {
                (true, _) => 0.0,
                (false, 2) => ((j + 1) as f64 * c * 0.2).cos() + 1.5,
                _ => 0.01 * ((i * (j + 7)) % 13) as f64,
            }
        });
        let room = Room {
            outside: &outside,
            dry: &dry,
        };
        for disks in [
            block_qr_within(phi.as_ref(), &grid, 4, 2.0, room).unwrap(),
            block_dopt_within(phi.as_ref(), &grid, 4, 2.0, room).unwrap(),
        ] {
            assert_eq!(disks.len(), 4);
            let mut seen = std::collections::BTreeSet::new();
            for d in &disks {
                assert!(!dry[grid.index(d.centre)], "a disk centred on land: {:?}", d.centre);
                assert!(d.cells.iter().all(|&c| !dry[c] && !outside[c]), "{:?}", d.cells);
                assert!(d.cells.iter().all(|&c| seen.insert(c)), "disks share a cell");
            }
            assert!(
                disks.iter().filter(|d| d.centre.row == 2).count() >= 2,
                "the middle channel, where the modes are, gets disks: {:?}",
                disks.iter().map(|d| d.centre).collect::<Vec<_>>()
            );
        }
    }

    /// Open water first: a strait between two coasts holds the modes, an open sea beside it
    /// holds room for disks. The disks go to the open sea while it has room (none reaches
    /// land), and only the one it has no room for reaches the coast.
    #[test]
    fn disks_go_in_open_water_while_it_has_room() {
        let grid = Grid::new(12, 30, 1.0).unwrap();
        // Land everywhere but the strait (row 5) and a basin of 5 x 5 (rows 7-11, columns
        // 0-4): room in open water for exactly one disk of radius 2.
        let dry: Vec<bool> = (0..grid.len())
            .map(|i| {
                let (r, c) = (grid.cell(i).row, grid.cell(i).col);
                matches!(r, 4 | 6) || r <= 3 || (r >= 7 && c >= 5)
            })
            .collect();
        let phi = Mat::from_fn(grid.len(), 1, |i, _| match (dry[i], grid.cell(i).row) {
            (true, _) => 0.0,
            (false, 5) => 1.0,
            _ => 0.1,
        });
        let room = Room {
            outside: &[],
            dry: &dry,
        };
        let disks = block_qr_within(phi.as_ref(), &grid, 2, 2.0, room).unwrap();
        assert_eq!(disks.len(), 2);
        let reaches_land = |d: &Disk| grid.disk(d.centre, 2.0).iter().any(|&c| dry[c]);
        assert!(
            !reaches_land(&disks[0]) && disks[0].centre.row >= 7,
            "{:?}",
            disks[0].centre
        );
        assert!(
            reaches_land(&disks[1]) && !dry[grid.index(disks[1].centre)],
            "{:?}",
            disks[1].centre
        );
        // Without land in the room, the same basis and grid give the grid's own disks.
        let open = block_qr(phi.as_ref(), &grid, 4, 2.0).unwrap();
        assert!(open.iter().all(|d| d.cells == grid.disk(d.centre, 2.0)));
    }
}
