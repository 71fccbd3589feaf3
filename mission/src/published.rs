//! The model as the server publishes it on `model/latest`: assembled from the fitted model and
//! the newest fused estimate, and encoded, once a version.
//!
//! At 192 x 384 and rank 10 the published model is 13.6 MB, and assembling and encoding it took
//! about a tenth of the epoch after the placement. Neither needs the placement's result, and the
//! placement does not change the model, so the server makes it beside the placement, on the
//! other core ([`crate::server::ServerCore`]); a model asked for at any other time (after a
//! restore, the last epoch) is made then.

use crate::protocol::{self, Body, ModelUpdate};
use fleet_math::dmd::DmdModel;
use std::sync::Arc;

/// What the published model is made of, read from the server in a moment: everything it knows
/// without the fitted model (version, steps, grid, land), the fitted model (shared), and the
/// forecast variance still to compute. Assembling it may then run on another thread.
pub struct ModelParts {
    /// The published model with its modes, estimate and variances left empty.
    pub shell: ModelUpdate,
    pub model: Arc<DmdModel>,
    pub forecast_variance: Box<dyn FnOnce() -> Vec<f64> + Send>,
    /// The variance per cell reported before any estimate (the prediction's).
    pub prior_variance: f64,
}

impl ModelParts {
    /// The published model, with `last` the newest fused estimate and its variance.
    pub fn assemble(self, last: Option<(&[f64], &[f64])>) -> ModelUpdate {
        let (mut update, model) = self.assemble_lean(last);
        [update.modes_re, update.modes_im] = modes_f32(&model);
        update
    }

    /// [`Self::assemble`] without the modes, and the model they come from: what is put every
    /// epoch, and what a get's whole model is made of when one is asked for.
    pub fn assemble_lean(self, last: Option<(&[f64], &[f64])>) -> (ModelUpdate, Arc<DmdModel>) {
        let forecast_variance = tracing::info_span!("forecast variance").in_scope(self.forecast_variance);
        let _span = tracing::info_span!("model assembled").entered();
        let m = &self.model;
        let n = m.modes.modes.nrows();
        let narrow = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let update = ModelUpdate {
            dt: m.dt,
            eigenvalues: m.modes.eigenvalues.iter().map(|l| [l.re, l.im]).collect(),
            amplitudes: m.amplitudes.iter().map(|a| [a.re, a.im]).collect(),
            estimate: last.map(|l| narrow(l.0)).unwrap_or_default(),
            variance: last.map_or_else(|| vec![self.prior_variance as f32; n], |l| narrow(l.1)),
            forecast_variance: narrow(&forecast_variance),
            ..self.shell
        };
        (update, self.model)
    }
}

/// The modes as they travel: `f32`, cell by cell, the real and the imaginary parts apart.
fn modes_f32(m: &DmdModel) -> [Vec<f32>; 2] {
    let (n, r) = (m.modes.modes.nrows(), m.modes.modes.ncols());
    let mut modes_re = Vec::with_capacity(n * r);
    let mut modes_im = Vec::with_capacity(n * r);
    for i in 0..n {
        for j in 0..r {
            modes_re.push(m.modes.modes[(i, j)].re as f32);
            modes_im.push(m.modes.modes[(i, j)].im as f32);
        }
    }
    [modes_re, modes_im]
}

/// The published model's encodings on the wire, the model as the live views and recordings
/// translate it, and what it was made of (so a model that changed since is made again, never
/// sent stale).
///
/// The model put on `model/latest` every epoch leaves out its modes: the estimate and its
/// variances are what an observer draws, the modes only what one that forecasts needs, and they
/// were 87% of the bytes (5.9 of 6.8 MB at 192 x 384, 47 of 54 MB at 384 x 768), every epoch,
/// on every link and in the recording. A get on `model/latest` answers the whole model
/// ([`Self::full`]), encoded when first asked for.
#[derive(Debug, Clone)]
pub struct Published {
    /// The model without its modes, encoded: what is put every epoch and recorded.
    pub bytes: Vec<u8>,
    /// The model without its modes (no translation reads them).
    pub shown: Body,
    /// The modes, as they travel (`f32`), or the model to make them from when first asked for
    /// (the model put every epoch never needs them: at 192 x 384 making them took 5.9 MB and
    /// a pass over the modes every epoch), and the whole model's encoding once asked for.
    modes: Modes,
    full: std::sync::OnceLock<Vec<u8>>,
    pub(crate) of: Made,
    /// When it was handed to the publisher the moment it was made ([`crate::server::Publisher`]:
    /// beside the placement, not after it); `None`: not yet, the node puts it itself.
    pub handed_out: Option<std::time::Instant>,
}

