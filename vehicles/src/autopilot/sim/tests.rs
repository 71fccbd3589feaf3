//! The simulated autopilot against what ArduPilot does, message by message.

use super::*;
use fleet_math::grid::Grid;
use fleet_mission::config::MavlinkConfig;
use fleet_mission::site::Site;

fn sim(frame: Frame) -> SimAutopilot {
    let site = MavlinkConfig::default().site(&Grid::new(48, 96, 1.0).unwrap());
    let spec = SimSpec {
        frame,
        sysid: 3,
        site,
        max_speed: 2.0,
        turn_rate: PI / 2.0,
        cruise_alt: 30.0,
        turn_radius: 0.0,
        wp_radius: 0.0,
        gps_delay_s: 0.0,
        disarm_delay_s: 10.0,
        speedup: 1.0,
        safety: Default::default(),
        wind: Default::default(),
    };
    SimAutopilot::new(spec, Vector3::zeros())
}

const GCS: MavHeader = MavHeader {
    system_id: 255,
    component_id: 190,
    sequence: 0,
};

fn long(command: MavCmd, p1: f32, p2: f32) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        command,
        param1: p1,
        param2: p2,
        target_system: 3,
        target_component: 1,
        ..Default::default()
    })
}

fn results(out: &[MavMessage]) -> Vec<MavResult> {
    out.iter()
        .filter_map(|m| {
            if let MavMessage::COMMAND_ACK(a) = m {
                Some(a.result)
            } else {
                None
            }
        })
        .collect()
}

#[test]
fn home_parameters_and_the_fence_bit_answer_as_ardupilot_does() {
    let mut s = sim(Frame::Boat);
    // Home: acked, then HOME_POSITION at the boot place (the site's origin here).
    s.handle(&GCS, &long(MavCmd::MAV_CMD_GET_HOME_POSITION, 0.0, 0.0));
    let out = s.take();
    assert_eq!(results(&out), vec![MavResult::MAV_RESULT_ACCEPTED]);
    let Some(MavMessage::HOME_POSITION(h)) = out.get(1) else {
        panic!("no HOME_POSITION after the ack: {out:?}")
    };
    let [lat, lon, _] = s.spec.site.origin;
    assert_eq!(
        (h.latitude, h.longitude),
        ((lat * 1e7).round() as i32, (lon * 1e7).round() as i32)
    );
    s.handle(
        &GCS,
        &long(MavCmd::MAV_CMD_REQUEST_MESSAGE, HOME_POSITION_DATA::ID as f32, 0.0),
    );
    assert!(matches!(s.take().get(1), Some(MavMessage::HOME_POSITION(_))));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_REQUEST_MESSAGE, 33.0, 0.0));
    assert_eq!(results(&s.take()), vec![MavResult::MAV_RESULT_UNSUPPORTED]);

    // The whole list, each value what the simulation uses, counted and indexed.
    s.handle(
        &GCS,
        &MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA {
            target_system: 3,
            target_component: 1,
        }),
    );
    let values: Vec<PARAM_VALUE_DATA> = s
        .take()
        .into_iter()
        .filter_map(|m| {
            if let MavMessage::PARAM_VALUE(v) = m {
                Some(v)
            } else {
                None
            }
        })
        .collect();
    let named = |n: &str| {
        values
            .iter()
            .find(|v| v.param_id.to_str().unwrap() == n)
            .unwrap_or_else(|| panic!("no {n} in {values:?}"))
            .param_value
    };
    assert_eq!(values.len(), 14);
    assert!(values
        .iter()
        .enumerate()
        .all(|(i, v)| v.param_index as usize == i && v.param_count == 14));
    assert!(
        values
            .windows(2)
            .all(|w| w[0].param_id.to_str().unwrap() < w[1].param_id.to_str().unwrap()),
        "sorted by name, as ArduPilot lists them"
    );
    assert_eq!(
        (named("CRUISE_SPEED"), named("MAV_SYSID"), named("FENCE_ENABLE")),
        (2.0, 3.0, 0.0)
    );
    assert!((named("ATC_STR_RAT_MAX") - 90.0).abs() < 1e-4);
    // A set takes effect in the simulation and is echoed; a bad or read-only one is not taken.
    let set = |name: &str, v: f32| {
        MavMessage::PARAM_SET(PARAM_SET_DATA {
            param_value: v,
            target_system: 3,
            target_component: 1,
            param_id: name.into(),
            param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
        })
    };
    s.handle(&GCS, &set("CRUISE_SPEED", 3.5));
    assert!(matches!(s.take().as_slice(), [MavMessage::PARAM_VALUE(v)] if v.param_value == 3.5));
    assert_eq!(s.spec.max_speed, 3.5);
    for (name, v, now) in [
        ("CRUISE_SPEED", -1.0, 3.5),
        ("MAV_SYSID", 9.0, 3.0),
        ("FENCE_ENABLE", 0.5, 0.0),
        ("FENCE_ACTION", 7.0, 1.0),
    ] {
        s.handle(&GCS, &set(name, v));
        assert!(
            matches!(s.take().as_slice(), [MavMessage::PARAM_VALUE(p)] if p.param_value == now),
            "{name}"
        );
    }
    s.handle(&GCS, &set("NO_SUCH_PARAM", 1.0));
    assert!(s.take().is_empty());
    let read = |index: i16, name: &str| {
        MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
            param_index: index,
            target_system: 3,
            target_component: 1,
            param_id: name.into(),
        })
    };
    s.handle(&GCS, &read(-1, "CRUISE_SPEED"));
    s.handle(&GCS, &read(8, ""));
    let got: Vec<String> = s
        .take()
        .into_iter()
        .filter_map(|m| {
            if let MavMessage::PARAM_VALUE(v) = m {
                Some(v.param_id.to_str().unwrap().to_string())
            } else {
                None
            }
        })
        .collect();
    assert_eq!(got, ["CRUISE_SPEED", "MAV_SYSID"]);
    // ArduPilot 4.7 renamed SYSID_THISMAV to MAV_SYSID and answers no read of the old name.
    s.handle(&GCS, &read(-1, "SYSID_THISMAV"));
    assert!(s.take().is_empty(), "the old name is not answered");

    // No fence breach: the geofence health bit is set.
    let MavMessage::SYS_STATUS(st) = s.sys_status() else {
        panic!()
    };
    assert!(st
        .onboard_control_sensors_health
        .contains(MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE));
}

