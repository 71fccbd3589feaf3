//! A fence breach as ArduPilot shows it: a rover driven out of its fence changes mode by its
//! `FENCE_ACTION` without a word, and reports the breach in FENCE_STATUS. The bridge must read
//! that, take the vehicle out of the allocation with the reason, and put it back only when the
//! autopilot is GUIDED and inside again.

use fleet_math::grid::Grid;
use fleet_mission::config::MavlinkConfig;
use mavlink::dialects::ardupilotmega::*;
use mavlink::MavHeader;
use nalgebra::Vector3;
use std::net::UdpSocket;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};
use vehicles::autopilot::modes::{Control, Frame};
use vehicles::autopilot::serve;
use vehicles::autopilot::sim::{SimAutopilot, SimSpec};
use vehicles::bridge::{Bridge, BridgeSpec};
use vehicles::link::frame_bytes;

const GCS: MavHeader = MavHeader {
    system_id: 255,
    component_id: 190,
    sequence: 0,
};

fn wait_for(what: &str, secs: f64, mut cond: impl FnMut() -> bool) -> Duration {
    let start = Instant::now();
    while !cond() {
        assert!(start.elapsed().as_secs_f64() < secs, "{what}: not within {secs} s");
        std::thread::sleep(Duration::from_millis(10));
    }
    start.elapsed()
}

fn param_set(name: &str, value: f32) -> Vec<u8> {
    frame_bytes(
        GCS,
        &MavMessage::PARAM_SET(PARAM_SET_DATA {
            param_value: value,
            target_system: 7,
            target_component: 1,
            param_id: name.into(),
            param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
        }),
    )
}

#[test]
fn a_boat_driven_out_of_its_fence_leaves_the_allocation_and_comes_back_guided_and_inside() {
    let m = MavlinkConfig::default();
    let site = m.site(&Grid::new(24, 48, 1.0).unwrap());
    let mut vehicle = SimSpec::from_config(Frame::Boat, 7, site, &m);
    vehicle.speedup = 4.0;
    let port = UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let stop = Arc::new(AtomicBool::new(false));
    let launch = Vector3::new(12.0, 12.0, 0.0);
    serve::spawn(
        &format!("udpin:127.0.0.1:{port}"),
        SimAutopilot::new(vehicle.clone(), launch),
        None,
        stop.clone(),
    )
    .unwrap();
    let spec = BridgeSpec {
        acceptance_m: 1.0,
        heartbeat_timeout: Duration::from_secs(3),
        home: launch,
        // A 40 m square (east, north) with the launch point inside as the rally point.
        fence_m: vec![[0.0, 0.0], [40.0, 0.0], [40.0, 40.0], [0.0, 40.0]],
        rally: vec![launch],
        ready_timeout: Duration::from_secs(20),
        ..BridgeSpec::plain(vehicle)
    };
    let mut bridge = Bridge::connect(&format!("udpout:127.0.0.1:{port}"), spec, None).unwrap();
    wait_for("the boat is driven (fence confirmed, GUIDED, armed)", 30.0, || {
        bridge.status().guided
    });

    // The fault: a 5 m/s push to the south, more than the boat's 2 m/s, out over the fence's
    // southern edge (north = 0).
    bridge.from_gcs(&param_set("SIM_WIND_DIR", 0.0)).unwrap();
    bridge.from_gcs(&param_set("SIM_WIND_SPD", 5.0)).unwrap();
    wait_for("the boat is outside", 30.0, || {
        bridge.state().ned.is_some_and(|p| p.x < 0.0)
    });
    // FENCE_STATUS comes once a second: out of the allocation within two, with the reason.
    let within = wait_for("left out with the reason", 2.5, || {
        let s = bridge.status();
        !s.guided && s.failsafe.as_deref().is_some_and(|f| f.starts_with("fence breach"))
    });
    println!("left out {:.2} s after the boat was seen outside", within.as_secs_f64());
    assert_eq!(bridge.status().mode, "RTL", "FENCE_ACTION = 1 took it to RTL");

    // The push ends; RTL brings it inside. Still out: the autopilot is not GUIDED.
    bridge.from_gcs(&param_set("SIM_WIND_SPD", 0.0)).unwrap();
    wait_for("back inside", 30.0, || bridge.state().breach.is_none());
    let s = bridge.status();
    assert!(!s.guided, "inside but in {}: still out of the allocation", s.mode);
    assert!(
        s.failsafe
            .as_deref()
            .is_some_and(|f| f.contains("left GUIDED for RTL by itself")),
        "{s:?}"
    );

    // The operator puts it back in GUIDED: in the allocation again, no reason left.
    let guided = frame_bytes(
        GCS,
        &MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_DO_SET_MODE,
            param1: 1.0,
            param2: Frame::Boat.mode(Control::Guided) as f32,
            target_system: 7,
            target_component: 1,
            ..Default::default()
        }),
    );
    bridge.from_gcs(&guided).unwrap();
    wait_for("back in the allocation", 5.0, || bridge.status().guided);
    assert_eq!(bridge.status().failsafe, None);
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
}
