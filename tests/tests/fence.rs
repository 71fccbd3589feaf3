//! The site's boundary binds the planner: with a concave fence (an L, from a QGroundControl
//! `.plan`), every disk and every aerial place of a whole `fleet up` mission is inside it, for
//! block QR and for horizon placement; without the fence the same missions sense in its notch.

use fleet_mission::config::MissionConfig;
use fleet_mission::fence::inside;
use fleet_mission::protocol::{Body, Context};
use fleet_mission::site::Site;
use fleet_records::recording::Recording;
use hetfleet_tests::*;
use std::path::Path;

/// The tiny mission's 48 m x 24 m site without its north-east quarter, metres `[east, north]`.
const ELL: [[f64; 2]; 6] = [
    [0.0, 0.0],
    [48.0, 0.0],
    [48.0, 12.0],
    [24.0, 12.0],
    [24.0, 24.0],
    [0.0, 24.0],
];

/// Every plan the server handed out in the mission at `dir` (from its recording): per target,
/// its position (grid metres) and cells.
fn planned(run_dir: &Path) -> Vec<([f64; 2], Vec<u32>, String)> {
    let rec = Recording::read(&run_dir.join("recording.mcap")).unwrap();
    let mut ctx = Context::new(rec.grid);
    ctx.vehicles = rec.mission.vehicles().into_iter().map(|v| v.id).collect();
    rec.messages
        .iter()
        .filter(|m| m.topic.contains("/plan/"))
        .flat_map(|m| match fleet_mission::protocol::decode(&m.data, &ctx).unwrap() {
            Body::Plan(p) => p
                .targets
                .into_iter()
                .map(move |t| (t.position, t.cells, p.vehicle.to_string()))
                .collect::<Vec<_>>(),
            other => panic!("a plan reply that is not a plan: {other:?}"),
        })
        .collect()
}

