//! One step's estimates: the aerials' frame assembled and upsampled, then fused with the
//! boats' disks (the `paper` and `inverse-variance` schemes, with the boats' gappy estimate or
//! the model's prediction) or run through the modal Kalman filter (`kalman`), which observes
//! the aerial lattice and the disks directly.

use super::between::Sources;
use super::{aerial_detail_variance, plus, Assimilator, Fuser, Setup};
use crate::protocol::Sample;
use crate::team::{Missing, TeamError};
use fleet_math::fusion::{fuse, AerialFrame, Estimate, Measured, Scheme};
use fleet_math::kalman::{self, Observation};
use fleet_math::sensing::gappy;
use std::collections::HashMap;
use std::sync::Arc;

/// One step of the aerials: the estimate on the fine grid (the coarse frame upsampled, for
/// the heuristic schemes and the aerial-only team) and what they saw this step, the lattice
/// cells with each value's own noise variance (what the Kalman filter observes: those errors
/// are independent, the upsampled field's are not).
#[derive(Debug, Clone, PartialEq)]
pub struct AerialSight {
    pub estimate: Estimate,
    /// The interpolation's own error variance per fine cell (from the frame's curvature).
    pub interpolation: Vec<f64>,
    pub cells: Vec<usize>,
    pub values: Vec<f64>,
    pub variance: Vec<f64>,
    /// The fine cells the frame observes (the filter's dense observation): those off land (a
    /// cell interpolated from a lattice cell nobody saw has that fill's variance).
    pub covered: Vec<bool>,
    /// The fine cells whose interpolation leans on a lattice cell nobody saw this step and that
    /// was filled from further than a diagonal neighbour (a refused frame, a wide cloud; not a
    /// coast's land): there the aerials' estimate is no estimate of the field, and no evidence
    /// of how the filter compares with their interpolation.
    pub filled: Vec<bool>,
}

impl Setup {
    /// The aerials' sight of a step from their samples (any order): the coarse frame
    /// reassembled, each value with its sampling aerial's noise at that distance, upsampled
    /// with its variance. `None` without samples (the assimilator then holds its last sight).
    /// It reads the mission's settings only, so it is made on any thread
    /// ([`Assimilator::aerial_sight_later`]).
    fn aerial_sight(&self, samples: &[Sample]) -> Result<Option<AerialSight>, TeamError> {
        if samples.is_empty() {
            return Ok(None);
        }
        let grid = &self.grid;
        let mut frame = AerialFrame::assemble(grid, self.cfg.aerial_stride, samples, self.aerial_noise())?;
        let seen: Vec<usize> = (0..frame.seen.len()).filter(|&k| frame.seen[k]).collect();
        let cells = seen.iter().map(|&k| grid.index(frame.lattice.fine_cell(k))).collect();
        let values = seen.iter().map(|&k| frame.values[k]).collect();
        let variance = seen.iter().map(|&k| frame.variance[k].max(1e-12)).collect();
        if seen.is_empty() {
            return Err(TeamError::NotReady(Missing::AerialData));
        }
        let unseen: Vec<usize> = (0..frame.seen.len()).filter(|&k| !frame.seen[k]).collect();
        let far = fill_unseen(&mut frame, &unseen);
        // A fine cell is a fill where a far value has any weight (none far: none, without a
        // pass over the field).
        let filled = match far.contains(&true) {
            true => frame
                .lattice
                .upsample_bilinear(&far.iter().map(|&f| if f { 1.0 } else { 0.0 }).collect::<Vec<_>>())?
                .into_iter()
                .map(|w| w > 1e-9)
                .collect(),
            false => vec![false; grid.len()],
        };
        let estimate = frame.upsample()?;
        let interpolation = frame.interpolation_variance()?;
        // The dense observation is of the water: a cell interpolated from a filled lattice value
        // carries that value's large variance in `estimate.variance`.
        let mut covered = vec![true; grid.len()];
        self.land.iter().for_each(|&c| covered[c] = false);
        Ok(Some(AerialSight {
            estimate,
            interpolation,
            cells,
            values,
            variance,
            covered,
            filled,
        }))
    }
}

