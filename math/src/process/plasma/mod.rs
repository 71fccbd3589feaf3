//! The plasma-cloud simulator (`docs/simulator.md`): the 2-D field-line-integrated
//! striation model of an ionospheric barium cloud, nondimensional (length = the cloud's
//! e-folding radius `a`, velocity = `|E0|/B`, time = `a / V0`, density = `N / N_peak`).
//!
//! - transport `dn/dt + div(n v) = D lap(n)` by flux-corrected transport ([`transport`]);
//! - drift `v = V0 + z x grad(psi) - U_f`, `V0 = E0 x z`;
//! - current continuity `div(Sigma grad psi) = div(Sigma E0)`, `Sigma = n + sigma_x`, solved
//!   every half step by FFT-preconditioned CG ([`potential`]).
//!
//! The velocities come from a corner stream function, so their discrete divergence is exactly
//! zero and conservation and bounds do not depend on the solver's tolerance. Time stepping is
//! a predictor-corrector (two solves a step) at CFL 0.4.
//!
//! Grid: `nx` columns along x (the drift), `ny` rows along y, square cells `h = lx / nx`, so
//! `ly = ny h`; frames are stored as `(rows = y, cols = x)`.

pub mod potential;
pub mod transport;

use super::FieldSeries;
use faer::Mat;
use potential::{PotentialSolver, SolveError, SolveStats};
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};
use transport::{FaceVelocity, Fct};

/// Every parameter of a run (all nondimensional).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlasmaParams {
    /// Cells along x (columns) and y (rows).
    pub nx: usize,
    pub ny: usize,
    /// Domain length along x; the cell size is `lx / nx` and `ly = ny * h`.
    pub lx: f64,
    /// Ambient electric field (drift `V0 = E0 x z`).
    pub e0: [f64; 2],
    /// Background / peak density (conductivity ratio `M = 1 / n_b`).
    pub n_b: f64,
    /// Relative amplitude of the seeded smooth noise.
    pub eps: f64,
    /// Non-advected conductivity added to `n`.
    pub sigma_x: f64,
    /// Diffusion coefficient.
    pub diffusion: f64,
    /// Velocity of the simulation frame.
    pub u_frame: [f64; 2],
    /// Initial cloud centre as fractions of `(lx, ly)`.
    pub centre: [f64; 2],
    /// Time between frames; frame `k` is at `t = k * out_dt` (frame 0 is the initial cloud).
    pub out_dt: f64,
    /// Damping layer over the last `sponge` fraction of x (0 = off).
    pub sponge: f64,
    /// Relative residual of the potential solves.
    pub tol: f64,
    /// CFL number.
    pub cfl: f64,
    pub seed: u64,
}

impl Default for PlasmaParams {
    /// The specification's defaults (`cloud1`): 384 x 96 cells over 16 x 4, `n_b = 0.25`.
    fn default() -> Self {
        Self {
            nx: 384,
            ny: 96,
            lx: 16.0,
            e0: [0.0, 1.0],
            n_b: 0.25,
            eps: 0.05,
            sigma_x: 0.0,
            diffusion: 1e-4,
            u_frame: [0.45, 0.0],
            centre: [1.0 / 3.0, 0.5],
            out_dt: 0.25,
            sponge: 0.15,
            tol: 1e-6,
            cfl: 0.4,
            seed: 7,
        }
    }
}

/// The three named clouds (the paper's names; parameters ours, `docs/simulator.md`).
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
#[strum(serialize_all = "kebab-case", parse_err_ty = String, parse_err_fn = preset_name_error)]
pub enum Preset {
    /// The specification's defaults: fingers by t ~ 20-25.
    Cloud1,
    /// The simplest: lower conductivity contrast (M = 3), little noise: mostly convects.
    Cloud2,
    /// The most unstable: M = 5, twice the noise, frames further apart (t to ~30).
    Cloud10,
}

