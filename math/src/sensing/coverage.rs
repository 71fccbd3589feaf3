//! Coverage control for aerials (paper Sect. 4.2.2): Lloyd iterations towards a centroidal
//! Voronoi partition of the grid's cells under a density `phi`, minimising
//! `H(R) = sum_j sum_{q in V_j} |q - p_j|^2 phi(q)` (eq. coverage with `f(d) = d^2`, the
//! integral taken over cell centres, each cell weighing its area).
//!
//! The density comes from the temporal modes ([`temporal_density`]): each mode's growth or
//! decay rate `|Re omega_j|` weighted by its local magnitude `|Phi_qj alpha_j|`, normalised to a
//! maximum of 1, plus a floor so no part of the workspace is ever abandoned. The uniform
//! density starts the mission ([`uniform_formation`]).

use super::SensingError;
use crate::dmd::DmdModel;
use crate::grid::{Cell, Grid};

/// Positions in metres, `(x, y)` with x along columns (as [`Grid::centre_m`]).
pub type Point = (f64, f64);

/// Density per cell for the aerials: `floor + (1 - floor) * s(q) / max s`, with
/// `s(q) = sum_j |Re omega_j| |Phi_qj alpha_j|`. A model whose modes neither grow nor decay
/// gives the uniform density. `floor` in [0, 1].
pub fn temporal_density(model: &DmdModel, floor: f64) -> Result<Vec<f64>, SensingError> {
    if !(0.0..=1.0).contains(&floor) {
        return Err(SensingError::Input(format!(
            "density floor must be in [0, 1], got {floor}"
        )));
    }
    let omega = model.continuous_eigenvalues();
    let phi = &model.modes.modes;
    let n = phi.nrows();
    let mut s = vec![0.0; n];
    for (j, w) in omega.iter().enumerate() {
        let rate = w.re.abs();
        if !rate.is_finite() || rate == 0.0 {
            continue;
        }
        let a = model.amplitudes[j];
        // |z| as the square root of |z|^2, not `hypot` (a library call per cell and mode, a
        // third of the density's time): the magnitudes here are far from over- or underflow.
        for (sq, p) in s.iter_mut().zip(phi.col(j).iter()) {
            *sq += rate * (p * a).norm_sqr().sqrt();
        }
    }
    let max = s.iter().cloned().fold(0.0, f64::max);
    if !(max.is_finite() && max > 0.0) {
        return Ok(vec![1.0; n]);
    }
    Ok(s.iter().map(|v| floor + (1.0 - floor) * v / max).collect())
}

/// Where Lloyd's iterations ended.
#[derive(Debug, Clone)]
pub struct Coverage {
    /// Final generator positions (metres).
    pub positions: Vec<Point>,
    /// For each cell, the index of the generator whose Voronoi region holds it.
    pub owner: Vec<usize>,
    /// The cost `H` before the first iteration and after each one (never increases).
    pub cost: Vec<f64>,
    pub iterations: usize,
}

/// The allowed cell centre nearest each position (`excluded` empty: positions unchanged): a
/// Lloyd centroid of a concave site can fall outside it. `None` when every cell is excluded.
pub fn snap_inside(grid: &Grid, excluded: &[bool], positions: &[Point]) -> Option<Vec<Point>> {
    if excluded.is_empty() {
        return Some(positions.to_vec());
    }
    let allowed: Vec<Point> = (0..grid.len())
        .filter(|&i| !excluded.get(i).copied().unwrap_or(false))
        .map(|i| grid.centre_m(grid.cell(i)))
        .collect();
    if allowed.is_empty() {
        return None;
    }
    Some(
        positions
            .iter()
            .map(|&p| match grid.cell_at(p.0, p.1).map(|c| grid.index(c)) {
                Some(i) if !excluded[i] => p,
                _ => *allowed
                    .iter()
                    .min_by(|a, b| (a.0 - p.0).hypot(a.1 - p.1).total_cmp(&(b.0 - p.0).hypot(b.1 - p.1)))
                    .expect("not empty"),
            })
            .collect(),
    )
}