#[test]
fn a_boat_arms_goes_guided_and_reaches_its_target_within_its_limits() {
    let mut s = sim(Frame::Boat);
    s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 15.0));
    assert_eq!(results(&s.take()), [MavResult::MAV_RESULT_ACCEPTED; 2]);
    // Behind it (heading north, goal south-east): it must turn first.
    let goal = Vector3::new(-6.0, 8.0, 5.0);
    let target = SET_POSITION_TARGET_LOCAL_NED_DATA {
        x: goal.x as f32,
        y: goal.y as f32,
        z: goal.z as f32,
        target_system: 3,
        coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
        ..Default::default()
    };
    s.handle(&GCS, &MavMessage::SET_POSITION_TARGET_LOCAL_NED(target));
    let mut t = 0.0;
    let mut last = s.pos;
    let mut last_heading = s.heading;
    while s.pos.xy() != goal.xy() && t < 30.0 {
        s.step(0.05);
        t += 0.05;
        assert!((s.pos - last).norm() <= 2.0 * 0.05 + 1e-9, "speed limit");
        assert!(
            wrap(s.heading - last_heading).abs() <= PI / 2.0 * 0.05 + 1e-9,
            "turn-rate limit"
        );
        assert_eq!(s.pos.z, 0.0, "a boat stays on the surface");
        (last, last_heading) = (s.pos, s.heading);
    }
    // 10 m at 2 m/s, plus the turn: more than 5 s, well under 30.
    assert!(t > 5.0 && t < 30.0, "took {t} s");
}

#[test]
fn an_unarmed_or_held_vehicle_does_not_move_and_unknown_commands_are_unsupported() {
    let mut s = sim(Frame::Multirotor);
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 4.0));
    s.handle(
        &GCS,
        &MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
            x: 10.0,
            target_system: 3,
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
            ..Default::default()
        }),
    );
    s.step(1.0);
    assert_eq!(s.pos, Vector3::zeros(), "disarmed");
    s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 0.0, 0.0));
    s.step(1.0);
    assert_eq!(s.pos, Vector3::zeros(), "held");
    assert_eq!(s.role(), Some(Control::Hold));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 1.0, 0.0));
    assert_eq!(s.role(), Some(Control::Guided));
    s.take();
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 99.0));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_GRIPPER, 0.0, 0.0));
    assert_eq!(
        results(&s.take()),
        [MavResult::MAV_RESULT_DENIED, MavResult::MAV_RESULT_UNSUPPORTED]
    );
    // Another system's command is not ours.
    let mut other = long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 0.0);
    *other.target_system_id_mut().unwrap() = 4;
    s.handle(&GCS, &other);
    assert!(s.armed && s.take().is_empty());
}

