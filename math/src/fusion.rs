//! Multi-fidelity fusion (paper Sect. 4.1): aerial low-resolution frames, upsampled to the
//! grid, combined with the high-fidelity estimate (the boats' gappy reconstruction, or the
//! model's prediction at steps without boat data) into one snapshot per step.
//!
//! Every estimate carries a per-cell variance so the combination can be weighed and the
//! result's uncertainty reported:
//! - aerial: each coarse cell is seen by the nearest aerial (its Voronoi region, paper Fig. 5)
//!   with noise standard deviation `sigma0 + growth * distance` ([`AerialNoise`]); bilinear
//!   upsampling propagates it as `sum w_i^2 var_i`;
//! - boats: the gappy estimate's `phi_i K phi_i^T` (see [`crate::sensing::gappy`]), and the
//!   measured cells themselves with the boats' noise variance.
//!
//! Two schemes ([`Scheme`]): `paper` is our reading of the paper's combination, which it does
//! not spell out: the unweighted mean of the available estimates, with the cells a boat
//! measured set to the measurement. `inverse-variance` weighs every source (aerial, high-fidelity
//! estimate, boat measurement) by the inverse of its variance in each cell.

use crate::grid::{Grid, StridedGrid};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};
use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum FusionError {
    #[error("{0}")]
    Input(String),
    #[error(transparent)]
    Grid(#[from] crate::grid::GridError),
}

/// A full-grid estimate and its per-cell error variance.
#[derive(Debug, Clone, PartialEq)]
pub struct Estimate {
    pub values: Vec<f64>,
    pub variance: Vec<f64>,
}

impl Estimate {
    /// Check lengths, finiteness, and non-negative variances.
    pub fn validate(&self, n: usize) -> Result<(), FusionError> {
        if self.values.len() != n || self.variance.len() != n {
            return Err(FusionError::Input(format!(
                "estimate has {} values and {} variances for {n} cells",
                self.values.len(),
                self.variance.len()
            )));
        }
        if let Some(i) = self.values.iter().position(|v| !v.is_finite()) {
            return Err(FusionError::Input(format!("estimate value at cell {i} is not finite")));
        }
        if let Some(i) = self.variance.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(FusionError::Input(format!(
                "estimate variance at cell {i} is {}",
                self.variance[i]
            )));
        }
        Ok(())
    }
}

/// An aerial's sensor noise ([`Noise`]): standard
/// deviation `sigma0 + growth_per_m * d` at distance `d` metres from the sensor.
pub type AerialNoise = Noise;

/// A sensor's noise: standard deviation `sigma0 + growth_per_m * distance` (boats: growth 0).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Noise {
    /// The standard deviation at the sensor, in the field's units.
    pub sigma0: f64,
    /// How much it grows per metre of distance from the sensor.
    pub growth_per_m: f64,
}

impl Noise {
    /// The standard deviation at `d_m` metres from the sensor.
    pub fn std_at(&self, d_m: f64) -> f64 {
        self.sigma0 + self.growth_per_m * d_m
    }
}

/// What a sensor read, as the fusion needs it: where the sensor was (metres `(x, y)`), and a
/// value at each of some cells (flat grid indices). The fleet's wire type (the protocol's
/// `Sample`) is one; the mathematics does not depend on how readings travel.
pub trait Reading {
    fn position(&self) -> [f64; 2];
    fn cells(&self) -> &[u32];
    fn values(&self) -> &[f64];
}

/// A reading drawn here (a simulated frame).
#[derive(Clone)]
struct Drawn {
    position: [f64; 2],
    cells: Vec<u32>,
    values: Vec<f64>,
}

impl Reading for Drawn {
    fn position(&self) -> [f64; 2] {
        self.position
    }
    fn cells(&self) -> &[u32] {
        &self.cells
    }
    fn values(&self) -> &[f64] {
        &self.values
    }
}

fn check_noise(noise: &AerialNoise) -> Result<(), FusionError> {
    if !(noise.sigma0.is_finite() && noise.sigma0 >= 0.0 && noise.growth_per_m.is_finite() && noise.growth_per_m >= 0.0)
    {
        return Err(FusionError::Input(format!(
            "sensor noise must be finite and >= 0, got {noise:?}"
        )));
    }
    Ok(())
}

