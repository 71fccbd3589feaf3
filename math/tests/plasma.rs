//! The plasma-cloud specification's sanity checks (`docs/simulator.md`, "Checks"), on
//! grids small enough for the test suite. Each tolerance says where it comes from.

use fleet_math::process::plasma::{PlasmaCloud, PlasmaParams};

/// A quiet base: no diffusion, no sponge, tight solves, lab frame.
fn base(nx: usize, ny: usize, lx: f64) -> PlasmaParams {
    PlasmaParams {
        nx,
        ny,
        lx,
        diffusion: 0.0,
        sponge: 0.0,
        tol: 1e-12,
        u_frame: [0.0, 0.0],
        ..PlasmaParams::default()
    }
}

fn cell_xy(p: &PlasmaParams, k: usize) -> (f64, f64) {
    let h = p.h();
    (((k % p.nx) as f64 + 0.5) * h, ((k / p.nx) as f64 + 0.5) * h)
}

#[test]
fn conservation_and_bounds() {
    // Periodic, sponge off, the default cloud (with diffusion) on a coarse grid, 60 steps.
    // FCT is conservative by construction (every flux leaves one cell and enters another) and
    // the velocity field is discretely divergence-free, so mass changes only by rounding:
    // ~1e-16 per step over ~2e3 cells -> 1e-13 relative is a wide margin. Bounds: FCT keeps
    // each cell within its neighbours' old values; 1e-12 allows for rounding only.
    let p = PlasmaParams {
        nx: 96,
        ny: 24,
        sponge: 0.0,
        tol: 1e-8,
        ..PlasmaParams::default()
    };
    let mut sim = PlasmaCloud::new(p).unwrap();
    let mass0: f64 = sim.density.iter().sum();
    let (lo, hi) = sim
        .density
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
    for _ in 0..60 {
        let dt = sim.stable_dt();
        sim.step(dt).unwrap();
        let (l, h) = sim
            .density
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        assert!(
            l >= lo - 1e-12 && h <= hi + 1e-12,
            "bounds [{l}, {h}] left [{lo}, {hi}]"
        );
    }
    let mass: f64 = sim.density.iter().sum();
    assert!(
        ((mass - mass0) / mass0).abs() < 1e-13,
        "mass drift {}",
        (mass - mass0) / mass0
    );
    assert!(sim.time > 1.0, "the run should have moved the cloud (t = {})", sim.time);
}

/// Growth rate of the y-Fourier mode `m` of the slab's unstable (left) edge.
fn slab_growth_rate(m: usize, nx: usize, ny: usize) -> f64 {
    let mut p = base(nx, ny, 16.0);
    // The slab drifts with the unperturbed flow (psi = 0 when Sigma = Sigma(x), E0 along y):
    // move the frame with it so its left half stays at x < 8.
    p.u_frame = [1.0, 0.0];
    p.out_dt = 0.05;
    let k = 2.0 * std::f64::consts::PI * m as f64 / p.ly();
    let n0: Vec<f64> = (0..p.nx * p.ny)
        .map(|c| {
            let (x, y) = cell_xy(&p, c);
            let d = 1e-4 * (k * y).cos();
            p.n_b + (1.0 - p.n_b) * (1.0 + ((x - 6.0 - d) / 0.25).tanh()) * (1.0 - ((x - 10.0 - d) / 0.25).tanh()) / 4.0
        })
        .collect();
    let mut sim = PlasmaCloud::with_density(p.clone(), n0).unwrap();
    let amplitude = |sim: &PlasmaCloud| -> f64 {
        let (mut re, mut im) = (0.0, 0.0);
        for j in 0..p.ny {
            let y = (j as f64 + 0.5) * p.h();
            let integral: f64 = (0..p.nx)
                .filter(|&i| ((i as f64 + 0.5) * p.h()) < 8.0)
                .map(|i| sim.density[j * p.nx + i] * p.h())
                .sum();
            re += integral * (k * y).cos();
            im += integral * (k * y).sin();
        }
        re.hypot(im)
    };
    // Least-squares slope of ln(amplitude) over t in [3, 5], after the non-modal transient
    // (steps of at most 0.025, like the lab-frame CFL step of the prototype).
    let mut pts = vec![];
    let mut t = 0.0;
    while t < 5.0 - 1e-9 {
        t += 0.025;
        sim.advance_to(t).unwrap();
        if t >= 3.0 - 1e-9 {
            pts.push((t, amplitude(&sim).ln()));
        }
    }
    let n = pts.len() as f64;
    let (mt, ml) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    pts.iter().map(|p| (p.0 - mt) * (p.1 - ml)).sum::<f64>() / pts.iter().map(|p| (p.0 - mt).powi(2)).sum::<f64>()
}