/// Lloyd's algorithm on the cells of `grid` under `density` (one non-negative value per cell),
/// from `start`, until no generator moves more than `tol_m` metres or `max_iter` iterations.
/// A generator whose region carries no density stays where it is.
pub fn lloyd(
    grid: &Grid,
    density: &[f64],
    start: &[Point],
    max_iter: usize,
    tol_m: f64,
) -> Result<Coverage, SensingError> {
    grid.check_len(density.len())
        .map_err(|e| SensingError::Input(e.to_string()))?;
    if let Some(i) = density.iter().position(|d| !(d.is_finite() && *d >= 0.0)) {
        return Err(SensingError::Input(format!(
            "density of cell {i} is {} (must be finite and >= 0)",
            density[i]
        )));
    }
    if start.is_empty() {
        return Err(SensingError::Input("coverage needs at least one vehicle".into()));
    }
    if start.iter().any(|p| !(p.0.is_finite() && p.1.is_finite())) {
        return Err(SensingError::Input("non-finite start position".into()));
    }
    let centres: Vec<Point> = (0..grid.len()).map(|i| grid.centre_m(grid.cell(i))).collect();
    let mut p = start.to_vec();
    let mut owner = vec![0usize; grid.len()];
    let (mut cost, mut iterations) = (Vec::with_capacity(max_iter + 1), 0);
    cost.push(partition(grid, density, &p, &mut owner));
    for _ in 0..max_iter {
        let sums = centroid_sums(&centres, density, &owner, p.len());
        let mut moved: f64 = 0.0;
        for (pj, (sx, sy, m)) in p.iter_mut().zip(sums) {
            if m > 0.0 {
                let c = (sx / m, sy / m);
                moved = moved.max((c.0 - pj.0).hypot(c.1 - pj.1));
                *pj = c;
            }
        }
        iterations += 1;
        cost.push(partition(grid, density, &p, &mut owner));
        if moved <= tol_m {
            break;
        }
    }
    Ok(Coverage {
        positions: p,
        owner,
        cost,
        iterations,
    })
}

/// Per generator, the sums of density times x, times y, and of density over its cells, each
/// added up in the cells' order (the same bits as a cell at a time). A run of cells of one
/// owner (a row's stretch of its region) is summed in registers: with the sums in memory each
/// cell waited for the last one's store.
fn centroid_sums(centres: &[Point], density: &[f64], owner: &[usize], a: usize) -> Vec<(f64, f64, f64)> {
    let mut sums = vec![(0.0, 0.0, 0.0); a];
    let mut q = 0;
    while q < owner.len() {
        let o = owner[q];
        let mut s = sums[o];
        while q < owner.len() && owner[q] == o {
            let ((x, y), d) = (centres[q], density[q]);
            (s.0, s.1, s.2) = (s.0 + d * x, s.1 + d * y, s.2 + d);
            q += 1;
        }
        sums[o] = s;
    }
    sums
}