/// Mean over cells of the squared difference of an estimate and the truth (the paper's MSE),
/// over the cells where the truth has a value: a NaN in the truth (land, cloud, no data) is
/// not scored. NaN when the truth has no value anywhere in the frame (a fully cloudy image,
/// an analysis time with every cell missing): the step is not scored, rather than scored a
/// perfect 0.
pub fn mse(estimate: &[f64], truth: &[f64]) -> f64 {
    let (sum, n) = estimate
        .iter()
        .zip(truth)
        .filter(|(_, y)| !y.is_nan())
        .fold((0.0, 0usize), |(s, n), (x, y)| (s + (x - y).powi(2), n + 1));
    if n == 0 {
        return f64::NAN;
    }
    sum / n as f64
}

/// The mean of per-step scores over the steps that were scored (a NaN is a step whose truth
/// had no value, [`mse`]); 0 when none was.
pub fn mean_scored(steps: &[f64]) -> f64 {
    let (sum, n) = steps
        .iter()
        .filter(|v| !v.is_nan())
        .fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    sum / n.max(1) as f64
}

/// Per-step scores with a step whose truth had no value (NaN) as no data (`None`): a gap in a
/// figure, a step left out of a comparison.
pub fn scored(steps: &[f64]) -> Vec<Option<f64>> {
    steps.iter().map(|&x| Some(x).filter(|x| !x.is_nan())).collect()
}

/// How many of the per-step scores are NaN: steps whose truth had no value, not scored.
pub fn unscored(steps: &[f64]) -> usize {
    steps.iter().filter(|v| v.is_nan()).count()
}

/// The cells of the stride lattice aerial `me` covers: those nearer to it than to any other
/// aerial (its Voronoi region), in lattice order. The server hands each aerial its region in
/// its plan; the aerial senses exactly those cells ([`draw`]).
pub fn aerial_region(grid: &Grid, stride: usize, aerials: &[(f64, f64)], me: usize) -> Result<Vec<usize>, FusionError> {
    if me >= aerials.len() {
        return Err(FusionError::Input(format!("aerial {me} of {}", aerials.len())));
    }
    let lattice = grid.strided(stride)?;
    Ok((0..lattice.rows * lattice.cols)
        .map(|k| lattice.fine_cell(k))
        .filter(|&cell| {
            let (x, y) = grid.centre_m(cell);
            nearest(aerials, x, y) == me
        })
        .map(|cell| grid.index(cell))
        .collect())
}

/// What a sensor at `pos` (metres) measures of `truth` at `cells`: each value with noise of
/// std `sigma0 + growth * distance`, one normal draw per cell in the order given. Aerials
/// (growth > 0) and boats (growth 0) are the same sensor model with other numbers.
pub fn draw<R: Rng + ?Sized>(
    grid: &Grid,
    truth: &[f64],
    pos: (f64, f64),
    cells: &[usize],
    noise: AerialNoise,
    rng: &mut R,
) -> Result<Vec<f64>, FusionError> {
    check_noise(&noise)?;
    if truth.len() != grid.len() {
        return Err(FusionError::Input(format!(
            "truth of {} values on a {}-cell grid",
            truth.len(),
            grid.len()
        )));
    }
    if let Some(c) = cells.iter().find(|&&c| c >= grid.len()) {
        return Err(FusionError::Input(format!(
            "cell {c} outside the {}-cell grid",
            grid.len()
        )));
    }
    Ok(cells
        .iter()
        .map(|&c| {
            let (x, y) = grid.centre_m(grid.cell(c));
            let z: f64 = <StandardNormal as Distribution<f64>>::sample(&StandardNormal, rng);
            truth[c] + noise.std_at((pos.0 - x).hypot(pos.1 - y)) * z
        })
        .collect())
}

