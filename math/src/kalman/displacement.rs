//! The error the filter does not model: the field's features in the wrong place.
//!
//! The filter's detail is independent per cell and fixed in space, so a front the forecast
//! puts a little off errs where the field is steep, by more than the detail's variance says
//! there (docs/decisions/031-placement-over-the-horizon.md). A displacement `delta` of the features, isotropic
//! with variance `s2` per axis (cells^2), errs by `grad x . delta` at a cell: variance
//! `s2 |grad x|^2`. `s2` is read from the boats' innovations against the forecast: their
//! excess over what the filter expects (its variance plus the boats' noise), regressed on the
//! forecast's squared gradient at their cells, with an intercept so that an excess spread
//! evenly over the cells (the detail's business) is not taken for a displacement.

/// Least squares of `innovation2 - expected = a + s2 * grad2` over the cells: `s2`, floored at
/// 0 (a displacement has a variance), or `None` when the squared gradient does not vary over
/// the cells (nothing to read it from) or the slices differ in length.
pub fn displacement_variance(innovation2: &[f64], expected: &[f64], grad2: &[f64]) -> Option<f64> {
    let n = innovation2.len();
    if n < 2
        || expected.len() != n
        || grad2.len() != n
        || innovation2.iter().chain(expected).chain(grad2).any(|v| !v.is_finite())
    {
        return None;
    }
    let g_mean = grad2.iter().sum::<f64>() / n as f64;
    let r = |i: usize| innovation2[i] - expected[i];
    let r_mean = (0..n).map(r).sum::<f64>() / n as f64;
    let sgg = grad2.iter().map(|g| (g - g_mean).powi(2)).sum::<f64>();
    let sgr = (0..n).map(|i| (grad2[i] - g_mean) * (r(i) - r_mean)).sum::<f64>();
    (sgg > 1e-300 * n as f64).then(|| (sgr / sgg).max(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_distr::{Distribution, StandardNormal};

    /// Monte Carlo: innovations drawn with variance `expected + 0.05 + s2 grad2` (an even
    /// excess of 0.05 besides the displacement) give back `s2` within 4 standard errors of
    /// the estimator (its standard error from the draw's own variances: a chi-square with one
    /// degree of freedom has variance 2 v^2).
    #[test]
    fn a_known_displacement_is_read_back_from_the_innovations() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let n = 20_000;
        let s2 = 0.7;
        let grad2: Vec<f64> = (0..n).map(|_| rng.random_range(0.0..0.2_f64).powi(2)).collect();
        let expected: Vec<f64> = (0..n).map(|_| rng.random_range(0.01..0.03)).collect();
        let var: Vec<f64> = (0..n).map(|i| expected[i] + 0.05 + s2 * grad2[i]).collect();
        let mut z2 = || -> f64 {
            let z: f64 = StandardNormal.sample(&mut rng);
            z * z
        };
        let innovation2: Vec<f64> = var.iter().map(|v| v * z2()).collect();
        let got = displacement_variance(&innovation2, &expected, &grad2).unwrap();
        let g_mean = grad2.iter().sum::<f64>() / n as f64;
        let sgg: f64 = grad2.iter().map(|g| (g - g_mean).powi(2)).sum();
        let se = (grad2
            .iter()
            .zip(&var)
            .map(|(g, v)| (g - g_mean).powi(2) * 2.0 * v * v)
            .sum::<f64>())
        .sqrt()
            / sgg;
        assert!(
            (got - s2).abs() < 4.0 * se,
            "read {got}, true {s2}, standard error {se}"
        );
        // Without a displacement it reads (nearly) none, never a negative one.
        let flat: Vec<f64> = (0..n).map(|i| (expected[i] + 0.05) * z2()).collect();
        let none = displacement_variance(&flat, &expected, &grad2).unwrap();
        assert!((0.0..4.0 * se).contains(&none), "{none}");
    }

    #[test]
    fn nothing_to_read_from() {
        assert_eq!(
            displacement_variance(&[1.0, 2.0], &[0.0, 0.0], &[0.3, 0.3]),
            None,
            "the gradient does not vary"
        );
        assert_eq!(displacement_variance(&[1.0], &[0.0], &[0.3]), None);
        assert_eq!(displacement_variance(&[1.0, 2.0], &[0.0], &[0.1, 0.3]), None);
        assert_eq!(displacement_variance(&[1.0, f64::NAN], &[0.0, 0.0], &[0.1, 0.3]), None);
        assert_eq!(
            displacement_variance(&[2.0, 1.0], &[0.0, 0.0], &[0.1, 0.3]),
            Some(0.0),
            "floored"
        );
    }
}
