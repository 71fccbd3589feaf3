//! Placement over the horizon (`placement = "horizon"`): the boats' disks chosen by how much
//! of the field's uncertainty they remove over the next `H` epochs, only where each boat can
//! be by its sampling step, disks and boats chosen together.
//!
//! The filter's look ahead ([`crate::kalman::Lookahead`]) gives, at the next sampling step with
//! the aerials' frames until then, the modal covariance `P` (q x q, over an orthonormal basis
//! `B`) and a detail variance `v_i` per cell, and what a value there is worth over the horizon
//! with the aerials still observing: `tr(dP M)` for a reduction `dP` of the modal covariance,
//! and a detail gain per cell. Measuring a disk `D` with noise `b` takes the modal covariance
//! to `P (I + J P)^-1`, `J = sum_{i in D} h_i h_i^T / (v_i + b)` (the detail marginalised), and
//! removes the detail gain of its cells: the objective is the expected reduction of the field's
//! variance summed over the horizon's steps.
//!
//! Greedy on that objective, one disk at a time, each conditioned on the disks already chosen,
//! among disks that do not overlap them and keep a boat for every chosen disk within reach (a
//! matching, checked at each pick); the final boat-to-disk matching is the one of least total
//! travel among those within reach.

use super::SensingError;
use crate::grid::{Cell, Grid};
use crate::kalman::Lookahead;
use faer::{Mat, MatRef};
use pathfinding::matrix::Matrix;

/// The uncertainty at the next sampling step, and what a value then is worth over the horizon
/// (the filter's [`crate::kalman::Lookahead`]).
pub struct Forecast<'a> {
    pub basis: MatRef<'a, f64>,
    /// The modal covariance and detail variance at the sampling step, and what a value then
    /// removes over the horizon.
    pub ahead: &'a Lookahead,
    /// Per cell: the variance of the error the filter does not model at the sampling step
    /// (a displacement of the field's features: [`crate::kalman::displacement_variance`]);
    /// empty: none.
    pub unmodelled: &'a [f64],
}

impl<'a> Forecast<'a> {
    /// What the planner reads of a filter's look ahead, over the filter's basis.
    pub fn of(basis: MatRef<'a, f64>, ahead: &'a Lookahead) -> Self {
        Self {
            basis,
            ahead,
            unmodelled: &[],
        }
    }

    /// The same with an error the filter does not model, of variance `unmodelled` per cell.
    pub fn with_unmodelled(self, unmodelled: &'a [f64]) -> Self {
        Self { unmodelled, ..self }
    }

    /// What a value at cell `i` removes of the unmodelled error at the sampling step: an error
    /// `u` the filter corrects with weight `k` leaves `(1 - k) u`, so `(2k - k^2) u` of its
    /// variance goes (the value's own noise is already in the detail gain).
    fn unmodelled_gain(&self, i: usize) -> f64 {
        self.unmodelled.get(i).map_or(0.0, |u| {
            let k = self.ahead.value_weight[i];
            (2.0 * k - k * k) * u
        })
    }
}

/// A boat: where it is (metres) and how far it can go before the sampling step.
#[derive(Debug, Clone, Copy)]
pub struct Boat {
    pub position: (f64, f64),
    pub reach_m: f64,
}

/// A chosen disk: its cells, centre, and the boat that goes there.
#[derive(Debug, Clone, PartialEq)]
pub struct Chosen {
    pub cells: Vec<usize>,
    pub centre: Cell,
    pub boat: usize,
}

struct Candidate {
    cells: Vec<usize>,
    centre: Cell,
    at: (f64, f64),
    info: Mat<f64>,
    detail_gain: f64,
    /// Whether the disk reaches land (its cells are then the wet ones): such a disk is a
    /// candidate only once no disk in open water is left ([`super::Room`]).
    coastal: bool,
}

/// The disks and their boats (at most one disk per boat; fewer when no admissible disk is
/// left), `noise_var` the boats' noise variance, `radius` the disks' in cells.
pub fn plan(
    grid: &Grid,
    f: &Forecast<'_>,
    boats: &[Boat],
    radius: f64,
    noise_var: f64,
) -> Result<Vec<Chosen>, SensingError> {
    plan_within(grid, f, boats, radius, noise_var, super::Room::OPEN)
}