/// Index of the point nearest to `(x, y)` (the lower index on ties).
fn nearest(points: &[(f64, f64)], x: f64, y: f64) -> usize {
    let mut best = (0, f64::INFINITY);
    for (j, p) in points.iter().enumerate() {
        let d = (p.0 - x).powi(2) + (p.1 - y).powi(2);
        if d < best.1 {
            best = (j, d);
        }
    }
    best.0
}

/// What the aerials saw at one step: the coarse lattice, values and noise variance per coarse
/// cell.
#[derive(Debug, Clone)]
pub struct AerialFrame {
    pub lattice: StridedGrid,
    pub values: Vec<f64>,
    pub variance: Vec<f64>,
    /// Which coarse cells some aerial saw (the others hold 0 with variance 0).
    pub seen: Vec<bool>,
}

impl AerialFrame {
    /// Simulate every aerial's sample of `truth` (its region, [`aerial_region`], drawn from
    /// where it is, [`draw`]) from one random stream and assemble the frame.
    pub fn sense<R: Rng + ?Sized>(
        grid: &Grid,
        truth: &[f64],
        stride: usize,
        aerials: &[(f64, f64)],
        noise: AerialNoise,
        rng: &mut R,
    ) -> Result<Self, FusionError> {
        if aerials.is_empty() {
            return Err(FusionError::Input("an aerial frame needs at least one aerial".into()));
        }
        let mut samples = vec![];
        for (me, &at) in aerials.iter().enumerate() {
            let region = aerial_region(grid, stride, aerials, me)?;
            let values = draw(grid, truth, at, &region, noise, rng)?;
            let cells = region.iter().map(|&c| c as u32).collect();
            samples.push(Drawn {
                position: [at.0, at.1],
                cells,
                values,
            });
        }
        Self::assemble(grid, stride, &samples, noise)
    }

    /// The frame from the aerials' samples of one step (any order): each coarse value with its
    /// sampling aerial's noise variance at that distance.
    pub fn assemble<R: Reading>(
        grid: &Grid,
        stride: usize,
        samples: &[R],
        noise: AerialNoise,
    ) -> Result<Self, FusionError> {
        check_noise(&noise)?;
        let lattice = grid.strided(stride)?;
        let m = lattice.rows * lattice.cols;
        let mut frame = Self {
            lattice,
            values: vec![0.0; m],
            variance: vec![0.0; m],
            seen: vec![false; m],
        };
        for s in samples {
            for (&c, &v) in s.cells().iter().zip(s.values()) {
                if c as usize >= grid.len() {
                    return Err(FusionError::Input(format!(
                        "aerial cell {c} outside the {}-cell grid",
                        grid.len()
                    )));
                }
                let cell = grid.cell(c as usize);
                let k = lattice.coarse_index(cell).ok_or_else(|| {
                    FusionError::Input(format!("aerial cell {c} is not on the stride-{stride} lattice"))
                })?;
                let (x, y) = grid.centre_m(cell);
                let [px, py] = s.position();
                let sd = noise.std_at((px - x).hypot(py - y));
                let var = sd * sd;
                let (was, was_var) = (frame.values[k], frame.variance[k]);
                (frame.values[k], frame.variance[k]) = match frame.seen[k] {
                    // Two aerials' readings of one cell (one covering for a doubted other): each
                    // weighed by its precision; an exact one (no noise) stands.
                    true if was_var > 0.0 && var > 0.0 => {
                        let (a, b) = (1.0 / was_var, 1.0 / var);
                        ((a * was + b * v) / (a + b), 1.0 / (a + b))
                    }
                    true if was_var == 0.0 => (was, was_var),
                    _ => (v, var),
                };
                frame.seen[k] = true;
            }
        }
        Ok(frame)
    }

