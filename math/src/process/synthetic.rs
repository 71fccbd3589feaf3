//! Synthetic fields with known dynamics, as in the paper's Sect. 5 studies. They follow the
//! peer scripts in `bench/peers/` formula for formula, so the same case means the same field
//! (the noise draws differ: ours come from a seeded ChaCha8 stream).

use super::FieldSeries;
use faer::Mat;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// Spatial profile of the Table 1 field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Table1Profile {
    /// `2 sech(x) sech(y)` (PyDMD's tutorial field; the peer scripts' default).
    Sech,
    /// `cosh(x) cosh(y)`.
    Cosh,
}

/// One case of the paper's Table 1 timing study.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Table1Case {
    /// Snapshot pairs `T` (so `T + 1` snapshots).
    pub pairs: usize,
    pub nx: usize,
    pub ny: usize,
    /// Pairs in the initial fit of the online methods.
    pub init: usize,
    /// Pairs per update `tau`.
    pub tau: usize,
}

/// The four cases of Table 1: `(T, nx, ny, init, tau)`.
pub const TABLE1_CASES: [Table1Case; 4] = [
    Table1Case {
        pairs: 500,
        nx: 10,
        ny: 10,
        init: 100,
        tau: 10,
    },
    Table1Case {
        pairs: 500,
        nx: 10,
        ny: 10,
        init: 100,
        tau: 100,
    },
    Table1Case {
        pairs: 1000,
        nx: 20,
        ny: 20,
        init: 400,
        tau: 100,
    },
    Table1Case {
        pairs: 2000,
        nx: 20,
        ny: 10,
        init: 200,
        tau: 100,
    },
];

impl Table1Case {
    /// Start column and width of each update batch after the initial fit.
    pub fn batches(&self) -> Vec<(usize, usize)> {
        let mut out = vec![];
        let mut m = self.init;
        while m < self.pairs {
            let t = self.tau.min(self.pairs - m);
            out.push((m, t));
            m += t;
        }
        out
    }
}

fn linspace(a: f64, b: f64, n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![a];
    }
    (0..n).map(|i| a + (b - a) * i as f64 / (n - 1) as f64).collect()
}

