//! Fusion of aerial frames with the boats' gappy estimate on a field both sources can represent
//! exactly (bilinear in (row, col), so upsampling is unbiased; rank 4, so gappy is unbiased):
//! only noise separates the estimates from the truth, and the reported variances must say how
//! much.

use faer::Mat;
use fleet_math::fusion::{fuse, AerialFrame, AerialNoise, Estimate, Measured, Scheme};
use fleet_math::grid::{Cell, Grid};
use fleet_math::sensing::gappy::reconstruct;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// The cells of a 49 x 97 grid and an orthonormal basis of {1, row, col, row*col}.
fn setup() -> (Grid, Mat<f64>) {
    let g = Grid::new(49, 97, 1.0).unwrap();
    let raw = Mat::from_fn(g.len(), 4, |i, j| {
        let c = g.cell(i);
        let (r, k) = (c.row as f64 / 48.0, c.col as f64 / 96.0);
        [1.0, r, k, r * k][j]
    });
    (g, raw.qr().compute_thin_Q())
}

fn mse(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len() as f64
}

struct Trial {
    aerial: f64,
    hifi: f64,
    inverse: f64,
    paper: f64,
    /// Mean reported variance of the inverse-variance fusion.
    reported: f64,
}

fn trial(seed: u64) -> Trial {
    let (g, phi) = setup();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let coef: Vec<f64> = (0..4).map(|_| rng.random_range(-20.0..20.0)).collect();
    let truth: Vec<f64> = (0..g.len())
        .map(|i| (0..4).map(|j| phi[(i, j)] * coef[j]).sum())
        .collect();

    // Two aerials at the quarter points; noise 0.2 at the aerial growing by 0.01 per metre.
    let aerials = [(24.25, 24.5), (72.75, 24.5)];
    let frame = AerialFrame::sense(
        &g,
        &truth,
        8,
        &aerials,
        AerialNoise {
            sigma0: 0.2,
            growth_per_m: 0.01,
        },
        &mut rng,
    )
    .unwrap();
    let aerial = frame.upsample().unwrap();

    // Three boats, radius 3, noise variance 0.25.
    let noise_var: f64 = 0.25;
    let cells: Vec<usize> = [Cell::new(10, 15), Cell::new(30, 50), Cell::new(40, 85)]
        .iter()
        .flat_map(|&c| g.disk(c, 3.0))
        .collect();
    let values: Vec<f64> = cells
        .iter()
        .map(|&c| {
            truth[c] + noise_var.sqrt() * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, &mut rng)
        })
        .collect();
    let gappy = reconstruct(phi.as_ref(), &cells, &values, noise_var).unwrap();
    let hifi = Estimate {
        values: gappy.field,
        variance: gappy.variance,
    };
    let measured = Some(Measured {
        cells: &cells,
        values: &values,
        noise_var,
    });

    let inv = fuse(Scheme::InverseVariance, g.len(), &[&aerial, &hifi], measured).unwrap();
    let paper = fuse(Scheme::Paper, g.len(), &[&aerial, &hifi], measured).unwrap();
    Trial {
        aerial: mse(&aerial.values, &truth),
        hifi: mse(&hifi.values, &truth),
        inverse: mse(&inv.values, &truth),
        paper: mse(&paper.values, &truth),
        reported: inv.variance.iter().sum::<f64>() / g.len() as f64,
    }
}

#[test]
fn inverse_variance_fusion_beats_either_source_alone() {
    let t = trial(11);
    println!(
        "fused MSE: aerial {:.4}, boats {:.4}, paper {:.4}, inverse-variance {:.4}",
        t.aerial, t.hifi, t.paper, t.inverse
    );
    assert!(
        t.inverse < t.aerial && t.inverse < t.hifi,
        "inverse-variance {} vs aerial {} and boats {}",
        t.inverse,
        t.aerial,
        t.hifi
    );
    // ... and the paper's unweighted mean, which ignores how good each source is here.
    assert!(
        t.inverse <= t.paper,
        "inverse-variance {} vs paper {}",
        t.inverse,
        t.paper
    );
}

#[test]
fn reported_variance_matches_the_error_over_trials() {
    // Averaged over 40 seeds the fused MSE is an unbiased estimate of the mean reported
    // variance; with ~40 x 4753 correlated cells the ratio lands within 20% (it is ~1.0).
    let (mut err, mut rep) = (0.0, 0.0);
    for s in 0..40 {
        let t = trial(100 + s);
        err += t.inverse;
        rep += t.reported;
    }
    let ratio = err / rep;
    assert!((0.8..1.25).contains(&ratio), "empirical / reported variance = {ratio}");
}

#[test]
fn upsampled_variance_is_exact_for_independent_noise() {
    // Monte Carlo of the upsampled noise at a few cells against sum w^2 var.
    let (g, _) = setup();
    let truth = vec![0.0; g.len()];
    let noise = AerialNoise {
        sigma0: 0.5,
        growth_per_m: 0.0,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let probe = [
        g.index(Cell::new(3, 5)),
        g.index(Cell::new(20, 44)),
        g.index(Cell::new(48, 96)),
    ];
    let mut sq = [0.0; 3];
    let trials = 4000;
    let mut reported = vec![];
    for _ in 0..trials {
        let up = AerialFrame::sense(&g, &truth, 8, &[(48.5, 24.5)], noise, &mut rng)
            .unwrap()
            .upsample()
            .unwrap();
        for (s, &p) in sq.iter_mut().zip(&probe) {
            *s += up.values[p].powi(2) / trials as f64;
        }
        reported = probe.iter().map(|&p| up.variance[p]).collect();
    }
    for (s, r) in sq.iter().zip(&reported) {
        assert!((s / r - 1.0).abs() < 0.1, "empirical {s} vs reported {r}");
    }
}