/// [`plan`] in the `room` the site leaves: no disk beyond its fence, none centred on land, each
/// disk its wet cells.
///
/// Long because the greedy choice, its conditioning and the reach check share one candidate state
/// that each pick updates; apart, that state would travel between functions.
pub fn plan_within(
    grid: &Grid,
    f: &Forecast<'_>,
    boats: &[Boat],
    radius: f64,
    noise_var: f64,
    room: super::Room<'_>,
) -> Result<Vec<Chosen>, SensingError> {
    let (n, q) = (f.basis.nrows(), f.basis.ncols());
    grid.check_len(n).map_err(|e| SensingError::Input(e.to_string()))?;
    if f.ahead.modal_weight.nrows() != q
        || f.ahead.modal_weight.ncols() != q
        || f.ahead.cov.nrows() != q
        || f.ahead.cov.ncols() != q
        || f.ahead.detail_var.len() != n
        || f.ahead.detail_gain.len() != n
        || f.ahead.value_weight.len() != n
    {
        return Err(SensingError::Input(format!(
            "a forecast over {q} modes on {n} cells needs {q} x {q} weights and \
            covariance and {n} detail variances, gains and value weights"
        )));
    }
    if !(f.unmodelled.is_empty() || f.unmodelled.len() == n) {
        return Err(SensingError::Input(format!(
            "{} unmodelled variances on {n} cells",
            f.unmodelled.len()
        )));
    }
    if f.ahead.value_weight.iter().any(|k| !(0.0..=1.0).contains(k)) {
        return Err(SensingError::Input("value weights must be in [0, 1]".into()));
    }
    if !(noise_var > 0.0 && noise_var.is_finite() && radius >= 0.0 && radius.is_finite()) {
        return Err(SensingError::Input(format!(
            "noise variance {noise_var} and radius {radius} must be positive and finite"
        )));
    }
    if let Some(b) = boats
        .iter()
        .find(|b| !(b.position.0.is_finite() && b.position.1.is_finite() && b.reach_m >= 0.0))
    {
        return Err(SensingError::Input(format!(
            "boat at {:?} with reach {}",
            b.position, b.reach_m
        )));
    }
    if f.ahead
        .detail_var
        .iter()
        .chain(&f.ahead.detail_gain)
        .chain(f.unmodelled)
        .any(|v| !(v.is_finite() && *v >= 0.0))
    {
        return Err(SensingError::Input(
            "detail and unmodelled variances and gains must be finite and >= 0".into(),
        ));
    }
    let m = f.ahead.modal_weight.clone();
    // Candidate centres every half radius (every cell for small disks).
    let every = ((radius / 2.0).floor() as usize).max(1);
    let mut candidates = vec![];
    for r in (0..grid.rows).step_by(every) {
        for c in (0..grid.cols).step_by(every) {
            let centre = Cell::new(r, c);
            if room.is_dry(grid.index(centre)) {
                continue;
            }
            let whole = grid.disk(centre, radius);
            let coastal = whole.iter().any(|&i| room.is_dry(i));
            let cells = room.wet(whole);
            let mut info = Mat::<f64>::zeros(q, q);
            let mut detail_gain = 0.0;
            for &i in &cells {
                let w = 1.0 / (f.ahead.detail_var[i] + noise_var);
                let h = f.basis.row(i);
                for a in 0..q {
                    for b in 0..q {
                        info[(a, b)] += h[a] * h[b] * w;
                    }
                }
                detail_gain += f.ahead.detail_gain[i] + f.unmodelled_gain(i);
            }
            candidates.push(Candidate {
                at: grid.centre_m(centre),
                cells,
                centre,
                info,
                detail_gain,
                coastal,
            });
        }
    }
    let mut cov = f.ahead.cov.clone();
    let mut taken: Vec<bool> = super::qr::blocked(grid, room)?.iter().map(|&b| b > 0.0).collect();
    let mut chosen: Vec<usize> = vec![];
    let mut coast = false;
    let reachable = |b: &Boat, at: (f64, f64)| (b.position.0 - at.0).hypot(b.position.1 - at.1) <= b.reach_m;
    while chosen.len() < boats.len() {
        let mut best: Option<(f64, usize, Mat<f64>)> = None;
        for (ci, cand) in candidates.iter().enumerate() {
            if cand.cells.is_empty()
                || (cand.coastal && !coast)
                || cand.cells.iter().any(|&i| taken[i])
                || !boats.iter().any(|b| reachable(b, cand.at))
            {
                continue;
            }
            let post = conditioned(cov.as_ref(), cand.info.as_ref())?;
            let gain = trace_product(&(cov.as_ref() - post.as_ref()), &m) + cand.detail_gain;
            if best.as_ref().is_none_or(|(g, _, _)| gain > *g) {
                let mut with = chosen.clone();
                with.push(ci);
                if matching(&with, &candidates, boats, reachable)?.is_some() {
                    best = Some((gain, ci, post));
                }
            }
        }
        let Some((_, ci, post)) = best else {
            if coast || !candidates.iter().any(|c| c.coastal) {
                break;
            }
            coast = true; // no disk in open water left: the rest reach the coast
            continue;
        };
        cov = post;
        candidates[ci].cells.iter().for_each(|&i| taken[i] = true);
        chosen.push(ci);
    }
    let Some(assignment) = matching(&chosen, &candidates, boats, reachable)? else {
        return Ok(vec![]);
    };
    Ok(chosen
        .iter()
        .zip(assignment)
        .map(|(&ci, boat)| Chosen {
            cells: candidates[ci].cells.clone(),
            centre: candidates[ci].centre,
            boat,
        })
        .collect())
}

