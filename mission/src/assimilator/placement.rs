//! The next epoch's places: boats' disks by the configured placement (one function per
//! strategy: block QR or D-optimal on the model's modes, random, or the filter's look ahead
//! over the horizon), boats assigned to disks by least total travel, and aerials by Lloyd's
//! coverage under a density (the model's temporal modes, or the forecast's variance).

use super::{aerial_detail_variance, Assimilator, AssimilatorState, Setup};
use crate::team::{Missing, Placement, TeamError};
use fleet_math::dmd::DmdModel;
use fleet_math::grid::{Cell, Grid};
use fleet_math::kalman::{self, Lookahead, ModalFilter};
use fleet_math::sensing::{assign::assign, coverage, horizon, qr};
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeSet;

/// A boat's disk: the cells it covers and its centre `(row, col)`.
pub type BoatDisk = (Vec<usize>, (usize, usize));

/// Where every vehicle should be for the next epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct Allocation {
    /// Per boat (in vehicle order): the disk's cells and centre, or `None` when there are more
    /// boats than disks.
    pub boats: Vec<Option<BoatDisk>>,
    /// Per aerial: its coverage position (metres).
    pub aerials: Vec<(f64, f64)>,
    /// Vehicles (by index: aerials, then boats) left out: on operator hold or without an
    /// autopilot. They sense nothing; the others share the work.
    pub held: BTreeSet<usize>,
    /// Aerials whose camera the health tests doubt (suspect or excluded: frames refused, or
    /// none sent): the others cover the site as if they were not there, and each keeps its own
    /// region, so its frames are still tested and a camera that reads true again is seen (where
    /// two aerials read a cell, each reading is weighed by its precision).
    pub doubted: BTreeSet<usize>,
}

impl Allocation {
    /// The lattice cells aerial `a` senses: those nearest it among the aerials that take part
    /// (not held), the doubted ones other than `a` set aside. `None` for a held aerial.
    pub fn aerial_region(&self, grid: &Grid, stride: usize, a: usize) -> Option<Vec<usize>> {
        let (ids, positions): (Vec<usize>, Vec<(f64, f64)>) = (0..self.aerials.len())
            .filter(|b| !self.held.contains(b) && (*b == a || !self.doubted.contains(b)))
            .map(|b| (b, self.aerials[b]))
            .unzip();
        let me = ids.iter().position(|&b| b == a)?;
        fleet_math::fusion::aerial_region(grid, stride, &positions, me).ok()
    }
}

/// `placement = "horizon"`: the filter at the boats' next sampling step, its look ahead over
/// the horizon, and its forecast's mean and variance there.
struct HorizonView {
    at_sampling: ModalFilter,
    ahead: Lookahead,
    mean: Vec<f64>,
    variance: Vec<f64>,
}

impl Assimilator {
    /// Next epoch's places: block QR (or the configured alternative) on the model's modes,
    /// boats assigned by least total travel, aerials by Lloyd under the temporal density.
    pub fn allocate(&mut self) -> Result<Allocation, TeamError> {
        self.allocate_without(&Default::default())
    }

