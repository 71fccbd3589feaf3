//! The model as published on `model/latest`: made beside each epoch's placement (on the other
//! core) and handed to the [`Publisher`] the moment it is made, or made when asked for if the
//! model changed since.

use super::ServerCore;
use crate::assimilator::Allocation;
use crate::protocol::ModelUpdate;
use crate::published::{Made, ModelParts, Published};
use crate::team::TeamError;

/// Takes an epoch's model the moment it is made, on the thread that made it (the node's hands
/// it to its Zenoh publisher): observers need not wait for the placement, which takes longer
/// (30 of 120 ms at 192 x 384) and which they do not read. It must not block.
pub type Publisher = std::sync::Arc<dyn Fn(&Published) + Send + Sync>;

/// The published model and where it goes.
#[derive(Clone, Default)]
pub(super) struct Publication {
    /// The model as published and its encoding, made beside the epoch's placement (or when
    /// asked for, if the model changed since).
    pub(super) published: Option<Published>,
    /// Where an epoch's model goes the moment it is made, beside the placement
    /// ([`ServerCore::with_publisher`]; `None`: it waits for the caller).
    pub(super) publisher: Option<Publisher>,
}

impl ServerCore {
    /// The model as published on `model/latest` (`None` before the first fit), with the
    /// newest estimate's reported variance per cell and the forecast's to the next boat step.
    pub fn model_update(&self) -> Option<ModelUpdate> {
        Some(self.model_parts()?.assemble(self.history.last()))
    }

    /// What the published model is made of (`None` before the first fit).
    pub(super) fn model_parts(&self) -> Option<ModelParts> {
        let shell = ModelUpdate {
            version: self.version,
            epoch: self.epoch.saturating_sub(1),
            step: self.history.len().saturating_sub(1) as u64,
            grid: *self.assim.grid(),
            dt: 0.0,
            eigenvalues: vec![],
            modes_re: vec![],
            modes_im: vec![],
            amplitudes: vec![],
            estimate: vec![],
            variance: vec![],
            forecast_steps: self.cfg.boat_period as u64,
            forecast_variance: vec![],
            land: self.assim.land().iter().map(|&c| c as u32).collect(),
            level: self.assim.field_level(),
        };
        Some(ModelParts {
            shell,
            model: self.assim.model_shared()?,
            forecast_variance: Box::new(self.assim.forecast_variance_later(self.cfg.boat_period as u64)),
            prior_variance: self.assim.prediction_variance(),
        })
    }

    pub(super) fn made(&self) -> Made {
        Made {
            version: self.version,
            next_epoch: self.epoch,
            steps: self.history.len(),
        }
    }

    /// The model as published on `model/latest` and its encoding, taken out to send: the one
    /// made beside the epoch's placement, or made now if the model changed since (`None` before
    /// the first fit). Give it back with [`Self::keep_published`] for the next reader.
    pub fn take_published(&mut self) -> Option<Published> {
        let made = self.made();
        // A stale one is dropped here, its memory (54 MB at 384 x 768) freed before the new one.
        if let Some(p) = self.publication.published.take().filter(|p| p.of == made) {
            return Some(p);
        }
        self.model_update().map(|m| Published::of(m, made))
    }

    pub fn keep_published(&mut self, p: Published) {
        self.publication.published = Some(p);
    }

    /// The published model made for the model as it is now, if one was (a reader that cannot
    /// wait for one to be made uses [`Self::model_update`]).
    pub fn published(&self) -> Option<&Published> {
        self.publication.published.as_ref().filter(|p| p.of == self.made())
    }

    /// The next epoch's allocation, and beside it (on the other core) the model to publish:
    /// neither needs the other, and the placement leaves the model as it is.
    ///
    /// The model goes to the publisher as soon as it is made, unless a re-admission's re-fit
    /// follows (that one publishes the model it makes).
    pub(super) fn place_and_publish(&mut self) -> Result<Allocation, TeamError> {
        let holds = self.planning.holds[&self.epoch].clone();
        let (parts, made) = (self.model_parts(), self.made());
        self.publication.published = None;
        let publisher = self
            .publication
            .publisher
            .clone()
            .filter(|_| self.sensors.readmit_from.is_none());
        let (assim, history) = (&mut self.assim, &self.history);
        let (plan, published) = crate::side_by_side::beside(
            || tracing::info_span!("placement").in_scope(|| assim.allocate_without(&holds)),
            || {
                let mut p = Published::of_lean(parts?.assemble_lean(history.last()), made);
                if let Some(publish) = &publisher {
                    publish(&p);
                    p.handed_out = Some(std::time::Instant::now());
                }
                Some(p)
            },
        );
        self.publication.published = published;
        plan
    }

    /// Hand every epoch's model to `publisher` the moment it is made ([`Publisher`]).
    pub fn with_publisher(mut self, publisher: Publisher) -> Self {
        self.publication.publisher = Some(publisher);
        self
    }
}