#[test]
fn a_mission_uploads_with_the_handshake_runs_and_reports_each_item() {
    let mut s = sim(Frame::Boat);
    // ArduRover's defaults: items reached within WP_RADIUS, turns on TURN_RADIUS under way.
    (s.spec.wp_radius, s.spec.turn_radius) = (2.0, 0.9);
    let site = s.spec.site;
    s.handle(
        &GCS,
        &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: 5,
            target_system: 3,
            target_component: 1,
            ..Default::default()
        }),
    );
    // Home (never flown), a waypoint, a speed change to 4 m/s, two more waypoints.
    let wps = [(99.0, 99.0), (5.0, 0.0), (f64::NAN, 4.0), (5.0, 5.0), (0.0, 5.0)];
    for (seq, (n, e)) in wps.iter().enumerate() {
        let out = s.take();
        assert!(
            matches!(&out[..], [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == seq as u16 && r.target_system == 255),
            "{out:?}"
        );
        if n.is_nan() {
            let speed = MISSION_ITEM_INT_DATA {
                seq: seq as u16,
                command: MavCmd::MAV_CMD_DO_CHANGE_SPEED,
                param2: *e as f32,
                target_system: 3,
                ..Default::default()
            };
            s.handle(&GCS, &MavMessage::MISSION_ITEM_INT(speed));
            continue;
        }
        let (lat, lon, _) = site.global_of(&Vector3::new(*n, *e, 0.0));
        let item = MISSION_ITEM_INT_DATA {
            seq: seq as u16,
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            x: (lat * 1e7).round() as i32,
            y: (lon * 1e7).round() as i32,
            target_system: 3,
            autocontinue: 1,
            ..Default::default()
        };
        s.handle(&GCS, &MavMessage::MISSION_ITEM_INT(item));
    }
    assert!(
        matches!(&s.take()[..], [MavMessage::MISSION_ACK(a)] if a.mavtype == MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 10.0));
    let mut reached = vec![];
    for _ in 0..2000 {
        s.step(0.05);
        reached.extend(s.take().into_iter().filter_map(|m| {
            if let MavMessage::MISSION_ITEM_REACHED(r) = m {
                Some(r.seq)
            } else {
                None
            }
        }));
    }
    assert_eq!(reached, [1, 3, 4], "the waypoints, from 1 (0 is home)");
    assert!((s.pos - Vector3::new(0.0, 5.0, 0.0)).norm() < 0.05, "{}", s.pos);
    assert_eq!(s.role(), Some(Control::Hold), "holds at the end");
    assert_eq!(s.spec.max_speed, 4.0, "the speed item was done");
    // Download gives the same items back, home as item 0.
    s.handle(
        &GCS,
        &MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            target_system: 3,
            target_component: 1,
            ..Default::default()
        }),
    );
    assert!(matches!(&s.take()[..], [MavMessage::MISSION_COUNT(c)] if c.count == 5));
    s.handle(
        &GCS,
        &MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq: 0,
            target_system: 3,
            target_component: 1,
            ..Default::default()
        }),
    );
    let [lat, lon, _] = site.origin;
    assert!(
        matches!(&s.take()[..], [MavMessage::MISSION_ITEM_INT(i)] if (i.x, i.y) == ((lat * 1e7).round() as i32, (lon * 1e7).round() as i32)),
        "item 0 is home"
    );
}

#[test]
fn return_to_launch_brings_it_home_and_reposition_sends_it_out() {
    let mut s = sim(Frame::Multirotor);
    let site = s.spec.site;
    s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    s.handle(
        &GCS,
        &long(
            MavCmd::MAV_CMD_DO_SET_MODE,
            1.0,
            s.spec.frame.mode(Control::Guided) as f32,
        ),
    );
    let mut takeoff = long(MavCmd::MAV_CMD_NAV_TAKEOFF, 0.0, 0.0);
    if let MavMessage::COMMAND_LONG(c) = &mut takeoff {
        c.param7 = 10.0;
    }
    s.handle(&GCS, &takeoff);
    // DO_REPOSITION by COMMAND_INT (degrees * 1e7) to 40 m north, 30 m east, 20 m up.
    let (lat, lon, _) = site.global_of(&Vector3::new(40.0, 30.0, 0.0));
    let c = COMMAND_INT_DATA {
        command: MavCmd::MAV_CMD_DO_REPOSITION,
        x: (lat * 1e7).round() as i32,
        y: (lon * 1e7).round() as i32,
        z: 20.0,
        target_system: 3,
        ..Default::default()
    };
    s.handle(&GCS, &MavMessage::COMMAND_INT(c));
    assert_eq!(s.role(), Some(Control::Guided));
    for _ in 0..1000 {
        s.step(0.05);
    }
    assert!((s.pos - Vector3::new(40.0, 30.0, -20.0)).norm() < 0.05, "{}", s.pos);
    s.handle(&GCS, &long(MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH, 0.0, 0.0));
    assert_eq!(s.role(), Some(Control::Return));
    for _ in 0..1000 {
        s.step(0.05);
    }
    assert!(
        s.pos.norm() < 0.05 && s.landed && !s.armed,
        "back home, landed and disarmed (ArduCopter's RTL): {}",
        s.pos
    );
    assert!(results(&s.take()).iter().all(|r| *r == MavResult::MAV_RESULT_ACCEPTED));
}