    /// [`Self::allocate`] with some vehicles (indices: aerials, then boats) left out: the
    /// disks go to the other boats (as many disks as boats free), Lloyd places the other
    /// aerials, and the held keep their places.
    pub fn allocate_without(&mut self, held: &BTreeSet<usize>) -> Result<Allocation, TeamError> {
        let Some((model, _)) = self.state.fitted.clone() else {
            return Err(TeamError::NotReady(Missing::Model));
        };
        let cfg = self.setup.cfg.clone();
        let roster = crate::roster::Roster::of(&cfg);
        let excluded = self.state.screen.left_out();
        let free: Vec<usize> = (0..cfg.boats)
            .filter(|&b| !held.contains(&roster.boat_index(b)) && !excluded.contains(&roster.boat_index(b)))
            .collect();
        let view = self.horizon_view()?;
        // A doubted aerial keeps its place; Lloyd spreads the others over the whole site. Its
        // region is only as good as its frames: a silent one's was lost (+2,526% on the 500 hPa
        // height for a camera dark from mid-mission), an over-exposed one's refused frames too.
        let doubted: BTreeSet<usize> = (0..cfg.aerials)
            .filter(|&a| self.state.screen.verdict_unless_ok(a).is_some() && !held.contains(&a))
            .collect();
        let staying: BTreeSet<usize> = held.union(&doubted).copied().collect();
        let starts = self.state.aerial_positions.clone();
        let Assimilator { setup, state } = self;
        // The boats' disks and the aerials' places depend on the same model, not on each
        // other: made on the two cores at once (the aerials' Lloyd was a quarter of the
        // placement at 192 x 384).
        let (boats, aerials) = crate::side_by_side::beside(
            || {
                let _span = tracing::info_span!("boats placed").entered();
                match &view {
                    Some(v) => place_boats_over_the_horizon(setup, state, v, &free),
                    None => place_boats_on_modes(setup, state, &free),
                }
            },
            || {
                let _span = tracing::info_span!("aerials placed").entered();
                let density = setup.aerial_density(&model, view.as_ref().map(|v| v.variance.as_slice()))?;
                setup.place_aerials(&density, starts, &staying)
            },
        );
        let mut boats = boats?;
        self.state.aerial_positions = aerials?;
        // A boat whose sensor is excluded (or silent) counts for nothing in the placement (its
        // disk would be a hole in the map), and measures where it is: its values are still
        // tested, and it comes back when they read true again.
        for b in (0..cfg.boats)
            .filter(|&b| excluded.contains(&roster.boat_index(b)) && !held.contains(&roster.boat_index(b)))
        {
            let grid = &self.setup.grid;
            let (x, y) = self.state.boat_positions[b];
            let clamp = |v: f64, n: usize| ((v / grid.cell_m).max(0.0) as usize).min(n - 1);
            let here = Cell::new(clamp(y, grid.rows), clamp(x, grid.cols));
            let room = self.setup.room();
            let cells: Vec<usize> = room
                .wet(grid.disk(here, cfg.radius))
                .into_iter()
                .filter(|&c| !room.is_outside(c))
                .collect();
            boats[b] = (!cells.is_empty()).then_some((cells, (here.row, here.col)));
        }
        Ok(Allocation {
            boats,
            aerials: self.state.aerial_positions.clone(),
            held: held.clone(),
            doubted,
        })
    }

    /// The boats' noise variance, floored.
    fn boat_var(&self) -> f64 {
        (self.setup.cfg.boat_sigma * self.setup.cfg.boat_sigma).max(1e-12)
    }

    /// `placement = "horizon"`: the filter's forecast at the next sampling step, and its
    /// uncertainty there and over the horizon with the aerials observing as in their last
    /// frame (each lattice value with its noise, the estimate everywhere with the
    /// interpolation's error and the calibrated extra, as the filter's step weighs them).
    /// `None` for the other placements.
    fn horizon_view(&self) -> Result<Option<HorizonView>, TeamError> {
        let (cfg, s) = (&self.setup.cfg, &self.state);
        if cfg.placement != Placement::Horizon {
            return Ok(None);
        }
        let (Some((f, at)), Some(held)) = (&s.filter, &s.held_aerial) else {
            return Err(TeamError::NotReady(Missing::Model));
        };
        let to = (cfg.boat_period as u64).saturating_sub(*at).max(1) as usize;
        let variance: Vec<f64> = self
            .setup
            .lattice
            .iter()
            .map(|&c| held.variance[c].max(1e-12))
            .collect();
        let everywhere = aerial_detail_variance(
            &held.variance,
            &s.held_interpolation,
            s.aerial_extra.mean(),
            &self.setup.on_lattice,
        );
        let aerials = kalman::Scheduled {
            cells: &self.setup.lattice,
            variance: &variance,
            everywhere: &everywhere,
        };
        let at_sampling = f.ahead(to);
        let (mean, var) = at_sampling.field();
        let ahead = f.look_ahead(to, cfg.horizon_epochs * cfg.boat_period, &aerials, self.boat_var())?;
        Ok(Some(HorizonView {
            at_sampling,
            ahead,
            mean,
            variance: var,
        }))
    }
}