impl Assimilator {
    /// An aerial sight in the field's anomalies about the initialisation's mean (as the
    /// filter holds the field): its lattice values and its estimate less the mean there.
    fn anomaly_of(&self, sight: &AerialSight) -> AerialSight {
        let mut a = sight.clone();
        a.values
            .iter_mut()
            .zip(self.mean_at(&sight.cells))
            .for_each(|(v, m)| *v -= m);
        a.estimate.values = self.less_mean(a.estimate.values);
        a
    }

    /// The aerial estimate of a step from the aerials' samples ([`Setup::aerial_sight`]),
    /// held for the steps without any.
    pub fn aerial_estimate(&mut self, samples: &[Sample]) -> Result<AerialSight, TeamError> {
        let sight = self.setup.aerial_sight(samples)?;
        self.hold_aerial(sight)
    }

    /// A function making a step's aerial sight from `samples` on any thread, while the
    /// assimilator goes on (the model server makes the next step's beside the filter's step);
    /// its result goes to [`Self::hold_aerial`].
    pub fn aerial_sight_later(
        &self,
        samples: Vec<Sample>,
    ) -> impl FnOnce() -> Result<Option<AerialSight>, TeamError> + Send + use<> {
        let setup = Arc::clone(&self.setup);
        move || setup.aerial_sight(&samples)
    }

    /// A step's aerial sight, held for the steps after it without any; without one (no
    /// samples), the sight held, which covers no cell and observes nothing.
    pub fn hold_aerial(&mut self, sight: Option<AerialSight>) -> Result<AerialSight, TeamError> {
        let s = &mut self.state;
        let Some(sight) = sight else {
            let estimate = s.held_aerial.clone().ok_or(TeamError::NotReady(Missing::AerialData))?;
            return Ok(AerialSight {
                covered: vec![false; estimate.values.len()],
                filled: vec![false; estimate.values.len()],
                estimate,
                interpolation: s.held_interpolation.clone(),
                cells: vec![],
                values: vec![],
                variance: vec![],
            });
        };
        s.held_aerial = Some(sight.estimate.clone());
        s.held_interpolation = sight.interpolation.clone();
        Ok(sight)
    }

    /// The field `ahead` steps after the newest snapshot as the fleet knows it without any boat
    /// value of that step, with its variance, at `cells` (by cell): the filter's forecast
    /// updated with the aerials' lattice and frame (`fusion = "kalman"`), or the aerials'
    /// estimate with its calibrated extra. What a boat's values are tested against
    /// ([`crate::health`]).
    pub(super) fn boat_reference(
        &self,
        ahead: u64,
        sight: &AerialSight,
        cells: &[usize],
    ) -> Result<HashMap<usize, (f64, f64)>, TeamError> {
        let Some((f, at)) = self.state.filter.as_ref() else {
            let (values, variance) = (&sight.estimate.values, &sight.estimate.variance);
            let extra = self.state.aerial_extra.mean();
            return Ok(cells.iter().map(|&c| (c, (values[c], variance[c] + extra))).collect());
        };
        let aerial = &self.anomaly_of(sight);
        let f = tracing::info_span!("reference ahead").in_scope(|| f.ahead(ahead.saturating_sub(*at) as usize));
        let lattice = Observation {
            cells: &aerial.cells,
            values: &aerial.values,
            variance: &aerial.variance,
        };
        let (_, seen, values, variance) = tracing::info_span!("reference dense")
            .in_scope(|| dense(aerial, self.state.aerial_extra.mean(), &self.setup.on_lattice));
        let dense = Observation {
            cells: &seen,
            values: &values,
            variance: &variance,
        };
        let (mean, variance) =
            tracing::info_span!("reference conditioned").in_scope(|| f.field_at_after(&[lattice], &[dense], cells))?;
        let mean = mean.iter().zip(self.mean_at(cells)).map(|(a, m)| a + m);
        Ok(cells.iter().copied().zip(mean.zip(variance)).collect())
    }

    /// Fuse one step `ahead` steps after the model's newest snapshot, as the [`Fuser`] says:
    /// one step of the filter, or the aerial estimate blended with the boats' gappy estimate
    /// (when `boats` has samples) or the model's prediction. Boat steps also re-calibrate each
    /// source against the boats' measurements.
    pub fn fuse_step(&mut self, ahead: u64, sight: &AerialSight, boats: &[Sample]) -> Result<Estimate, TeamError> {
        // A canonical order (disks do not overlap, so first cells differ): the result does not
        // depend on the order the boats' samples arrived in.
        let mut boats: Vec<&Sample> = boats.iter().collect();
        boats.sort_by_key(|s| (s.cells.first().copied(), s.cells.len()));
        let measured = BoatValues {
            cells: boats.iter().flat_map(|s| s.cells.iter().map(|&c| c as usize)).collect(),
            values: boats.iter().flat_map(|s| s.values.iter().copied()).collect(),
            variances: boat_variances(&boats, self.setup.cfg.boat_sigma),
        };
        match self.setup.fuser {
            Fuser::Filter => self.fuse_filtered(ahead, sight, &measured),
            Fuser::Blend(scheme) => self.fuse_blended(scheme, ahead, sight, &measured),
        }
    }

