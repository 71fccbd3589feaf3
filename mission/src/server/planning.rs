//! The allocations: the plan each epoch was sensed under (made by the placement after the
//! epoch before), the vehicles held out of it, and each vehicle's plan from them.

use super::{ServerCore, VehicleSpec};
use crate::assimilator::Allocation;
use crate::protocol::{Plan, Target, VehicleId, VehicleKind};
use crate::team::TeamError;
use std::collections::{BTreeMap, BTreeSet};

/// The plans handed out and the vehicles held.
#[derive(Clone, Default)]
pub(super) struct Planning {
    /// The plan each epoch was sensed under (to check boats measured their disks).
    pub(super) plans: BTreeMap<u64, Allocation>,
    /// Vehicles (by index) the operator holds or whose autopilot is lost, as telemetry says.
    pub(super) held: BTreeSet<usize>,
    /// The held set each epoch's allocation was made with (a re-fit makes the same plans).
    pub(super) holds: BTreeMap<u64, BTreeSet<usize>>,
}

impl ServerCore {
    /// Whether the planner may allocate a vehicle (from its telemetry); takes effect at the next
    /// allocation. Returns whether it changed.
    pub fn set_available(&mut self, vehicle: &VehicleId, available: bool) -> bool {
        let Some(index) = self.vehicles.index_of(vehicle) else {
            return false;
        };
        if available {
            self.planning.held.remove(&index)
        } else {
            self.planning.held.insert(index)
        }
    }

    /// Vehicles left out of the next allocation.
    pub fn held(&self) -> Vec<VehicleId> {
        self.planning
            .held
            .iter()
            .map(|&i| self.vehicles.at(i).id.clone())
            .collect()
    }

    /// Vehicles left out of epoch `e`'s allocation.
    pub fn held_at(&self, e: u64) -> Vec<VehicleId> {
        self.planning.holds.get(&e).map_or_else(Vec::new, |h| {
            h.iter().map(|&i| self.vehicles.at(i).id.clone()).collect()
        })
    }

    /// The allocation vehicles sense epoch `e` under (`None` before it is computed). Epoch 0
    /// is the uniform formation.
    pub fn allocation(&self, e: u64) -> Option<Allocation> {
        if e == 0 {
            return Some(Allocation {
                boats: vec![None; self.cfg.boats],
                aerials: self.assim.aerial_positions().to_vec(),
                held: BTreeSet::new(),
                doubted: BTreeSet::new(),
            });
        }
        self.planning.plans.get(&e).cloned()
    }

    /// Send the boats somewhere else in epoch `e` (planned, not yet assimilated): `boats[slot]`
    /// is a disk's cells and centre `(row, col)`, or `None` for a boat that stays and senses
    /// nothing. The vehicles' plans for `e` follow. For offline experiments that place the
    /// boats themselves (the oracle of `fleet experiment`): a re-fit from an earlier epoch
    /// (a late batch) re-plans `e` and forgets this.
    pub fn redirect_boats(
        &mut self,
        e: u64,
        boats: Vec<Option<crate::assimilator::BoatDisk>>,
    ) -> Result<(), TeamError> {
        let grid = *self.assim.grid();
        if boats.len() != self.cfg.boats {
            return Err(TeamError::Config(format!(
                "redirect_boats: {} disks for {} boats",
                boats.len(),
                self.cfg.boats
            )));
        }
        if let Some((_, (r, c))) = boats.iter().flatten().find(|(cells, (r, c))| {
            cells.iter().any(|&i| i >= grid.len()) || !grid.contains(fleet_math::grid::Cell::new(*r, *c))
        }) {
            return Err(TeamError::Config(format!(
                "redirect_boats: the disk at ({r}, {c}) leaves the {} x {} grid",
                grid.rows, grid.cols
            )));
        }
        if e < self.epoch || e == 0 {
            return Err(TeamError::Config(format!(
                "redirect_boats: epoch {e} is not planned and open (next to assimilate: {})",
                self.epoch
            )));
        }
        let plan = self
            .planning
            .plans
            .get_mut(&e)
            .ok_or_else(|| TeamError::Config(format!("redirect_boats: epoch {e} has no plan yet")))?;
        for (slot, b) in boats.iter().enumerate() {
            if let Some((_, (r, c))) = b {
                self.assim
                    .set_boat_position(slot, grid.centre_m(fleet_math::grid::Cell::new(*r, *c)));
            }
        }
        plan.boats = boats;
        Ok(())
    }

    /// The plan of one vehicle from epoch `e` on: where to be and what to sense at each of
    /// its sampling steps of epochs `e .. e + horizon`, all under epoch `e`'s allocation (the
    /// model's spatial modes, and so the disks, stay until the next update; a vehicle cut off
    /// from the server keeps following the later targets).
    pub fn plan(&self, vehicle: &VehicleId, e: u64, horizon: u64) -> Option<Plan> {
        let &VehicleSpec { index, kind, slot, .. } = self.vehicles.get(vehicle)?;
        let alloc = self.allocation(e)?;
        let grid = self.assim.grid();
        let (position, radius, cells) = match kind {
            // Left out: stays where it is, senses nothing.
            VehicleKind::Aerial if alloc.held.contains(&index) => (alloc.aerials[index], 0.0, vec![]),
            VehicleKind::Boat if alloc.held.contains(&index) => (self.assim.boat_positions()[slot], 0.0, vec![]),
            VehicleKind::Aerial => {
                let region = alloc.aerial_region(grid, self.cfg.aerial_stride, index)?;
                (alloc.aerials[index], 0.0, region)
            }
            VehicleKind::Boat => match &alloc.boats[slot] {
                Some((cells, (r, c))) => (
                    grid.centre_m(fleet_math::grid::Cell::new(*r, *c)),
                    self.cfg.radius,
                    cells.clone(),
                ),
                None => (self.assim.boat_positions()[slot], 0.0, vec![]),
            },
        };
        let cells: Vec<u32> = cells.into_iter().map(|c| c as u32).collect();
        let targets = (e..e.saturating_add(horizon.max(1)))
            .flat_map(|ep| self.schedule.sample_steps(kind, ep).into_iter().map(move |k| (ep, k)))
            .map(|(ep, k)| Target {
                epoch: ep,
                step: k as u64,
                position: [position.0, position.1],
                radius,
                cells: cells.clone(),
            })
            .collect();
        Some(Plan {
            vehicle: vehicle.clone(),
            model_version: self.version,
            epoch: e,
            targets,
        })
    }
}
