//! The filter's uncertainty ahead with the aerials' frames still to come: what placement over
//! the horizon (`placement = "horizon"`) weighs a disk by.
//!
//! A covariance depends on where and how well a field is observed, never on the values, so the
//! posterior covariance at a future step, given that the aerials go on observing as they do
//! now, is known in advance (the Riccati recursion without data). Until the boats' sampling
//! step every step is a prediction and the aerials' update. What a boat's value at the
//! sampling step removes from the field's variance, summed over the horizon's steps with the
//! aerials still observing, is then:
//! - for the detail (independent per cell), exact: two scalar recursions per cell, with and
//!   without the value;
//! - for the modes, to first order: a reduction `dP` at the sampling step is `L dP L^T` a step
//!   later, `L = (I + P J)^-1 A` (`P` the prediction's covariance, `J` the aerials'
//!   information), so over the horizon it removes `tr(dP M)`, `M = sum_t Phi_t^T Phi_t`,
//!   `Phi_t = L_t ... L_1` (the basis is orthonormal: a field's variance is its modal
//!   covariance's trace).
//!
//! Ignoring the aerials (the forecast alone) makes the detail's variance the same at every
//! cell between two boat steps; with them, a cell keeps what the aerials cannot see there (the
//! interpolation's error), which is where a boat is worth most.

use super::{symmetrised, FilterError, ModalFilter};
use faer::{Mat, MatRef};

/// What the aerials see at every step (taken as the last frame's): the lattice cells with each
/// value's noise variance (the modal update) and the aerial estimate's variance at every cell
/// (the detail's update; empty: none).
#[derive(Debug, Clone, Copy)]
pub struct Scheduled<'a> {
    pub cells: &'a [usize],
    pub variance: &'a [f64],
    pub everywhere: &'a [f64],
}

/// The filter's uncertainty at the boats' next sampling step, and what a value then is worth
/// over the horizon.
#[derive(Debug, Clone)]
pub struct Lookahead {
    /// Modal covariance at the sampling step after the aerials' update there.
    pub cov: Mat<f64>,
    /// Detail variance per cell at the sampling step before any update there (what the modal
    /// update weighs a value by).
    pub detail_var: Vec<f64>,
    /// `M`: a reduction `dP` of the modal covariance at the sampling step removes `tr(dP M)`
    /// from the field's variance summed over the horizon.
    pub modal_weight: Mat<f64>,
    /// Per cell: the detail variance one value with the boats' noise at the sampling step
    /// removes, summed over the horizon's steps.
    pub detail_gain: Vec<f64>,
    /// Per cell: the weight the detail's update gives a value with the boats' noise at the
    /// sampling step, after the aerials' update there (`v / (v + noise)`): the share of an
    /// error the filter does not model that the value corrects.
    pub value_weight: Vec<f64>,
}