    /// [`Fuser::Filter`]: the model predicts only the boats' cells (for the sources'
    /// calibration: the filter forecasts by itself), then one filter step. The aerials' extra
    /// is their misfit beyond the interpolation's modelled error, measured where there is one
    /// (between the lattice).
    fn fuse_filtered(&mut self, ahead: u64, sight: &AerialSight, b: &BoatValues) -> Result<Estimate, TeamError> {
        let (pred, _) = self.state.fitted.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let boat_var = b.typical(self.setup.cfg.boat_sigma);
        if !b.cells.is_empty() {
            let at = pred.predict_at(ahead as f64, &b.cells);
            let at_cells: Vec<f64> = at.iter().zip(self.mean_at(&b.cells)).map(|(a, m)| a + m).collect();
            self.calibrate_prediction(&at_cells, b, boat_var);
            let on_lattice = &self.setup.on_lattice;
            let between: Vec<(usize, f64)> = b.pairs().filter(|&(c, _)| !on_lattice[c]).collect();
            self.calibrate_aerials(sight, &between, |c| sight.interpolation[c], boat_var);
        }
        let fused = self.filter_step(ahead, sight, &b.cells, &b.values, &b.variances)?;
        Ok(self.setup.dry_estimate(fused))
    }

    /// [`Fuser::Blend`]: the model's prediction of the whole field (N x r complex products;
    /// the boats' gappy estimate falls back on it), the sources calibrated on the boats'
    /// cells, then the aerial estimate and the boats' fused by `scheme`.
    fn fuse_blended(
        &mut self,
        scheme: Scheme,
        ahead: u64,
        sight: &AerialSight,
        b: &BoatValues,
    ) -> Result<Estimate, TeamError> {
        let (pred, _) = self.state.fitted.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        let predicted = self.plus_mean(pred.predict(ahead as f64));
        let boat_var = b.typical(self.setup.cfg.boat_sigma);
        if !b.cells.is_empty() {
            let at_cells: Vec<f64> = b.cells.iter().map(|&c| predicted[c]).collect();
            self.calibrate_prediction(&at_cells, b, boat_var);
            let all: Vec<(usize, f64)> = b.pairs().collect();
            self.calibrate_aerials(sight, &all, |_| 0.0, boat_var);
        }
        let hifi = self.boats_estimate(predicted, &b.cells, &b.values, boat_var)?;
        let mut aerial = sight.estimate.clone();
        let extra = self.state.aerial_extra.mean();
        aerial.variance.iter_mut().for_each(|v| *v += extra);
        let measured = (!b.cells.is_empty()).then_some(Measured {
            cells: &b.cells,
            values: &b.values,
            noise_var: boat_var,
        });
        let fused = fuse(scheme, self.setup.grid.len(), &[&aerial, &hifi], measured)?;
        Ok(self.setup.dry_estimate(fused))
    }

    /// The prediction's error from the boats' innovations at the measured cells, less the
    /// boats' own noise: it is mostly model error, which is not in its noise model.
    /// `predicted` is the model's prediction at the boats' cells, in their order.
    fn calibrate_prediction(&mut self, predicted: &[f64], b: &BoatValues, boat_var: f64) {
        let squared = predicted
            .iter()
            .zip(&b.values)
            .map(|(p, v)| (p - v).powi(2))
            .sum::<f64>();
        self.state.pred_var = (squared / b.cells.len() as f64 - boat_var).max(1e-12);
    }

