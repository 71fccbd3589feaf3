//! The mission as Foxglove shows it: what the server hears and says, translated into Foxglove's
//! own message schemas, so a recording (or the live view's `--foxglove` server) opens in
//! Foxglove with the vehicles on the Map panel and the fields on a 3D panel, not as opaque
//! CBOR. The schemas and their protobuf encoding are the Foxglove SDK's (`foxglove::messages`);
//! the state and counters are plain JSON with a JSON schema (Foxglove decodes both natively).
//!
//! Channels ([`topics`]): each vehicle's `LocationFix` from its telemetry; the site (the fence)
//! and each vehicle's plan (its planned places; a boat's sensing disks) as styled
//! `GeoJSON`; the estimate, its standard deviation and the truth (where the server has one) as
//! `Grid`s in the site's frame (x east, y north, metres of the grid, cell (0, 0) at the origin),
//! land cells NaN; the model's state and the server's counters as JSON.

use fleet_math::grid::Grid;
use fleet_mission::config::MissionConfig;
use fleet_mission::fence::SiteFence;
use fleet_mission::protocol::{
    AutopilotLink, Body, ModelUpdate, Plan, ServerStatus, Telemetry, VehicleId, VehicleKind,
};
use fleet_mission::site::Site;
use foxglove::messages as fx;
use foxglove::{Encode, Schema};
use std::collections::BTreeMap;

/// The channels' topics.
pub mod topics {
    /// Prefix of every Foxglove channel (beside the mission's own keys in a recording).
    pub const PREFIX: &str = "/foxglove";
    pub const SITE: &str = "/foxglove/site";
    pub const ESTIMATE: &str = "/foxglove/estimate";
    pub const STD: &str = "/foxglove/std";
    pub const TRUTH: &str = "/foxglove/truth";
    pub const MODEL: &str = "/foxglove/model";
    pub const SERVER: &str = "/foxglove/server";
    /// A vehicle's newest plan: `/foxglove/plans/<id>`.
    pub fn plan(id: &str) -> String {
        format!("/foxglove/plans/{id}")
    }
    /// A vehicle's position: `/foxglove/vehicles/<id>`.
    pub fn vehicle(id: &str) -> String {
        format!("/foxglove/vehicles/{id}")
    }
}

/// The frame the grids are drawn in: the site's, x east and y north, grid metres.
pub const SITE_FRAME: &str = "site";

/// One message for a Foxglove channel: the channel (topic, schema, encoding) and its bytes.
#[derive(Debug, Clone)]
pub struct FoxMessage {
    pub channel: FoxChannel,
    pub data: Vec<u8>,
}

/// A Foxglove channel before any message: its topic, schema and encoding.
#[derive(Debug, Clone)]
pub struct FoxChannel {
    pub topic: String,
    pub schema: Schema,
    pub encoding: String,
}

impl FoxChannel {
    fn of<T: Encode>(topic: impl Into<String>) -> Self {
        Self {
            topic: topic.into(),
            schema: T::get_schema().expect("Foxglove's messages have schemas"),
            encoding: T::get_message_encoding(),
        }
    }

    fn json(topic: &str, schema: &'static str, title: &str) -> Self {
        Self {
            topic: topic.into(),
            schema: Schema::new(title, "jsonschema", schema.as_bytes()),
            encoding: "json".into(),
        }
    }
}

impl FoxMessage {
    fn on(channel: FoxChannel, data: Vec<u8>) -> Self {
        Self { channel, data }
    }

    fn encoded<T: Encode>(topic: impl Into<String>, m: &T) -> Self {
        let mut data = Vec::with_capacity(m.encoded_len().unwrap_or(256));
        m.encode(&mut data).expect("a Vec grows to any message");
        Self::on(FoxChannel::of::<T>(topic), data)
    }

    fn json(topic: &str, schema: &'static str, title: &str, value: &serde_json::Value) -> Self {
        let data = serde_json::to_vec(value).expect("JSON values serialise");
        Self::on(FoxChannel::json(topic, schema, title), data)
    }
}

/// What the translation needs to know of the mission.
pub struct FoxgloveView {
    site: Site,
    grid: Grid,
    fence: Option<SiteFence>,
    kinds: BTreeMap<VehicleId, VehicleKind>,
    /// Shared with the server that owns it (a copy was the truth's size again: 238 MB at
    /// 384 x 768, 101 frames).
    truth: Option<std::sync::Arc<fleet_math::process::frames::Frames>>,
}