/// ArduPilot's RTL with rally points (`AP_Rally::calc_best_rally_or_home_location`): the
/// nearest of them and of home with `RALLY_INCL_HOME = 1` (its default), of them alone with 0.
#[test]
fn rtl_goes_to_the_nearest_of_the_rally_points_and_home_unless_rally_incl_home_is_0() {
    for (include, want) in [(None, Vector3::zeros()), (Some(0.0), Vector3::new(40.0, 40.0, 0.0))] {
        let mut s = sim(Frame::Boat);
        let site = s.spec.site;
        let rally = [at(&site, MavCmd::MAV_CMD_NAV_RALLY_POINT, 0.0, 40.0, 40.0)];
        assert_eq!(
            upload(&mut s, MavMissionType::MAV_MISSION_TYPE_RALLY, &rally),
            MavMissionResult::MAV_MISSION_ACCEPTED
        );
        if let Some(v) = include {
            s.handle(
                &GCS,
                &MavMessage::PARAM_SET(PARAM_SET_DATA {
                    param_value: v,
                    target_system: 3,
                    target_component: 1,
                    param_id: "RALLY_INCL_HOME".into(),
                    param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
                }),
            );
        }
        s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
        // From 15 m north and east of home: home is nearer than the rally point.
        s.pos = Vector3::new(15.0, 15.0, 0.0);
        s.handle(&GCS, &long(MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH, 0.0, 0.0));
        assert_eq!(s.role(), Some(Control::Return));
        for _ in 0..1000 {
            s.step(0.05);
        }
        assert!(
            (s.pos - want).norm() < 0.05,
            "RALLY_INCL_HOME {include:?}: at {}, not {want}",
            s.pos
        );
    }
}

fn count(n: u16, kind: MavMissionType) -> MavMessage {
    MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: n,
        target_system: 3,
        target_component: 1,
        mission_type: kind,
        ..Default::default()
    })
}

#[test]
fn a_stalled_upload_is_asked_again_each_second_then_cancelled_after_eight() {
    let mut s = sim(Frame::Boat);
    s.handle(&GCS, &count(2, MavMissionType::MAV_MISSION_TYPE_FENCE));
    s.take();
    let (mut asks, mut cancelled, mut said) = (0, false, vec![]);
    // Quarter seconds add up exactly: the eighth ask comes at 8 s, the cancel after.
    for _ in 0..100 {
        s.step(0.25);
        for m in s.take() {
            match m {
                MavMessage::MISSION_REQUEST_INT(r) => asks += usize::from(r.seq == 0),
                MavMessage::MISSION_ACK(a) => {
                    cancelled = a.mavtype == MavMissionResult::MAV_MISSION_OPERATION_CANCELLED
                }
                MavMessage::STATUSTEXT(t) => said.push(t.text.to_str().unwrap_or_default().to_string()),
                _ => {}
            }
        }
    }
    assert_eq!((asks, cancelled), (8, true));
    assert!(said.iter().any(|t| t == "Fence upload timeout"), "{said:?}");
}