    /// The variance of bilinear interpolation's own error at every fine cell, from the frame's
    /// curvature. Between lattice nodes a stride apart, linear interpolation of a field whose
    /// second difference over that spacing is `D` errs by `t (1 - t) / 2 * D` at fraction `t`
    /// (exact for a quadratic). `D^2` is measured on the lattice along rows and along columns,
    /// less the noise's share (`var_{k-1} + 4 var_k + var_{k+1}`), spread to the fine cells
    /// bilinearly, and the two directions add. Cells beyond the last lattice row or column are
    /// held at its value: `k` cells beyond, that errs by `k / stride` times the field's first
    /// difference over a stride there (exact for a linear field), measured on the last two
    /// lattice rows or columns less the noise's share (`var_{k-1} + var_k`).
    pub fn interpolation_variance(&self) -> Result<Vec<f64>, FusionError> {
        let (rows, cols, s) = (self.lattice.rows, self.lattice.cols, self.lattice.stride);
        let at = |r: usize, c: usize| r * cols + c;
        let second = |k0: usize, k1: usize, k2: usize| {
            let d = self.values[k0] - 2.0 * self.values[k1] + self.values[k2];
            (d * d - (self.variance[k0] + 4.0 * self.variance[k1] + self.variance[k2])).max(0.0)
        };
        let first = |k0: usize, k1: usize| {
            let d = self.values[k1] - self.values[k0];
            (d * d - (self.variance[k0] + self.variance[k1])).max(0.0)
        };
        let (mut along_rows, mut along_cols) = (vec![0.0; rows * cols], vec![0.0; rows * cols]);
        let (mut end_rows, mut end_cols) = (vec![0.0; rows * cols], vec![0.0; rows * cols]);
        for r in 0..rows {
            for c in 0..cols {
                if rows >= 3 {
                    let m = r.clamp(1, rows - 2);
                    along_rows[at(r, c)] = second(at(m - 1, c), at(m, c), at(m + 1, c));
                }
                if cols >= 3 {
                    let m = c.clamp(1, cols - 2);
                    along_cols[at(r, c)] = second(at(r, m - 1), at(r, m), at(r, m + 1));
                }
                if rows >= 2 {
                    end_rows[at(r, c)] = first(at(rows - 2, c), at(rows - 1, c));
                }
                if cols >= 2 {
                    end_cols[at(r, c)] = first(at(r, cols - 2), at(r, cols - 1));
                }
            }
        }
        let up = |v: &[f64]| self.lattice.upsample_bilinear(v);
        let (dr, dc) = (up(&along_rows)?, up(&along_cols)?);
        // The ends' terms weigh only the fine rows (columns) beyond the last lattice row
        // (column): elsewhere their weight is 0 and the term exactly 0, so they are upsampled
        // there only (a band of under a stride), not over the whole grid.
        let fine = self.lattice.fine;
        let (row0, col0) = ((rows - 1) * s, (cols - 1) * s);
        let er = self.lattice.upsample_bilinear_from(&end_rows, row0, 0)?;
        let ec = self.lattice.upsample_bilinear_from(&end_cols, 0, col0)?;
        let band_cols = fine.cols.saturating_sub(col0);
        // (weight of the second difference, weight of the end's first difference)
        let weight = |i: usize, n: usize| {
            let last = (n - 1) * s;
            if i >= last {
                return (0.0, ((i - last) as f64 / s as f64).powi(2));
            }
            let t = (i % s) as f64 / s as f64;
            ((t * (1.0 - t) / 2.0).powi(2), 0.0)
        };
        Ok(crate::par::map(fine.len(), 4, |i| {
            let (r, c) = (i / fine.cols, i % fine.cols);
            let ((wr, xr), (wc, xc)) = (weight(r, rows), weight(c, cols));
            let mut v = wr * dr[i];
            if r >= row0 {
                v += xr * er[(r - row0) * fine.cols + c];
            }
            v += wc * dc[i];
            if c >= col0 {
                v += xc * ec[r * band_cols + c - col0];
            }
            v
        }))
    }

    /// Bilinear upsampling to the fine grid, with the propagated variance.
    pub fn upsample(&self) -> Result<Estimate, FusionError> {
        Ok(Estimate {
            values: self.lattice.upsample_bilinear(&self.values)?,
            variance: self.lattice.upsample_variance(&self.variance)?,
        })
    }
}

/// Boat measurements at one step: cells, values and the boats' noise variance.
#[derive(Debug, Clone, Copy)]
pub struct Measured<'a> {
    pub cells: &'a [usize],
    pub values: &'a [f64],
    pub noise_var: f64,
}

