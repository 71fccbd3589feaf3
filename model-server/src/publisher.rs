//! The model's publisher: a task of its own that puts every model on `model/latest`, in the
//! order it was handed over. The core hands it each epoch's model the moment it is made, beside
//! the placement ([`fleet_mission::server::Publisher`]), so observers do not wait for the boats'
//! plans; the node hands it the models it makes itself (after a re-fit, on a restart), through
//! the same queue so that an older model never overtakes a newer one.

use fleet_mission::published::Published;
use fleet_mission::server::Publisher;
use fleet_net::{zenoh, Traffic};
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::{mpsc, oneshot};
use tracing::warn;

enum Out {
    Put(Vec<u8>, Traffic),
    /// Answered once every put handed over before it is out.
    Flush(oneshot::Sender<()>),
}

pub struct ModelPublisher {
    tx: mpsc::UnboundedSender<Out>,
}

impl ModelPublisher {
    /// Start the task putting on `key` over `session`.
    pub fn start(session: zenoh::Session, key: String) -> Self {
        let (tx, mut rx) = mpsc::unbounded_channel();
        tokio::spawn(async move {
            while let Some(out) = rx.recv().await {
                match out {
                    Out::Put(bytes, traffic) => {
                        if let Err(e) = fleet_net::put_bytes(&session, &key, bytes, traffic).await {
                            warn!("the model was not put: {e}");
                        }
                    }
                    Out::Flush(done) => drop(done.send(())),
                }
            }
        });
        Self { tx }
    }

    /// What the core calls with each epoch's model (it only queues: it never blocks the
    /// placement beside it).
    pub fn hook(&self) -> Publisher {
        let tx = self.tx.clone();
        Arc::new(move |p: &Published| queue(&tx, p))
    }

    /// Put `p` unless the core already handed it over; when it went out either way.
    pub fn publish(&self, p: &mut Published) -> Instant {
        if let Some(at) = p.handed_out {
            return at;
        }
        queue(&self.tx, p);
        *p.handed_out.insert(Instant::now())
    }

    /// Wait until every model handed over is out (before the session closes).
    pub async fn flush(&self) {
        let (done, out) = oneshot::channel();
        if self.tx.send(Out::Flush(done)).is_ok() {
            drop(out.await);
        }
    }
}

/// Queue `p`'s put (the task gone, at the node's end, there is no one left to put it to).
fn queue(tx: &mpsc::UnboundedSender<Out>, p: &Published) {
    drop(tx.send(Out::Put(p.bytes.clone(), Traffic::of(&p.shown))));
}
