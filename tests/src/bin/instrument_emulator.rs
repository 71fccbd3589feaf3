//! An instrument that is not the vehicle, for the tests: it holds the mission's truth (the
//! world), hears where each boat really is from the fleet's ground-station stream (the
//! autopilots' GLOBAL_POSITION_INT, as QGroundControl does), and at each boat sampling step
//! sends what a disk-sensing instrument there would read (every cell of the mission's radius
//! around the boat's cell, the truth plus Gaussian noise of the mission's boat sigma) to the
//! boat's UDP sensor port as NDJSON readings. Every reading sent is logged, so a test can
//! find each one in the server's batches.
//!
//! `instrument-emulator --mission M --gcs-port G --send boat-1=127.0.0.1:15602 ... --seed N
//! --log sent.ndjson`; exits when the mission's last step has passed.

use fleet_mission::config::MissionConfig;
use fleet_mission::instrument::MissionClock;
use fleet_mission::protocol::VehicleKind;
use hetfleet_tests::GroundStation;
use mavlink::dialects::common::MavMessage;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::collections::{BTreeMap, BTreeSet};
use std::io::Write;
use std::sync::{Arc, Mutex};

struct Args {
    mission: std::path::PathBuf,
    gcs_port: u16,
    send: Vec<(String, String)>,
    seed: u64,
    log: std::path::PathBuf,
}

fn args() -> Args {
    let mut a = Args {
        mission: "".into(),
        gcs_port: 0,
        send: vec![],
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
            "--send" => {
                let (id, addr) = v.split_once('=').expect("--send ID=ADDR:PORT");
                a.send.push((id.into(), addr.into()));
            }
            other => panic!("unknown argument {other}"),
        }
    }
    a
}

fn main() {
    let a = args();
    let mission = MissionConfig::load(Some(&a.mission)).expect("the mission");
    let truth = mission.truth(|_| {}).expect("the truth");
    let (grid, frames) = mission.workspace(&truth).expect("the workspace");
    let clock = mission.clock().expect("a mission with [time]");
    let site = mission.mavlink.site(&grid);
    let schedule = mission.schedule(frames);
    let sampling: BTreeSet<u64> = (0..schedule.epochs())
        .flat_map(|e| schedule.sample_steps(VehicleKind::Boat, e))
        .map(|k| k as u64)
        .collect();
    let sysids: BTreeMap<u8, String> = a
        .send
        .iter()
        .map(|(id, _)| (mission.sysid(id).expect("a vehicle of the mission"), id.clone()))
        .collect();
    let fixes: Arc<Mutex<BTreeMap<String, (f64, f64)>>> = Arc::default();
    let gcs = GroundStation::listen(a.gcs_port);
    let heard = fixes.clone();
    std::thread::spawn(move || loop {
        if let (h, MavMessage::GLOBAL_POSITION_INT(p)) = gcs.recv() {
            if let Some(id) = sysids.get(&(h.system_id as u8)) {
                heard
                    .lock()
                    .unwrap()
                    .insert(id.clone(), (p.lat as f64 / 1e7, p.lon as f64 / 1e7));
            }
        }
    });
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("a socket");
    let mut log = std::fs::File::create(&a.log).expect("the log");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
    let noise = Normal::new(0.0, mission.team.boat_sigma).expect("a noise");
    let mut sent: BTreeSet<(u64, String)> = BTreeSet::new();
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
        for (id, addr) in &a.send {
            let due = sampling.contains(&k) && now >= t && !sent.contains(&(k, id.clone()));
            let Some(&(lat, lon)) = fixes.lock().unwrap().get(id).filter(|_| due) else {
                continue;
            };
            let (x, y) = site.grid_of(&site.ned_of_global(lat, lon, site.origin[2]));
            let Some(here) = grid.cell_at(x, y) else { continue };
            let mut lines = String::new();
            for c in grid.disk(here, mission.team.radius) {
                let value = truth.snapshots[(c, k as usize)] + noise.sample(&mut rng);
                let (cx, cy) = grid.centre_m(grid.cell(c));
                let (lat, lon, _) = site.global_of(&site.ned_of((cx, cy), 0.0));
                let reading = serde_json::json!({"t": t, "lat": lat, "lon": lon, "value": value,
                    "sigma": mission.team.boat_sigma});
                lines.push_str(&format!("{reading}\n"));
                let entry = serde_json::json!({"vehicle": id, "step": k, "cell": c, "value": value});
                writeln!(log, "{entry}").expect("logging");
            }
            socket.send_to(lines.as_bytes(), addr).expect("sending");
            sent.insert((k, id.clone()));
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}