#[test]
fn an_upload_follows_ardupilots_rules_for_counts_and_duplicates() {
    let mut s = sim(Frame::Boat);
    let fence = MavMissionType::MAV_MISSION_TYPE_FENCE;
    let site = s.spec.site;
    let cmd = MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION;
    let corners = [(-50.0, -50.0), (-50.0, 50.0), (50.0, 50.0), (50.0, -50.0)];
    let items: Vec<_> = corners
        .iter()
        .enumerate()
        .map(|(seq, &(n, e))| MISSION_ITEM_INT_DATA {
            seq: seq as u16,
            mission_type: fence,
            target_system: 3,
            ..at(&site, cmd, 4.0, n, e)
        })
        .collect();
    let item = |i: usize| MavMessage::MISSION_ITEM_INT(items[i].clone());
    let acks = |out: &[MavMessage]| -> Vec<MavMissionResult> {
        out.iter()
            .filter_map(|m| {
                if let MavMessage::MISSION_ACK(a) = m {
                    Some(a.mavtype)
                } else {
                    None
                }
            })
            .collect()
    };
    s.handle(&GCS, &count(4, fence));
    s.handle(&GCS, &item(0));
    s.handle(&GCS, &item(1));
    // A second count from the same sender starts the upload again at item 0.
    s.handle(&GCS, &count(4, fence));
    assert!(matches!(s.take().last(), Some(MavMessage::MISSION_REQUEST_INT(r)) if r.seq == 0));
    s.handle(&GCS, &item(0));
    // A duplicate (and an item ahead) are answered INVALID_SEQUENCE; the upload stays open.
    s.handle(&GCS, &item(0));
    s.handle(&GCS, &item(3));
    use MavMissionResult::*;
    assert_eq!(
        acks(&s.take()),
        [MAV_MISSION_INVALID_SEQUENCE, MAV_MISSION_INVALID_SEQUENCE]
    );
    // Someone else's count, and a read-back, while it is open: DENIED.
    let other = MavHeader { system_id: 254, ..GCS };
    s.handle(&other, &count(1, fence));
    s.handle(
        &GCS,
        &MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            mission_type: fence,
            ..Default::default()
        }),
    );
    assert_eq!(acks(&s.take()), [MAV_MISSION_DENIED, MAV_MISSION_DENIED]);
    for i in 1..4 {
        s.handle(&GCS, &item(i));
    }
    assert_eq!(acks(&s.take()), [MAV_MISSION_ACCEPTED]);
    assert_eq!(s.fence_items.len(), 4);
}

/// Upload `items` of `kind` with the handshake; the ack's result.
fn upload(s: &mut SimAutopilot, kind: MavMissionType, items: &[MISSION_ITEM_INT_DATA]) -> MavMissionResult {
    s.handle(
        &GCS,
        &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: items.len() as u16,
            target_system: 3,
            target_component: 1,
            mission_type: kind,
            ..Default::default()
        }),
    );
    for _ in 0..=items.len() {
        for m in s.take() {
            match m {
                MavMessage::MISSION_REQUEST_INT(r) => {
                    assert_eq!(r.mission_type, kind);
                    let item = MISSION_ITEM_INT_DATA {
                        seq: r.seq,
                        target_system: 3,
                        mission_type: kind,
                        ..items[r.seq as usize].clone()
                    };
                    s.handle(&GCS, &MavMessage::MISSION_ITEM_INT(item));
                }
                MavMessage::MISSION_ACK(a) => {
                    assert_eq!(a.mission_type, kind);
                    return a.mavtype;
                }
                _ => {}
            }
        }
    }
    panic!("no MISSION_ACK");
}

fn at(site: &Site, command: MavCmd, param1: f32, north: f64, east: f64) -> MISSION_ITEM_INT_DATA {
    let (lat, lon, _) = site.global_of(&Vector3::new(north, east, 0.0));
    MISSION_ITEM_INT_DATA {
        command,
        param1,
        frame: MavFrame::MAV_FRAME_GLOBAL_INT,
        x: (lat * 1e7).round() as i32,
        y: (lon * 1e7).round() as i32,
        ..Default::default()
    }
}