/// How estimates are combined.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
    strum::EnumString,
    strum::Display,
    strum::VariantNames,
    schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
#[strum(serialize_all = "kebab-case", parse_err_ty = String, parse_err_fn = scheme_name_error)]
pub enum Scheme {
    /// Unweighted mean of the available estimates; measured cells take the measurement.
    Paper,
    /// Per-cell inverse-variance weighting of every source, measured cells included.
    InverseVariance,
    /// A Kalman filter in the model's modal coordinates (`crate::kalman`; the assimilator runs
    /// it). As a one-step combination of estimates without a model, it is inverse-variance.
    Kalman,
}

/// Fuse the available estimates (any of them may be absent; at least one estimate or
/// measurement is needed) into one snapshot with its per-cell variance. Sources are assumed
/// independent. A zero-variance source is exact and wins its cell under `inverse-variance`.
pub fn fuse(
    scheme: Scheme,
    n: usize,
    estimates: &[&Estimate],
    measured: Option<Measured<'_>>,
) -> Result<Estimate, FusionError> {
    for e in estimates {
        e.validate(n)?;
    }
    if let Some(m) = &measured {
        check_measured(m, n)?;
    }
    if estimates.is_empty() && measured.is_none_or(|m| m.cells.len() < n) {
        return Err(FusionError::Input(
            "nothing to fuse: no estimate covers the grid".into(),
        ));
    }
    let mut out = Estimate {
        values: vec![0.0; n],
        variance: vec![0.0; n],
    };
    match scheme {
        Scheme::Paper => {
            let k = estimates.len() as f64;
            for e in estimates {
                for i in 0..n {
                    out.values[i] += e.values[i] / k;
                    out.variance[i] += e.variance[i] / (k * k);
                }
            }
            if let Some(m) = measured {
                for (&c, &v) in m.cells.iter().zip(m.values) {
                    out.values[c] = v;
                    out.variance[c] = m.noise_var;
                }
            }
        }
        Scheme::InverseVariance | Scheme::Kalman => {
            // Per cell: sum of w*x and of w = 1/var over the sources; exact sources separately.
            let mut acc = vec![Acc::default(); n];
            for e in estimates {
                for (a, (v, var)) in acc.iter_mut().zip(e.values.iter().zip(&e.variance)) {
                    a.add(*v, *var);
                }
            }
            if let Some(m) = measured {
                for (&c, &v) in m.cells.iter().zip(m.values) {
                    acc[c].add(v, m.noise_var);
                }
            }
            for (i, a) in acc.iter().enumerate() {
                (out.values[i], out.variance[i]) = a.result();
            }
        }
    }
    Ok(out)
}

fn check_measured(m: &Measured<'_>, n: usize) -> Result<(), FusionError> {
    if m.cells.len() != m.values.len() {
        return Err(FusionError::Input(format!(
            "{} measured cells but {} values",
            m.cells.len(),
            m.values.len()
        )));
    }
    if let Some(c) = m.cells.iter().find(|&&c| c >= n) {
        return Err(FusionError::Input(format!(
            "measured cell {c} outside the {n}-cell grid"
        )));
    }
    if let Some(v) = m.values.iter().find(|v| !v.is_finite()) {
        return Err(FusionError::Input(format!("non-finite measurement {v}")));
    }
    if !(m.noise_var.is_finite() && m.noise_var >= 0.0) {
        return Err(FusionError::Input(format!(
            "boat noise variance must be finite and >= 0, got {}",
            m.noise_var
        )));
    }
    Ok(())
}

/// Inverse-variance accumulator of one cell.
#[derive(Debug, Clone, Copy, Default)]
struct Acc {
    wx: f64,
    w: f64,
    exact_sum: f64,
    exact_n: u32,
}

impl Acc {
    fn add(&mut self, x: f64, var: f64) {
        if var == 0.0 {
            self.exact_sum += x;
            self.exact_n += 1;
        } else {
            self.wx += x / var;
            self.w += 1.0 / var;
        }
    }

    fn result(&self) -> (f64, f64) {
        if self.exact_n > 0 {
            (self.exact_sum / self.exact_n as f64, 0.0)
        } else {
            (self.wx / self.w, 1.0 / self.w)
        }
    }
}

