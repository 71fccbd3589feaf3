//! What the view knows about the mission, built from the messages it receives (pure: no
//! network, no clock of its own; times are seconds since the watch started, passed in).
//! `/api/state` is [`View::state`]; the heat maps are [`View::fields`].

use fleet_math::grid::Grid;
use fleet_math::process::frames::Frames;
use fleet_mission::protocol::VehicleId;
use fleet_mission::protocol::{
    AutopilotLink, Body, LinkState, ModelUpdate, Plan, ServerStatus, Telemetry, VehicleKind,
};
use serde::Serialize;
use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;

/// How many past positions of each vehicle the view keeps (its track).
pub const TRACK_LEN: usize = 300;

/// The workspace on the Earth: latitude and longitude of the grid's corners.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Geo {
    /// South-west (grid (0, 0)) and north-east corners, `[lat, lon]` degrees.
    pub south_west: [f64; 2],
    pub north_east: [f64; 2],
    /// Physical extent, east and north (m).
    pub size_m: [f64; 2],
}

#[derive(Debug, Clone, Serialize)]
pub struct VehicleView {
    pub id: String,
    pub kind: VehicleKind,
    pub position: Option<[f64; 2]>,
    /// Radians from +x (east).
    pub heading: Option<f64>,
    pub battery: Option<f64>,
    pub step: Option<u64>,
    /// `up` (its Zenoh liveliness token is present), `lost` (the token went: no word within
    /// the link lease), `left` (the token went after the server said the mission finished:
    /// the vehicle is done, not lost), or `unseen` (never heard of).
    pub link: &'static str,
    /// Seconds since the watch started at which it was lost.
    pub lost_since_s: Option<f64>,
    /// What the vehicle says of its own radio link in its last telemetry (`up`, `down`).
    pub radio: Option<&'static str>,
    pub outbox_depth: Option<u64>,
    pub mode: String,
    /// Past positions (single precision: centimetres over kilometres).
    pub track: VecDeque<[f32; 2]>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ModelView {
    pub version: u64,
    pub epoch: u64,
    pub step: u64,
    /// Continuous-time eigenvalues `ln(lambda) / dt`, `[re, im]`.
    pub eigenvalues_ct: Vec<[f64; 2]>,
    pub forecast_steps: u64,
    /// When the model's step began, in UTC (RFC 3339), with mission time (`[time]`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub utc: Option<String>,
}

/// The per-cell fields behind the heat maps (row-major, the model grid).
#[derive(Debug, Clone, Serialize)]
pub struct Fields {
    pub version: u64,
    pub step: u64,
    pub rows: usize,
    pub cols: usize,
    pub estimate: Vec<f64>,
    pub variance: Vec<f64>,
    /// The mixed-reality truth at the estimate's step (absent in the field).
    pub truth: Option<Vec<f64>>,
}

/// The view's whole state.
pub struct View {
    mission: String,
    grid: Grid,
    geo: Geo,
    lease_s: f64,
    vehicles: BTreeMap<VehicleId, VehicleView>,
    model: Option<ModelView>,
    fields: Option<Fields>,
    status: Option<ServerStatus>,
    plans: BTreeMap<VehicleId, Plan>,
    /// `(epoch, MSE of the estimate against the truth)` per model, when the truth is known.
    mse: Vec<(u64, f64)>,
    /// The node's own truth, shared with its Foxglove view (not copied step by step: at
    /// 384 x 768 each copy was the truth's 238 MB again).
    truth: Option<Arc<Frames>>,
    /// Messages the watch refused (not decodable, wrong grid, unknown vehicle).
    refused: u64,
    plans_taken: u64,
    /// Mission time, when the mission has it: steps are then spans of UTC.
    clock: Option<fleet_mission::instrument::MissionClock>,
    /// When the newest link event was (seconds since the watch started).
    last_link_event_s: f64,
}

/// `/api/state`: everything but the per-cell fields.
#[derive(Serialize)]
pub struct State<'a> {
    pub mission: &'a str,
    pub grid: [usize; 2],
    pub cell_m: f64,
    pub geo: Geo,
    pub lease_s: f64,
    pub vehicles: Vec<&'a VehicleView>,
    pub model: Option<&'a ModelView>,
    pub server: Option<&'a ServerStatus>,
    /// Absent from the pushed state (pages get the plans as their own event, once per change).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub plans: Option<Vec<&'a Plan>>,
    pub mse: &'a [(u64, f64)],
    pub refused: u64,
}