/// `P (I + J P)^-1`.
fn conditioned(p: MatRef<'_, f64>, j: MatRef<'_, f64>) -> Result<Mat<f64>, SensingError> {
    let q = p.nrows();
    let mut a = p * j;
    for i in 0..q {
        a[(i, i)] += 1.0;
    }
    let post = faer::linalg::solvers::Solve::solve(&a.partial_piv_lu(), p);
    if post.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
        return Err(SensingError::Numerical(
            "conditioning the forecast covariance lost finiteness".into(),
        ));
    }
    Ok(post)
}

fn trace_product(a: &Mat<f64>, b: &Mat<f64>) -> f64 {
    (0..a.nrows())
        .map(|i| (0..a.ncols()).map(|k| a[(i, k)] * b[(k, i)]).sum::<f64>())
        .sum()
}

/// For the disks `chosen` (indices into `candidates`), the boat of each in a matching of least
/// total travel with every boat within reach of its disk (`None`: no such matching).
fn matching(
    chosen: &[usize],
    candidates: &[Candidate],
    boats: &[Boat],
    reachable: impl Fn(&Boat, (f64, f64)) -> bool,
) -> Result<Option<Vec<usize>>, SensingError> {
    if chosen.is_empty() {
        return Ok(Some(vec![]));
    }
    if chosen.len() > boats.len() {
        return Ok(None);
    }
    // Travel in millimetres; out of reach costs more than every reachable leg together.
    let far = 1i64 << 50;
    let weights = Matrix::from_rows(chosen.iter().map(|&ci| {
        let at = candidates[ci].at;
        boats
            .iter()
            .map(|b| {
                if reachable(b, at) {
                    ((b.position.0 - at.0).hypot(b.position.1 - at.1) * 1e3).round() as i64
                } else {
                    far
                }
            })
            .collect::<Vec<_>>()
    }))
    .map_err(|e| SensingError::Numerical(format!("{e:?}")))?;
    let (total, row_to_col) = pathfinding::kuhn_munkres::kuhn_munkres_min(&weights);
    Ok((total < far).then_some(row_to_col))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One mode that lives on the left half of a 10 x 20 grid: every disk on the right half
    /// removes nothing of the modal uncertainty.
    fn left_mode(grid: &Grid) -> Mat<f64> {
        let raw: Vec<f64> = (0..grid.len())
            .map(|i| if grid.cell(i).col < 10 { 1.0 } else { 0.0 })
            .collect();
        let norm = raw.iter().map(|v| v * v).sum::<f64>().sqrt();
        Mat::from_fn(grid.len(), 1, |i, _| raw[i] / norm)
    }

    /// Land on every other column (a comb of piers: every disk reaches land, no open water is
    /// left). The disk still goes where the mode is, centred on water, holding only the wet
    /// cells; before disks could reach land, the boat got none.
    #[test]
    fn a_disk_goes_where_the_uncertainty_is_even_when_every_disk_reaches_land() {
        let grid = Grid::new(10, 20, 1.0).unwrap();
        let dry: Vec<bool> = (0..grid.len()).map(|i| grid.cell(i).col % 2 == 1).collect();
        let b = left_mode(&grid);
        let b = Mat::from_fn(grid.len(), 1, |i, j| if dry[i] { 0.0 } else { b[(i, j)] });
        let ahead = Lookahead {
            cov: Mat::from_fn(1, 1, |_, _| 1.0),
            detail_var: vec![1e-6; grid.len()],
            modal_weight: Mat::from_fn(1, 1, |_, _| 2.0),
            detail_gain: vec![0.0; grid.len()],
            value_weight: vec![0.5; grid.len()],
        };
        let f = Forecast::of(b.as_ref(), &ahead);
        let boats = [Boat {
            position: (19.5, 5.5),
            reach_m: 100.0,
        }];
        let room = super::super::Room {
            outside: &[],
            dry: &dry,
        };
        let got = plan_within(&grid, &f, &boats, 2.0, 1e-4, room).unwrap();
        assert_eq!(got.len(), 1);
        assert!(
            got[0].centre.col < 10,
            "the disk goes where the mode is: {:?}",
            got[0].centre
        );
        assert!(!dry[grid.index(got[0].centre)], "centred on land: {:?}", got[0].centre);
        assert!(got[0].cells.iter().all(|&c| !dry[c]));
    }

    #[test]
    fn disks_go_where_the_uncertainty_is_and_each_boat_within_reach() {
        let grid = Grid::new(10, 20, 1.0).unwrap();
        let b = left_mode(&grid);
        let m = Mat::from_fn(1, 1, |_, _| 2.0);
        let p = Mat::from_fn(1, 1, |_, _| 1.0);
        let (dv, gain) = (vec![1e-6; grid.len()], vec![0.0; grid.len()]);
        let weight = vec![0.5; grid.len()];
        let ahead = Lookahead {
            cov: p.clone(),
            detail_var: dv.clone(),
            modal_weight: m.clone(),
            detail_gain: gain.clone(),
            value_weight: weight.clone(),
        };
        let f = Forecast::of(b.as_ref(), &ahead);
        let boats = [Boat {
            position: (19.5, 5.5),
            reach_m: 100.0,
        }];
        let got = plan(&grid, &f, &boats, 2.0, 1e-4).unwrap();
        assert_eq!(got.len(), 1);
        assert!(
            got[0].centre.col < 10,
            "the disk goes where the mode is: {:?}",
            got[0].centre
        );
        // Out of reach of the left half, the boat still gets the best place it can reach
        // (nothing to gain there, but a place), never one it cannot.
        let slow = [Boat {
            position: (19.5, 5.5),
            reach_m: 3.0,
        }];
        let got = plan(&grid, &f, &slow, 2.0, 1e-4).unwrap();
        for c in &got {
            let (x, y) = grid.centre_m(c.centre);
            assert!((x - 19.5).hypot(y - 5.5) <= 3.0, "disk at {:?} out of reach", c.centre);
        }
    }

    #[test]
    fn the_greedy_gain_counts_what_earlier_disks_removed() {
        // A persistent detail, equal everywhere: two boats pick two disjoint disks, and the
        // second disk is a different place (the first one's detail is known now).
        let grid = Grid::new(10, 20, 1.0).unwrap();
        let b = left_mode(&grid);
        let m = Mat::from_fn(1, 1, |_, _| 1.8);
        let p = Mat::from_fn(1, 1, |_, _| 1e-9);
        let dv = vec![1.0; grid.len()];
        let weight = vec![0.5; grid.len()];
        let ahead = Lookahead {
            cov: p.clone(),
            detail_var: dv.clone(),
            modal_weight: m.clone(),
            detail_gain: dv.clone(),
            value_weight: weight.clone(),
        };
        let f = Forecast::of(b.as_ref(), &ahead);
        let boats = [
            Boat {
                position: (0.0, 0.0),
                reach_m: 1e9,
            },
            Boat {
                position: (20.0, 10.0),
                reach_m: 1e9,
            },
        ];
        let got = plan(&grid, &f, &boats, 2.0, 1e-2).unwrap();
        assert_eq!(got.len(), 2);
        assert!(got[0].cells.iter().all(|c| !got[1].cells.contains(c)), "disks overlap");
        assert_ne!(got[0].boat, got[1].boat);
    }

    #[test]
    fn with_the_modes_known_a_disk_goes_where_the_aerials_leave_most_unseen() {
        // The same detail variance everywhere at the sampling step, but the look ahead says a
        // value in a band of columns is worth more over the horizon (what the aerials cannot
        // see there): the disk lands in that band.
        let grid = Grid::new(10, 20, 1.0).unwrap();
        let b = left_mode(&grid);
        let (m, p) = (Mat::from_fn(1, 1, |_, _| 1.0), Mat::from_fn(1, 1, |_, _| 1e-12));
        let dv = vec![0.1; grid.len()];
        let weight = vec![0.5; grid.len()];
        let gain: Vec<f64> = (0..grid.len())
            .map(|i| {
                if (14..17).contains(&grid.cell(i).col) {
                    0.3
                } else {
                    0.05
                }
            })
            .collect();
        let ahead = Lookahead {
            cov: p.clone(),
            detail_var: dv.clone(),
            modal_weight: m.clone(),
            detail_gain: gain.clone(),
            value_weight: weight.clone(),
        };
        let f = Forecast::of(b.as_ref(), &ahead);
        let got = plan(
            &grid,
            &f,
            &[Boat {
                position: (0.0, 0.0),
                reach_m: 1e9,
            }],
            1.0,
            1e-2,
        )
        .unwrap();
        assert!(
            (14..17).contains(&got[0].centre.col),
            "the disk is at {:?}",
            got[0].centre
        );
    }

    #[test]
    fn a_disk_goes_to_the_front_the_filter_does_not_model() {
        // The filter's own numbers are the same everywhere; an error it does not model (a
        // displacement, steep cells) lies along one column band: the disk lands there, and
        // counts `(2k - k^2) u` of it (with k = 1, all of it; with k = 0, none: the filter
        // would not take the value, so nothing to gain and the placement falls back).
        let grid = Grid::new(10, 20, 1.0).unwrap();
        let b = left_mode(&grid);
        let (m, p) = (Mat::from_fn(1, 1, |_, _| 1.0), Mat::from_fn(1, 1, |_, _| 1e-12));
        let (dv, gain) = (vec![0.1; grid.len()], vec![0.05; grid.len()]);
        let front: Vec<f64> = (0..grid.len())
            .map(|i| if (3..6).contains(&grid.cell(i).col) { 0.4 } else { 0.0 })
            .collect();
        let weight = vec![0.5; grid.len()];
        let ahead = Lookahead {
            cov: p.clone(),
            detail_var: dv.clone(),
            modal_weight: m.clone(),
            detail_gain: gain.clone(),
            value_weight: weight.clone(),
        };
        let f = Forecast::of(b.as_ref(), &ahead).with_unmodelled(&front);
        let got = plan(
            &grid,
            &f,
            &[Boat {
                position: (19.0, 9.0),
                reach_m: 1e9,
            }],
            1.0,
            1e-2,
        )
        .unwrap();
        assert!(
            (3..6).contains(&got[0].centre.col),
            "the disk is at {:?}",
            got[0].centre
        );
        let at = grid.index(Cell::new(5, 4));
        assert!((f.unmodelled_gain(at) - 0.75 * 0.4).abs() < 1e-15);
        let deaf = vec![0.0; grid.len()];
        assert_eq!(
            Forecast::of(
                f.basis,
                &Lookahead {
                    value_weight: deaf,
                    ..ahead.clone()
                }
            )
            .with_unmodelled(&front)
            .unmodelled_gain(at),
            0.0
        );
        assert!(
            plan(&grid, &f.with_unmodelled(&front[1..]), &[], 1.0, 1e-2).is_err(),
            "one unmodelled variance per cell"
        );
    }

    #[test]
    fn bad_input_is_refused() {
        let grid = Grid::new(4, 4, 1.0).unwrap();
        let b = Mat::<f64>::zeros(16, 1);
        let a = Mat::<f64>::identity(1, 1);
        let dv = vec![f64::NAN; 16];
        let ahead = Lookahead {
            cov: a.clone(),
            detail_var: dv.clone(),
            modal_weight: a.clone(),
            detail_gain: dv.clone(),
            value_weight: [0.5; 16].to_vec(),
        };
        let f = Forecast::of(b.as_ref(), &ahead);
        assert!(plan(&grid, &f, &[], 1.0, 1e-4).is_err());
    }
}