#[test]
fn an_enforced_fence_refuses_targets_outside_and_a_breach_returns_to_the_nearest_rally_point() {
    let mut s = sim(Frame::Boat);
    let site = s.spec.site;
    // A 40 m x 40 m square fence (north, east from 0 to 40) and two rally points.
    let corners = [(0.0, 0.0), (0.0, 40.0), (40.0, 40.0), (40.0, 0.0)];
    let fence: Vec<_> = corners
        .iter()
        .map(|&(n, e)| at(&site, MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 4.0, n, e))
        .collect();
    assert_eq!(
        upload(&mut s, MavMissionType::MAV_MISSION_TYPE_FENCE, &fence),
        MavMissionResult::MAV_MISSION_ACCEPTED
    );
    let rally = [
        at(&site, MavCmd::MAV_CMD_NAV_RALLY_POINT, 0.0, 2.0, 2.0),
        at(&site, MavCmd::MAV_CMD_NAV_RALLY_POINT, 0.0, 30.0, 35.0),
    ];
    assert_eq!(
        upload(&mut s, MavMissionType::MAV_MISSION_TYPE_RALLY, &rally),
        MavMissionResult::MAV_MISSION_ACCEPTED
    );
    // A mission item is no fence, and the mission list is not touched by either upload.
    let wp = at(&site, MavCmd::MAV_CMD_NAV_WAYPOINT, 0.0, 0.0, 0.0);
    assert_eq!(
        upload(
            &mut s,
            MavMissionType::MAV_MISSION_TYPE_FENCE,
            std::slice::from_ref(&wp)
        ),
        MavMissionResult::MAV_MISSION_UNSUPPORTED
    );
    assert!(s.mission.is_empty() && s.fence_items.len() == 4 && s.rally.len() == 2);
    // Each list downloads by its type.
    s.handle(
        &GCS,
        &MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            target_system: 3,
            target_component: 1,
            mission_type: MavMissionType::MAV_MISSION_TYPE_FENCE,
        }),
    );
    assert!(
        matches!(&s.take()[..], [MavMessage::MISSION_COUNT(c)] if c.count == 4 && c.mission_type == MavMissionType::MAV_MISSION_TYPE_FENCE)
    );

    // Not yet enforced: a target outside is taken.
    s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 15.0));
    s.take();
    let target = |n: f32, e: f32| {
        MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
            x: n,
            y: e,
            target_system: 3,
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
            ..Default::default()
        })
    };
    s.handle(&GCS, &target(60.0, 10.0));
    assert_eq!(s.goal.map(|g| g.x), Some(60.0));
    // Enforced: a rover takes a target outside (ArduRover does; the breach then acts), one
    // inside too, and a reposition outside is denied.
    let set = |name: &str, v: f32| {
        MavMessage::PARAM_SET(PARAM_SET_DATA {
            param_value: v,
            target_system: 3,
            target_component: 1,
            param_id: name.into(),
            param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
        })
    };
    s.handle(&GCS, &set("FENCE_ENABLE", 1.0));
    s.handle(&GCS, &target(10.0, 50.0));
    assert_eq!(s.goal.map(|g| (g.x, g.y)), Some((10.0, 50.0)));
    s.handle(&GCS, &target(10.0, 20.0));
    assert_eq!(s.goal.map(|g| (g.x, g.y)), Some((10.0, 20.0)));
    // A copter ignores one outside without a word, and fails a reposition there.
    let mut c = sim(Frame::Multirotor);
    c.fence = s.fence.clone();
    c.spec.safety.fence_enable = true;
    c.goal = Some(Vector3::new(10.0, 20.0, -30.0));
    c.take();
    c.handle(&GCS, &target(10.0, 50.0));
    assert_eq!(c.goal.map(|g| (g.x, g.y)), Some((10.0, 20.0)));
    assert!(c.take().is_empty(), "no answer");
    let (lat, lon, _) = site.global_of(&Vector3::new(10.0, 50.0, 0.0));
    let far = COMMAND_INT_DATA {
        command: MavCmd::MAV_CMD_DO_REPOSITION,
        x: (lat * 1e7).round() as i32,
        y: (lon * 1e7).round() as i32,
        target_system: 3,
        ..Default::default()
    };
    c.handle(&GCS, &MavMessage::COMMAND_INT(far.clone()));
    assert_eq!(results(&c.take()), [MavResult::MAV_RESULT_FAILED]);
    s.handle(&GCS, &MavMessage::COMMAND_INT(far));
    assert_eq!(results(&s.take()), [MavResult::MAV_RESULT_DENIED]);
    let MavMessage::SYS_STATUS(st) = s.sys_status() else {
        panic!()
    };
    assert!(
        st.onboard_control_sensors_enabled
            .contains(MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE)
            && st
                .onboard_control_sensors_health
                .contains(MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE)
    );

    // A mission that leaves the fence (an operator's, in AUTO): breach, RTL to the nearer
    // rally point; the health bit drops while outside, and FENCE_STATUS counts it.
    let out_wp = at(&site, MavCmd::MAV_CMD_NAV_WAYPOINT, 0.0, 30.0, 60.0);
    assert_eq!(
        upload(&mut s, MavMissionType::MAV_MISSION_TYPE_MISSION, &[wp, out_wp]),
        MavMissionResult::MAV_MISSION_ACCEPTED
    );
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 10.0));
    let mut said = vec![];
    let mut unhealthy = false;
    for _ in 0..1200 {
        s.step(0.05);
        said.extend(s.take().into_iter().filter_map(|m| {
            if let MavMessage::STATUSTEXT(t) = m {
                Some(t.text.to_str().unwrap().to_string())
            } else {
                None
            }
        }));
        if let MavMessage::SYS_STATUS(st) = s.sys_status() {
            unhealthy |= !st
                .onboard_control_sensors_health
                .contains(MavSysStatusSensor::MAV_SYS_STATUS_GEOFENCE);
        }
    }
    assert_eq!(s.role(), Some(Control::Return));
    // A rover breaches in silence, as ArduRover does: FENCE_STATUS and the mode tell.
    assert!(!said.iter().any(|t| t.contains("reach")), "{said:?}");
    assert!(unhealthy && !s.breached, "unhealthy while outside, then back inside");
    assert!(
        (s.pos.xy() - Vector3::new(30.0, 35.0, 0.0).xy()).norm() < 0.05,
        "at the nearer rally point: {}",
        s.pos
    );
    assert!(
        matches!(s.fence_status(), Some(MavMessage::FENCE_STATUS(f)) if f.breach_count == 1 && f.breach_status == 0)
    );
}

