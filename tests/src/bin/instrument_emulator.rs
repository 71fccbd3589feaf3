//! An instrument that is not the vehicle, for the tests: it holds the mission's truth (the
//! world), hears where each boat really is from the fleet's ground-station stream (the
//! autopilots' GLOBAL_POSITION_INT, as QGroundControl does), and at each boat sampling step
//! sends what a disk-sensing instrument there would read (every cell of the mission's radius
//! around the boat's cell, the truth plus Gaussian noise of the mission's boat sigma) to the
//! boat's UDP sensor port as NDJSON readings. Every reading sent is logged, so a test can
//! find each one in the server's batches.
//!
//! With `--frames av-1=DIR` it is also each aerial's camera: at every aerial sampling step it
//! writes a GeoTIFF of the whole site (WGS 84, one pixel per model cell) into the aerial's
//! directory, the truth plus the aerial's noise at each cell's distance from where the aerial
//! really is, timed by its TIFF DateTime, written aside and renamed in.
//!
//! `--send boat-3=-` writes that boat's readings to standard output (for a vehicle reading
//! `stdin`). `--stuck boat-1=STEP` makes that boat's disk instrument a stuck probe from step
//! STEP on: every value it sends is the first one it read at that step (a fault for the
//! server's health tests to find, sent through the same interface as every reading). Every
//! STATUSTEXT the ground-station stream carries is logged beside the log (`.statustext`).
//! `--fault ID=KIND@STEP` makes that vehicle's instrument fail from step STEP as the fault
//! study's do (`bias`, `stuck`, `spikes`, `drift` for a boat's disk or sonde, `overexposed` for
//! an aerial's frames, `silent` for a camera that writes none; `fleet::experiment::faults::Fault`),
//! through the same interface. `--cloudy av-2=STEP` writes that aerial's frame of step STEP with
//! no value at any pixel (NaN throughout: a fully cloudy image), a frame that saw nothing.
//!
//! `--mavlink boat-2=PORT` makes it that boat's sonde on its autopilot: a companion computer on
//! the simulated autopilot's companion link (`udpout:127.0.0.1:PORT`) that hears the autopilot's
//! GLOBAL_POSITION_INT and SYSTEM_TIME there and, at each boat sampling step, sends one
//! NAMED_VALUE_FLOAT `--name` (default SONDE) stamped with the autopilot's boot time of its
//! newest fix (as a Lua script's `gcs:send_named_float` is): a point instrument, the truth at the
//! boat's cell plus the boat noise. With `--hostile-mavlink true` it also sends, once, a NaN value
//! (`not_finite`), a value stamped an hour after the autopilot's clock (`from_future`) and 64
//! garbage bytes (unreadable: the autopilot drops them) on each such link.
//!
//! `instrument-emulator --mission M --gcs-port G --send boat-1=127.0.0.1:15602 ... --mavlink boat-2=PORT
//! --frames av-1=DIR ... [--truth field.npy] --seed N --log sent.ndjson`; exits when the
//! mission's last step has passed. `--truth` is the world when the mission has none.

use fleet::experiment::faults::{Fault, FaultKind};
use fleet_mission::config::MissionConfig;
use fleet_mission::instrument::MissionClock;
use fleet_mission::protocol::VehicleKind;
use hetfleet_tests::GroundStation;
use mavlink::dialects::ardupilotmega::MavMessage;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::collections::{BTreeMap, BTreeSet};
use std::io::Write;
use std::sync::{Arc, Mutex};

struct Args {
    mission: std::path::PathBuf,
    gcs_port: u16,
    send: Vec<(String, String)>,
    frames: Vec<(String, std::path::PathBuf)>,
    mavlink: Vec<(String, u16)>,
    name: String,
    hostile_mavlink: bool,
    stuck: BTreeMap<String, u64>,
    faults: BTreeMap<String, (FaultKind, u64)>,
    cloudy: BTreeMap<String, u64>,
    truth: Option<std::path::PathBuf>,
    seed: u64,
    log: std::path::PathBuf,
}