    /// The aerials' error beyond their noise model from the boats' values at `at` (cell,
    /// value), beyond `modelled(cell)` (the interpolation's error where the fuser models it):
    /// the aerials' error is mostly interpolation, which their noise model leaves out.
    fn calibrate_aerials(
        &mut self,
        sight: &AerialSight,
        at: &[(usize, f64)],
        modelled: impl Fn(usize) -> f64,
        boat_var: f64,
    ) {
        if at.is_empty() {
            return;
        }
        let expected = at
            .iter()
            .map(|&(c, _)| sight.estimate.variance[c] + modelled(c) + boat_var)
            .sum::<f64>();
        let seen = at
            .iter()
            .map(|&(c, v)| (sight.estimate.values[c] - v).powi(2))
            .sum::<f64>();
        self.state.aerial_extra.add(seen - expected, at.len());
    }

    /// The boats' estimate of the whole field for the heuristic schemes: their gappy
    /// reconstruction on the model's modes, or the model's prediction without boat data.
    fn boats_estimate(
        &self,
        predicted: Vec<f64>,
        cells: &[usize],
        vals: &[f64],
        boat_var: f64,
    ) -> Result<Estimate, TeamError> {
        let n = self.setup.grid.len();
        let prediction = |values| Estimate {
            values,
            variance: vec![self.state.pred_var; n],
        };
        if cells.is_empty() {
            return Ok(prediction(predicted));
        }
        let (_, basis) = self.state.fitted.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
        // The modes hold the field's anomalies: the gappy fit is of the values less the mean.
        let anomalies: Vec<f64> = vals.iter().zip(self.mean_at(cells)).map(|(v, m)| v - m).collect();
        match gappy::reconstruct(faer::Mat::as_ref(basis), cells, &anomalies, boat_var) {
            Ok(mut g) => {
                g.field = self.plus_mean(g.field);
                // Truncation error: the fit's residual at the measured cells, inflated for
                // the degrees of freedom the fit used.
                let dof = (cells.len() as f64 - basis.ncols() as f64).max(1.0);
                let resid = cells
                    .iter()
                    .zip(vals)
                    .map(|(&c, v)| (g.field[c] - v).powi(2))
                    .sum::<f64>()
                    / dof;
                let extra = (resid - boat_var).max(0.0);
                Ok(Estimate {
                    values: g.field,
                    variance: g.variance.iter().map(|v| v + extra).collect(),
                })
            }
            // Too few independent cells for the modes: keep the prediction.
            Err(fleet_math::sensing::SensingError::Underdetermined { .. }) => Ok(prediction(predicted)),
            Err(e) => Err(e.into()),
        }
    }

    /// `fusion = "kalman"`: one step of the filter. The modes see the lattice cells the
    /// aerials saw this step (each with its noise at that distance) and the boats' disks (their
    /// noise); the detail (what the modes cannot hold) then sees the residuals. Before the
    /// update, the detail's forecast variance is checked against both sources' innovations
    /// and rescaled (adaptive inflation, damped and capped). At boat steps the filter's noise
    /// levels are re-estimated from the boats' innovations ([`kalman::ModalFilter::adapt_noise`])
    /// and so is the displacement the filter does not model.
    fn filter_step(
        &mut self,
        ahead: u64,
        sight: &AerialSight,
        cells: &[usize],
        vals: &[f64],
        vars: &[f64],
    ) -> Result<Estimate, TeamError> {
        // The filter holds the field's anomalies about its mean level: what it observes is
        // taken as anomalies, what it gives back as the field.
        let aerial = self.anomaly_of(sight);
        let vals: Vec<f64> = vals.iter().zip(self.mean_at(cells)).map(|(v, m)| v - m).collect();
        let (values, variance) = self.filtered(ahead, (sight, &aerial), cells, &vals, vars)?;
        Ok(Estimate {
            values: self.plus_mean(values),
            variance,
        })
    }