impl ModalFilter {
    /// The uncertainty `to_sampling` (>= 1) steps ahead, the aerials observing at each step,
    /// and what a value with noise `sample_var` there removes over `steps` (>= 1) steps from
    /// the sampling step on.
    ///
    /// Long because it is one recursion: the covariance's steps to the sampling step and over the
    /// horizon, in the order the filter's own step takes them, so the two can be read side by side.
    pub fn look_ahead(
        &self,
        to_sampling: usize,
        steps: usize,
        aerials: &Scheduled<'_>,
        sample_var: f64,
    ) -> Result<Lookahead, FilterError> {
        let (n, q) = (self.basis.nrows(), self.dim());
        if to_sampling == 0 || steps == 0 {
            return Err(FilterError::Input(format!(
                "looking {to_sampling} steps ahead over {steps} steps: both must be at least 1"
            )));
        }
        if !(sample_var > 0.0 && sample_var.is_finite()) {
            return Err(FilterError::Input(format!("sample variance {sample_var}")));
        }
        if aerials.cells.len() != aerials.variance.len()
            || !(aerials.everywhere.is_empty() || aerials.everywhere.len() == n)
        {
            return Err(FilterError::Input(format!(
                "{} aerial cells with {} variances, {} variances everywhere on {n} cells",
                aerials.cells.len(),
                aerials.variance.len(),
                aerials.everywhere.len()
            )));
        }
        if let Some((c, v)) = aerials
            .cells
            .iter()
            .zip(aerials.variance)
            .find(|(&c, &v)| c >= n || !(v >= 0.0 && v.is_finite()))
        {
            return Err(FilterError::Input(format!("aerial cell {c} with variance {v}")));
        }
        if aerials.everywhere.iter().any(|v| !(*v > 0.0 && v.is_finite())) {
            return Err(FilterError::Input(
                "the aerial estimate's variances must be positive and finite".into(),
            ));
        }
        let a = self.dynamics.as_ref();
        let (mut p, mut d) = (self.cov.clone(), self.detail_var.clone());
        let mut at_sampling: Option<(Mat<f64>, Vec<f64>)> = None;
        let (mut phi, mut m) = (Mat::<f64>::identity(q, q), Mat::<f64>::identity(q, q));
        let (mut with_value, mut gain, mut weight) = (vec![], vec![0.0; n], vec![]);
        for t in 1..to_sampling + steps {
            let predicted = self.predicted_cov(p.as_ref());
            d.iter_mut().for_each(|v| *v = self.predicted_detail(*v));
            let j = self.information(aerials, &d);
            let mut s = predicted.as_ref() * j.as_ref();
            for i in 0..q {
                s[(i, i)] += 1.0;
            }
            let lu = s.partial_piv_lu();
            p = symmetrised(faer::linalg::solvers::Solve::solve(&lu, predicted.as_ref()));
            if t == to_sampling {
                at_sampling = Some((p.clone(), d.clone()));
            }
            seen(&mut d, aerials.everywhere);
            if t == to_sampling {
                weight = d.iter().map(|v| v / (v + sample_var)).collect();
                with_value = d.iter().map(|v| v * sample_var / (v + sample_var)).collect();
            } else if t > to_sampling {
                phi = faer::linalg::solvers::Solve::solve(&lu, a) * phi.as_ref();
                m += phi.transpose() * phi.as_ref();
                with_value.iter_mut().for_each(|v| *v = self.predicted_detail(*v));
                seen(&mut with_value, aerials.everywhere);
            }
            if t >= to_sampling {
                gain.iter_mut()
                    .zip(d.iter().zip(&with_value))
                    .for_each(|(g, (v, w))| *g += v - w);
            }
        }
        let (cov, detail_var) = at_sampling.expect("the loop passes the sampling step");
        super::check_finite(
            "the covariance ahead",
            cov.col_iter()
                .flat_map(|c| c.iter().copied().collect::<Vec<_>>())
                .chain(m.col_iter().flat_map(|c| c.iter().copied().collect::<Vec<_>>())),
        )
        .map_err(|_| FilterError::Numerical("the covariance ahead lost finiteness".into()))?;
        Ok(Lookahead {
            cov,
            detail_var,
            modal_weight: m,
            detail_gain: gain,
            value_weight: weight,
        })
    }

    /// `A P A^T + q I`.
    pub(super) fn predicted_cov(&self, p: MatRef<'_, f64>) -> Mat<f64> {
        let a = self.dynamics.as_ref();
        let mut next = a * p * a.transpose();
        for i in 0..self.dim() {
            next[(i, i)] += self.process;
        }
        symmetrised(next)
    }

    /// One step of the detail's variance: towards the model error at the persistence's rate.
    pub(super) fn predicted_detail(&self, v: f64) -> f64 {
        let rho2 = self.persistence * self.persistence;
        rho2 * v + (1.0 - rho2) * self.model_error
    }

    /// `J = sum h h^T / (noise + detail variance)` over the aerials' lattice cells.
    fn information(&self, aerials: &Scheduled<'_>, detail_var: &[f64]) -> Mat<f64> {
        let q = self.dim();
        let mut j = Mat::<f64>::zeros(q, q);
        for (&c, &v) in aerials.cells.iter().zip(aerials.variance) {
            let (h, w) = (self.basis.row(c), 1.0 / (v + detail_var[c]).max(1e-300));
            for x in 0..q {
                for y in 0..q {
                    j[(x, y)] += h[x] * h[y] * w;
                }
            }
        }
        j
    }
}

/// The detail's variance after the aerial estimate (variance `e` per cell; none when empty).
fn seen(d: &mut [f64], e: &[f64]) {
    for (v, e) in d.iter_mut().zip(e) {
        *v = *v * e / (*v + e);
    }
}

#[cfg(test)]
mod tests {
    use super::super::Observation;
    use super::*;

    /// Two modes on 30 cells, a rotation with decay, a persistent detail.
    fn filter() -> ModalFilter {
        let n = 30;
        let raw = Mat::from_fn(n, 2, |i, j| {
            ((i + 1) as f64 * (j + 1) as f64 * 0.41).sin() + 0.3 * j as f64
        });
        let b = raw.qr().compute_thin_Q();
        let (c, s) = (0.97 * 0.2f64.cos(), 0.97 * 0.2f64.sin());
        let a = Mat::from_fn(2, 2, |i, j| [[c, -s], [s, c]][i][j]);
        let p = Mat::from_fn(2, 2, |i, j| if i == j { 0.5 } else { 0.1 });
        let mut f = ModalFilter::new(b, a, vec![0.3, -0.2], p, 0.02, 0.04).unwrap();
        f.persistence = 0.8;
        f.detail_var = (0..n).map(|i| 0.01 + 0.002 * i as f64).collect();
        f
    }