fn args() -> Args {
    let mut a = Args {
        mission: "".into(),
        gcs_port: 0,
        send: vec![],
        frames: vec![],
        mavlink: vec![],
        name: "SONDE".into(),
        hostile_mavlink: false,
        stuck: BTreeMap::new(),
        faults: BTreeMap::new(),
        cloudy: BTreeMap::new(),
        truth: None,
        seed: 0,
        log: "sent.ndjson".into(),
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    for pair in argv.chunks(2) {
        let [k, v] = pair else {
            panic!("arguments come in pairs")
        };
        match k.as_str() {
            "--mission" => a.mission = v.into(),
            "--gcs-port" => a.gcs_port = v.parse().expect("--gcs-port"),
            "--seed" => a.seed = v.parse().expect("--seed"),
            "--log" => a.log = v.into(),
            "--truth" => a.truth = Some(v.into()),
            "--send" => {
                let (id, addr) = v.split_once('=').expect("--send ID=ADDR:PORT");
                a.send.push((id.into(), addr.into()));
            }
            "--name" => a.name = v.into(),
            "--stuck" => {
                let (id, step) = v.split_once('=').expect("--stuck ID=STEP");
                a.stuck.insert(id.into(), step.parse().expect("--stuck ID=STEP"));
            }
            "--fault" => {
                let (id, what) = v.split_once('=').expect("--fault ID=KIND@STEP");
                let (kind, step) = what.split_once('@').expect("--fault ID=KIND@STEP");
                let kind = kind
                    .parse()
                    .unwrap_or_else(|_| panic!("--fault {v}: no fault kind {kind}"));
                a.faults
                    .insert(id.into(), (kind, step.parse().expect("--fault ID=KIND@STEP")));
            }
            "--cloudy" => {
                let (id, step) = v.split_once('=').expect("--cloudy ID=STEP");
                a.cloudy.insert(id.into(), step.parse().expect("--cloudy ID=STEP"));
            }
            "--hostile-mavlink" => a.hostile_mavlink = v.parse().expect("--hostile-mavlink true|false"),
            "--mavlink" => {
                let (id, port) = v.split_once('=').expect("--mavlink ID=PORT");
                a.mavlink.push((id.into(), port.parse().expect("--mavlink ID=PORT")));
            }
            "--frames" => {
                let (id, dir) = v.split_once('=').expect("--frames ID=DIR");
                a.frames.push((id.into(), dir.into()));
            }
            other => panic!("unknown argument {other}"),
        }
    }
    a
}

/// Long because one loop steps the three kinds of emulated instrument (cameras writing frames,
/// MAVLink companions, probes on a socket or stdout) on one clock, one truth and one stream of
/// noise draws, in that order: apart, each would take all of the world's state, and the draws'
/// order (so the logged values a test compares) is the loop's.
fn main() {
    let a = args();
    let mission = MissionConfig::load(Some(&a.mission)).expect("the mission");
    // The world: a truth file kept aside from the mission (a run without a truth), or the
    // mission's own.
    let truth = match &a.truth {
        Some(p) => fleet_math::process::dataset::load(p, 1.0).expect("the truth file"),
        None => mission
            .truth(|_| {})
            .expect("the truth")
            .expect("a mission with a truth"),
    };
    let (grid, frames) = (
        fleet_math::grid::Grid::new(truth.rows, truth.cols, 1.0).expect("a grid"),
        truth.frames(),
    );
    let clock = mission.clock().expect("a mission with [time]");
    let site = mission.mavlink.site(&grid);
    let schedule = mission.schedule(frames);
    let sampling: BTreeSet<u64> = (0..schedule.epochs())
        .flat_map(|e| schedule.sample_steps(VehicleKind::Boat, e))
        .map(|k| k as u64)
        .collect();
    let aerial_steps: BTreeSet<u64> = (0..schedule.epochs())
        .flat_map(|e| schedule.sample_steps(VehicleKind::Aerial, e))
        .map(|k| k as u64)
        .collect();
    let sysids: BTreeMap<u8, String> = a
        .send
        .iter()
        .map(|(id, _)| id)
        .chain(a.frames.iter().map(|(id, _)| id))
        .map(|id| (mission.sysid(id).expect("a vehicle of the mission"), id.clone()))
        .collect();
    let fixes: Arc<Mutex<BTreeMap<String, (f64, f64)>>> = Arc::default();
    let gcs = GroundStation::listen(a.gcs_port);
    let heard = fixes.clone();
    // What the ground station is told of the sensors, logged beside what was sent.
    let mut said = std::fs::File::create(a.log.with_extension("statustext")).expect("the STATUSTEXT log");
    std::thread::spawn(move || loop {
        match gcs.recv() {
            (h, MavMessage::GLOBAL_POSITION_INT(p)) => {
                if let Some(id) = sysids.get(&(h.system_id as u8)) {
                    heard
                        .lock()
                        .unwrap()
                        .insert(id.clone(), (p.lat as f64 / 1e7, p.lon as f64 / 1e7));
                }
            }
            (h, MavMessage::STATUSTEXT(t)) => {
                let entry = serde_json::json!({"system": h.system_id, "component": h.component_id,
                    "severity": t.severity as u8, "text": t.text.to_str().unwrap_or_default()});
                let _ = writeln!(said, "{entry}");
            }
            _ => {}
        }
    });
    let port_of: BTreeMap<String, u16> = a.mavlink.iter().cloned().collect();
    let companions: Vec<(String, Companion)> = a
        .mavlink
        .iter()
        .map(|(id, port)| {
            (
                id.clone(),
                Companion::connect(*port, mission.sysid(id).expect("a vehicle")),
            )
        })
        .collect();
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("a socket");
    let mut log = std::fs::File::create(&a.log).expect("the log");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
    let noise = Normal::new(0.0, mission.team.boat_sigma).expect("a noise");
    let faults = failing(&a, &mission, frames);
    let mut sent: BTreeSet<(u64, String)> = BTreeSet::new();
    let mut stuck_at: BTreeMap<String, f64> = BTreeMap::new();
    loop {
        let now = MissionClock::now();
        let Some(k) = clock.step_of(now) else {
            std::thread::sleep(std::time::Duration::from_millis(20));
            continue;
        };
        if k >= frames as u64 {
            return;
        }
        let t = clock.time_of(k) + 0.5 * clock.step_s;
        for (id, dir) in &a.frames {
            let due = aerial_steps.contains(&k) && now >= t && !sent.contains(&(k, id.clone()));
            let Some(&(lat, lon)) = fixes.lock().unwrap().get(id).filter(|_| due) else {
                continue;
            };
            if faults.get(id).is_some_and(|f| f.silences(k)) {
                sent.insert((k, id.clone()));
                continue; // a camera gone dark writes no frame
            }
            let at = site.grid_of(&site.ned_of_global(lat, lon, site.origin[2]));
            let noise = mission.noise(VehicleKind::Aerial);
            let mut values: Vec<f64> = (0..grid.len())
                .map(|c| {
                    let (x, y) = grid.centre_m(grid.cell(c));
                    let sd = noise.std_at((at.0 - x).hypot(at.1 - y));
                    truth.snapshots[(c, k as usize)] + sd * Normal::new(0.0, 1.0).unwrap().sample(&mut rng)
                })
                .collect();
            if let Some(f) = faults.get(id) {
                f.alter(k, &mut values);
            }
            if a.cloudy.get(id) == Some(&k) {
                values.fill(f64::NAN);
            }
            write_frame(dir, &grid, &site, &values, t);
            sent.insert((k, id.clone()));
        }
        for (id, link) in &companions {
            let due = sampling.contains(&k) && now >= t && !sent.contains(&(k, id.clone()));
            // The newest fix, once it is of this step (the value is stamped with its time).
            let Some((boot_ms, lat, lon)) = link.fix_in(k, &clock).filter(|_| due) else {
                continue;
            };
            let (x, y) = site.grid_of(&site.ned_of_global(lat, lon, site.origin[2]));
            let Some(here) = grid.cell_at(x, y) else { continue };
            let c = grid.index(here);
            let mut value = [truth.snapshots[(c, k as usize)] + noise.sample(&mut rng)];
            if let Some(f) = faults.get(id) {
                f.alter(k, &mut value);
            }
            let value = value[0] as f32;
            link.send_value(boot_ms, &a.name, value);
            if a.hostile_mavlink && !link.hostile_sent.swap(true, std::sync::atomic::Ordering::Relaxed) {
                link.send_hostile(boot_ms, &a.name, *port_of.get(id).expect("a companion port"));
            }
            let entry = serde_json::json!({"vehicle": id, "step": k, "cell": c, "value": value as f64});
            writeln!(log, "{entry}").expect("logging");
            sent.insert((k, id.clone()));
        }
        for (id, addr) in &a.send {
            let due = sampling.contains(&k) && now >= t && !sent.contains(&(k, id.clone()));
            let Some(&(lat, lon)) = fixes.lock().unwrap().get(id).filter(|_| due) else {
                continue;
            };
            let (x, y) = site.grid_of(&site.ned_of_global(lat, lon, site.origin[2]));
            let Some(here) = grid.cell_at(x, y) else { continue };
            let mut lines = String::new();
            let cells = grid.disk(here, mission.team.radius);
            let mut values: Vec<f64> = cells
                .iter()
                .map(|&c| truth.snapshots[(c, k as usize)] + noise.sample(&mut rng))
                .collect();
            if let Some(f) = faults.get(id) {
                f.alter(k, &mut values);
            }
            for (&c, mut value) in cells.iter().zip(values) {
                if a.stuck.get(id).is_some_and(|&from| k >= from) {
                    value = *stuck_at.entry(id.clone()).or_insert(value);
                }
                let (cx, cy) = grid.centre_m(grid.cell(c));
                let (lat, lon, _) = site.global_of(&site.ned_of((cx, cy), 0.0));
                let reading = serde_json::json!({"t": t, "lat": lat, "lon": lon, "value": value,
                    "sigma": mission.team.boat_sigma});
                lines.push_str(&format!("{reading}\n"));
                let entry = serde_json::json!({"vehicle": id, "step": k, "cell": c, "value": value});
                writeln!(log, "{entry}").expect("logging");
            }
            if addr == "-" {
                // To standard output: piped into a vehicle reading `stdin`.
                let mut out = std::io::stdout().lock();
                out.write_all(lines.as_bytes())
                    .and_then(|_| out.flush())
                    .expect("writing to stdout");
            } else {
                socket.send_to(lines.as_bytes(), addr).expect("sending");
            }
            sent.insert((k, id.clone()));
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// A GeoTIFF of `values` (one per model cell) over the site, one pixel per cell, timed `t`:
/// written aside, then renamed into `dir` (as a camera pipeline should).
fn write_frame(
    dir: &std::path::Path,
    grid: &fleet_math::grid::Grid,
    site: &fleet_mission::site::Site,
    values: &[f64],
    t: f64,
) {
    use tiff::encoder::{colortype::Gray64Float, TiffEncoder};
    use tiff::tags::Tag;
    let (north, west, _) = site.global_of(&site.ned_of((0.0, grid.height_m()), 0.0));
    let (south, east, _) = site.global_of(&site.ned_of((grid.width_m(), 0.0), 0.0));
    let scale = [
        (east - west) / grid.cols as f64,
        (north - south) / grid.rows as f64,
        0.0,
    ];
    let north_up: Vec<f64> = (0..grid.rows)
        .rev()
        .flat_map(|r| values[r * grid.cols..(r + 1) * grid.cols].iter().copied())
        .collect();
    let stamp = MissionClock::rfc3339(t);
    let datetime = format!("{} {}", stamp[..10].replace('-', ":"), &stamp[11..19]);
    let tmp = dir.join(format!(".frame-{t}.partial"));
    let file = std::io::BufWriter::new(std::fs::File::create(&tmp).expect("a frame file"));
    let mut enc = TiffEncoder::new(file).expect("an encoder");
    let mut image = enc
        .new_image::<Gray64Float>(grid.cols as u32, grid.rows as u32)
        .expect("an image");
    image.encoder().write_tag(Tag::ModelPixelScaleTag, &scale[..]).unwrap();
    image
        .encoder()
        .write_tag(Tag::ModelTiepointTag, &[0.0, 0.0, 0.0, west, north, 0.0][..])
        .unwrap();
    let keys: [u16; 12] = [1, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326];
    image.encoder().write_tag(Tag::GeoKeyDirectoryTag, &keys[..]).unwrap();
    image.encoder().write_tag(Tag::DateTime, datetime.as_str()).unwrap();
    image.write_data(&north_up).expect("the pixels");
    // Named by the whole second (the `_YYYYMMDDTHHMMSSZ` form), as the DateTime says.
    let name = format!("frame_{}Z.tif", stamp[..19].replace(['-', ':'], ""));
    std::fs::rename(&tmp, dir.join(name)).expect("renaming the frame in");
}

/// `(time_boot_ms, lat, lon)` of the autopilot's newest fix, and UTC seconds at its boot.
type Heard = (Option<(u32, f64, f64)>, Option<f64>);

/// A companion computer on a simulated autopilot's companion link: what it last heard of the
/// autopilot's position and clock, and the link to send values on.
struct Companion {
    conn: Arc<dyn mavlink::MavConnection<MavMessage> + Send + Sync>,
    sysid: u8,
    heard: Arc<Mutex<Heard>>,
    hostile_sent: std::sync::atomic::AtomicBool,
}

impl Companion {
    /// Connect to the companion link on `port` of the autopilot of system `sysid`: a HEARTBEAT
    /// a second (so the autopilot's `udpin` knows where we are), and a thread that listens.
    fn connect(port: u16, sysid: u8) -> Self {
        let conn: Arc<dyn mavlink::MavConnection<MavMessage> + Send + Sync> =
            Arc::from(mavlink::connect::<MavMessage>(&format!("udpout:127.0.0.1:{port}")).expect("the companion link"));
        let heard: Arc<Mutex<Heard>> = Arc::default();
        let (rx, h) = (conn.clone(), heard.clone());
        std::thread::spawn(move || loop {
            match rx.recv() {
                Ok((hd, MavMessage::GLOBAL_POSITION_INT(p))) if hd.system_id == sysid as u32 => {
                    h.lock().unwrap().0 = Some((p.time_boot_ms, p.lat as f64 / 1e7, p.lon as f64 / 1e7));
                }
                Ok((hd, MavMessage::SYSTEM_TIME(t))) if hd.system_id == sysid as u32 && t.time_unix_usec > 0 => {
                    h.lock().unwrap().1 = Some(t.time_unix_usec as f64 / 1e6 - t.time_boot_ms as f64 / 1e3);
                }
                _ => {}
            }
        });
        let beat = conn.clone();
        std::thread::spawn(move || loop {
            let hb = MavMessage::HEARTBEAT(mavlink::dialects::ardupilotmega::HEARTBEAT_DATA {
                mavtype: mavlink::dialects::ardupilotmega::MavType::MAV_TYPE_ONBOARD_CONTROLLER,
                autopilot: mavlink::dialects::ardupilotmega::MavAutopilot::MAV_AUTOPILOT_INVALID,
                mavlink_version: 3,
                ..Default::default()
            });
            let _ = beat.send(&Self::header(sysid), &hb);
            std::thread::sleep(std::time::Duration::from_secs(1));
        });
        Self {
            conn,
            sysid,
            heard,
            hostile_sent: false.into(),
        }
    }

    /// A companion computer's header on the vehicle's system.
    fn header(sysid: u8) -> mavlink::MavHeader {
        mavlink::MavHeader {
            system_id: sysid as u32,
            component_id: 191,
            sequence: 0,
        }
    }

    /// The newest fix, when it falls in step `k` by the autopilot's clock.
    fn fix_in(&self, k: u64, clock: &MissionClock) -> Option<(u32, f64, f64)> {
        let (fix, boot_utc) = *self.heard.lock().unwrap();
        let (ms, lat, lon) = fix?;
        (clock.step_of(boot_utc? + ms as f64 / 1e3) == Some(k)).then_some((ms, lat, lon))
    }

    /// A NaN, a value stamped an hour ahead, and garbage bytes to the companion link's `port`.
    fn send_hostile(&self, time_boot_ms: u32, name: &str, port: u16) {
        self.send_value(time_boot_ms, name, f32::NAN);
        self.send_value(time_boot_ms + 3_600_000, name, 1.0);
        let garbage: Vec<u8> = (0..64u8).map(|i| i.wrapping_mul(37) ^ 0xfd).collect();
        let s = std::net::UdpSocket::bind("127.0.0.1:0").expect("a socket");
        // (From another socket: the autopilot's udpin answers its last sender, which stays us.)
        let _ = s.send_to(&garbage, ("127.0.0.1", port));
    }

    fn send_value(&self, time_boot_ms: u32, name: &str, value: f32) {
        let m = MavMessage::NAMED_VALUE_FLOAT(mavlink::dialects::ardupilotmega::NAMED_VALUE_FLOAT_DATA {
            time_boot_ms,
            value,
            name: name.into(),
        });
        self.conn.send(&Self::header(self.sysid), &m).expect("sending a value");
    }
}

/// Each `--fault` as the fault study's [`Fault`]: the noise it is sized by is the vehicle's
/// kind's (a camera's at the aerial's own position, a boat's), its drift reaches its full size
/// at the mission's last step, and its random draws follow `--seed`.
fn failing(a: &Args, mission: &MissionConfig, frames: usize) -> BTreeMap<String, Fault> {
    a.faults
        .iter()
        .map(|(id, &(kind, from))| {
            let sigma = match kind.kind() {
                VehicleKind::Aerial => mission.team.aerial_sigma0,
                VehicleKind::Boat => mission.team.boat_sigma,
            };
            let last = frames.saturating_sub(1) as u64;
            (
                id.clone(),
                Fault {
                    kind,
                    vehicle: 0,
                    from,
                    last,
                    sigma,
                    seed: a.seed,
                },
            )
        })
        .collect()
}