impl View {
    /// A view of `vehicles` (id, kind) on `grid`; `truth` the field the vehicles sample, when known.
    pub fn new(
        mission: &str,
        grid: Grid,
        geo: Geo,
        lease_s: f64,
        vehicles: &[(VehicleId, VehicleKind)],
        truth: Option<Arc<Frames>>,
    ) -> Self {
        let vehicles = vehicles
            .iter()
            .map(|(id, kind)| {
                let v = VehicleView {
                    id: id.to_string(),
                    kind: *kind,
                    position: None,
                    heading: None,
                    battery: None,
                    step: None,
                    link: "unseen",
                    lost_since_s: None,
                    radio: None,
                    outbox_depth: None,
                    mode: String::new(),
                    track: VecDeque::new(),
                };
                (id.clone(), v)
            })
            .collect();
        Self {
            mission: mission.into(),
            grid,
            geo,
            lease_s,
            vehicles,
            model: None,
            fields: None,
            status: None,
            plans: BTreeMap::new(),
            mse: vec![],
            truth,
            refused: 0,
            plans_taken: 0,
            clock: None,
            last_link_event_s: 0.0,
        }
    }

    /// Steps on the mission's clock: the model's step is shown in UTC too.
    pub fn with_clock(mut self, clock: Option<fleet_mission::instrument::MissionClock>) -> Self {
        self.clock = clock;
        self
    }

    /// Take one decoded message. Returns whether the view changed.
    pub fn apply(&mut self, body: Body) -> bool {
        match body {
            Body::Telemetry(t) => self.telemetry(t),
            Body::Model(m) => self.model(m),
            Body::Status(s) => {
                if s.finished {
                    self.lost_at_the_end_left();
                }
                self.status = Some(s);
                true
            }
            Body::Plan(p) => {
                if !self.vehicles.contains_key(&p.vehicle) {
                    self.refused += 1;
                    return false;
                }
                if self.plans.get(&p.vehicle) == Some(&p) {
                    return false;
                }
                self.plans.insert(p.vehicle.clone(), p);
                self.plans_taken += 1;
                true
            }
            Body::Batch(_) | Body::Ack(_) | Body::Override(_) => false,
        }
    }

    /// Whether the server has published a model (its status says `version`) newer than the one
    /// shown: a put this view missed (it joined after its get was answered, or its link's lease
    /// ran out while the model went by). Versions count from 1; 0 is "no model yet".
    pub fn behind(&self, version: u64) -> bool {
        self.model.as_ref().map_or(0, |m| m.version) < version
    }

    /// Count a message the watch could not use.
    pub fn refuse(&mut self) {
        self.refused += 1;
    }