#[test]
fn the_battery_drains_with_use_and_running_low_takes_it_home_once() {
    let mut s = sim(Frame::Boat);
    // 100 mAh above the 4,000 mAh low mark.
    s.spec.safety.battery_start_mah = Some(4_100.0);
    s = SimAutopilot::new(s.spec.clone(), Vector3::new(1.0, 1.0, 0.0));
    let battery = |s: &SimAutopilot| {
        if let MavMessage::SYS_STATUS(st) = s.sys_status() {
            (st.battery_remaining, st.current_battery)
        } else {
            panic!()
        }
    };
    assert_eq!(battery(&s), (21, 5), "20.5 % left, 0.05 A disarmed");
    // Disarmed for a simulated hour: 50 mAh at 0.05 A.
    s.step(3600.0);
    assert!((s.consumed_mah - (15_900.0 + 50.0)).abs() < 1e-6, "{}", s.consumed_mah);
    assert!(s.failsafe.is_none(), "no failsafe disarmed");
    // Armed, driving away at full speed: 10 A, so 50 mAh take 18 s.
    s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 15.0));
    let target = SET_POSITION_TARGET_LOCAL_NED_DATA {
        x: 40.0,
        y: 1.0,
        target_system: 3,
        coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
        ..Default::default()
    };
    s.handle(&GCS, &MavMessage::SET_POSITION_TARGET_LOCAL_NED(target));
    s.take();
    let mut t = 0.0;
    while s.failsafe.is_none() && t < 60.0 {
        s.step(0.05);
        t += 0.05;
    }
    assert!((17.5..19.5).contains(&t), "ran low after {t} s");
    assert_eq!(s.role(), Some(Control::Return));
    let said = s.take();
    assert!(
        said.iter().any(|m| matches!(m, MavMessage::STATUSTEXT(x) if x.text.to_str().unwrap().starts_with("Failsafe: battery low") && x.severity == MavSeverity::MAV_SEVERITY_CRITICAL)),
        "{said:?}"
    );
    assert!(matches!(s.heartbeat(), MavMessage::HEARTBEAT(h) if h.system_status == MavState::MAV_STATE_CRITICAL));
    assert_eq!(battery(&s).0, 20);
    // Home, at the launch point; said once.
    for _ in 0..1000 {
        s.step(0.05);
    }
    assert!(
        (s.pos.xy() - Vector3::new(1.0, 1.0, 0.0).xy()).norm() < 0.05,
        "{}",
        s.pos
    );
    assert!(!s.take().iter().any(|m| matches!(m, MavMessage::STATUSTEXT(_))));
}