/// What a published model was made of: a model published earlier is still current while these
/// are the same.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Made {
    /// The model's version.
    pub(crate) version: u64,
    /// The epoch the server waits for next.
    pub(crate) next_epoch: u64,
    /// Steps in the history (a re-fit of the same epoch can change them).
    pub(crate) steps: usize,
}

/// The published model's modes: made (a model that came whole), or still in the model.
#[derive(Debug, Clone)]
enum Modes {
    Made([Vec<f32>; 2]),
    Of(Arc<DmdModel>),
}

impl Published {
    /// A whole model's encodings (its modes taken out).
    pub(crate) fn of(mut update: ModelUpdate, made: Made) -> Self {
        let modes = Modes::Made(update.take_modes());
        Self::encoded(update, modes, made)
    }

    /// A model without its modes, made from `model` when the whole model is first asked for.
    pub(crate) fn of_lean((update, model): (ModelUpdate, Arc<DmdModel>), made: Made) -> Self {
        Self::encoded(update, Modes::Of(model), made)
    }

    fn encoded(update: ModelUpdate, modes: Modes, made: Made) -> Self {
        let _span = tracing::info_span!("model encoded").entered();
        let shown = Body::Model(update);
        Self {
            bytes: protocol::encode(&shown),
            shown,
            modes,
            full: std::sync::OnceLock::new(),
            of: made,
            handed_out: None,
        }
    }

    /// The whole model, its modes in, encoded (what a get on `model/latest` answers).
    pub fn full(&self) -> &[u8] {
        self.full.get_or_init(|| match &self.shown {
            Body::Model(m) => {
                let [modes_re, modes_im] = match &self.modes {
                    Modes::Made(modes) => modes.clone(),
                    Modes::Of(model) => modes_f32(model),
                };
                protocol::encode(&Body::Model(ModelUpdate {
                    modes_re,
                    modes_im,
                    ..m.clone()
                }))
            }
            other => protocol::encode(other),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What is put every epoch is the model less its modes, and what a get answers is the
    /// whole model, to the bit.
    #[test]
    fn the_model_is_put_without_its_modes_and_answered_whole() {
        let grid = fleet_math::grid::Grid::new(4, 5, 1.0).unwrap();
        let update = ModelUpdate {
            version: 3,
            epoch: 2,
            step: 40,
            grid,
            dt: 0.25,
            eigenvalues: vec![[0.9, 0.1], [0.5, 0.0]],
            modes_re: (0..40).map(|i| i as f32 * 0.1).collect(),
            modes_im: (0..40).map(|i| -(i as f32)).collect(),
            amplitudes: vec![[1.0, 0.0], [0.2, 0.3]],
            estimate: vec![0.5; 20],
            variance: vec![0.01; 20],
            forecast_steps: 5,
            forecast_variance: vec![0.02; 20],
            land: vec![3],
            level: 0.0,
        };
        let made = Made {
            version: 3,
            next_epoch: 3,
            steps: 41,
        };
        let p = Published::of(update.clone(), made);
        let ctx = protocol::Context::new(grid);
        let lean = ModelUpdate {
            modes_re: vec![],
            modes_im: vec![],
            ..update.clone()
        };
        assert_eq!(protocol::decode(&p.bytes, &ctx), Ok(Body::Model(lean.clone())));
        assert_eq!(p.shown, Body::Model(lean));
        assert_eq!(protocol::decode(p.full(), &ctx), Ok(Body::Model(update)));
        // The whole model is the lean one and the modes' 2 x 40 f32s.
        assert!(p.full().len() >= p.bytes.len() + 2 * 40 * 4);
    }
}