    fn telemetry(&mut self, t: Telemetry) -> bool {
        let Some(v) = self.vehicles.get_mut(&t.vehicle) else {
            self.refused += 1;
            return false;
        };
        v.position = Some(t.position);
        v.heading = Some(t.heading);
        v.battery = Some(t.battery);
        v.step = Some(t.step);
        v.outbox_depth = Some(t.outbox_depth);
        v.radio = Some(match t.link {
            LinkState::Up => "up",
            LinkState::Down => "down",
        });
        v.mode = match &t.autopilot {
            None => "fleet".into(),
            Some(a) => match a.link {
                // What it waits for before the planner drives it ("connecting: GPS fix").
                AutopilotLink::Connecting => match &a.waiting {
                    Some(w) => format!("connecting: {w}"),
                    None => "connecting".into(),
                },
                AutopilotLink::Lost => "autopilot lost".into(),
                // A failsafe's reason beside the mode it caused ("RTL, armed: Failsafe: battery low ...").
                // Left to the operator: why, as the autopilot said it.
                AutopilotLink::Up => format!(
                    "{}{}{}{}",
                    a.mode,
                    if a.armed { ", armed" } else { "" },
                    a.failsafe.as_ref().map_or_else(String::new, |f| format!(": {f}")),
                    a.waiting
                        .as_ref()
                        .map_or_else(String::new, |w| format!(" (waiting for {w})"))
                ),
            },
        };
        let at = [t.position[0] as f32, t.position[1] as f32];
        if v.track.back() != Some(&at) {
            v.track.push_back(at);
            if v.track.len() > TRACK_LEN {
                v.track.pop_front();
            }
        }
        true
    }

    fn model(&mut self, m: ModelUpdate) -> bool {
        let n = self.grid.len();
        let r = m.eigenvalues.len();
        if m.grid != self.grid
            || !m.has_a_field(n)
            || m.amplitudes.len() != r
            || m.variance.len() != n
            || m.land.iter().any(|&c| c as usize >= n)
        {
            self.refused += 1;
            return false;
        }
        if self.model.as_ref().is_some_and(|old| old.version >= m.version) {
            return false;
        }
        // The fused estimate at the model's step, or (from a server that does not send it)
        // the model's own field there, Re(Phi alpha).
        let mut estimate: Vec<f64> = if m.estimate.len() == n {
            m.estimate.iter().map(|&v| f64::from(v)).collect()
        } else {
            (0..n)
                .map(|i| {
                    (0..r)
                        .map(|k| {
                            f64::from(m.modes_re[i * r + k]) * m.amplitudes[k][0]
                                - f64::from(m.modes_im[i * r + k]) * m.amplitudes[k][1]
                        })
                        .sum()
                })
                .collect()
        };
        // Land has no estimate: NaN, which the page paints as land (and the truth has none).
        let mut variance: Vec<f64> = m.variance.iter().map(|&v| f64::from(v)).collect();
        for &c in &m.land {
            (estimate[c as usize], variance[c as usize]) = (f64::NAN, f64::NAN);
        }
        let step = m.step as usize;
        let truth = (self.truth.as_ref())
            .filter(|t| step < t.frames())
            .and_then(|t| match t.frame(step) {
                Ok(x) => Some(x),
                Err(e) => {
                    tracing::warn!(step, "the truth could not be read to score the model: {e}");
                    None
                }
            });
        if let Some(t) = &truth {
            let mse = fleet_math::fusion::mse(&estimate, t);
            self.mse.retain(|(e, _)| *e != m.epoch);
            self.mse.push((m.epoch, mse));
        }
        let eigenvalues_ct = m
            .eigenvalues
            .iter()
            .map(|&[re, im]| {
                let (modulus, arg) = (re.hypot(im), im.atan2(re));
                [modulus.ln() / m.dt, arg / m.dt]
            })
            .collect();
        self.model = Some(ModelView {
            version: m.version,
            epoch: m.epoch,
            step: m.step,
            eigenvalues_ct,
            forecast_steps: m.forecast_steps,
            utc: self
                .clock
                .map(|c| fleet_mission::instrument::MissionClock::rfc3339(c.time_of(m.step))),
        });
        self.fields = Some(Fields {
            version: m.version,
            step: m.step,
            rows: self.grid.rows,
            cols: self.grid.cols,
            estimate,
            variance,
            truth,
        });
        true
    }

