//! The model as the server publishes it on `model/latest`: assembled from the fitted model and
//! the newest fused estimate, and encoded, once a version.
//!
//! At 192 x 384 and rank 10 the published model is 13.6 MB, and assembling and encoding it took
//! about a tenth of the epoch after the placement. Neither needs the placement's result, and the
//! placement does not change the model, so the server makes it beside the placement, on the
//! other core ([`crate::server::ServerCore`]); a model asked for at any other time (after a
//! restore, the last epoch) is made then.

use crate::dmd::DmdModel;
use crate::protocol::{self, Body, ModelUpdate};
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
        let forecast_variance = tracing::info_span!("forecast variance").in_scope(self.forecast_variance);
        let _span = tracing::info_span!("model assembled").entered();
        let m = &self.model;
        let (n, r) = (m.modes.modes.nrows(), m.modes.modes.ncols());
        let mut modes_re = Vec::with_capacity(n * r);
        let mut modes_im = Vec::with_capacity(n * r);
        for i in 0..n {
            for j in 0..r {
                modes_re.push(m.modes.modes[(i, j)].re as f32);
                modes_im.push(m.modes.modes[(i, j)].im as f32);
            }
        }
        let narrow = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        ModelUpdate {
            dt: m.dt,
            eigenvalues: m.modes.eigenvalues.iter().map(|l| [l.re, l.im]).collect(),
            modes_re,
            modes_im,
            amplitudes: m.amplitudes.iter().map(|a| [a.re, a.im]).collect(),
            estimate: last.map(|l| narrow(l.0)).unwrap_or_default(),
            variance: last.map_or_else(|| vec![self.prior_variance as f32; n], |l| narrow(l.1)),
            forecast_variance: narrow(&forecast_variance),
            ..self.shell
        }
    }
}

/// The published model's encoding on the wire, the model as the live views and recordings
/// translate it, and what it was made of (so a model that changed since is made again, never
/// sent stale).
#[derive(Debug, Clone)]
pub struct Published {
    pub bytes: Vec<u8>,
    /// The model without its modes (they are in `bytes`, and no translation reads them: 47 of
    /// the 54 MB at 384 x 768, not kept twice).
    pub shown: Body,
    pub(crate) of: Made,
}

/// What a published model was made of: the model's version, the next epoch, and the steps in
/// the history.
pub(crate) type Made = (u64, u64, usize);

impl Published {
    pub(crate) fn of(update: ModelUpdate, made: Made) -> Self {
        let body = Body::Model(update);
        let bytes = tracing::info_span!("model encoded").in_scope(|| protocol::encode(&body));
        let shown = match body {
            Body::Model(m) => Body::Model(ModelUpdate {
                modes_re: vec![],
                modes_im: vec![],
                ..m
            }),
            other => other,
        };
        Self { bytes, shown, of: made }
    }
}