    /// [`Self::filter_step`] in the field's anomalies: `aerial` is `sight` less the mean level,
    /// `vals` the boats' values less it; the field's anomaly and its variance.
    fn filtered(
        &mut self,
        ahead: u64,
        (sight, aerial): (&AerialSight, &AerialSight),
        cells: &[usize],
        vals: &[f64],
        vars: &[f64],
    ) -> Result<(Vec<f64>, Vec<f64>), TeamError> {
        let raw_forecast_mean = self.state.mean.clone();
        let boat_vars: Vec<f64> = vars.iter().map(|v| v.max(1e-12)).collect();
        let boat_var = typical(
            &boat_vars,
            (self.setup.cfg.boat_sigma * self.setup.cfg.boat_sigma).max(1e-12),
        );
        let s = &mut self.state;
        let Some((f, at)) = s.filter.as_mut() else {
            return Err(TeamError::NotReady(Missing::Model));
        };
        while *at < ahead {
            f.predict();
            *at += 1;
        }
        // Boat innovations against the forecast, for the noise estimates.
        let prior = f.prior_at(cells);
        let boats = Observation {
            cells,
            values: vals,
            variance: &boat_vars,
        };
        let lattice = Observation {
            cells: &aerial.cells,
            values: &aerial.values,
            variance: &aerial.variance,
        };
        if !aerial.cells.is_empty() {
            f.learn_persistence(&lattice, 1.0)?;
            s.forecast_skill
                .extend(skill_on_lattice(sight, &prior, raw_forecast_mean.as_deref()));
        }
        let cap = kalman::variance_of(&aerial.estimate.values);
        check_detail(f, &prior, (&lattice, &boats), cap, &self.setup.on_lattice)?;
        // The detail: the aerial estimate at every cell (noise, interpolation and the
        // calibrated extra), then the boats; between the lattice, as far as the boats have seen
        // the filter beat the aerials there (`between`).
        let (aerial_var, seen, values, variance) = dense(aerial, s.aerial_extra.mean(), &self.setup.on_lattice);
        let dense = Observation {
            cells: &seen,
            values: &values,
            variance: &variance,
        };
        let sources = Sources {
            lattice,
            boats,
            dense,
            aerial: &aerial.estimate.values,
            aerial_var: &aerial_var,
            filled: &aerial.filled,
        };
        s.between.update(f, &sources, &self.setup.on_lattice)?;
        if !cells.is_empty() {
            s.innovation = Some(kalman::Innovation::of(&prior, vals, &boat_vars));
            f.adapt_noise(&prior, vals, boat_var);
            let grid = self.setup.grid;
            s.displacement = learn_displacement(
                s.displacement,
                &grid,
                &prior,
                raw_forecast_mean.as_deref(),
                vals,
                &boat_vars,
            )?;
        }
        Ok(f.field())
    }
}

/// A variance excess measured at a few cells per boat epoch (the squared innovations less what
/// the model expects there), pooled over the epochs by their cells' count with the weight of
/// the older ones falling by [`Pooled::KEEP`] each epoch. One epoch's excess rests on the
/// dozen cells between the lattice the boats saw: measured alone, it swung 4x from one epoch to
/// the next on the SST, and a variance taken low by chance made the map overconfident for the
/// five steps it was held (error^2 / variance 2x there). The interpolation's misfit is a
/// property of the field and the lattice, which change slowly: pooled, each epoch's cells
/// count, and a change still shows within a few epochs.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Pooled {
    excess: f64,
    cells: f64,
}

impl Pooled {
    /// The weight an epoch keeps at the next (the smoothing of the model error and the
    /// displacement: about three epochs' memory).
    const KEEP: f64 = 0.7;

    /// One epoch's summed excess over `cells` cells.
    fn add(&mut self, excess: f64, cells: usize) {
        self.excess = Self::KEEP * self.excess + excess;
        self.cells = Self::KEEP * self.cells + cells as f64;
    }

    /// The pooled excess per cell (a variance, so never below 0; 0 before any cell).
    pub(super) fn mean(&self) -> f64 {
        match self.cells > 0.0 {
            true => (self.excess / self.cells).max(0.0),
            false => 0.0,
        }
    }
}

/// The aerial frame as the filter's detail observes it: the variance per cell (noise, the
/// interpolation's error and, between the lattice, the calibrated `extra`), and the covered
/// cells with their values and variances.
fn dense(aerial: &AerialSight, extra: f64, on_lattice: &[bool]) -> (Vec<f64>, Vec<usize>, Vec<f64>, Vec<f64>) {
    let aerial_var = aerial_detail_variance(&aerial.estimate.variance, &aerial.interpolation, extra, on_lattice);
    let seen: Vec<usize> = (0..aerial.estimate.values.len())
        .filter(|&i| aerial.covered[i])
        .collect();
    let (values, variance) = seen.iter().map(|&i| (aerial.estimate.values[i], aerial_var[i])).unzip();
    (aerial_var, seen, values, variance)
}