impl FoxgloveView {
    /// The view of `mission` on `grid`; `truth` (the field the vehicles sample, where the
    /// server has it) adds the truth's grid at each model's step.
    pub fn new(
        mission: &MissionConfig,
        grid: Grid,
        truth: Option<std::sync::Arc<fleet_math::process::frames::Frames>>,
    ) -> Self {
        Self {
            site: mission.mavlink.site(&grid),
            grid,
            fence: mission.team.fence.clone(),
            kinds: mission.vehicles().into_iter().map(|v| (v.id, v.kind)).collect(),
            truth,
        }
    }

    /// What is known before anything is heard: the site.
    pub fn start(&self) -> Vec<FoxMessage> {
        vec![self.site_geojson()]
    }

    /// Every channel this view's messages can be on, known from the mission before anything is
    /// heard: a live server that advertises them all before its first client connects never
    /// advertises a channel to a client mid-mission (see `watch`'s Foxglove module for why).
    pub fn channels(&self) -> Vec<FoxChannel> {
        let mut out = vec![
            FoxChannel::of::<fx::GeoJson>(topics::SITE),
            FoxChannel::of::<fx::Grid>(topics::ESTIMATE),
            FoxChannel::of::<fx::Grid>(topics::STD),
            FoxChannel::json(topics::MODEL, MODEL_SCHEMA, MODEL_TITLE),
            FoxChannel::json(topics::SERVER, SERVER_SCHEMA, SERVER_TITLE),
        ];
        if self.truth.is_some() {
            out.push(FoxChannel::of::<fx::Grid>(topics::TRUTH));
        }
        for id in self.kinds.keys() {
            out.push(FoxChannel::of::<fx::LocationFix>(topics::vehicle(id)));
            out.push(FoxChannel::of::<fx::GeoJson>(topics::plan(id)));
        }
        out
    }

    /// `body`, heard or said at `ns` (Unix nanoseconds), as Foxglove messages (none for what
    /// Foxglove has no panel for: batches, acknowledgements).
    pub fn of(&self, body: &Body, ns: u64) -> Vec<FoxMessage> {
        let t = stamp(ns);
        match body {
            // A vehicle whose autopilot is still connecting has no position yet (it says 0, 0).
            Body::Telemetry(tm)
                if tm
                    .autopilot
                    .as_ref()
                    .is_some_and(|a| a.link == AutopilotLink::Connecting) =>
            {
                vec![]
            }
            Body::Telemetry(tm) => vec![self.location_fix(tm, t)],
            Body::Model(m) => self.model(m, t),
            Body::Plan(p) => vec![self.plan_geojson(p)],
            Body::Status(s) => vec![server_json(s)],
            _ => vec![],
        }
    }

    fn latlon(&self, xy: [f64; 2]) -> [f64; 2] {
        let (lat, lon, _) = self.site.global_of(&self.site.ned_of((xy[0], xy[1]), 0.0));
        [lat, lon]
    }

    fn location_fix(&self, tm: &Telemetry, t: fx::Timestamp) -> FoxMessage {
        let [latitude, longitude] = self.latlon(tm.position);
        let boat = self.kinds.get(&tm.vehicle) == Some(&VehicleKind::Boat);
        let meta = |k: &str, v: String| fx::KeyValuePair {
            key: k.into(),
            value: v,
        };
        let fix = fx::LocationFix {
            timestamp: Some(t),
            frame_id: tm.vehicle.to_string(),
            latitude,
            longitude,
            altitude: self.site.origin[2],
            // Heading is the telemetry's, radians clockwise from north.
            heading: Some(tm.heading),
            color: Some(if boat {
                rgba(0.1, 0.45, 0.95)
            } else {
                rgba(0.95, 0.5, 0.1)
            }),
            metadata: vec![
                meta("kind", if boat { "boat" } else { "aerial" }.into()),
                meta("step", tm.step.to_string()),
                meta("battery", format!("{:.2}", tm.battery)),
                meta("outbox", tm.outbox_depth.to_string()),
            ],
            ..Default::default()
        };
        FoxMessage::encoded(topics::vehicle(&tm.vehicle), &fix)
    }

    fn model(&self, m: &ModelUpdate, t: fx::Timestamp) -> Vec<FoxMessage> {
        let land = |v: Vec<f64>| masked(v, &m.land);
        let mut out = vec![];
        if !m.estimate.is_empty() {
            let estimate = m.estimate.iter().map(|&v| f64::from(v)).collect();
            out.push(self.grid_message(topics::ESTIMATE, "estimate", &land(estimate), t));
        }
        let std: Vec<f64> = m.variance.iter().map(|&v| f64::from(v).max(0.0).sqrt()).collect();
        out.push(self.grid_message(topics::STD, "std", &land(std), t));
        if let Some(truth) = self.truth.as_ref().filter(|s| (m.step as usize) < s.frames()) {
            match truth.frame(m.step as usize) {
                Ok(values) => out.push(self.grid_message(topics::TRUTH, "truth", &land(values), t)),
                Err(e) => tracing::warn!(step = m.step, "the truth's frame is not on the Foxglove channel: {e}"),
            }
        }
        out.push(model_json(m));
        out
    }