/// Assign each cell to its nearest generator (ties to the lower index) and return the cost.
///
/// A cell's squared distance to generator `j` is `dx^2 + dy^2`, `dx` a function of its column
/// and `dy` of its row alone: the squares are made once per column and per row (the same
/// values a cell's own would be, so the same sums, owners and cost to the bit). A row's cells
/// are then compared with one generator after another, in the generators' order (a strictly
/// nearer one takes the cell, so ties stay with the lower index): an addition, a comparison
/// and two selects per cell that run many cells at a time, where the nearest of one cell's
/// generators is a chain of dependent comparisons (the partition was most of the aerials'
/// placement, a third of the epoch's time with 8 aerials at 192 x 384).
fn partition(grid: &Grid, density: &[f64], p: &[Point], owner: &mut [usize]) -> f64 {
    let cols = grid.cols;
    let x: Vec<f64> = (0..cols).map(|col| grid.centre_m(Cell::new(0, col)).0).collect();
    let across: Vec<Vec<f64>> = p
        .iter()
        .map(|pj| x.iter().map(|&x| (x - pj.0).powi(2)).collect())
        .collect();
    let (mut nearest, mut d2) = (vec![0.0; cols], vec![f64::INFINITY; cols]);
    let mut h = 0.0;
    for row in 0..grid.rows {
        let y = grid.centre_m(Cell::new(row, 0)).1;
        nearest.fill(0.0);
        d2.fill(f64::INFINITY);
        for (j, (pj, dx)) in p.iter().zip(&across).enumerate() {
            nearer_here(&mut nearest, &mut d2, dx, (y - pj.1).powi(2), j as f64);
        }
        let cells = row * cols..(row + 1) * cols;
        owner[cells.clone()]
            .iter_mut()
            .zip(&nearest)
            .for_each(|(o, &b)| *o = b as usize);
        h = d2.iter().zip(&density[cells]).fold(h, |h, (&m, &w)| h + m * w);
    }
    h
}

/// A row's cells (`dx`: their squared distances across to generator `j`, `dy` down) taken by
/// `j` where it is strictly nearer than their nearest so far (`nearest`, `d2`); `j` as f64 is
/// exact. Two selects by one comparison: without blend instructions (the x86-64 baseline,
/// SSE2) the compiler makes the index's a store under a branch per cell, and which generator
/// is nearer changes along a row; with AVX2's blends ([`nearer_here`]) they run four cells at
/// once.
#[inline(always)]
fn nearer(nearest: &mut [f64], d2: &mut [f64], dx: &[f64], dy: f64, j: f64) {
    let n = dx.len();
    let (b, m) = (&mut nearest[..n], &mut d2[..n]);
    for c in 0..n {
        let d = dx[c] + dy;
        let closer = d < m[c];
        b[c] = if closer { j } else { b[c] };
        m[c] = if closer { d } else { m[c] };
    }
}

crate::simd::on_avx2! {
    /// [`nearer`] as this CPU runs it fastest.
    fn nearer_here(nearest: &mut [f64], d2: &mut [f64], dx: &[f64], dy: f64, j: f64) = nearer;
}