#[test]
fn linear_growth_rate_of_a_perturbed_slab() {
    // Exact rates from the 1-D eigenproblem: m=1 0.7206, m=2 1.1521. At 192 x 48 (h = 1/12,
    // three cells across the tanh edge of width 0.25) the specification's prototype measured
    // 0.717 and 1.133 (-0.5%, -1.7%) and we measure 0.714 and 1.122 (-0.9%, -2.7%): the edge is
    // barely resolved and the error grows with k h. So: 2% at m=1, 4% at m=2, and at m=2 the
    // error must shrink when the grid is refined to 384 x 96.
    let g1 = slab_growth_rate(1, 192, 48);
    let g2 = slab_growth_rate(2, 192, 48);
    let g2_fine = slab_growth_rate(2, 384, 96);
    println!(
        "slab growth rates: m=1 {g1:.4} (exact 0.7206), m=2 {g2:.4} at 192 x 48 and {g2_fine:.4} at 384 x 96 \
        (exact 1.1521)"
    );
    assert!((g1 / 0.7206 - 1.0).abs() < 0.02, "m=1 rate {g1}");
    assert!((g2 / 1.1521 - 1.0).abs() < 0.04, "m=2 rate {g2}");
    assert!(
        (g2_fine - 1.1521).abs() < (g2 - 1.1521).abs(),
        "refining did not help: {g2} -> {g2_fine}"
    );
    // Below the sharp-interface upper bounds (0.94, 1.89).
    assert!(g1 < 0.94 && g2 < 1.89);
}

/// Speed of a uniform cylinder's centre after one solve, `cells_per_radius` cells per R.
fn cylinder_speed(cells_per_radius: usize) -> f64 {
    let nx = 16 * cells_per_radius;
    let p = base(nx, nx, 16.0);
    let n0: Vec<f64> = (0..nx * nx)
        .map(|c| {
            let (x, y) = cell_xy(&p, c);
            let r = ((x - 8.0).powi(2) + (y - 8.0).powi(2)).sqrt();
            0.25 + 0.75 * (1.0 - ((r - 1.0) / 0.02).tanh()) / 2.0
        })
        .collect();
    let sim = PlasmaCloud::with_density(p, n0).unwrap();
    // The centre (8, 8) is a cell corner: average the two x-faces that meet there.
    let (i, j) = (nx / 2 - 1, nx / 2);
    0.5 * (sim.velocity.u[(j - 1) * nx + i] + sim.velocity.u[j * nx + i])
}