    /// A field as a `Grid` of one FLOAT32 field named `name`, row-major as the model's cells.
    fn grid_message(&self, topic: &str, name: &str, values: &[f64], t: fx::Timestamp) -> FoxMessage {
        let g = grid_of(&self.grid, name, values, t);
        FoxMessage::encoded(topic, &g)
    }

    fn site_geojson(&self) -> FoxMessage {
        let mut features = vec![];
        if let Some(f) = &self.fence {
            // The fence's vertices are physical metres east and north of the origin.
            let unscaled = |[e, n]: [f64; 2]| self.latlon([e / self.site.scale.x, n / self.site.scale.y]);
            let ring: Vec<[f64; 2]> = f.polygon_m.iter().map(|&p| unscaled(p)).collect();
            features.push(polygon(&ring, "fence", "#d62728", 0.0));
        }
        let (w, h) = (self.grid.width_m(), self.grid.height_m());
        let extent: Vec<[f64; 2]> = [[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]
            .iter()
            .map(|&p| self.latlon(p))
            .collect();
        features.push(polygon(&extent, "model grid", "#7f7f7f", 0.0));
        geojson_message(topics::SITE, features)
    }

    /// A vehicle's plan: each place as a point, a boat's disks for the plan's own epoch.
    fn plan_geojson(&self, plan: &Plan) -> FoxMessage {
        let boat = self.kinds.get(&plan.vehicle) == Some(&VehicleKind::Boat);
        let colour = if boat { "#1f77b4" } else { "#ff7f0e" };
        let mut features = vec![];
        for target in &plan.targets {
            let name = format!("{}: epoch {} step {}", plan.vehicle, target.epoch, target.step);
            features.push(point(self.latlon(target.position), &name, colour));
            if boat && target.radius > 0.0 && target.epoch == plan.epoch {
                let r = target.radius * self.grid.cell_m;
                let ring: Vec<[f64; 2]> = (0..DISK_VERTICES)
                    .map(|k| {
                        let a = k as f64 * std::f64::consts::TAU / DISK_VERTICES as f64;
                        self.latlon([target.position[0] + r * a.cos(), target.position[1] + r * a.sin()])
                    })
                    .collect();
                features.push(polygon(&ring, &format!("{name} disk"), colour, 0.15));
            }
        }
        geojson_message(&topics::plan(&plan.vehicle), features)
    }
}

/// Vertices of a sensing disk drawn on the map.
const DISK_VERTICES: usize = 16;

/// Degrees to 1e-7 (about a centimetre): what a map can show, and a third of the JSON.
fn round7(x: f64) -> f64 {
    (x * 1e7).round() / 1e7
}

/// Unix nanoseconds as Foxglove's timestamp.
pub fn stamp(ns: u64) -> fx::Timestamp {
    fx::Timestamp::new((ns / 1_000_000_000) as u32, (ns % 1_000_000_000) as u32)
}

fn rgba(r: f64, g: f64, b: f64) -> fx::Color {
    fx::Color { r, g, b, a: 1.0 }
}

/// The cells off the model grid (land) as NaN: Foxglove leaves them undrawn.
fn masked(mut values: Vec<f64>, land: &[u32]) -> Vec<f64> {
    for &c in land {
        if let Some(v) = values.get_mut(c as usize) {
            *v = f64::NAN;
        }
    }
    values
}

/// A `Grid` of `values` (row-major, `grid.rows x grid.cols`) as one FLOAT32 field.
pub fn grid_of(grid: &Grid, name: &str, values: &[f64], t: fx::Timestamp) -> fx::Grid {
    let data: Vec<u8> = values.iter().flat_map(|&v| (v as f32).to_le_bytes()).collect();
    fx::Grid {
        timestamp: Some(t),
        frame_id: SITE_FRAME.into(),
        pose: Some(fx::Pose {
            position: Some(fx::Vector3 { x: 0.0, y: 0.0, z: 0.0 }),
            orientation: Some(fx::Quaternion {
                x: 0.0,
                y: 0.0,
                z: 0.0,
                w: 1.0,
            }),
        }),
        column_count: grid.cols as u32,
        cell_size: Some(fx::Vector2 {
            x: grid.cell_m,
            y: grid.cell_m,
        }),
        row_stride: (grid.cols * 4) as u32,
        cell_stride: 4,
        fields: vec![fx::PackedElementField {
            name: name.into(),
            offset: 0,
            r#type: fx::packed_element_field::NumericType::Float32 as i32,
        }],
        data: data.into(),
    }
}

fn polygon(ring: &[[f64; 2]], name: &str, colour: &str, fill: f64) -> serde_json::Value {
    // GeoJSON is [lon, lat], its rings closed.
    let mut coords: Vec<[f64; 2]> = ring.iter().map(|&[lat, lon]| [round7(lon), round7(lat)]).collect();
    coords.extend(coords.first().copied());
    serde_json::json!({
        "type": "Feature",
        "geometry": {"type": "Polygon", "coordinates": [coords]},
        "properties": {"name": name, "style": {"color": colour, "weight": 2, "fillColor": colour, "fillOpacity": fill}},
    })
}

fn point([lat, lon]: [f64; 2], name: &str, colour: &str) -> serde_json::Value {
    serde_json::json!({
        "type": "Feature",
        "geometry": {"type": "Point", "coordinates": [round7(lon), round7(lat)]},
        "properties": {"name": name, "style": {"color": colour}},
    })
}

fn geojson_message(topic: &str, features: Vec<serde_json::Value>) -> FoxMessage {
    let doc = serde_json::json!({"type": "FeatureCollection", "features": features});
    FoxMessage::encoded(
        topic,
        &fx::GeoJson {
            geojson: doc.to_string(),
        },
    )
}

const MODEL_TITLE: &str = "hetfleet.Model";
const MODEL_SCHEMA: &str = r#"{
  "title": "hetfleet.Model",
  "description": "The model the server published: version, epoch, step, rank, variance summary",
  "type": "object",
  "properties": {
    "version": {"type": "integer"}, "epoch": {"type": "integer"}, "step": {"type": "integer"},
    "rank": {"type": "integer"}, "dt": {"type": "number"}, "forecast_steps": {"type": "integer"},
    "cells": {"type": "integer"}, "land_cells": {"type": "integer"},
    "mean_variance": {"type": "number"}, "max_variance": {"type": "number"},
    "eigenvalues": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}}
  },
  "required": ["version", "epoch", "step", "rank"]
}"#;

