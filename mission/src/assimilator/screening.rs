//! Each step's readings tested before they are fused ([`crate::health`]): the aerials' frames
//! against the model's forecast, the boats' values against what the fleet knows of the step
//! without them, and the vehicles that said nothing where they were sent.

use super::{cells_of, AerialSight, Assimilator};
use crate::protocol::Sample;
use crate::team::TeamError;

impl Assimilator {
    /// The aerials' samples of a step `ahead` steps after the newest snapshot, each frame
    /// tested against the model's forecast ([`crate::health::Screen::aerials`]; all of them
    /// with `sensor_health = false` or before the first model).
    pub fn screen_aerials(&mut self, step: u64, ahead: u64, samples: Vec<crate::health::VehicleSample>) -> Vec<Sample> {
        if !self.setup.cfg.sensor_health {
            return samples.into_iter().map(|t| t.sample).collect();
        }
        let _span = tracing::info_span!("screen aerials").entered();
        let cells = cells_of(&samples);
        let mean = self.mean_at(&cells);
        let forecast = self.state.fitted.as_ref().map(|(p, _)| {
            let at = p.predict_at(ahead as f64, &cells);
            cells
                .iter()
                .copied()
                .zip(at.iter().zip(&mean).map(|(a, m)| a + m))
                .collect()
        });
        let grid = self.setup.grid;
        self.state.screen.aerials(&grid, step, samples, forecast.as_ref())
    }

    /// The boats' samples of a step `ahead` steps after the newest snapshot, tested against
    /// what the fleet knows of it without any boat value of the step
    /// ([`crate::health::Screen::boats`]).
    pub fn screen_boats(
        &mut self,
        step: u64,
        ahead: u64,
        samples: Vec<crate::health::VehicleSample>,
        aerial: &AerialSight,
    ) -> Result<Vec<Sample>, TeamError> {
        if !self.setup.cfg.sensor_health || samples.is_empty() {
            return Ok(samples.into_iter().map(|t| t.sample).collect());
        }
        let _span = tracing::info_span!("screen boats").entered();
        let cells = cells_of(&samples);
        let field = tracing::info_span!("boat reference").in_scope(|| self.boat_reference(ahead, aerial, &cells))?;
        let (grid, sigma) = (self.setup.grid, self.setup.cfg.boat_sigma);
        let lattice = aerial
            .cells
            .iter()
            .zip(aerial.values.iter().zip(&aerial.variance))
            .map(|(&c, (&y, &v))| (c, (y, v)))
            .collect();
        let reference = crate::health::Reference {
            field: &field,
            lattice: &lattice,
        };
        let _tests = tracing::info_span!("boat tests").entered();
        Ok(self.state.screen.boats(&grid, step, samples, reference, sigma))
    }

    /// Vehicles (indices) that sent no reading though they had a disk or a region, judged at
    /// `step`: marked silent ([`crate::health::Screen::silent`]).
    pub fn screen_silent(&mut self, step: u64, vehicles: &[usize]) {
        if self.setup.cfg.sensor_health {
            vehicles.iter().for_each(|&v| self.state.screen.silent(v, step));
        }
    }

    /// Every sensor's health, the verdicts changed since the last call, and the readings'
    /// counts.
    pub fn screen(&mut self) -> &mut crate::health::Screen {
        &mut self.state.screen
    }

    pub fn screen_state(&self) -> &crate::health::Screen {
        &self.state.screen
    }
}