#[test]
fn uniform_cylinder_drifts_at_the_analytic_speed() {
    // K = 4: V_c = 2 V0 / (1 + K) = 0.400; periodic images in y raise it by
    // 1 / (1 - (pi^2/3) A R^2 / Ly^2), A = 3/5, to 0.4031. The discrete value has an O(h)
    // error (the prototype: 0.4127 at R/h = 8, 0.4087 at 16): we require ours within 0.002 of
    // those, and the error against 0.4031 to shrink by at least 1.7x from R/h = 8 to 16.
    let a = 0.6;
    let exact = 0.4 / (1.0 - std::f64::consts::PI.powi(2) / 3.0 * a / 256.0);
    let (s8, s16) = (cylinder_speed(8), cylinder_speed(16));
    println!("cylinder speed: {s8:.4} at R/h = 8, {s16:.4} at 16 (analytic {exact:.4})");
    assert!((s8 - 0.4127).abs() < 0.002, "{s8}");
    assert!((s16 - 0.4087).abs() < 0.002, "{s16}");
    assert!((s8 - exact).abs() / (s16 - exact).abs() > 1.7);
}

#[test]
fn steady_shear_matches_the_exact_velocity() {
    // Sigma = 1 + 0.5 sin(2 pi x / Lx), E0 along x: v_y = -E0x / (Sigma <1/Sigma>). The
    // discrete solution is second order; at 16 cells per unit length the error is ~1e-4 of
    // the velocity, so 1e-3 relative is a tight but safe bound.
    let mut p = base(256, 8, 16.0);
    p.e0 = [1.0, 0.0];
    let tau = std::f64::consts::TAU;
    let sigma = |x: f64| 1.0 + 0.5 * (tau * x / 16.0).sin();
    let mean_inv = 1.0 / (1.0f64 - 0.25).sqrt();
    let n0: Vec<f64> = (0..p.nx * p.ny).map(|c| sigma(cell_xy(&p, c).0)).collect();
    let sim = PlasmaCloud::with_density(p.clone(), n0).unwrap();
    let mut worst: f64 = 0.0;
    for c in 0..p.nx * p.ny {
        let x = cell_xy(&p, c).0;
        let exact = -1.0 / (sigma(x) * mean_inv);
        worst = worst.max((sim.velocity.v[c] - exact).abs() / exact.abs());
        assert!(
            sim.velocity.u[c].abs() < 1e-10,
            "no x drift expected, got {}",
            sim.velocity.u[c]
        );
    }
    println!("steady shear: max relative error {worst:.2e}");
    assert!(worst < 1e-3, "{worst}");
}

#[test]
fn mirror_symmetry_is_kept() {
    // No noise, cloud centred in y, even Ny, solves to 1e-12: the mirror image in y is also a
    // solution, so the two halves may differ only by rounding (1e-11 up to t = 3).
    let p = PlasmaParams {
        nx: 192,
        ny: 48,
        eps: 0.0,
        tol: 1e-12,
        ..PlasmaParams::default()
    };
    let mut sim = PlasmaCloud::new(p.clone()).unwrap();
    sim.advance_to(3.0).unwrap();
    let mut worst: f64 = 0.0;
    for j in 0..p.ny / 2 {
        for i in 0..p.nx {
            worst = worst.max((sim.density[j * p.nx + i] - sim.density[(p.ny - 1 - j) * p.nx + i]).abs());
        }
    }
    println!("mirror asymmetry at t = 3: {worst:.2e}");
    assert!(worst <= 1e-11, "{worst}");
}

#[test]
fn bad_parameters_are_errors_not_panics() {
    for p in [
        PlasmaParams {
            nx: 2,
            ..PlasmaParams::default()
        },
        PlasmaParams {
            n_b: 0.0,
            ..PlasmaParams::default()
        },
        PlasmaParams {
            n_b: f64::NAN,
            ..PlasmaParams::default()
        },
        PlasmaParams {
            out_dt: -1.0,
            ..PlasmaParams::default()
        },
        PlasmaParams {
            cfl: 2.0,
            ..PlasmaParams::default()
        },
    ] {
        assert!(PlasmaCloud::new(p).is_err());
    }
    let p = base(8, 8, 1.0);
    assert!(PlasmaCloud::with_density(p.clone(), vec![1.0; 63]).is_err());
    assert!(PlasmaCloud::with_density(p, vec![-1.0; 64]).is_err());
}