const SERVER_TITLE: &str = "hetfleet.ServerStatus";
const SERVER_SCHEMA: &str = r#"{
  "title": "hetfleet.ServerStatus",
  "description": "The model server's status and counters (server/status)",
  "type": "object",
  "properties": {
    "version": {"type": "integer"}, "next_epoch": {"type": "integer"}, "finished": {"type": "boolean"},
    "batches": {"type": "integer"}, "duplicates": {"type": "integer"},
    "rejected": {"type": "object", "additionalProperties": {"type": "integer"}},
    "alive": {"type": "array", "items": {"type": "string"}},
    "waiting_for": {"type": "array", "items": {"type": "string"}},
    "pending_epochs": {"type": "integer"},
    "latency_p50_ms": {"type": "number"}, "latency_p99_ms": {"type": "number"}
  },
  "required": ["version", "batches"],
  "additionalProperties": true
}"#;

fn model_json(m: &ModelUpdate) -> FoxMessage {
    let sea: Vec<f64> = m
        .variance
        .iter()
        .enumerate()
        .filter(|(i, _)| m.land.binary_search(&(*i as u32)).is_err())
        .map(|(_, &v)| f64::from(v))
        .collect();
    let mean = sea.iter().sum::<f64>() / sea.len().max(1) as f64;
    let value = serde_json::json!({
        "version": m.version, "epoch": m.epoch, "step": m.step, "rank": m.eigenvalues.len(),
        "dt": m.dt, "forecast_steps": m.forecast_steps, "cells": m.variance.len(),
        "land_cells": m.land.len(), "mean_variance": mean,
        "max_variance": sea.iter().copied().fold(0.0, f64::max),
        "eigenvalues": m.eigenvalues,
    });
    FoxMessage::json(topics::MODEL, MODEL_SCHEMA, MODEL_TITLE, &value)
}