fn fleet_up(mission: &Path, out: &Path) {
    let o = run(
        "fleet",
        &["up", mission.to_str().unwrap(), "--out", out.to_str().unwrap()],
    );
    assert!(o.status.success(), "fleet up: {}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn a_concave_fence_keeps_every_disk_and_aerial_place_inside_for_qr_and_horizon() {
    let dir = scratch("fence");
    let m = MissionConfig::load(Some(&root().join("config/mission-tiny.toml"))).unwrap();
    let site = Site {
        origin: m.mavlink.origin,
        scale: nalgebra::Vector2::new(1.0, 1.0),
    };
    let latlon: Vec<[f64; 2]> = ELL
        .iter()
        .map(|[e, n]| {
            let (lat, lon, _) = site.global_of(&site.ned_of((*e, *n), 0.0));
            [lat, lon]
        })
        .collect();
    let plan = serde_json::json!({"fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
        "geoFence": {"version": 2, "circles": [], "polygons": [{"inclusion": true, "version": 1, "polygon": latlon}]}});
    std::fs::write(dir.join("site.plan"), serde_json::to_string_pretty(&plan).unwrap()).unwrap();
    for placement in ["qr", "horizon"] {
        for fenced in [true, false] {
            let ep = vec![format!("tcp/127.0.0.1:{}", free_port())];
            let case = dir.join(format!("{placement}-{fenced}"));
            std::fs::create_dir_all(&case).unwrap();
            let mission = tiny_mission(&case, &ep, &ep);
            edit(&mission, "seed = 5", &format!("seed = 5\nplacement = \"{placement}\""));
            if fenced {
                std::fs::copy(dir.join("site.plan"), case.join("site.plan")).unwrap();
                edit(&mission, "[mavlink]\n", "[mavlink]\nboundary = \"site.plan\"\n");
            }
            // What a real ArduPilot does (issue 38): ArduPilot's FENCE_MARGIN (2 m) and a
            // boat's TURN_RADIUS (0.9 m) by default, a WP_RADIUS of 3 m and a GPS fix 20 s after
            // boot; fence action RTL (the default); copters on the ground until told to take off.
            edit(
                &mission,
                "[mavlink]\n",
                "[mavlink]\nwp_radius_m = 3.0\nsim_gps_delay_s = 20.0\n",
            );
            let out = case.join("run");
            fleet_up(&mission, &out);
            let grid = Recording::read(&out.join("recording.mcap")).unwrap().grid;
            let (mut boat_cells, mut in_notch, mut places) = (0, 0, 0);
            for (position, cells, vehicle) in planned(&out) {
                places += 1;
                assert!(
                    !fenced || inside(&ELL, position),
                    "{placement}: {vehicle} sent to {position:?}, outside the fence"
                );
                for c in cells.iter().filter(|_| vehicle.starts_with("boat")) {
                    let (x, y) = grid.centre_m(grid.cell(*c as usize));
                    boat_cells += 1;
                    if !inside(&ELL, [x, y]) {
                        in_notch += 1;
                    }
                }
            }
            println!(
                "{placement}, fenced {fenced}: {places} places, {boat_cells} disk cells, {in_notch} outside the L"
            );
            // Every autopilot took the fence and enforced it, and the ways between places were
            // routed round the notch: no breach, nobody returned to launch or held. Each waited for
            // its fix, armed at the first asking (its launch point clear of the fence's margin),
            // and the copters took off before the planner drove them; none disarmed or was left
            // to the operator.
            for v in m.vehicles() {
                let log = std::fs::read_to_string(out.join(format!("logs/{}.log", v.id))).unwrap();
                // ("PreArm: Need Position Estimate" before the fix is ArduPilot's own word.)
                for bad in [
                    "says: Arm:",
                    "left to the operator",
                    "disarmed in GUIDED",
                    "not ready after",
                ] {
                    assert!(!log.contains(bad), "{placement}: {} said {bad:?}:\n{log}", v.id);
                }
                assert!(
                    log.contains("the planner drives it"),
                    "{placement}: {} never driven:\n{log}",
                    v.id
                );
                // At the end each returns to its launch point (`end_action = "rtl"`).
                assert!(
                    log.contains("the autopilot ends it") && log.contains("mode=\"RTL\""),
                    "{placement}: {} did not end with RTL:\n{log}",
                    v.id
                );
                assert!(
                    log.contains("fence enabled"),
                    "{placement}: {} did not enable the fence:\n{log}",
                    v.id
                );
                assert!(
                    !log.contains("Fence breach"),
                    "{placement}: {} breached the fence:\n{log}",
                    v.id
                );
            }
            let events = std::fs::read_to_string(out.join("events.jsonl")).unwrap();
            assert!(
                !events.contains("\"hold\""),
                "{placement}: a vehicle left the allocation"
            );
            assert!(boat_cells > 0, "{placement}: no disk at all");
            // Every place reached (within the autopilot's WP_RADIUS), so every reading is the
            // planned place's: the networked estimate is the offline loop's.
            let report = std::fs::read_to_string(out.join("report.md")).unwrap();
            assert!(
                report.contains("Network equals offline: **yes"),
                "{placement}: {report}"
            );
            if fenced {
                assert_eq!(in_notch, 0, "{placement}: disk cells outside the fence");
                // The exported QGC plans carry the mission's fence, not the grid's rectangle.
                let o = run(
                    "fleet",
                    &[
                        "export",
                        out.to_str().unwrap(),
                        "--qgc-plan",
                        case.join("next.plan").to_str().unwrap(),
                    ],
                );
                assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
                let doc: serde_json::Value =
                    serde_json::from_slice(&std::fs::read(case.join("next.boat-1.plan")).unwrap()).unwrap();
                let fence: Vec<[f64; 2]> =
                    serde_json::from_value(doc["geoFence"]["polygons"][0]["polygon"].clone()).unwrap();
                assert_eq!(fence.len(), latlon.len());
                for (a, b) in fence.iter().zip(&latlon) {
                    assert!(
                        (a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9,
                        "{a:?} vs {b:?}"
                    );
                }
            } else {
                assert!(
                    in_notch > 0,
                    "{placement}: without the fence no disk touches the notch, so this test could not fail"
                );
            }
        }
    }
    // The launch points (the autopilots' homes and rally points) clear the margin plus the turn,
    // and boat-3's autopilot boots 30 m and more from the grid's corner, where its EKF origin is.
    let m = MissionConfig::load(Some(&dir.join("qr-true/mission.toml"))).unwrap();
    let grid = fleet_math::grid::Grid::new(24, 48, 1.0).unwrap();
    let launch = fleet_mission::launch::launch_points(&m, &grid).unwrap();
    assert!(launch.iter().all(|p| fleet_mission::fence::clearance(&ELL, *p) >= 2.9));
    assert!(launch[4][0].hypot(launch[4][1]) >= 30.0, "{launch:?}");
    // A fence with no room for the margin is refused when the mission is read: one line, exit 2.
    edit(
        &dir.join("qr-true/mission.toml"),
        "[mavlink]\n",
        "[mavlink]\nfence_margin_m = 12.0\n",
    );
    let o = run(
        "fleet",
        &[
            "up",
            dir.join("qr-true/mission.toml").to_str().unwrap(),
            "--out",
            dir.join("narrow").to_str().unwrap(),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("fence_margin_m = 12") && err.contains("no room") && err.trim().lines().count() == 1,
        "{err}"
    );
    // A mission whose boundary file has no geofence is one line, exit 2, naming the file.
    let ep = vec![format!("tcp/127.0.0.1:{}", free_port())];
    let mission = tiny_mission(&dir, &ep, &ep);
    std::fs::write(
        dir.join("nofence.plan"),
        r#"{"fileType": "Plan", "version": 1, "mission": {"items": []}}"#,
    )
    .unwrap();
    edit(&mission, "[mavlink]\n", "[mavlink]\nboundary = \"nofence.plan\"\n");
    let o = run(
        "fleet",
        &[
            "up",
            mission.to_str().unwrap(),
            "--out",
            dir.join("bad").to_str().unwrap(),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("nofence.plan") && err.contains("without a geofence") && err.trim().lines().count() == 1,
        "{err}"
    );
}