/// A name that is not a [`Scheme`]'s.
fn scheme_name_error(got: &str) -> String {
    use strum::VariantNames as _;
    format!(
        "fusion scheme must be one of {}, got {got:?}",
        Scheme::VARIANTS.join(", ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame whose truth has no value is not scored (NaN, not a perfect 0), and the means
    /// over steps leave it out; a partly missing frame is scored where the truth has a value.
    #[test]
    fn a_frame_without_a_truth_is_not_scored() {
        let nan = f64::NAN;
        assert_eq!(mse(&[1.0, 2.0, 3.0], &[1.0, nan, 5.0]), 2.0);
        assert!(mse(&[1.0, 2.0], &[nan, nan]).is_nan());
        assert_eq!(mean_scored(&[1.0, nan, 3.0]), 2.0);
        assert_eq!((mean_scored(&[nan]), mean_scored(&[])), (0.0, 0.0));
        assert_eq!(unscored(&[1.0, nan, 3.0, nan]), 2);
    }

    /// A noiseless frame of `f` on `grid`'s lattice of `stride`: the truth, the upsampled frame,
    /// and the interpolation variance it predicts.
    fn exact_frame(grid: Grid, stride: usize, f: impl Fn(crate::grid::Cell) -> f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let truth: Vec<f64> = (0..grid.len()).map(|i| f(grid.cell(i))).collect();
        let lattice = grid.strided(stride).unwrap();
        let m = lattice.rows * lattice.cols;
        let frame = AerialFrame {
            lattice,
            values: (0..m).map(|k| f(lattice.fine_cell(k))).collect(),
            variance: vec![0.0; m],
            seen: vec![true; m],
        };
        (
            truth,
            frame.upsample().unwrap().values,
            frame.interpolation_variance().unwrap(),
        )
    }

    #[test]
    fn the_interpolation_error_of_a_quadratic_is_predicted_exactly() {
        // f = 0.01 row^2 + 0.3 col (bilinear interpolation is exact along columns): its error
        // at every cell is the formula's, to rounding; at lattice rows it is 0.
        let grid = Grid::new(21, 31, 1.0).unwrap();
        let (truth, up, predicted) = exact_frame(grid, 5, |c| 0.01 * (c.row * c.row) as f64 + 0.3 * c.col as f64);
        for i in 0..grid.len() {
            let err2 = (up[i] - truth[i]).powi(2);
            assert!(
                (err2.sqrt() - predicted[i].sqrt()).abs() < 1e-9,
                "cell {:?}: error {} predicted {}",
                grid.cell(i),
                err2.sqrt(),
                predicted[i].sqrt()
            );
        }
    }

    #[test]
    fn the_error_beyond_the_last_lattice_row_and_column_is_predicted_for_a_linear_field() {
        // 23 x 34 cells, stride 5: rows 21-22 and columns 31-33 lie beyond the lattice and are
        // held at its last value; for a linear field the hold errs by the slope times the
        // distance, which the first difference over a stride predicts exactly.
        let grid = Grid::new(23, 34, 1.0).unwrap();
        let (truth, up, predicted) = exact_frame(grid, 5, |c| 0.02 * c.row as f64 - 0.05 * c.col as f64);
        let mut beyond = 0;
        for i in 0..grid.len() {
            let (r, c) = (grid.cell(i).row, grid.cell(i).col);
            let err = up[i] - truth[i];
            if r > 20 || c > 30 {
                beyond += 1;
                assert!(
                    err.abs() > 1e-3,
                    "cell {r},{c} is beyond the lattice: the hold errs there"
                );
            }
            // Both directions' errors are independent in the model (variances add); in the
            // corner beyond both, the linear field's two errors add with the same sign or not,
            // so compare there the variance with the sum of squares of each direction's part.
            let (er, ec) = (0.02 * r.saturating_sub(20) as f64, 0.05 * c.saturating_sub(30) as f64);
            assert!(
                (predicted[i] - (er * er + ec * ec)).abs() < 1e-12,
                "cell {r},{c}: predicted {} for errors {er}, {ec} (actual {err})",
                predicted[i]
            );
        }
        assert_eq!(beyond, 23 * 34 - 21 * 31);
    }

    fn est(v: f64, var: f64, n: usize) -> Estimate {
        Estimate {
            values: vec![v; n],
            variance: vec![var; n],
        }
    }

    #[test]
    fn a_cell_two_aerials_read_is_weighed_by_their_precisions() {
        // One lattice cell (0, 0) read by an aerial on it (sd 1) and one 2 m away (sd 1 + 2 =
        // 3): precisions 1 and 1/9, so (1 * 1 + 10 / 9) / (10 / 9) = 1.9 and variance 0.9, in
        // either order. A noiseless reading stands.
        let grid = Grid::new(4, 4, 1.0).unwrap();
        let noise = Noise {
            sigma0: 1.0,
            growth_per_m: 1.0,
        };
        let (near, far) = (
            Drawn {
                position: [0.5, 0.5],
                cells: vec![0],
                values: vec![1.0],
            },
            Drawn {
                position: [2.5, 0.5],
                cells: vec![0],
                values: vec![10.0],
            },
        );
        for pair in [[&near, &far], [&far, &near]] {
            let f = AerialFrame::assemble(&grid, 2, &pair.map(|d| d.clone()), noise).unwrap();
            assert!((f.values[0] - 1.9).abs() < 1e-12 && (f.variance[0] - 0.9).abs() < 1e-12);
        }
        let exact = Noise {
            sigma0: 0.0,
            growth_per_m: 0.0,
        };
        let f = AerialFrame::assemble(&grid, 2, &[near.clone(), far.clone()], exact).unwrap();
        assert_eq!((f.values[0], f.variance[0]), (1.0, 0.0));
    }

    #[test]
    fn inverse_variance_weighs_by_precision() {
        let (a, b) = (est(1.0, 1.0, 3), est(4.0, 0.5, 3));
        let f = fuse(Scheme::InverseVariance, 3, &[&a, &b], None).unwrap();
        // weights 1 and 2: (1 + 8) / 3 = 3, variance 1/3.
        assert!((f.values[0] - 3.0).abs() < 1e-12 && (f.variance[0] - 1.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn paper_scheme_is_the_mean_with_measurements_overriding() {
        let (a, b) = (est(1.0, 1.0, 3), est(4.0, 0.5, 3));
        let m = Measured {
            cells: &[2],
            values: &[7.0],
            noise_var: 0.1,
        };
        let f = fuse(Scheme::Paper, 3, &[&a, &b], Some(m)).unwrap();
        assert_eq!(f.values, vec![2.5, 2.5, 7.0]);
        assert!((f.variance[0] - 0.375).abs() < 1e-12 && f.variance[2] == 0.1);
    }

    #[test]
    fn exact_sources_win() {
        let (a, b) = (est(1.0, 0.0, 2), est(4.0, 0.5, 2));
        let f = fuse(Scheme::InverseVariance, 2, &[&a, &b], None).unwrap();
        assert_eq!(f.values, vec![1.0, 1.0]);
        assert_eq!(f.variance, vec![0.0, 0.0]);
    }

    #[test]
    fn bad_input_is_an_error() {
        let a = est(1.0, 1.0, 3);
        assert!(fuse(Scheme::Paper, 4, &[&a], None).is_err());
        assert!(fuse(Scheme::Paper, 3, &[], None).is_err());
        let nan = est(f64::NAN, 1.0, 3);
        assert!(fuse(Scheme::Paper, 3, &[&nan], None).is_err());
        let neg = est(1.0, -1.0, 3);
        assert!(fuse(Scheme::InverseVariance, 3, &[&neg], None).is_err());
        let m = Measured {
            cells: &[5],
            values: &[1.0],
            noise_var: 0.1,
        };
        assert!(fuse(Scheme::Paper, 3, &[&a], Some(m)).is_err());
        assert!("bogus".parse::<Scheme>().is_err());
        assert_eq!(
            "inverse-variance".parse::<Scheme>().unwrap().to_string(),
            "inverse-variance"
        );
    }
}