impl Preset {
    pub fn params(self) -> PlasmaParams {
        let d = PlasmaParams::default();
        match self {
            Self::Cloud1 => d,
            Self::Cloud2 => PlasmaParams {
                n_b: 1.0 / 3.0,
                eps: 0.01,
                out_dt: 0.15,
                ..d
            },
            Self::Cloud10 => PlasmaParams {
                n_b: 0.2,
                eps: 0.1,
                out_dt: 0.3,
                ..d
            },
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PlasmaError {
    #[error("invalid parameter: {0}")]
    Param(String),
    #[error(transparent)]
    Solve(#[from] SolveError),
}

impl PlasmaParams {
    pub fn h(&self) -> f64 {
        self.lx / self.nx as f64
    }

    pub fn ly(&self) -> f64 {
        self.ny as f64 * self.h()
    }

    pub fn validate(&self) -> Result<(), PlasmaError> {
        let bad = |m: String| Err(PlasmaError::Param(m));
        if self.nx < 4 || self.ny < 4 {
            return bad(format!(
                "grid must be at least 4 x 4 cells, got {} x {}",
                self.ny, self.nx
            ));
        }
        if self.nx * self.ny > 50_000_000 {
            return bad(format!("grid of {} cells is too large", self.nx * self.ny));
        }
        let finite = [
            self.lx,
            self.e0[0],
            self.e0[1],
            self.n_b,
            self.eps,
            self.sigma_x,
            self.diffusion,
            self.u_frame[0],
            self.u_frame[1],
            self.centre[0],
            self.centre[1],
            self.out_dt,
            self.sponge,
            self.tol,
            self.cfl,
        ];
        if finite.iter().any(|v| !v.is_finite()) {
            return bad("every parameter must be finite".into());
        }
        if self.lx <= 0.0 {
            return bad(format!("lx must be positive, got {}", self.lx));
        }
        if !(self.n_b > 0.0 && self.n_b < 1.0) {
            return bad(format!("n_b must be in (0, 1), got {}", self.n_b));
        }
        if !(0.0..1.0).contains(&self.eps) {
            return bad(format!("eps must be in [0, 1), got {}", self.eps));
        }
        if self.sigma_x < 0.0 || self.diffusion < 0.0 {
            return bad("sigma_x and diffusion must be >= 0".into());
        }
        if !(self.out_dt > 0.0
            && (0.0..1.0).contains(&self.sponge)
            && self.tol > 0.0
            && self.tol < 1.0
            && self.cfl > 0.0
            && self.cfl <= 1.0)
        {
            return bad("out_dt > 0, sponge in [0, 1), tol in (0, 1) and cfl in (0, 1] are required".into());
        }
        Ok(())
    }

    /// The specification's initial density: a Gaussian cloud on the background, times
    /// `1 + eps xi` with `xi` smooth seeded noise of max abs 1.
    pub fn initial_density(&self) -> Vec<f64> {
        let (nx, ny, h) = (self.nx, self.ny, self.h());
        let (xc, yc) = (self.centre[0] * self.lx, self.centre[1] * self.ly());
        let xi = smooth_noise(nx, ny, self.seed);
        (0..nx * ny)
            .map(|k| {
                let (x, y) = (((k % nx) as f64 + 0.5) * h, ((k / nx) as f64 + 0.5) * h);
                let r2 = (x - xc).powi(2) + (y - yc).powi(2);
                (self.n_b + (1.0 - self.n_b) * (-r2).exp()) * (1.0 + self.eps * xi[k])
            })
            .collect()
    }
}

/// i.i.d. U[-1, 1] per cell, three passes of the periodic 3x3 filter [1 2 1] x [1 2 1] / 16,
/// scaled to max abs 1.
pub fn smooth_noise(nx: usize, ny: usize, seed: u64) -> Vec<f64> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut a: Vec<f64> = (0..nx * ny).map(|_| rng.random_range(-1.0..=1.0)).collect();
    let g = potential::Periodic::new(nx, ny);
    let w = [1.0, 2.0, 1.0];
    for _ in 0..3 {
        let mut b = vec![0.0; nx * ny];
        for j in 0..ny {
            let rows = [g.js[j], j, g.jn[j]];
            for i in 0..nx {
                let cols = [g.iw[i], i, g.ie[i]];
                let mut s = 0.0;
                for (wr, &r) in w.iter().zip(&rows) {
                    for (wc, &c) in w.iter().zip(&cols) {
                        s += wr * wc * a[r * nx + c];
                    }
                }
                b[j * nx + i] = s / 16.0;
            }
        }
        a = b;
    }
    let m = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if m > 0.0 {
        a.iter_mut().for_each(|v| *v /= m);
    }
    a
}

/// A running simulation.
pub struct PlasmaCloud {
    pub params: PlasmaParams,
    /// Density, row-major `(y, x)`.
    pub density: Vec<f64>,
    /// Periodic part of the potential.
    pub psi: Vec<f64>,
    pub velocity: FaceVelocity,
    pub time: f64,
    pub steps: u64,
    solver: PotentialSolver,
    fct: Fct,
    sigma: Vec<f64>,
    half: Vec<f64>,
    next: Vec<f64>,
    /// The previous step's length and starting potential, and this step's (for warm starts).
    prev_dt: Option<f64>,
    psi_old: Vec<f64>,
    psi_start: Vec<f64>,
    /// Corner stream function (work array of the velocities).
    corners: Vec<f64>,
}

impl PlasmaCloud {
    /// Start from the specification's initial cloud.
    pub fn new(params: PlasmaParams) -> Result<Self, PlasmaError> {
        params.validate()?;
        let n0 = params.initial_density();
        Self::with_density(params, n0)
    }

    /// Start from any density (the checks use slabs and cylinders). Solves the potential once.
    pub fn with_density(params: PlasmaParams, density: Vec<f64>) -> Result<Self, PlasmaError> {
        params.validate()?;
        let n = params.nx * params.ny;
        if density.len() != n {
            return Err(PlasmaError::Param(format!(
                "density has {} values for {n} cells",
                density.len()
            )));
        }
        if let Some(k) = density.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(PlasmaError::Param(format!("density at cell {k} is {}", density[k])));
        }
        let grid = potential::Periodic::new(params.nx, params.ny);
        let h = params.h();
        let mut me = Self {
            solver: PotentialSolver::new(params.nx, params.ny, h, params.tol),
            fct: Fct::new(grid, h, params.diffusion),
            velocity: FaceVelocity {
                u: vec![0.0; n],
                v: vec![0.0; n],
            },
            psi: vec![0.0; n],
            sigma: vec![0.0; n],
            half: vec![0.0; n],
            next: vec![0.0; n],
            prev_dt: None,
            psi_old: vec![0.0; n],
            psi_start: vec![0.0; n],
            corners: vec![0.0; n],
            density,
            time: 0.0,
            steps: 0,
            params,
        };
        me.update_potential(false)?;
        Ok(me)
    }

    pub fn solver_stats(&self) -> SolveStats {
        self.solver.stats
    }

    /// Solve the potential from `half` (the predictor) or `density`, and form the velocities.
    fn update_potential(&mut self, from_half: bool) -> Result<(), PlasmaError> {
        let src = if from_half { &self.half } else { &self.density };
        for (s, n) in self.sigma.iter_mut().zip(src) {
            *s = n + self.params.sigma_x;
        }
        self.solver.solve(&self.sigma, self.params.e0, &mut self.psi)?;
        self.form_velocity();
        Ok(())
    }

    /// Face velocities from the corner stream function `c = mean of the 4 surrounding psi`.
    fn form_velocity(&mut self) {
        let p = &self.params;
        let g = &self.solver.grid;
        let (nx, ny, h) = (p.nx, p.ny, p.h());
        let v0 = [p.e0[1], -p.e0[0]]; // E0 x z
        let (u0, w0) = (v0[0] - p.u_frame[0], v0[1] - p.u_frame[1]);
        let psi = &self.psi;
        // corner[j nx + i] is c at (i+1/2, j+1/2).
        let corner = &mut self.corners;
        for j in 0..ny {
            let (r, rn) = (j * nx, g.jn[j] * nx);
            for i in 0..nx {
                corner[r + i] = 0.25 * (psi[r + i] + psi[r + g.ie[i]] + psi[rn + i] + psi[rn + g.ie[i]]);
            }
        }
        for j in 0..ny {
            let (r, rs) = (j * nx, g.js[j] * nx);
            for i in 0..nx {
                let c = corner[r + i];
                self.velocity.u[r + i] = u0 - (c - corner[rs + i]) / h;
                self.velocity.v[r + i] = w0 + (c - corner[r + g.iw[i]]) / h;
            }
        }
    }

    /// The time step allowed by CFL and diffusion.
    pub fn stable_dt(&self) -> f64 {
        let h = self.params.h();
        let umax = self.velocity.u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let vmax = self.velocity.v.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let mut dt = if umax + vmax > 0.0 {
            self.params.cfl / (umax / h + vmax / h)
        } else {
            f64::INFINITY
        };
        if self.params.diffusion > 0.0 {
            dt = dt.min(0.2 * h * h / (2.0 * self.params.diffusion));
        }
        dt
    }

    /// One predictor-corrector step of length `dt`.
    /// Each solve is warm-started from a linear extrapolation in time of the last two
    /// potentials, which saved a third of the CG iterations (9.0 -> 6.1 per solve on cloud1).
    pub fn step(&mut self, dt: f64) -> Result<(), PlasmaError> {
        self.fct
            .step(&self.density, &self.density, &self.velocity, 0.5 * dt, &mut self.half);
        // psi_start = psi^n; psi_old = psi^(n-1) from the previous step (when there was one).
        self.psi_start.copy_from_slice(&self.psi);
        if let Some(prev_dt) = self.prev_dt {
            let f = 0.5 * dt / prev_dt;
            for ((x, a), b) in self.psi.iter_mut().zip(&self.psi_start).zip(&self.psi_old) {
                *x = a + f * (a - b);
            }
        }
        self.update_potential(true)?;
        self.fct
            .step(&self.density, &self.half, &self.velocity, dt, &mut self.next);
        std::mem::swap(&mut self.density, &mut self.next);
        self.apply_sponge(dt);
        for (x, a) in self.psi.iter_mut().zip(&self.psi_start) {
            *x = 2.0 * *x - a;
        }
        self.update_potential(false)?;
        std::mem::swap(&mut self.psi_old, &mut self.psi_start);
        self.prev_dt = Some(dt);
        self.time += dt;
        self.steps += 1;
        Ok(())
    }

    /// Relax the density to the background over the last `sponge` fraction of x.
    fn apply_sponge(&mut self, dt: f64) {
        let p = &self.params;
        if p.sponge <= 0.0 {
            return;
        }
        let (nx, h) = (p.nx, p.h());
        let start = (1.0 - p.sponge) * p.lx;
        let width = p.sponge * p.lx;
        let factor: Vec<f64> = (0..nx)
            .map(|i| {
                let x = (i as f64 + 0.5) * h;
                if x > start {
                    let w = (x - start) / width;
                    (-2.0 * w * w * dt).exp()
                } else {
                    1.0
                }
            })
            .collect();
        for row in self.density.chunks_exact_mut(nx) {
            for (n, f) in row.iter_mut().zip(&factor) {
                if *f < 1.0 {
                    *n = p.n_b + (*n - p.n_b) * f;
                }
            }
        }
    }

    /// Advance to exactly `t` (the last substep shortened to land on it).
    pub fn advance_to(&mut self, t: f64) -> Result<(), PlasmaError> {
        while self.time < t - 1e-12 * t.abs().max(1.0) {
            let dt = self.stable_dt().min(t - self.time);
            self.step(dt)?;
        }
        self.time = self.time.max(t);
        Ok(())
    }

    /// Run `frames` frames (frame 0 the current state), calling `progress(k)` after each.
    pub fn run(&mut self, frames: usize, mut progress: impl FnMut(usize)) -> Result<FieldSeries, PlasmaError> {
        let n = self.density.len();
        let mut snapshots = Mat::zeros(n, frames);
        let t0 = self.time;
        for k in 0..frames {
            self.advance_to(t0 + k as f64 * self.params.out_dt)?;
            for (i, v) in self.density.iter().enumerate() {
                snapshots[(i, k)] = *v;
            }
            progress(k);
        }
        Ok(FieldSeries {
            rows: self.params.ny,
            cols: self.params.nx,
            dt: self.params.out_dt,
            snapshots,
        })
    }
}

/// A name that is not a [`Preset`]'s.
fn preset_name_error(got: &str) -> String {
    use strum::VariantNames as _;
    format!("preset must be one of {}, got {got:?}", Preset::VARIANTS.join(", "))
}