    #[test]
    fn without_aerials_the_weights_are_the_dynamics_and_the_detail_decays() {
        let f = filter();
        let none = Scheduled {
            cells: &[],
            variance: &[],
            everywhere: &[],
        };
        let (to, steps, b) = (3, 4, 0.01);
        let got = f.look_ahead(to, steps, &none, b).unwrap();
        // M = sum_{t < steps} (A^t)^T A^t, and the covariance is the forecast's.
        let a = f.dynamics().to_owned();
        let (mut power, mut m) = (Mat::<f64>::identity(2, 2), Mat::<f64>::zeros(2, 2));
        for _ in 0..steps {
            m += power.transpose() * power.as_ref();
            power = a.as_ref() * power.as_ref();
        }
        let ahead = f.ahead(to);
        for i in 0..2 {
            for j in 0..2 {
                assert!((got.modal_weight[(i, j)] - m[(i, j)]).abs() < 1e-12);
                assert!((got.cov[(i, j)] - ahead.cov[(i, j)]).abs() < 1e-12);
            }
        }
        // The detail: what a value removes, v^2 / (v + b), decays as rho^2 per step.
        for (c, g) in got.detail_gain.iter().enumerate() {
            let v = ahead.detail_var[c];
            let want: f64 = (0..steps).map(|t| 0.64f64.powi(t as i32) * v * v / (v + b)).sum();
            assert!((g - want).abs() < 1e-12 * want, "cell {c}: {g} against {want}");
            assert!((got.detail_var[c] - v).abs() < 1e-15);
            assert!((got.value_weight[c] - v / (v + b)).abs() < 1e-15);
        }
    }

    /// The filter itself run ahead with data that carries no news (each value its prediction):
    /// covariances do not depend on the values.
    fn run(f: &mut ModalFilter, lattice: &[usize], noise: &[f64], everywhere: &[f64], boat: Option<(&[usize], f64)>) {
        f.predict();
        let (field, _) = f.field();
        let modal: Vec<f64> = field.iter().zip(&f.detail).map(|(x, d)| x - d).collect();
        let values: Vec<f64> = lattice.iter().map(|&c| field[c]).collect();
        let (cells_b, var_b): (Vec<usize>, Vec<f64>) =
            boat.map_or((vec![], vec![]), |(c, v)| (c.to_vec(), vec![v; c.len()]));
        let values_b: Vec<f64> = cells_b.iter().map(|&c| field[c]).collect();
        f.update(&[
            Observation {
                cells: lattice,
                values: &values,
                variance: noise,
            },
            Observation {
                cells: &cells_b,
                values: &values_b,
                variance: &var_b,
            },
        ])
        .unwrap();
        let all: Vec<usize> = (0..field.len()).collect();
        let at: Vec<f64> = all.iter().map(|&c| modal[c] + f.detail[c]).collect();
        let at_b: Vec<f64> = cells_b.iter().map(|&c| at[c]).collect();
        f.update_detail(&[
            Observation {
                cells: &all,
                values: &at,
                variance: everywhere,
            },
            Observation {
                cells: &cells_b,
                values: &at_b,
                variance: &var_b,
            },
        ])
        .unwrap();
    }

    fn total_variance(f: &ModalFilter) -> f64 {
        f.field().1.iter().sum()
    }