/// The formation aerials hold at the start: Lloyd under the uniform density from generators
/// spread evenly along the workspace's longer axis (deterministic).
pub fn uniform_formation(grid: &Grid, n: usize) -> Result<Coverage, SensingError> {
    let (w, h) = (grid.width_m(), grid.height_m());
    let start: Vec<Point> = (0..n)
        .map(|j| {
            let f = (j as f64 + 0.5) / n as f64;
            // A slight stagger off the axis lets Lloyd leave the line when more than two share it.
            let off = if j % 2 == 0 { 0.45 } else { 0.55 };
            if w >= h {
                (f * w, off * h)
            } else {
                (off * w, f * h)
            }
        })
        .collect();
    lloyd(grid, &vec![1.0; grid.len()], &start, 200, 1e-6 * grid.cell_m)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    #[test]
    fn cost_never_increases() {
        let g = Grid::new(30, 50, 1.0).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for _ in 0..20 {
            let density: Vec<f64> = (0..g.len()).map(|_| rng.random_range(0.0..1.0)).collect();
            let start: Vec<Point> = (0..4)
                .map(|_| (rng.random_range(0.0..50.0), rng.random_range(0.0..30.0)))
                .collect();
            let c = lloyd(&g, &density, &start, 50, 0.0).unwrap();
            for w in c.cost.windows(2) {
                assert!(w[1] <= w[0] * (1.0 + 1e-12), "cost went up: {:?}", c.cost);
            }
            assert!(c.cost.last().unwrap() < &c.cost[0]);
        }
    }

    /// The partition by rows and columns is the partition one cell at a time, to the bit
    /// (owners and cost), with generators anywhere, outside the grid too, and with exact ties:
    /// generators mirrored about a column of centres or at the same place (ties go to the lower
    /// index in both).
    #[test]
    fn the_partition_by_rows_is_the_partition_by_cells() {
        fn by_cells(grid: &Grid, density: &[f64], p: &[Point], owner: &mut [usize]) -> f64 {
            let mut h = 0.0;
            for q in 0..grid.len() {
                let (x, y) = grid.centre_m(grid.cell(q));
                let (mut best, mut d2) = (0, f64::INFINITY);
                for (j, pj) in p.iter().enumerate() {
                    let d = (x - pj.0).powi(2) + (y - pj.1).powi(2);
                    if d < d2 {
                        (best, d2) = (j, d);
                    }
                }
                owner[q] = best;
                h += d2 * density[q];
            }
            h
        }
        let g = Grid::new(23, 37, 2.5).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for case in 0..30 {
            let density: Vec<f64> = (0..g.len()).map(|_| rng.random_range(0.0..1.0)).collect();
            let mut p: Vec<Point> = (0..1 + case % 9)
                .map(|_| (rng.random_range(-10.0..100.0), rng.random_range(-10.0..60.0)))
                .collect();
            if case % 3 == 0 {
                let (x, y) = g.centre_m(Cell::new(5, 9));
                p.extend([(x - 7.5, y), (x + 7.5, y), (x, y - 5.0), p[0]]);
            }
            let (mut fast, mut slow) = (vec![0; g.len()], vec![0; g.len()]);
            let h = partition(&g, &density, &p, &mut fast);
            assert_eq!(
                h.to_bits(),
                by_cells(&g, &density, &p, &mut slow).to_bits(),
                "case {case}"
            );
            assert_eq!(fast, slow, "case {case}");
        }
        // This CPU's compilation of the row step is the baseline's, to the bit (ties too).
        let dx: Vec<f64> = (0..203).map(|i| ((i * 37) % 11) as f64 * 0.5).collect();
        let start: Vec<f64> = (0..203).map(|i| ((i * 13) % 7) as f64).collect();
        let (mut a, mut b) = ((vec![1.0; 203], start.clone()), (vec![1.0; 203], start));
        for (j, dy) in [(2.0, 0.5), (3.0, 0.0), (4.0, 0.0)] {
            nearer(&mut a.0, &mut a.1, &dx, dy, j);
            nearer_here(&mut b.0, &mut b.1, &dx, dy, j);
        }
        assert_eq!(a, b);
        // Some cells kept, some taken, none by 4 (each a tie with 3: the lower stays).
        assert!(a.0.contains(&1.0) && a.0.contains(&3.0) && !a.0.contains(&4.0));
    }

    /// The centroid sums by runs of one owner are a cell at a time's, to the bit, with owners
    /// in runs, alternating every cell, and a generator owning nothing.
    #[test]
    fn the_centroid_sums_by_runs_are_a_cell_at_a_times() {
        let g = Grid::new(9, 31, 1.5).unwrap();
        let centres: Vec<Point> = (0..g.len()).map(|i| g.centre_m(g.cell(i))).collect();
        let density: Vec<f64> = (0..g.len()).map(|i| ((i * 7919) % 101) as f64 / 101.0).collect();
        for owner in [
            (0..g.len()).map(|i| (i / 17) % 3).collect::<Vec<_>>(),
            (0..g.len()).map(|i| i % 2).collect(),
            (0..g.len()).map(|i| usize::from(g.cell(i).col > 20) * 3).collect(),
        ] {
            let mut want = vec![(0.0, 0.0, 0.0); 4];
            for (q, &(x, y)) in centres.iter().enumerate() {
                let s: &mut (f64, f64, f64) = &mut want[owner[q]];
                (s.0, s.1, s.2) = (s.0 + density[q] * x, s.1 + density[q] * y, s.2 + density[q]);
            }
            let got = centroid_sums(&centres, &density, &owner, 4);
            let bits = |v: &[(f64, f64, f64)]| -> Vec<[u64; 3]> {
                v.iter()
                    .map(|s| [s.0.to_bits(), s.1.to_bits(), s.2.to_bits()])
                    .collect()
            };
            assert_eq!(bits(&got), bits(&want));
        }
    }

    #[test]
    fn two_aerials_split_a_uniform_rectangle_in_halves() {
        let g = Grid::new(20, 40, 1.0).unwrap();
        let c = uniform_formation(&g, 2).unwrap();
        let left = c.owner.iter().filter(|&&o| o == 0).count();
        assert_eq!(left, g.len() / 2);
        // Each owns one 20 x 20 half and sits at its centroid.
        for q in 0..g.len() {
            assert_eq!(c.owner[q], usize::from(g.cell(q).col >= 20));
        }
        let mut p = c.positions.clone();
        p.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (pj, want) in p.iter().zip([(10.0, 10.0), (30.0, 10.0)]) {
            assert!((pj.0 - want.0).abs() < 1e-6 && (pj.1 - want.1).abs() < 1e-6, "{p:?}");
        }
    }

    #[test]
    fn density_pulls_generators() {
        // Nearly all the density in the right quarter (a floor of 0.01 elsewhere): both aerials
        // are drawn right of the 1/4 and 3/4 points where the uniform density would put them;
        // the right one to near the dense strip's centroid (x = 35).
        let g = Grid::new(20, 40, 1.0).unwrap();
        let density: Vec<f64> = (0..g.len())
            .map(|q| if g.cell(q).col >= 30 { 1.0 } else { 0.01 })
            .collect();
        let c = lloyd(&g, &density, &[(10.0, 10.0), (30.0, 10.0)], 500, 1e-9).unwrap();
        let mut x: Vec<f64> = c.positions.iter().map(|p| p.0).collect();
        x.sort_by(f64::total_cmp);
        assert!(x[0] > 11.0 && (x[1] - 35.0).abs() < 0.5, "{:?}", c.positions);
    }

    #[test]
    fn density_follows_growing_and_decaying_modes() {
        use crate::dmd::Modes;
        use faer::{c64, Mat};
        // Mode 0 neutral (|lambda| = 1) everywhere; mode 1 decays, living on the left half only.
        let g = Grid::new(4, 8, 1.0).unwrap();
        let modes = Mat::from_fn(g.len(), 2, |q, j| {
            c64::new(if j == 0 || g.cell(q).col < 4 { 1.0 } else { 0.0 }, 0.0)
        });
        let model = DmdModel {
            modes: Modes {
                eigenvalues: vec![c64::new(1.0, 0.0), c64::new(0.5, 0.0)],
                modes,
            },
            amplitudes: vec![c64::new(1.0, 0.0), c64::new(2.0, 0.0)],
            dt: 0.1,
        };
        let d = temporal_density(&model, 0.2).unwrap();
        for (q, dq) in d.iter().enumerate() {
            let want = if g.cell(q).col < 4 { 1.0 } else { 0.2 };
            assert!((dq - want).abs() < 1e-12, "cell {q}: {dq}");
        }
        // Only neutral modes: uniform.
        let mut flat = model.clone();
        flat.modes.eigenvalues[1] = c64::new(0.0, 1.0);
        assert!(temporal_density(&flat, 0.2).unwrap().iter().all(|&v| v == 1.0));
        assert!(temporal_density(&model, 1.5).is_err());
    }

    #[test]
    fn bad_input_is_an_error() {
        let g = Grid::new(4, 4, 1.0).unwrap();
        assert!(lloyd(&g, &[1.0; 3], &[(1.0, 1.0)], 5, 0.0).is_err());
        assert!(lloyd(&g, &[f64::NAN; 16], &[(1.0, 1.0)], 5, 0.0).is_err());
        assert!(lloyd(&g, &[1.0; 16], &[], 5, 0.0).is_err());
        assert!(lloyd(&g, &[-1.0; 16], &[(1.0, 1.0)], 5, 0.0).is_err());
    }
}