/// `placement = "horizon"`: the disks whose values remove the most of the forecast's
/// variance over the horizon, each within reach of a boat by the sampling step.
fn place_boats_over_the_horizon(
    setup: &Setup,
    s: &mut AssimilatorState,
    v: &HorizonView,
    free: &[usize],
) -> Result<Vec<Option<BoatDisk>>, TeamError> {
    let (cfg, grid) = (&setup.cfg, &setup.grid);
    let reach = setup.boat_speed * cfg.boat_period as f64;
    let fleet: Vec<horizon::Boat> = free
        .iter()
        .map(|&b| horizon::Boat {
            position: s.boat_positions[b],
            reach_m: reach,
        })
        .collect();
    // What the filter does not model at the sampling step: the forecast's features
    // displaced, of variance s2 |grad x|^2 per cell.
    let unmodelled: Vec<f64> = grid
        .squared_gradient(&v.mean)?
        .iter()
        .map(|g2| s.displacement * g2)
        .collect();
    let f = horizon::Forecast::of(v.at_sampling.basis(), &v.ahead).with_unmodelled(&unmodelled);
    let mut boats = vec![None; cfg.boats];
    let noise_var = (cfg.boat_sigma * cfg.boat_sigma).max(1e-12);
    for c in horizon::plan_within(grid, &f, &fleet, cfg.radius, noise_var, setup.room())? {
        let b = free[c.boat];
        s.boat_positions[b] = grid.centre_m(c.centre);
        boats[b] = Some((c.cells, (c.centre.row, c.centre.col)));
    }
    Ok(boats)
}

/// Disks on the model's modes (block QR, D-optimal) or at random, the free boats assigned
/// to them by least total travel.
fn place_boats_on_modes(
    setup: &Setup,
    s: &mut AssimilatorState,
    free: &[usize],
) -> Result<Vec<Option<BoatDisk>>, TeamError> {
    let (cfg, grid, room) = (&setup.cfg, &setup.grid, setup.room());
    let (_, basis) = s.fitted.as_ref().ok_or(TeamError::NotReady(Missing::Model))?;
    let disks: Vec<Vec<usize>> = match (free.len(), cfg.placement) {
        (0, _) => vec![],
        (k, Placement::Qr) => qr::block_qr_within(faer::Mat::as_ref(basis), grid, k, cfg.radius, room)?
            .into_iter()
            .map(|d| d.cells)
            .collect(),
        (k, Placement::DOptimal) => qr::block_dopt_within(faer::Mat::as_ref(basis), grid, k, cfg.radius, room)?
            .into_iter()
            .map(|d| d.cells)
            .collect(),
        (k, Placement::Random) => random_disks(grid, k, cfg.radius, room, &mut s.placement_rng),
        (_, Placement::Horizon) => return Err(TeamError::NotReady(Missing::Model)),
    };
    let centres: Vec<(usize, usize)> = disks.iter().map(|d| centre_of(grid, d, room)).collect();
    let targets: Vec<(f64, f64)> = centres.iter().map(|&(r, c)| grid.centre_m(Cell::new(r, c))).collect();
    let starts: Vec<(f64, f64)> = free.iter().map(|&b| s.boat_positions[b]).collect();
    let (assignment, _) = if free.is_empty() {
        (vec![], 0.0)
    } else {
        assign(&starts, &targets, 1.0)?
    };
    let mut boats = vec![None; cfg.boats];
    for (&b, a) in free.iter().zip(&assignment) {
        if let Some(t) = a {
            boats[b] = Some((disks[*t].clone(), centres[*t]));
            s.boat_positions[b] = targets[*t];
        }
    }
    Ok(boats)
}