fn add_noise(m: &mut Mat<f64>, variance: f64, seed: u64) {
    if variance <= 0.0 {
        return;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let normal = Normal::new(0.0, variance.sqrt()).expect("finite positive std");
    for j in 0..m.ncols() {
        for x in m.col_mut(j).iter_mut() {
            *x += normal.sample(&mut rng);
        }
    }
}

/// Table 1's field: `g(x, y) Re[(1.9 i)^-t] = g(x, y) 1.9^-t cos(pi t / 2)` on `[-3, 3]^2`,
/// `t` in `[0, 6]` over `T + 1` snapshots, plus i.i.d. noise of the given variance.
/// Grid rows are `y` (ny), columns `x` (nx).
pub fn table1_field(case: &Table1Case, profile: Table1Profile, noise_var: f64, seed: u64) -> FieldSeries {
    let (nx, ny, t_count) = (case.nx, case.ny, case.pairs + 1);
    let xs = linspace(-3.0, 3.0, nx);
    let ys = linspace(-3.0, 3.0, ny);
    let ts = linspace(0.0, 6.0, t_count);
    let g: Vec<f64> = ys
        .iter()
        .flat_map(|&y| {
            xs.iter().map(move |&x| match profile {
                Table1Profile::Sech => 2.0 / x.cosh() / y.cosh(),
                Table1Profile::Cosh => x.cosh() * y.cosh(),
            })
        })
        .collect();
    let temporal: Vec<f64> = ts
        .iter()
        .map(|&t| 1.9f64.powf(-t) * (std::f64::consts::FRAC_PI_2 * t).cos())
        .collect();
    let mut z = Mat::from_fn(nx * ny, t_count, |i, j| g[i] * temporal[j]);
    add_noise(&mut z, noise_var, seed);
    FieldSeries {
        rows: ny,
        cols: nx,
        dt: 6.0 / case.pairs as f64,
        snapshots: z,
    }
}

/// The Fig. 7 eigenvalue study's field on a 20 x 20 grid over `[-1, 1]^2`, `dt = 0.01`, 1000
/// steps (1001 snapshots): a dominant mode with continuous-time eigenvalue exactly `-1`, an
/// oscillating pair at `-4 +- 2 pi i` and a fast mode at `-8`:
/// `g1 e^-t + 0.5 e^-4t (a cos 2 pi t + b sin 2 pi t) + 0.3 g4 e^-8t` plus noise.
pub struct EigStudy;

impl EigStudy {
    pub const DT: f64 = 0.01;
    pub const STEPS: usize = 1000;
    pub const GRID: usize = 20;
    pub const INIT: usize = 400;
    pub const TAU: usize = 10;
    /// The true dominant continuous-time eigenvalue.
    pub const TRUE_EIGENVALUE: f64 = -1.0;

    pub fn field(noise_var: f64, seed: u64) -> FieldSeries {
        let n = Self::GRID;
        let xs = linspace(-1.0, 1.0, n);
        let pi = std::f64::consts::PI;
        let mut g1 = vec![];
        let mut a = vec![];
        let mut b = vec![];
        let mut g4 = vec![];
        for &y in &xs {
            for &x in &xs {
                g1.push((-(x * x + y * y) / 0.5).exp());
                a.push((pi * x).sin() * (pi * y).cos());
                b.push((pi * x).cos() * (pi * y).sin());
                g4.push((pi * x / 2.0).cos() * y);
            }
        }
        let mut z = Mat::from_fn(n * n, Self::STEPS + 1, |i, j| {
            let t = j as f64 * Self::DT;
            g1[i] * (-t).exp()
                + 0.5 * (-4.0 * t).exp() * (a[i] * (2.0 * pi * t).cos() + b[i] * (2.0 * pi * t).sin())
                + 0.3 * g4[i] * (-8.0 * t).exp()
        });
        add_noise(&mut z, noise_var, seed);
        FieldSeries {
            rows: n,
            cols: n,
            dt: Self::DT,
            snapshots: z,
        }
    }
}

/// The smooth 48 x 96 (colatitude x longitude) field of the sensor-placement peer script:
/// travelling zonal waves plus a moving blob, `noise` standard deviation of i.i.d. noise.
/// Column `j` is the snapshot at `times[j]`, flattened `i = lat * 96 + lon`.
pub fn smooth_sphere_field(times: &[f64], noise: f64, seed: u64) -> FieldSeries {
    const NLAT: usize = 48;
    const NLON: usize = 96;
    let pi = std::f64::consts::PI;
    let th: Vec<f64> = (1..=NLAT).map(|i| pi * i as f64 / (NLAT + 1) as f64).collect();
    let ph: Vec<f64> = (0..NLON).map(|j| 2.0 * pi * j as f64 / NLON as f64).collect();
    let mut z = Mat::zeros(NLAT * NLON, times.len());
    for (k, &t) in times.iter().enumerate() {
        let thc = pi / 2.0 + 0.6 * (0.4 * t).sin();
        let phc = (0.5 * t).rem_euclid(2.0 * pi);
        for (a, &th) in th.iter().enumerate() {
            for (b, &ph) in ph.iter().enumerate() {
                let (s, c) = (th.sin(), th.cos());
                let mut f = s * s * (2.0 * (ph - 0.3 * t)).cos()
                    + 0.7 * s.powi(3) * c * (3.0 * (ph + 0.2 * t)).sin()
                    + 0.3 * c * (0.7 * t).cos()
                    + 0.4 * c * c * (0.5 * t).sin();
                let d = ph - phc;
                let dph = d.sin().atan2(d.cos());
                f += 0.8 * (-((th - thc).powi(2) + (s * dph).powi(2)) / 0.1).exp();
                z[(a * NLON + b, k)] = f;
            }
        }
    }
    if noise > 0.0 {
        add_noise(&mut z, noise * noise, seed);
    }
    FieldSeries {
        rows: NLAT,
        cols: NLON,
        dt: times.get(1).map_or(1.0, |t1| t1 - times[0]),
        snapshots: z,
    }
}

/// An orthonormal basis (N x r) of `r` smooth random functions on `grid` (products of random
/// low-frequency sines and cosines plus a tilt): a stand-in for a model's spatial modes in
/// sensing tests and benchmarks.
pub fn smooth_basis(grid: &crate::grid::Grid, r: usize, seed: u64) -> Mat<f64> {
    use rand::RngExt;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let tau = std::f64::consts::TAU;
    let mut raw = Mat::zeros(grid.len(), r);
    for j in 0..r {
        let (kx, ky, px, py): (f64, f64, f64, f64) = (
            rng.random_range(0.5..3.0),
            rng.random_range(0.5..3.0),
            rng.random_range(0.0..tau),
            rng.random_range(0.0..tau),
        );
        for i in 0..grid.len() {
            let c = grid.cell(i);
            let (x, y) = (c.col as f64 / grid.cols as f64, c.row as f64 / grid.rows as f64);
            raw[(i, j)] = (kx * tau * x + px).sin() * (ky * tau * y + py).cos() + 0.3 * (x - 0.5) * (j as f64);
        }
    }
    raw.qr().compute_thin_Q()
}

/// A moving, rotating, slowly spreading Gaussian plume on a `rows x cols` grid over
/// `[0, 2] x [0, 1]` (x along columns): the centre circles the domain's middle once over the
/// record while the plume's long axis turns half a turn and its amplitude decays as `e^-0.2 t`,
/// `t` in `[0, 10]`; plus i.i.d. noise of variance `noise_var`. A field whose modes are not
/// few: what a changing plume looks like to DMD.
pub fn plume_field(rows: usize, cols: usize, frames: usize, noise_var: f64, seed: u64) -> FieldSeries {
    let mut z = Mat::zeros(rows * cols, frames);
    for k in 0..frames {
        z.col_mut(k)
            .iter_mut()
            .zip(plume_frame(rows, cols, frames, k))
            .for_each(|(z, v)| *z = v);
    }
    add_noise(&mut z, noise_var, seed);
    FieldSeries {
        rows,
        cols,
        dt: plume_dt(frames),
        snapshots: z,
    }
}

/// The time between [`plume_field`]'s frames.
fn plume_dt(frames: usize) -> f64 {
    if frames > 1 {
        10.0 / (frames - 1) as f64
    } else {
        1.0
    }
}

/// Frame `k` of [`plume_field`] without noise (the same values, to the bit), made alone: what a
/// benchmark samples from without holding every frame.
pub fn plume_frame(rows: usize, cols: usize, frames: usize, k: usize) -> Vec<f64> {
    let pi = std::f64::consts::PI;
    let t_end = 10.0;
    let t = k as f64 * plume_dt(frames);
    let phase = 2.0 * pi * t / t_end;
    let (xc, yc) = (1.0 + 0.5 * phase.cos(), 0.5 + 0.25 * phase.sin());
    let angle = 0.5 * phase;
    let (ca, sa) = (angle.cos(), angle.sin());
    let (sl, sw) = (0.25 + 0.01 * t, 0.08 + 0.005 * t);
    let amp = (-0.2 * t).exp();
    let mut z = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        let y = (r as f64 + 0.5) / rows as f64;
        for c in 0..cols {
            let x = 2.0 * (c as f64 + 0.5) / cols as f64;
            let (dx, dy) = (x - xc, y - yc);
            let (along, across) = (ca * dx + sa * dy, -sa * dx + ca * dy);
            z.push(amp * (-0.5 * (along * along / (sl * sl) + across * across / (sw * sw))).exp());
        }
    }
    z
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plume frame made alone is the series' frame to the bit (a bench samples from it).
    #[test]
    fn a_plume_frame_made_alone_is_the_series_frame() {
        let s = plume_field(6, 10, 7, 0.0, 3);
        for k in [0, 3, 6] {
            let alone: Vec<u64> = plume_frame(6, 10, 7, k).iter().map(|v| v.to_bits()).collect();
            let whole: Vec<u64> = s.snapshots.col(k).iter().map(|v| v.to_bits()).collect();
            assert_eq!(alone, whole, "frame {k}");
        }
        assert_eq!(s.dt, 10.0 / 6.0);
    }
}
