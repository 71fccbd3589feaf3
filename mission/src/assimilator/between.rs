//! The field between the aerials' lattice: where the filter's estimate rests on its model, and
//! whether the model has earned it.
//!
//! On the lattice the aerials measure the field; between it, the aerials' estimate is their
//! interpolation and the filter's is that interpolation weighed against the model's forecast.
//! How good the forecast is there is a property of the model on this field, not of the filter:
//! on a smooth cloud whose fronts the model carries it beats the interpolation several times
//! over; on a monthly anomaly whose years are independent it is worse, and its errors share the
//! interpolation's (the model learned from earlier estimates), which no noise level in the
//! filter can express: the filter then leaned on it and its map was worse than the aerials'.
//! So the filter's skill there is measured where there is a truth to measure it against, the
//! boats' cells off the lattice: the slope of the boats' residual from the aerials'
//! interpolation on the filter's departure from it (the filter run without the boats, so they
//! judge it independently), shrunk by its standard error and held in [0, 1], is `skill`. The
//! estimate there is the interpolation plus `skill` times the departure: with no skill shown
//! (and before the first boat value) the aerials' own estimate, never worse than it; with full
//! skill the filter's. Its variance is the two sources' variances blended the same way.
//! (Tried and not kept: the textbook update for correlated errors, with the correlation of the
//! two errors measured at the boats: it rests on the filter's variances being right in scale,
//! and was worse than the aerials on both real fields.)

use fleet_math::kalman::{FilterError, ModalFilter, Observation};

/// What the boats have shown of the filter between the lattice (a value: part of the
/// assimilator's state).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Between {
    /// The filter's skill beyond the aerials' interpolation, in [0, 1] (0 until measured).
    pub skill: f64,
    /// Decaying sums of the regression: residual x departure, and departure^2.
    cross: f64,
    square: f64,
}

/// How much of the past a boat step's sums keep (as the filter's noise levels are smoothed).
const MEMORY: f64 = 0.7;

/// One step's sources as the filter sees them, and the aerials' estimate with its variance.
pub struct Sources<'a> {
    pub lattice: Observation<'a>,
    pub boats: Observation<'a>,
    /// The aerials' interpolated frame at every cell it covers.
    pub dense: Observation<'a>,
    pub aerial: &'a [f64],
    pub aerial_var: &'a [f64],
    /// Cells where the aerials' estimate is a fill (a lattice cell nobody saw): not evidence.
    pub filled: &'a [bool],
}

/// The two estimates of the field, with their variances per cell.
struct Evidence<'a> {
    aerial: &'a [f64],
    aerial_var: &'a [f64],
    filtered: Vec<f64>,
    filtered_var: Vec<f64>,
}

impl<'a> Evidence<'a> {
    fn of(f: &ModalFilter, src: &Sources<'a>) -> Self {
        let (filtered, filtered_var) = f.field();
        Self {
            aerial: src.aerial,
            aerial_var: src.aerial_var,
            filtered,
            filtered_var,
        }
    }
}

impl Between {
    /// The filter's update by one step's sources: the modes by the lattice and the boats, the
    /// detail by the dense frame, then the field between the lattice blended by the skill the
    /// boats have shown (learned first at a boat step, from the filter updated without them;
    /// where the aerials' estimate is a fill, the filter's own), then the detail by the boats.
    pub fn update(&mut self, f: &mut ModalFilter, src: &Sources<'_>, on_lattice: &[bool]) -> Result<(), FilterError> {
        if !src.boats.cells.is_empty() {
            // The boats' cells where the aerials' estimate is their interpolation (off the
            // lattice, not a fill), and the filter there updated without the boats.
            let (cells, vals): (Vec<usize>, Vec<f64>) = src
                .boats
                .cells
                .iter()
                .zip(src.boats.values)
                .filter(|(&c, _)| !on_lattice[c] && !src.filled[c])
                .unzip();
            let (filtered, _) = f.field_at_after(&[src.lattice], &[src.dense], &cells)?;
            self.learn(src.aerial, &cells, &vals, &filtered);
        }
        f.update(&[src.lattice, src.boats])?;
        f.update_detail(&[src.dense])?;
        let evidence = Evidence::of(f, src);
        // Where the aerials' estimate is a fill (a lattice cell nobody saw), the filter's own.
        let cells: Vec<usize> = src
            .dense
            .cells
            .iter()
            .copied()
            .filter(|&c| !on_lattice[c] && !src.filled[c])
            .collect();
        let (values, variance): (Vec<f64>, Vec<f64>) = cells.iter().map(|&c| self.estimate(c, &evidence)).unzip();
        f.assign(&Observation {
            cells: &cells,
            values: &values,
            variance: &variance,
        })?;
        f.update_detail(&[src.boats])
    }