    /// A vehicle's Zenoh liveliness token appeared (`alive`) or went (its session said nothing
    /// within the link lease, or it left) at `now_s`. Returns whether the view changed.
    pub fn liveliness(&mut self, id: &str, alive: bool, now_s: f64) -> bool {
        let Some(v) = self.vehicles.get_mut(id) else {
            return false;
        };
        self.last_link_event_s = self.last_link_event_s.max(now_s);
        let finished = self.status.as_ref().is_some_and(|s| s.finished);
        let (link, since) = match (alive, finished) {
            (true, _) => ("up", None),
            (false, true) => ("left", None),
            (false, false) => ("lost", Some(now_s)),
        };
        if v.link == link {
            return false;
        }
        (v.link, v.lost_since_s) = (link, since);
        true
    }

    /// The server says the mission finished, and the vehicles that finished with it may have
    /// gone before that word arrived (their tokens and the status travel on different keys):
    /// a vehicle whose outbox was empty and whose token went within a lease of the newest link
    /// event has left, not been lost. One lost earlier, or with batches still to send, stays lost.
    fn lost_at_the_end_left(&mut self) {
        let since = self.last_link_event_s - self.lease_s;
        for v in self.vehicles.values_mut() {
            let recent = v.lost_since_s.is_some_and(|t| t >= since);
            if v.link == "lost" && recent && v.outbox_depth == Some(0) {
                (v.link, v.lost_since_s) = ("left", None);
            }
        }
    }

