//! An epoch's readings, as the vehicle keeps them until it sends the batch: per step and cell,
//! the inverse-variance mean of what fell there (a sonde at 1 Hz gives many readings per cell;
//! independent noise averages down), so what is held is bounded by the open steps times the
//! cells, whatever the rate. And the tally of what came in and what was refused.

use super::placer::Placed;
use super::reading::Refusal;
use crate::protocol::Sample;
use std::collections::BTreeMap;
use std::ops::Range;

/// How often one kind of refusal is said in the log (each is counted every time).
pub const SAY_EVERY_S: f64 = 10.0;

#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Mean {
    /// Sum of weights (1 / sigma^2) and of weighted values.
    w: f64,
    wv: f64,
    /// Sum of positions (grid metres) and their count.
    x: f64,
    y: f64,
    n: u64,
}

/// Readings kept by step and cell.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Collected {
    steps: BTreeMap<u64, BTreeMap<usize, Mean>>,
}

impl Collected {
    /// Keep a placed reading; `sigma` is the mission's noise for the vehicle's kind, used when
    /// the reading does not say its own.
    pub fn add(&mut self, p: &Placed, sigma: f64) {
        let s = p.sigma.unwrap_or(sigma).max(1e-12);
        let w = 1.0 / (s * s);
        let m = self.steps.entry(p.step).or_default().entry(p.cell).or_default();
        m.w += w;
        m.wv += w * p.value;
        m.x += p.position.0;
        m.y += p.position.1;
        m.n += 1;
    }

    /// A frame of `step` on `grid` (a value per cell, `None` where it has none): each value a
    /// reading at its cell's centre with the noise `sigma`.
    pub fn add_frame(&mut self, step: u64, grid: &fleet_math::grid::Grid, values: &[Option<f64>], sigma: f64) {
        for (cell, v) in values.iter().enumerate().filter_map(|(c, v)| Some((c, (*v)?))) {
            let p = Placed {
                step,
                cell,
                position: grid.centre_m(grid.cell(cell)),
                value: v,
                sigma: None,
            };
            self.add(&p, sigma);
        }
    }

    /// The samples of `steps` (one per step with readings: its cells in order, each value the
    /// mean of the readings there with its own standard deviation), forgetting everything
    /// before `steps.end`.
    pub fn take(&mut self, steps: Range<u64>) -> Vec<Sample> {
        let later = self.steps.split_off(&steps.end);
        let taken = std::mem::replace(&mut self.steps, later);
        taken
            .into_iter()
            .filter(|(k, _)| steps.contains(k))
            .map(|(step, cells)| {
                let n: u64 = cells.values().map(|m| m.n).sum();
                let (x, y) = cells.values().fold((0.0, 0.0), |(x, y), m| (x + m.x, y + m.y));
                Sample {
                    step,
                    position: [x / n as f64, y / n as f64],
                    cells: cells.keys().map(|&c| c as u32).collect(),
                    values: cells.values().map(|m| m.wv / m.w).collect(),
                    sigma: Some(cells.values().map(|m| m.w.recip().sqrt()).collect()),
                }
            })
            .collect()
    }

    /// Readings held (cells with a value, over the open steps).
    pub fn len(&self) -> usize {
        self.steps.values().map(BTreeMap::len).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.steps.is_empty()
    }
}

/// What a vehicle's sensor source delivered: readings received, accepted and refused by kind.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Tally {
    pub received: u64,
    pub accepted: u64,
    /// Accepted frames with no value at any cell.
    pub empty_frames: u64,
    refused: BTreeMap<Refusal, u64>,
    said: BTreeMap<Refusal, f64>,
}

impl Tally {
    pub fn accept(&mut self) {
        self.received += 1;
        self.accepted += 1;
    }

    /// Count a refusal at `now` (seconds); whether a log line is due for its kind (the first,
    /// then at most one every [`SAY_EVERY_S`]).
    pub fn refuse(&mut self, kind: Refusal, now: f64) -> bool {
        self.received += 1;
        *self.refused.entry(kind).or_default() += 1;
        let due = self.said.get(&kind).is_none_or(|&t| now - t >= SAY_EVERY_S);
        if due {
            self.said.insert(kind, now);
        }
        due
    }

    pub fn refused(&self, kind: Refusal) -> u64 {
        self.refused.get(&kind).copied().unwrap_or(0)
    }

    /// Refusals by kind name, for telemetry and status.
    pub fn refusals(&self) -> BTreeMap<String, u64> {
        self.refused.iter().map(|(k, &n)| (k.to_string(), n)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn placed(step: u64, cell: usize, value: f64, sigma: Option<f64>) -> Placed {
        Placed {
            step,
            cell,
            position: (cell as f64, 0.0),
            value,
            sigma,
        }
    }

    #[test]
    fn readings_in_one_cell_average_by_their_noise() {
        let mut c = Collected::default();
        // 1.0 with sigma 1 and 4.0 with sigma 2: weights 1 and 1/4, mean (1 + 1) / 1.25 = 1.6,
        // sigma 1 / sqrt(1.25).
        c.add(&placed(3, 7, 1.0, Some(1.0)), 9.0);
        c.add(&placed(3, 7, 4.0, Some(2.0)), 9.0);
        c.add(&placed(3, 2, 5.0, None), 0.5);
        c.add(&placed(4, 2, 6.0, None), 0.5);
        c.add(&placed(9, 2, 7.0, None), 0.5);
        assert_eq!(c.len(), 4);
        let s = c.take(3..5);
        assert_eq!(s.len(), 2);
        assert_eq!((s[0].step, s[0].cells.clone()), (3, vec![2, 7]));
        assert!((s[0].values[1] - 1.6).abs() < 1e-12);
        let sd = s[0].sigma.as_ref().unwrap();
        assert!((sd[1] - 1.25f64.recip().sqrt()).abs() < 1e-12 && sd[0] == 0.5);
        assert_eq!((s[1].step, s[1].values.clone()), (4, vec![6.0]));
        // Taken steps are gone; later ones stay.
        assert_eq!(c.len(), 1);
        assert!(c.take(0..5).is_empty());
        assert_eq!(c.take(0..10)[0].values, vec![7.0]);
        assert!(c.is_empty());
    }

    #[test]
    fn each_kind_is_counted_every_time_and_said_once_in_a_while() {
        let mut t = Tally::default();
        assert!(t.refuse(Refusal::Malformed, 0.0));
        assert!(!t.refuse(Refusal::Malformed, 5.0));
        assert!(t.refuse(Refusal::TooOld, 5.0));
        assert!(t.refuse(Refusal::Malformed, 10.0));
        t.accept();
        assert_eq!((t.received, t.accepted, t.refused(Refusal::Malformed)), (5, 1, 3));
        assert_eq!(t.refusals()["too_old"], 1);
    }
}