    /// Learn from the boats' values `vals` at cells between the lattice where the aerials'
    /// estimate is their interpolation (off the lattice, not a fill), against the filter's
    /// estimate there without the boats (`filtered`); the regression's sums decay by [`MEMORY`]
    /// a boat step.
    fn learn(&mut self, aerial: &[f64], cells: &[usize], vals: &[f64], filtered: &[f64]) {
        let at: Vec<(f64, f64)> = cells
            .iter()
            .zip(vals)
            .zip(filtered)
            .map(|((&c, &v), &x)| (v - aerial[c], x - aerial[c]))
            .collect();
        if at.is_empty() {
            return;
        }
        self.cross = MEMORY * self.cross + at.iter().map(|(r, d)| r * d).sum::<f64>();
        self.square = MEMORY * self.square + at.iter().map(|(_, d)| d * d).sum::<f64>();
        if !(self.square > 0.0) {
            return;
        }
        // The slope shrunk by its standard error (`b^2 / (b^2 + se^2)`): a slope these cells
        // cannot tell from 0 counts for little.
        let slope = self.cross / self.square;
        let misfit = at.iter().map(|(r, d)| (r - slope * d).powi(2)).sum::<f64>() / at.len() as f64;
        let se2 = misfit / self.square;
        let spread = slope * slope + se2;
        self.skill = match spread > 0.0 {
            true => (slope * slope * slope / spread).clamp(0.0, 1.0),
            false => 0.0, // the boats found the aerials exact: nothing to weigh
        };
    }

    /// The estimate between the lattice and its variance at `c`.
    fn estimate(&self, c: usize, e: &Evidence<'_>) -> (f64, f64) {
        let k = self.skill;
        (
            e.aerial[c] + k * (e.filtered[c] - e.aerial[c]),
            k * e.filtered_var[c] + (1.0 - k) * e.aerial_var[c],
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn evidence<'a>(aerial: &'a [f64], filtered: Vec<f64>) -> Evidence<'a> {
        let n = aerial.len();
        Evidence {
            aerial,
            aerial_var: &[2.0; 64][..n],
            filtered,
            filtered_var: vec![1.0; n],
        }
    }

    /// Known answers: before any boat value the estimate is the aerials' own; boats that
    /// find the field where the filter says gives skill near 1 (the filter's estimate); boats
    /// that find the aerials right give 0 (theirs), whatever the filter's variance claims; a
    /// step without a boat value between the lattice (a boat on it: [`Between::update`] leaves
    /// those out) learns nothing.
    #[test]
    fn the_skill_is_what_the_boats_found() {
        let aerial: Vec<f64> = (0..64).map(|i| (i as f64 * 0.37).sin()).collect();
        let filtered: Vec<f64> = aerial
            .iter()
            .enumerate()
            .map(|(i, a)| a + (i as f64 * 1.3).cos())
            .collect();
        let cells: Vec<usize> = (0..64).collect();
        let mut b = Between::default();
        let e = evidence(&aerial, filtered.clone());
        assert_eq!(b.estimate(5, &e), (aerial[5], 2.0));
        b.learn(&aerial, &cells, &filtered, &filtered);
        assert!(b.skill > 0.999, "{}", b.skill);
        assert!((b.estimate(5, &e).0 - filtered[5]).abs() < 1e-2);
        let mut b = Between::default();
        for _ in 0..5 {
            b.learn(&aerial, &cells, &aerial, &filtered);
        }
        assert_eq!(b.skill, 0.0);
        assert_eq!(b.estimate(9, &e), (aerial[9], 2.0));
        let mut b = Between::default();
        b.learn(&aerial, &[], &[], &[]);
        assert_eq!(b, Between::default());
    }

    /// A step's boats on the lattice or on a fill are no evidence of the filter between the
    /// lattice ([`Between::update`] leaves them out): the skill stays where it was; the same
    /// boats off the lattice move it.
    #[test]
    fn boats_on_the_lattice_or_a_fill_teach_nothing() {
        let n = 16;
        let basis = faer::Mat::from_fn(n, 1, |_, _| 0.25); // one flat mode, orthonormal
        let filter = ModalFilter::new(
            basis,
            faer::Mat::identity(1, 1),
            vec![0.0],
            faer::Mat::identity(1, 1),
            0.01,
            0.1,
        )
        .unwrap();
        let aerial: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin()).collect();
        let aerial_var = vec![0.05; n];
        let dense: Vec<usize> = (0..n).collect();
        let on_lattice: Vec<bool> = (0..n).map(|c| c % 4 == 0).collect();
        let filled: Vec<bool> = (0..n).map(|c| c == 5).collect();
        let skill_after = |boats: &[usize]| {
            let values: Vec<f64> = boats.iter().map(|&c| aerial[c] + 0.8).collect();
            let noise = vec![0.01; boats.len()];
            let lattice: Vec<usize> = (0..n).filter(|&c| on_lattice[c]).collect();
            let (lat_y, lat_v): (Vec<f64>, Vec<f64>) = lattice.iter().map(|&c| (aerial[c], 0.05)).unzip();
            let src = Sources {
                lattice: Observation {
                    cells: &lattice,
                    values: &lat_y,
                    variance: &lat_v,
                },
                boats: Observation {
                    cells: boats,
                    values: &values,
                    variance: &noise,
                },
                dense: Observation {
                    cells: &dense,
                    values: &aerial,
                    variance: &aerial_var,
                },
                aerial: &aerial,
                aerial_var: &aerial_var,
                filled: &filled,
            };
            let mut b = Between::default();
            b.update(&mut filter.clone(), &src, &on_lattice).unwrap();
            b
        };
        assert_eq!(skill_after(&[0, 4, 5, 8]), Between::default());
        assert_ne!(skill_after(&[1, 2, 6, 9]), Between::default());
    }
}