impl Setup {
    /// Where the boats' disks may go: inside the fence, centred on water.
    fn room(&self) -> fleet_math::sensing::Room<'_> {
        fleet_math::sensing::Room {
            outside: &self.outside,
            dry: &self.dry,
        }
    }

    /// Where the aerials' coverage goes: the temporal density of `model`'s modes, or (with
    /// horizon placement) the forecast's variance, floored; nothing outside the fence.
    fn aerial_density(&self, model: &DmdModel, forecast_variance: Option<&[f64]>) -> Result<Vec<f64>, TeamError> {
        let floor = self.cfg.density_floor;
        let density = match forecast_variance {
            Some(var) => {
                let top = var.iter().cloned().fold(0.0, f64::max).max(1e-300);
                var.iter().map(|v| floor + (1.0 - floor) * v / top).collect()
            }
            None => coverage::temporal_density(model, floor)?,
        };
        let outside = |i: usize| self.excluded.get(i).copied().unwrap_or(false);
        Ok(density
            .iter()
            .enumerate()
            .map(|(i, &d)| if outside(i) { 0.0 } else { d })
            .collect())
    }

    /// The aerials' places from `positions`: Lloyd's iterations move those not `staying`.
    fn place_aerials(
        &self,
        density: &[f64],
        mut positions: Vec<(f64, f64)>,
        staying: &BTreeSet<usize>,
    ) -> Result<Vec<(f64, f64)>, TeamError> {
        let flying: Vec<usize> = (0..self.cfg.aerials).filter(|a| !staying.contains(a)).collect();
        if flying.is_empty() {
            return Ok(positions);
        }
        let starts: Vec<(f64, f64)> = flying.iter().map(|&a| positions[a]).collect();
        let placed = coverage::lloyd(&self.grid, density, &starts, 50, 1e-3)?.positions;
        let placed = coverage::snap_inside(&self.grid, &self.excluded, &placed)
            .ok_or_else(|| TeamError::Config("the site's boundary leaves no cell of the grid inside it".into()))?;
        for (&a, p) in flying.iter().zip(placed) {
            positions[a] = p;
        }
        Ok(positions)
    }
}

/// A disk's centre, the boat's target: the mean of its cells' rows and columns, rounded; where
/// that is dry (a disk wrapped round a headland), the disk's cell nearest it.
fn centre_of(grid: &Grid, disk: &[usize], room: fleet_math::sensing::Room<'_>) -> (usize, usize) {
    let (r, c) = disk.iter().fold((0.0, 0.0), |(r, c), &i| {
        (r + grid.cell(i).row as f64, c + grid.cell(i).col as f64)
    });
    let (r, c) = (r / disk.len() as f64, c / disk.len() as f64);
    let mean = ((r.round() as usize), (c.round() as usize));
    if !room.is_dry(grid.index(Cell::new(mean.0, mean.1))) {
        return mean;
    }
    let away = |i: &usize| (grid.cell(*i).row as f64 - r).hypot(grid.cell(*i).col as f64 - c);
    disk.iter()
        .min_by(|a, b| away(a).total_cmp(&away(b)).then(a.cmp(b)))
        .map_or(mean, |&i| (grid.cell(i).row, grid.cell(i).col))
}

/// `m` random non-overlapping disks in `room` (rejection sampling; fewer if the grid is full).
fn random_disks(
    grid: &Grid,
    m: usize,
    radius: f64,
    room: fleet_math::sensing::Room<'_>,
    rng: &mut ChaCha8Rng,
) -> Vec<Vec<usize>> {
    let mut taken: Vec<bool> = (0..grid.len()).map(|i| room.is_outside(i)).collect();
    let mut out = vec![];
    // Open water first, then (where that left boats without a disk) disks reaching the coast.
    let coastal_pass = if room.has_land() { m * 200 } else { 0 };
    for draw in 0..m * 200 + coastal_pass {
        if out.len() == m {
            break;
        }
        let c = Cell::new(rng.random_range(0..grid.rows), rng.random_range(0..grid.cols));
        let whole = grid.disk(c, radius);
        let coast = draw >= m * 200;
        if room.is_dry(grid.index(c)) || (!coast && whole.iter().any(|&i| room.is_dry(i))) {
            continue;
        }
        let d = room.wet(whole);
        if d.iter().all(|&i| !taken[i]) {
            d.iter().for_each(|&i| taken[i] = true);
            out.push(d);
        }
    }
    out
}
