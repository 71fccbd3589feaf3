//! Where an epoch's time goes: a `tracing` layer that adds up the time spent inside each span
//! name (the model server's phases: screening, the aerial estimate, the filter, the model
//! update, placement, encoding). A span's time counts while it is entered, so a nested span's
//! time is in its parent's too.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
use tracing::span::Id;
use tracing::Subscriber;
use tracing_subscriber::layer::{Context, SubscriberExt};
use tracing_subscriber::registry::LookupSpan;
use tracing_subscriber::Layer;

/// Time inside each span name, in first-entered order, shared with the subscriber.
#[derive(Debug, Clone, Default)]
pub struct Phases {
    totals: Arc<Mutex<Vec<(String, Duration)>>>,
}

/// When the span was last entered (kept in the span's extensions).
struct Entered(Instant);

impl Phases {
    /// A subscriber that records into these totals (for `tracing::subscriber::with_default`).
    pub fn subscriber(&self) -> impl Subscriber + Send + Sync {
        tracing_subscriber::registry().with(self.clone())
    }

    /// Forget what was recorded so far (the first fit, timed apart).
    pub fn reset(&self) {
        self.lock().clear();
    }

    pub fn totals(&self) -> Vec<(String, Duration)> {
        self.lock().clone()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<(String, Duration)>> {
        self.totals.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn add(&self, name: &str, d: Duration) {
        let mut totals = self.lock();
        match totals.iter_mut().find(|(n, _)| n == name) {
            Some((_, t)) => *t += d,
            None => totals.push((name.to_string(), d)),
        }
    }
}

impl<S: Subscriber + for<'a> LookupSpan<'a>> Layer<S> for Phases {
    fn on_enter(&self, id: &Id, ctx: Context<'_, S>) {
        if let Some(span) = ctx.span(id) {
            span.extensions_mut().replace(Entered(Instant::now()));
        }
    }

    fn on_exit(&self, id: &Id, ctx: Context<'_, S>) {
        let Some(span) = ctx.span(id) else { return };
        let entered = span.extensions_mut().remove::<Entered>();
        if let Some(Entered(at)) = entered {
            self.add(span.name(), at.elapsed());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    #[test]
    fn nested_spans_count_in_their_parents_and_repeat_entries_add_up() {
        let phases = Phases::default();
        tracing::subscriber::with_default(phases.subscriber(), || {
            for _ in 0..3 {
                let _outer = tracing::info_span!("outer").entered();
                tracing::info_span!("inner").in_scope(|| std::thread::sleep(Duration::from_millis(2)));
            }
        });
        let totals: BTreeMap<String, Duration> = phases.totals().into_iter().collect();
        assert_eq!(totals.keys().collect::<Vec<_>>(), ["inner", "outer"]);
        assert!(
            totals["inner"] >= Duration::from_millis(6),
            "three entries of 2 ms: {totals:?}"
        );
        assert!(
            totals["outer"] >= totals["inner"],
            "the parent holds its child: {totals:?}"
        );
        phases.reset();
        assert!(phases.totals().is_empty());
    }
}