fn server_json(s: &ServerStatus) -> FoxMessage {
    let value = serde_json::to_value(s).expect("the status serialises");
    FoxMessage::json(topics::SERVER, SERVER_SCHEMA, SERVER_TITLE, &value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_grid_holds_the_cells_row_major_as_little_endian_f32_with_land_as_nan() {
        let grid = Grid::new(2, 3, 2.5).unwrap();
        let values = masked(vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0], &[4]);
        let g = grid_of(&grid, "estimate", &values, stamp(1_500_000_000));
        assert_eq!((g.column_count, g.row_stride, g.cell_stride), (3, 12, 4));
        assert_eq!(g.data.len(), 24);
        let cell = |i: usize| f32::from_le_bytes(g.data[4 * i..4 * i + 4].try_into().unwrap());
        // Row 1 (north of row 0), column 0 is flat index 3.
        assert_eq!(cell(3), 3.0);
        assert!(cell(4).is_nan());
        assert_eq!(g.timestamp, Some(fx::Timestamp::new(1, 500_000_000)));
    }

    /// A live server creates every channel from `channels()` before its first client: each
    /// message the view makes must be on one of them, with the same schema and encoding.
    #[test]
    fn every_message_is_on_a_channel_known_before_anything_is_heard() {
        let mission = MissionConfig::load(None).unwrap();
        let grid = Grid::new(4, 6, 2.5).unwrap();
        let view = FoxgloveView::new(&mission, grid, None);
        let vehicle = mission.vehicles()[0].id.clone();
        let telemetry = Telemetry {
            vehicle: vehicle.clone(),
            step: 3,
            position: [1.0, 2.0],
            heading: 0.5,
            battery: 0.9,
            link: fleet_mission::protocol::LinkState::Up,
            outbox_depth: 0,
            autopilot: None,
            acked: None,
            readings: None,
            traffic: None,
            sensor: None,
        };
        let plan = Plan {
            vehicle,
            model_version: 1,
            epoch: 0,
            targets: vec![],
        };
        let n = grid.len();
        let model = ModelUpdate {
            version: 1,
            epoch: 0,
            step: 0,
            grid,
            dt: 1.0,
            eigenvalues: vec![],
            modes_re: vec![],
            modes_im: vec![],
            amplitudes: vec![],
            estimate: vec![0.0; n],
            variance: vec![1.0; n],
            forecast_steps: 1,
            forecast_variance: vec![1.0; n],
            land: vec![],
            level: 0.0,
        };
        let known: BTreeMap<String, FoxChannel> = view.channels().into_iter().map(|c| (c.topic.clone(), c)).collect();
        let bodies = [Body::Telemetry(telemetry), Body::Plan(plan), Body::Model(model)];
        let made: Vec<FoxMessage> = view
            .start()
            .into_iter()
            .chain(bodies.iter().flat_map(|b| view.of(b, 1)))
            .collect();
        assert!(made.len() >= 5, "{made:?}");
        for m in made {
            let c = known
                .get(&m.channel.topic)
                .unwrap_or_else(|| panic!("{} is not among the channels", m.channel.topic));
            let m = &m.channel;
            assert_eq!(
                (&c.schema.name, &c.schema.encoding, &c.encoding),
                (&m.schema.name, &m.schema.encoding, &m.encoding)
            );
        }
    }

    /// The layout in `docs/` names only panels it arranges and channels this module makes.
    #[test]
    fn the_foxglove_layout_arranges_its_panels_on_our_channels() {
        let layout: serde_json::Value = serde_json::from_str(include_str!("../../docs/foxglove-layout.json")).unwrap();
        let panels = layout["configById"].as_object().unwrap();
        fn leaves(v: &serde_json::Value, out: &mut Vec<String>) {
            match v {
                serde_json::Value::String(s) => out.push(s.clone()),
                v => ["first", "second"].iter().for_each(|k| leaves(&v[k], out)),
            }
        }
        let mut arranged = vec![];
        leaves(&layout["layout"], &mut arranged);
        arranged.sort();
        assert_eq!(arranged, panels.keys().cloned().collect::<Vec<_>>());
        let ours = [
            topics::ESTIMATE,
            topics::STD,
            topics::TRUTH,
            topics::MODEL,
            topics::SERVER,
        ];
        for (id, config) in panels {
            let named = config["topics"]
                .as_object()
                .map(|t| t.keys().cloned().collect::<Vec<_>>());
            let named = named.unwrap_or_else(|| config["topicPath"].as_str().map(String::from).into_iter().collect());
            assert!(named.iter().all(|t| ours.contains(&t.as_str())), "{id}: {named:?}");
        }
    }

    #[test]
    fn the_json_schemas_are_json() {
        for s in [MODEL_SCHEMA, SERVER_SCHEMA] {
            let v: serde_json::Value = serde_json::from_str(s).unwrap();
            assert_eq!(v["type"], "object");
        }
    }
}
