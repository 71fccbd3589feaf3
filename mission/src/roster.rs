//! Who is in the mission: the vehicles a team has, each with its id, its kind, its index (its
//! place in the list, aerials first: it picks the vehicle's random stream and MAVLink system
//! id) and its slot among its own kind. Every "which vehicle is this" question goes through
//! here, so the aerials-first convention is written once.

pub use crate::protocol::VehicleId;
use crate::protocol::VehicleKind;
use crate::team::TeamConfig;
use std::collections::BTreeMap;

/// One vehicle of the mission.
#[derive(Debug, Clone, PartialEq)]
pub struct VehicleSpec {
    pub id: VehicleId,
    pub kind: VehicleKind,
    /// Its place in the roster (aerials first).
    pub index: usize,
    /// Its place among the vehicles of its kind (boat `slot` is `boat-{slot + 1}`).
    pub slot: usize,
}

/// The vehicles of a team: `av-1..` then `boat-1..`, looked up by id in O(log n).
#[derive(Debug, Clone, PartialEq)]
pub struct Roster {
    vehicles: Vec<VehicleSpec>,
    by_id: BTreeMap<VehicleId, usize>,
    aerials: usize,
}

impl Roster {
    pub fn of(cfg: &TeamConfig) -> Self {
        let spec = |index, kind, slot, prefix: &str| VehicleSpec {
            id: VehicleId::new(&format!("{prefix}-{}", slot + 1)).expect("av-N and boat-N are ids"),
            kind,
            index,
            slot,
        };
        let vehicles: Vec<VehicleSpec> = (0..cfg.aerials)
            .map(|s| spec(s, VehicleKind::Aerial, s, "av"))
            .chain((0..cfg.boats).map(|s| spec(cfg.aerials + s, VehicleKind::Boat, s, "boat")))
            .collect();
        let by_id = vehicles.iter().map(|v| (v.id.clone(), v.index)).collect();
        Self {
            vehicles,
            by_id,
            aerials: cfg.aerials,
        }
    }

    pub fn all(&self) -> &[VehicleSpec] {
        &self.vehicles
    }

    pub fn len(&self) -> usize {
        self.vehicles.len()
    }

    pub fn is_empty(&self) -> bool {
        self.vehicles.is_empty()
    }

    pub fn get(&self, id: &str) -> Option<&VehicleSpec> {
        self.by_id.get(id).map(|&i| &self.vehicles[i])
    }

    pub fn index_of(&self, id: &str) -> Option<usize> {
        self.by_id.get(id).copied()
    }

    /// The vehicle at roster index `index`.
    pub fn at(&self, index: usize) -> &VehicleSpec {
        &self.vehicles[index]
    }

    pub fn ids(&self) -> Vec<VehicleId> {
        self.vehicles.iter().map(|v| v.id.clone()).collect()
    }

    /// The roster index of boat `slot`.
    pub fn boat_index(&self, slot: usize) -> usize {
        self.aerials + slot
    }

    /// The boat slot of roster index `index` (`None` for an aerial or past the end).
    pub fn boat_slot(&self, index: usize) -> Option<usize> {
        self.vehicles
            .get(index)
            .filter(|v| v.kind == VehicleKind::Boat)
            .map(|v| v.slot)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_indices_and_slots_agree() {
        let r = Roster::of(&TeamConfig {
            aerials: 2,
            boats: 3,
            ..Default::default()
        });
        assert_eq!(r.ids(), ["av-1", "av-2", "boat-1", "boat-2", "boat-3"]);
        for (i, v) in r.all().iter().enumerate() {
            assert_eq!(r.index_of(&v.id), Some(i));
            assert_eq!(r.get(&v.id), Some(v));
        }
        assert_eq!(
            r.get("boat-2").map(|v| (v.index, v.slot, v.kind)),
            Some((3, 1, VehicleKind::Boat))
        );
        assert_eq!(r.boat_slot(3), Some(1));
        assert_eq!(r.boat_slot(1), None, "an aerial has no boat slot");
        assert_eq!(r.boat_slot(5), None);
        assert_eq!(r.boat_index(2), 4);
        assert_eq!(r.get("boat-4"), None);
    }

    #[test]
    fn vehicle_ids_from_outside_are_checked() {
        assert_eq!(&*VehicleId::new("boat-1").unwrap(), "boat-1");
        for bad in ["", "boat/1", "a*", "b?x", "é", &"x".repeat(65)] {
            assert!(bad.parse::<VehicleId>().is_err(), "{bad:?} accepted");
        }
    }
}