    #[test]
    fn with_aerials_it_is_the_filters_own_recursion() {
        let f = filter();
        let lattice: Vec<usize> = (0..30).step_by(3).collect();
        let noise: Vec<f64> = lattice.iter().map(|&c| 0.005 + 0.001 * c as f64).collect();
        let everywhere: Vec<f64> = (0..30)
            .map(|c| {
                if c % 3 == 0 {
                    noise[c / 3]
                } else {
                    0.02 + 0.003 * (c % 7) as f64
                }
            })
            .collect();
        let sched = Scheduled {
            cells: &lattice,
            variance: &noise,
            everywhere: &everywhere,
        };
        let (to, steps) = (4, 6);
        // The covariance at the sampling step: the filter's after `to - 1` steps and the
        // prediction and the aerials' modal update of step `to`.
        let mut plain = f.clone();
        for _ in 0..to - 1 {
            run(&mut plain, &lattice, &noise, &everywhere, None);
        }
        let mut at = plain.clone();
        at.predict();
        let prior_detail = at.detail_var.clone();
        // The detail exactly: with and without a precise value at one cell, summed over the
        // horizon. The modes to first order: with a value of little information (noise 1e4),
        // the exact difference of the two runs' modal variance matches tr(dP M).
        let (b, cell, faint) = (0.01, 7usize, 1e4);
        let got = f.look_ahead(to, steps, &sched, b).unwrap();
        let faint_got = f.look_ahead(to, steps, &sched, faint).unwrap();
        let modal_var = |g: &ModalFilter| (0..2).map(|i| g.cov[(i, i)]).sum::<f64>();
        let (mut without, mut with, mut with_faint) = (plain.clone(), plain.clone(), plain.clone());
        let (mut detail_removed, mut modal_removed) = (0.0, 0.0);
        for t in 0..steps {
            run(&mut without, &lattice, &noise, &everywhere, None);
            run(
                &mut with,
                &lattice,
                &noise,
                &everywhere,
                (t == 0).then_some((&[cell][..], b)),
            );
            run(
                &mut with_faint,
                &lattice,
                &noise,
                &everywhere,
                (t == 0).then_some((&[cell][..], faint)),
            );
            if t == 0 {
                at.update(&[Observation {
                    cells: &lattice,
                    values: &lattice.iter().map(|&c| at.field().0[c]).collect::<Vec<_>>(),
                    variance: &noise,
                }])
                .unwrap();
                for i in 0..2 {
                    for j in 0..2 {
                        assert!(
                            (got.cov[(i, j)] - at.cov[(i, j)]).abs() < 1e-12,
                            "the covariance at the sampling step"
                        );
                    }
                }
                prior_detail
                    .iter()
                    .zip(&got.detail_var)
                    .for_each(|(x, y)| assert!((x - y).abs() < 1e-15));
            }
            if t == 0 {
                // The value's weight: the share of the detail's variance it removes there.
                let k = 1.0 - with.detail_var[cell] / without.detail_var[cell];
                assert!(
                    (got.value_weight[cell] - k).abs() < 1e-12,
                    "weight {} against the filter's {k}",
                    got.value_weight[cell]
                );
            }
            detail_removed += without.detail_var[cell] - with.detail_var[cell];
            modal_removed += modal_var(&without) - modal_var(&with_faint);
        }
        assert!(
            (got.detail_gain[cell] - detail_removed).abs() < 1e-12 * detail_removed,
            "{} against {detail_removed}",
            got.detail_gain[cell]
        );
        // tr(dP M), dP what the faint value removes at the sampling step.
        let h = Mat::from_fn(2, 1, |k, _| f.basis()[(cell, k)]);
        let w = 1.0 / (faint + faint_got.detail_var[cell]);
        let j = h.as_ref() * h.transpose() * faer::Scale(w);
        let post = {
            let mut s = faint_got.cov.as_ref() * j.as_ref();
            (0..2).for_each(|i| s[(i, i)] += 1.0);
            faer::linalg::solvers::Solve::solve(&s.partial_piv_lu(), faint_got.cov.as_ref())
        };
        let dp = faint_got.cov.as_ref() - post.as_ref();
        let predicted: f64 = (0..2)
            .map(|i| (0..2).map(|k| dp[(i, k)] * faint_got.modal_weight[(k, i)]).sum::<f64>())
            .sum();
        assert!(
            modal_removed > 0.0 && (predicted - modal_removed).abs() < 1e-3 * modal_removed,
            "{predicted} against {modal_removed}"
        );
        assert!(
            total_variance(&without) < total_variance(&f.ahead(to + steps - 1)),
            "the aerials' frames count"
        );
    }

    #[test]
    fn bad_input_is_refused() {
        let f = filter();
        let none = Scheduled {
            cells: &[],
            variance: &[],
            everywhere: &[],
        };
        assert!(f.look_ahead(0, 1, &none, 0.01).is_err());
        assert!(f.look_ahead(1, 1, &none, 0.0).is_err());
        assert!(f
            .look_ahead(
                1,
                1,
                &Scheduled {
                    cells: &[99],
                    variance: &[0.1],
                    everywhere: &[]
                },
                0.01
            )
            .is_err());
        assert!(f
            .look_ahead(
                1,
                1,
                &Scheduled {
                    cells: &[],
                    variance: &[],
                    everywhere: &[1.0; 3]
                },
                0.01
            )
            .is_err());
        assert!(f
            .look_ahead(
                1,
                1,
                &Scheduled {
                    cells: &[1],
                    variance: &[f64::NAN],
                    everywhere: &[]
                },
                0.01
            )
            .is_err());
    }
}