/// The forecast's skill against the aerials' lattice in the field's values (a mean level that
/// is part of the field counts as skill, as it did before the model learned anomalies).
fn skill_on_lattice(sight: &AerialSight, prior: &kalman::Prior, mean: Option<&Vec<f64>>) -> Option<f64> {
    let raw = Observation {
        cells: &sight.cells,
        values: &sight.values,
        variance: &sight.variance,
    };
    forecast_skill(&plus(mean, prior.mean.clone()), &raw)
}

/// The forecast's skill against a dense observation: 1 - (its mean squared error at the cells,
/// less the values' noise) / (the values' variance). `None` for a flat observation.
fn forecast_skill(forecast: &[f64], o: &Observation<'_>) -> Option<f64> {
    let spread = kalman::variance_of(o.values);
    if o.cells.is_empty() || !(spread > 0.0) {
        return None;
    }
    let error = o
        .cells
        .iter()
        .zip(o.values)
        .zip(o.variance)
        .map(|((&c, y), v)| (y - forecast[c]).powi(2) - v)
        .sum::<f64>()
        / o.cells.len() as f64;
    Some(1.0 - error / spread)
}

/// The detail's forecast variance checked against what each source saw and rescaled before
/// the update, never grown past the field's own variance (`cap`): every cell by the aerials'
/// check (every step, evenly spread: the detail's refresh and persistence are the same
/// everywhere), then the cells between the lattice by the boats' (at boat steps): the
/// interpolation's misfit there is seen only by them. A forecast worse than the aerials' check
/// allows raises the model error too ([`kalman::ModalFilter::raise_model_error`]), which the
/// detail's variance returns to at each predict.
fn check_detail(
    f: &mut kalman::ModalFilter,
    prior: &kalman::Prior,
    (lattice, boats): (&Observation<'_>, &Observation<'_>),
    cap: f64,
    on_lattice: &[bool],
) -> Result<(), TeamError> {
    if let Some(fit) = f.detail_fit(lattice)? {
        f.rescale_detail(fit, cap, 0..on_lattice.len());
        f.raise_model_error(fit, cap);
    }
    // The boats' cells are the prior's: their modal part is taken from it, not made again.
    if let Some(fit) = f.detail_fit_at_prior(prior, boats)? {
        f.rescale_detail(fit, cap, (0..on_lattice.len()).filter(|&c| !on_lattice[c]));
    }
    Ok(())
}

/// Give the lattice cells nobody saw this step (land, cloud, an aerial that did not report) a
/// value to interpolate from: the nearest seen lattice cell's value this step, as uncertain as
/// the seen values are spread (an earlier frame's value would go stale: land is never seen).
/// Which lattice cells were filled from further than a diagonal neighbour: there the fill is
/// no estimate of the field (a whole frame refused leaves half the lattice to one far edge).
fn fill_unseen(frame: &mut AerialFrame, unseen: &[usize]) -> Vec<bool> {
    let mut far = vec![false; frame.seen.len()];
    let seen: Vec<usize> = (0..frame.seen.len()).filter(|&k| frame.seen[k]).collect();
    let spread = kalman::variance_of(&seen.iter().map(|&k| frame.values[k]).collect::<Vec<_>>());
    let lattice = frame.lattice;
    for &k in unseen {
        let at = lattice.fine_cell(k);
        let d2 = |j: usize| {
            let c = lattice.fine_cell(j);
            (c.row as i64 - at.row as i64).pow(2) + (c.col as i64 - at.col as i64).pow(2)
        };
        let j = seen.iter().copied().min_by_key(|&j| (d2(j), j)).unwrap_or(k);
        (frame.values[k], frame.variance[k]) = (frame.values[j], frame.variance[j] + spread);
        let stride = lattice.stride as i64;
        far[k] = d2(j) > 2 * stride * stride;
    }
    far
}

/// The displacement the filter does not model, from the boats' innovations against the
/// forecast's squared gradient ([`kalman::displacement_variance`]); smoothed as the model error
/// is, and never more than the grid's own extent (it cannot run away).
fn learn_displacement(
    displacement: f64,
    grid: &fleet_math::grid::Grid,
    prior: &kalman::Prior,
    mean: Option<&Vec<f64>>,
    vals: &[f64],
    boat_vars: &[f64],
) -> Result<f64, TeamError> {
    let cells = &prior.cells;
    // The gradient of the field the features move in, not of its anomaly.
    let grad2 = grid.squared_gradient(&plus(mean, prior.mean.clone()))?;
    let innovation2: Vec<f64> = cells
        .iter()
        .zip(vals)
        .map(|(&c, v)| (v - prior.mean[c]).powi(2))
        .collect();
    let expected: Vec<f64> = prior.variance.iter().zip(boat_vars).map(|(p, b)| p + b).collect();
    let at: Vec<f64> = cells.iter().map(|&c| grad2[c]).collect();
    Ok(match kalman::displacement_variance(&innovation2, &expected, &at) {
        Some(s2) => {
            let extent = (grid.rows * grid.rows + grid.cols * grid.cols) as f64;
            (0.7 * displacement + 0.3 * s2).min(extent)
        }
        None => displacement,
    })
}