#[test]
fn readiness_the_ekf_origin_the_fence_margin_and_a_copters_takeoff_are_ardupilots() {
    // A boat booted 30 m east of the site's corner with a 20 s GPS delay: no position and no
    // arming before the fix, then its local frame is from where it booted.
    let mut s = sim(Frame::Boat);
    s.spec.gps_delay_s = 20.0;
    let mut s = SimAutopilot::new(s.spec.clone(), Vector3::new(3.0, 30.0, 0.0));
    assert!(s.position().is_empty() && s.arming_refusal().as_deref() == Some("Need Position Estimate"));
    s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    assert_eq!(results(&s.take()), vec![MavResult::MAV_RESULT_FAILED]);
    assert!(!s.armed);
    // Said as ArduPilot says a failing check: at once, then every 30 s while it fails.
    let prearm = |s: &mut SimAutopilot| {
        s.take()
            .iter()
            .filter(|m| matches!(m, MavMessage::STATUSTEXT(t) if t.text.to_str().unwrap() == "PreArm: Need Position Estimate"))
            .count()
    };
    s.step(0.1);
    assert_eq!(prearm(&mut s), 1);
    s.step(19.0);
    assert!(!s.has_fix());
    assert_eq!(prearm(&mut s), 0, "not again within 30 s");
    s.step(1.5);
    assert!(
        !s.take().iter().any(|m| matches!(m, MavMessage::GPS_GLOBAL_ORIGIN(_))),
        "a rover says its origin only when asked"
    );
    let Some(MavMessage::LOCAL_POSITION_NED(p)) = s.position().get(1).cloned() else {
        panic!("no local position after the fix")
    };
    assert_eq!(
        (p.x, p.y),
        (0.0, 0.0),
        "local NED is from the EKF origin, where it booted"
    );
    assert!(matches!(s.gps_global_origin(), Some(MavMessage::GPS_GLOBAL_ORIGIN(_))));
    // Outside an enforced fence it will not arm.
    let site = s.spec.site;
    let corner = |n: f64, e: f64| {
        let (lat, lon, _) = site.global_of(&Vector3::new(n, e, 0.0));
        MISSION_ITEM_INT_DATA {
            command: MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            param1: 4.0,
            x: (lat * 1e7).round() as i32,
            y: (lon * 1e7).round() as i32,
            ..Default::default()
        }
    };
    s.fence = Geofence::from_items(
        &[
            corner(1.0, 0.0),
            corner(1.0, 100.0),
            corner(50.0, 100.0),
            corner(50.0, 0.0),
        ],
        &site,
    )
    .unwrap();
    s.spec.safety.fence_enable = true;
    s.pos.x = 0.5;
    assert_eq!(s.arming_refusal().as_deref(), Some("Vehicle breaching Polygon fence"));
    // ArduPilot 4.7 arms inside the fence within its margin: a margin breach is recorded only.
    s.pos.x = 1.5;
    assert_eq!(s.arming_refusal(), None, "0.5 m inside, within FENCE_MARGIN 2 m");
    s.take();
    s.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    assert!(s.armed);
    assert!(
        s.take()
            .iter()
            .any(|m| matches!(m, MavMessage::STATUSTEXT(t) if t.text.to_str().unwrap() == "Throttle armed")),
        "a rover says it armed"
    );
    // Under way beside the fence, heading 45 degrees toward it, a goal along it is reached on
    // an arc of TURN_RADIUS: from 0.2 m inside, the arc breaches the fence.
    s.spec.turn_radius = 0.9;
    s.pos = Vector3::new(1.2, 10.0, 0.0);
    s.heading = 135f64.to_radians();
    s.set_mode(s.spec.frame.mode(Control::Guided));
    s.goal = Some(Vector3::new(1.2, 30.0, 0.0));
    s.step(2.0);
    assert!(s.breach_count > 0, "the turning arc crossed the fence");

    // A copter stays on the ground until told to take off, and disarms itself there.
    let mut c = sim(Frame::Multirotor);
    c.handle(
        &GCS,
        &long(
            MavCmd::MAV_CMD_DO_SET_MODE,
            1.0,
            c.spec.frame.mode(Control::Guided) as f32,
        ),
    );
    c.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    c.goal = Some(Vector3::new(20.0, 20.0, -30.0));
    c.step(5.0);
    assert!(
        c.armed && c.pos == Vector3::zeros(),
        "no takeoff: it stays on the ground"
    );
    c.step(6.0);
    assert!(!c.armed, "armed and idle on the ground past DISARM_DELAY: disarmed");
    c.handle(&GCS, &long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0));
    let mut takeoff = long(MavCmd::MAV_CMD_NAV_TAKEOFF, 0.0, 0.0);
    if let MavMessage::COMMAND_LONG(t) = &mut takeoff {
        t.param7 = 30.0;
    }
    c.take();
    c.handle(&GCS, &takeoff);
    assert_eq!(results(&c.take()), vec![MavResult::MAV_RESULT_ACCEPTED]);
    c.step(20.0);
    assert!(c.armed && (c.pos.z + 30.0).abs() < 1e-6, "at 30 m: {}", c.pos);
}