    pub fn state(&self) -> State<'_> {
        State {
            mission: &self.mission,
            grid: [self.grid.rows, self.grid.cols],
            cell_m: self.grid.cell_m,
            geo: self.geo,
            lease_s: self.lease_s,
            vehicles: self.vehicles.values().collect(),
            model: self.model.as_ref(),
            server: self.status.as_ref(),
            plans: Some(self.plans.values().collect()),
            mse: &self.mse,
            refused: self.refused,
        }
    }

    /// Every vehicle's plan, and how many plans have been taken (changes when they do).
    pub fn plans(&self) -> (u64, Vec<&Plan>) {
        (self.plans_taken, self.plans.values().collect())
    }

    pub fn fields(&self) -> Option<&Fields> {
        self.fields.as_ref()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_math::process::FieldSeries;

    fn view() -> View {
        let grid = Grid::new(2, 3, 1.0).unwrap();
        let geo = Geo {
            south_west: [55.0, 12.0],
            north_east: [55.1, 12.1],
            size_m: [3.0, 2.0],
        };
        let truth = Arc::new(Frames::in_memory(FieldSeries {
            rows: 2,
            cols: 3,
            dt: 1.0,
            snapshots: faer::Mat::from_fn(6, 4, |_, _| 1.0),
        }));
        View::new(
            "m",
            grid,
            geo,
            2.0,
            &[
                ("boat-1".parse().unwrap(), VehicleKind::Boat),
                ("av-1".parse().unwrap(), VehicleKind::Aerial),
            ],
            Some(truth),
        )
    }

    fn tele(id: &str, x: f64) -> Body {
        Body::Telemetry(Telemetry {
            vehicle: id.parse().unwrap(),
            step: 1,
            position: [x, 0.5],
            heading: 0.0,
            battery: 0.9,
            link: LinkState::Up,
            outbox_depth: 3,
            autopilot: None,
            acked: None,
            readings: None,
            traffic: None,
            sensor: None,
        })
    }

    fn model(version: u64, amplitude: f64) -> Body {
        let grid = Grid::new(2, 3, 1.0).unwrap();
        Body::Model(ModelUpdate {
            version,
            epoch: version,
            step: 2,
            grid,
            dt: 1.0,
            eigenvalues: vec![[0.5, 0.0]],
            modes_re: vec![1.0; 6],
            modes_im: vec![0.0; 6],
            amplitudes: vec![[amplitude, 0.0]],
            estimate: vec![],
            variance: vec![0.1; 6],
            forecast_steps: 1,
            forecast_variance: vec![0.2; 6],
            land: vec![],
            level: 0.0,
        })
    }

    #[test]
    fn telemetry_builds_tracks_and_a_lost_token_marks_the_vehicle_lost() {
        let mut v = view();
        assert!(v.apply(tele("boat-1", 0.5)));
        assert!(v.apply(tele("boat-1", 1.5)));
        assert!(!v.apply(tele("intruder", 1.5)), "an unknown vehicle is refused");
        assert_eq!(v.state().refused, 1);
        let boat = |v: &View| {
            v.state()
                .vehicles
                .iter()
                .find(|x| x.id == "boat-1")
                .map(|x| (*x).clone())
                .unwrap()
        };
        let b = boat(&v);
        assert_eq!(
            (b.track.len(), b.link, b.radio, b.outbox_depth),
            (2, "unseen", Some("up"), Some(3))
        );
        assert!(v.liveliness("boat-1", true, 1.5));
        assert!(!v.liveliness("boat-1", true, 1.6), "no change");
        assert!(v.liveliness("boat-1", false, 3.0));
        assert_eq!((boat(&v).link, boat(&v).lost_since_s), ("lost", Some(3.0)));
        assert!(!v.liveliness("intruder", true, 3.0));
        assert!(v.liveliness("boat-1", true, 4.0));
        assert_eq!((boat(&v).link, boat(&v).lost_since_s), ("up", None));
        // Once the server says the mission finished, a vehicle that goes has left, not been lost.
        let status = ServerStatus {
            version: 7,
            next_epoch: 7,
            finished: true,
            batches: 0,
            duplicates: 0,
            rejected: Default::default(),
            alive: vec![],
            waiting_for: vec![],
            pending_epochs: 0,
            latency_p50_ms: 0.0,
            latency_p99_ms: 0.0,
            readings: Default::default(),
            behind: Default::default(),
            skill: None,
            health: Default::default(),
            overrides: 0,
            holdout: None,
        };
        assert!(v.apply(Body::Status(status.clone())));
        assert!(v.liveliness("boat-1", false, 5.0));
        assert_eq!((boat(&v).link, boat(&v).lost_since_s), ("left", None));

        // The word that it finished may come after the vehicles went: one that went at the end
        // with nothing left to send has left; one lost long before, or with batches unsent,
        // stays lost.
        let mut v = view();
        for (id, outbox) in [("boat-1", 0), ("av-1", 2)] {
            let Body::Telemetry(mut t) = tele(id, 0.5) else {
                unreachable!()
            };
            t.outbox_depth = outbox;
            v.apply(Body::Telemetry(t));
            v.liveliness(id, true, 1.0);
        }
        v.liveliness("boat-1", false, 30.0);
        v.liveliness("av-1", false, 30.2);
        let link = |v: &View, id: &str| v.vehicles[id].link;
        v.apply(Body::Status(status.clone()));
        assert_eq!((link(&v, "boat-1"), link(&v, "av-1")), ("left", "lost"));
        let mut v = view();
        let Body::Telemetry(mut t) = tele("boat-1", 0.5) else {
            unreachable!()
        };
        t.outbox_depth = 0;
        v.apply(Body::Telemetry(t));
        v.liveliness("boat-1", false, 3.0);
        v.liveliness("av-1", true, 40.0);
        v.apply(Body::Status(status));
        assert_eq!(link(&v, "boat-1"), "lost", "lost mid-mission, long before the end");
    }

    #[test]
    fn a_vehicle_shows_what_its_autopilot_waits_for_and_its_refusal() {
        let mut v = view();
        let waiting = |link, w: &str| {
            let Body::Telemetry(mut t) = tele("boat-1", 0.5) else {
                unreachable!()
            };
            t.autopilot = Some(fleet_mission::protocol::AutopilotStatus {
                link,
                sysid: 3,
                mode: "MANUAL".into(),
                armed: false,
                guided: false,
                unreadable: 0,
                refused_from_gcs: 0,
                failsafe: None,
                waiting: Some(w.into()),
            });
            Body::Telemetry(t)
        };
        let mode = |v: &View| {
            v.state()
                .vehicles
                .iter()
                .find(|x| x.id == "boat-1")
                .unwrap()
                .mode
                .clone()
        };
        assert!(v.apply(waiting(AutopilotLink::Connecting, "GPS fix")));
        assert_eq!(mode(&v), "connecting: GPS fix");
        let refused = "arming (Arm: Vehicle breaching Polygon fence)";
        assert!(v.apply(waiting(AutopilotLink::Connecting, refused)));
        assert_eq!(mode(&v), format!("connecting: {refused}"));
        assert!(v.apply(waiting(
            AutopilotLink::Up,
            "the operator (not ready to drive: MANUAL; Arm: x)"
        )));
        assert_eq!(
            mode(&v),
            "MANUAL (waiting for the operator (not ready to drive: MANUAL; Arm: x))"
        );
    }

    #[test]
    fn a_model_gives_the_estimate_its_error_and_continuous_eigenvalues() {
        let mut v = view();
        assert!(!v.behind(0) && v.behind(1), "no model yet: any published one is newer");
        assert!(v.apply(model(1, 3.0)));
        let f = v.fields().unwrap();
        assert_eq!(f.estimate, vec![3.0; 6]);
        assert_eq!(f.truth.as_deref(), Some(&[1.0; 6][..]));
        // (3 - 1)^2 = 4 at every cell.
        assert_eq!(v.state().mse, &[(1, 4.0)]);
        let ct = &v.state().model.unwrap().eigenvalues_ct[0];
        assert!((ct[0] - 0.5f64.ln()).abs() < 1e-15 && ct[1] == 0.0);
        assert!(!v.apply(model(1, 5.0)), "an older or repeated version is not taken");
        assert!(
            !v.behind(1) && v.behind(2),
            "behind a server whose status says a newer model"
        );
        let mut bad = model(2, 1.0);
        if let Body::Model(m) = &mut bad {
            m.variance.pop();
        }
        assert!(!v.apply(bad), "a model of the wrong size is refused");
        assert_eq!(v.state().refused, 1);
        // With the fused estimate on the wire, that is what is drawn and scored (not the modes').
        let mut fused = model(3, 3.0);
        if let Body::Model(m) = &mut fused {
            m.estimate = vec![1.5, 1.5, 1.5, 0.5, 0.5, 0.5];
        }
        assert!(v.apply(fused));
        assert_eq!(v.fields().unwrap().estimate, vec![1.5, 1.5, 1.5, 0.5, 0.5, 0.5]);
        assert_eq!(v.state().mse.last(), Some(&(3, 0.25)));
        assert_eq!(v.state().model.unwrap().utc, None, "no mission time, no UTC");
        // The model as it is put every epoch: no modes, its estimate drawn; without either,
        // nothing to draw: refused.
        let lean = |version: u64, estimate: Vec<f32>| match model(version, 3.0) {
            Body::Model(m) => Body::Model(ModelUpdate {
                modes_re: vec![],
                modes_im: vec![],
                estimate,
                ..m
            }),
            other => other,
        };
        assert!(!v.apply(lean(4, vec![])), "no modes and no estimate: refused");
        assert!(v.apply(lean(5, vec![2.0; 6])));
        assert_eq!(v.fields().unwrap().estimate, vec![2.0; 6]);
    }

    #[test]
    fn with_mission_time_the_models_step_is_shown_in_utc() {
        let clock = fleet_mission::instrument::MissionClock {
            start: 1_795_597_200.0,
            step_s: 60.0,
        };
        let mut v = view().with_clock(Some(clock));
        assert!(v.apply(model(1, 3.0)));
        // Step 2 of 1-minute steps from 2026-11-25T09:00:00Z.
        assert_eq!(v.state().model.unwrap().utc.as_deref(), Some("2026-11-25T09:02:00Z"));
    }
}
