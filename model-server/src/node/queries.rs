//! The node's answers to queries: a vehicle's plan (held until it exists when the vehicle says
//! it will wait, so one question an epoch crosses the radio) and the model as published.

use super::{reply, HeldQuery, Server, HELD_PER_VEHICLE, MAX_HOLD_MS};
use fleet_mission::protocol::{self, Body, VehicleId};
use fleet_net::zenoh;
use std::time::{Duration, Instant};
use tracing::warn;

impl Server {
    /// `plan/<id>?epoch=<e>[;wait_ms=<w>]`: the vehicle's plan from epoch `e`, or, when it does
    /// not exist yet, the query held up to `w` ms until it does (one question an epoch over the
    /// radio instead of one every 250 ms), else an error reply saying so (the vehicle asks again).
    pub(super) async fn on_plan_query(&mut self, q: zenoh::query::Query) {
        let key = q.key_expr().as_str().to_string();
        let id = self
            .keys
            .id_after(&key, "plan")
            .and_then(|id| id.parse::<VehicleId>().ok());
        let number = |name: &str| q.parameters().get(name).and_then(|e| e.parse::<u64>().ok());
        let (epoch, wait_ms) = (number("epoch"), number("wait_ms").unwrap_or(0).min(MAX_HOLD_MS));
        let known = |id: &VehicleId| self.core.vehicles().iter().any(|v| &v.id == id);
        match (id, epoch) {
            (Some(id), Some(e)) if known(&id) && wait_ms > 0 && self.core.plan(&id, e, self.horizon()).is_none() => {
                self.hold(HeldQuery {
                    query: q,
                    vehicle: id,
                    epoch: e,
                    until: Instant::now() + Duration::from_millis(wait_ms),
                })
                .await;
            }
            (Some(id), Some(e)) => self.answer(q, &id, e).await,
            _ => reply(q, Err(format!("ask {key}?epoch=<n> for a known vehicle"))).await,
        }
    }

    pub(super) fn horizon(&self) -> u64 {
        self.mission.pace.horizon
    }

    /// Hold a plan query until its plan exists (at most [`HELD_PER_VEHICLE`] a vehicle: the
    /// oldest is answered that there is none yet).
    pub(super) async fn hold(&mut self, held: HeldQuery) {
        let mine: Vec<usize> = (0..self.held_queries.len())
            .filter(|&i| self.held_queries[i].vehicle == held.vehicle)
            .collect();
        if mine.len() >= HELD_PER_VEHICLE {
            let old = self.held_queries.remove(mine[0]);
            self.answer(old.query, &old.vehicle, old.epoch).await;
        }
        self.held_queries.push(held);
    }

    /// Answer the held plan queries whose plan exists now, and those whose wait is over (or
    /// whose mission is) that there is none yet.
    pub(super) async fn answer_held(&mut self) {
        let now = Instant::now();
        let (due, keep): (Vec<HeldQuery>, Vec<HeldQuery>) =
            std::mem::take(&mut self.held_queries).into_iter().partition(|h| {
                now >= h.until || self.core.finished() || self.core.plan(&h.vehicle, h.epoch, self.horizon()).is_some()
            });
        self.held_queries = keep;
        for h in due {
            self.answer(h.query, &h.vehicle, h.epoch).await;
        }
    }

    /// A plan query answered now: the plan (recorded), or why there is none.
    pub(super) async fn answer(&mut self, q: zenoh::query::Query, id: &VehicleId, e: u64) {
        let body = match self.core.plan(id, e, self.horizon()) {
            Some(plan) => Ok(Body::Plan(plan)),
            None if self.core.vehicles().iter().any(|v| &v.id == id) => Err(format!(
                "no plan for epoch {e} yet (model at epoch {})",
                self.core.next_epoch()
            )),
            None => Err(format!("unknown vehicle {id:?}")),
        };
        let bytes = body.map(|b| {
            let bytes = protocol::encode(&b);
            self.record_body(q.key_expr().as_str(), &b, &bytes);
            bytes
        });
        reply(q, bytes).await;
    }

    pub(super) async fn on_model_query(&self, q: zenoh::query::Query) {
        let bytes = match self.core.published() {
            Some(p) => Some(p.full().to_vec()),
            None => self.core.model_update().map(|m| protocol::encode(&Body::Model(m))),
        };
        let sent = match bytes {
            Some(bytes) => {
                q.reply(q.key_expr().clone(), bytes)
                    .encoding(fleet_net::encoding())
                    .await
            }
            None => q.reply_err("no model yet".as_bytes().to_vec()).await,
        };
        if let Err(e) = sent {
            warn!("replying to a model query: {e}");
        }
    }
}