/// Each boat value's noise variance: its own sigma when the instrument said it, else the
/// mission's boat sigma.
fn boat_variances(boats: &[&Sample], sigma: f64) -> Vec<f64> {
    boats
        .iter()
        .flat_map(|s| match &s.sigma {
            Some(sd) => sd.iter().map(|v| v * v).collect::<Vec<_>>(),
            None => vec![sigma * sigma; s.values.len()],
        })
        .collect()
}

/// The boats' values of one step in a canonical order: each cell's value and its noise
/// variance.
struct BoatValues {
    cells: Vec<usize>,
    values: Vec<f64>,
    variances: Vec<f64>,
}

impl BoatValues {
    /// The one noise variance ([`typical`]; `sigma^2` without values).
    fn typical(&self, sigma: f64) -> f64 {
        typical(&self.variances, sigma * sigma)
    }

    /// Each cell with its value.
    fn pairs(&self) -> impl Iterator<Item = (usize, f64)> + '_ {
        self.cells.iter().copied().zip(self.values.iter().copied())
    }
}

/// The one noise variance of the steps that take one (the heuristic schemes, the noise
/// adaptation): the common value when every value has the same (exactly, so a simulated
/// boat's numbers are the bits they were), else their mean; `none` without values.
fn typical(vars: &[f64], none: f64) -> f64 {
    match vars.first() {
        None => none,
        Some(&v) if vars.iter().all(|&w| w == v) => v,
        Some(_) => vars.iter().sum::<f64>() / vars.len() as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::Pooled;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    #[test]
    fn pooled_epochs_weigh_by_cells_and_forget_by_keep() {
        let mut p = Pooled::default();
        assert_eq!(p.mean(), 0.0);
        p.add(2.0, 4);
        assert!((p.mean() - 0.5).abs() < 1e-15);
        // An epoch below the model's expectation takes the pool below 0: a variance stays 0.
        p.add(-8.0, 4);
        assert_eq!(p.mean(), 0.0);
        // ... but its deficit is kept, not clipped away (the pool stays unbiased).
        p.add(20.0, 4);
        let (excess, cells) = (0.7 * (0.7 * 2.0 - 8.0) + 20.0, 0.7 * (0.7 * 4.0 + 4.0) + 4.0);
        assert!((p.mean() - excess / cells).abs() < 1e-12);
    }

    /// A misfit of variance 1 seen at 12 cells an epoch: one epoch's estimate has a relative
    /// standard deviation of sqrt(2 / 12) = 0.41; pooled with KEEP = 0.7, sqrt(2 / 12 * 0.09 /
    /// 0.51) = 0.17 (the weights' sum of squares over their squared sum). 2,000 trials of 20
    /// epochs: the mean within 3% of 1 (its standard error is 0.4%) and the deviation under
    /// 0.25, which one epoch alone (0.41) fails.
    #[test]
    fn a_pooled_excess_is_unbiased_and_steadier_than_one_epochs() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(37);
        let normal = Normal::new(0.0, 1.0).unwrap();
        let estimates: Vec<f64> = (0..2000)
            .map(|_| {
                let mut p = Pooled::default();
                for _ in 0..20 {
                    let excess: f64 = (0..12)
                        .map(|_| {
                            let e: f64 = normal.sample(&mut rng);
                            e * e
                        })
                        .sum();
                    p.add(excess, 12);
                }
                p.mean()
            })
            .collect();
        let mean = estimates.iter().sum::<f64>() / estimates.len() as f64;
        let sd = (estimates.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / estimates.len() as f64).sqrt();
        assert!((mean - 1.0).abs() < 0.03, "mean {mean}");
        assert!(sd < 0.25 && sd > 0.12, "sd {sd}");
    }
}
