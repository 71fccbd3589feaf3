//! A secured mission (`fleet secure`: user/password, access control, optionally mutual TLS)
//! over real Zenoh sessions: the fleet runs to the end; a session without credentials can
//! neither feed the server nor read the model; a vehicle authenticated as boat-1 cannot publish
//! as boat-2 or read another's plan; a replayed old batch is not assimilated twice.

use fleet_mission::config::MissionConfig;
use fleet_mission::protocol::{self, Body, Context, MeasurementBatch, Noise, Sample, VehicleKind};
use fleet_net::zenoh;
use hetfleet_tests::*;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The tiny mission with its configs from `fleet secure` (and a test CA with `tls`).
fn secure_mission(dir: &Path, tls: bool) -> (PathBuf, PathBuf) {
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = tiny_mission(dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    let secure = dir.join("secure");
    let mut args = vec![
        "secure".to_string(),
        mission.display().to_string(),
        "--out".into(),
        secure.display().to_string(),
    ];
    if tls {
        let ca = dir.join("ca");
        let m = MissionConfig::load(Some(&mission)).unwrap();
        let mut names: Vec<String> = fleet_mission::security::users(&m);
        names.insert(0, ca.display().to_string());
        let o = std::process::Command::new("bash")
            .arg(root().join("scripts/make-test-ca.sh"))
            .args(&names)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        args.extend(["--tls".into(), ca.display().to_string()]);
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = run("fleet", &args);
    assert!(
        o.status.success(),
        "fleet secure: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    edit(
        &mission,
        &format!("connect = [\"{ep}\"]"),
        &format!(
            "connect = [\"{ep}\"]\nserver_config = \"{0}/router.json5\"\nvehicle_config = \"{0}/{{id}}.json5\"",
            secure.display()
        ),
    );
    (mission, secure)
}

/// A client session as `user` (its config from `fleet secure`), or with no credentials at
/// all (`None`, plain TCP to `endpoint`); `None` when the router does not let it in.
async fn session_as(secure: &Path, user: Option<&str>, endpoint: &str) -> Option<zenoh::Session> {
    let mut cfg = match user {
        Some(u) => zenoh::Config::from_file(secure.join(format!("{u}.json5"))).unwrap(),
        None => zenoh::Config::default(),
    };
    if user.is_none() {
        cfg.insert_json5("connect/endpoints", &format!("[\"{endpoint}\"]"))
            .unwrap();
    }
    cfg.insert_json5("mode", "\"client\"").unwrap();
    cfg.insert_json5("scouting/multicast/enabled", "false").unwrap();
    cfg.insert_json5("connect/timeout_ms", "3000").unwrap();
    cfg.insert_json5("connect/exit_on_failure", "true").unwrap();
    zenoh::open(cfg).await.ok()
}

/// Whether a get on `selector` brings back any successful reply.
async fn can_get(s: &zenoh::Session, selector: &str) -> bool {
    let Ok(replies) = s.get(selector).timeout(Duration::from_secs(2)).await else {
        return false;
    };
    let mut ok = false;
    while let Ok(r) = replies.recv_async().await {
        ok |= r.result().is_ok();
    }
    ok
}

async fn put(s: &zenoh::Session, key: &str, bytes: Vec<u8>) {
    s.put(key, bytes).encoding(fleet_net::encoding()).await.unwrap();
}

fn secured_fleet(tls: bool) {
    let dir = scratch(if tls { "sec-tls" } else { "sec" });
    let (mission, secure) = secure_mission(&dir, tls);
    let m = MissionConfig::load(Some(&mission)).unwrap();
    let endpoint = m.network.connect[0].clone();
    let root_key = format!("fleet/{}", m.mission);
    let mp = mission.to_str().unwrap();
    let state = dir.join("state");
    let st = state.to_str().unwrap();
    let mut procs = Procs::default();
    let server = start_server(
        &mut procs,
        &["--mission", mp, "--state-dir", st],
        &dir.join("server.log"),
    );
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let garbage = vec![0xde, 0xad, 0xbe, 0xef];

    // Before the vehicles: an intruder without credentials, then boat-1's credentials misused.
    let (anonymous_in, cross_put) = rt.block_on(async {
        std::thread::sleep(Duration::from_millis(500));
        let anon = session_as(&secure, None, &endpoint).await;
        if let Some(a) = &anon {
            put(a, &format!("{root_key}/vehicle/boat-1/measurements"), garbage.clone()).await;
        }
        let boat1 = session_as(&secure, Some("boat-1"), &endpoint)
            .await
            .expect("boat-1's own credentials let it in");
        // As boat-2: refused by the router's access control, so the server never sees it.
        put(
            &boat1,
            &format!("{root_key}/vehicle/boat-2/measurements"),
            garbage.clone(),
        )
        .await;
        put(&boat1, &format!("{root_key}/model/latest"), garbage.clone()).await;
        // Its own key is open to it: this one arrives and is refused by the server's decoder
        // (the control that shows the channel works).
        put(
            &boat1,
            &format!("{root_key}/vehicle/boat-1/measurements"),
            garbage.clone(),
        )
        .await;
        let cross = can_get(&boat1, &format!("{root_key}/plan/boat-2?epoch=0")).await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        (anon.is_some(), cross)
    });
    assert!(!anonymous_in, "a session without credentials was let in");
    assert!(!cross_put, "boat-1 read boat-2's plan");

    // A vehicle whose password is wrong says so and stops (exit 2) instead of retrying forever.
    let wrong = dir.join("boat-1-wrong.json5");
    std::fs::write(
        &wrong,
        std::fs::read_to_string(secure.join("boat-1.json5"))
            .unwrap()
            .replacen("password\": \"", "password\": \"x", 1),
    )
    .unwrap();
    let o = std::process::Command::new(bin("vehicle"))
        .args([
            "--mission",
            mp,
            "--id",
            "boat-1",
            "--state-dir",
            dir.join("wrong-state").to_str().unwrap(),
            "--zenoh-config",
            wrong.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    let last = err.trim().lines().last().unwrap_or("");
    assert!(
        last.starts_with("vehicle: the router refused this node's session")
            && last.contains("user \"boat-1\"")
            && last.contains("boat-1-wrong.json5"),
        "{err}"
    );

    // The live view joins as the observer (its config from `fleet secure`).
    let view_port = free_port();
    let watch = std::process::Command::new(bin("fleet-watch"))
        .args(["--mission", mp, "--http", &format!("127.0.0.1:{view_port}")])
        .stderr(std::fs::File::create(dir.join("watch.log")).unwrap())
        .spawn()
        .unwrap();
    procs.0.push(watch);
    start_vehicles(&mut procs, &mission, st, &dir, &[]);
    let summary = server.finished(120);
    // What the observer may see, it saw: the model, every vehicle's telemetry and liveliness,
    // the plans, the server's status.
    eventually(10, "the view has the final model", || {
        web_state(view_port).is_some_and(|s| s["model"]["version"].as_u64() == Some(summary.model_version))
    });
    let view = web_state(view_port).unwrap();
    for v in view["vehicles"].as_array().unwrap() {
        assert!(
            v["position"].is_array() && v["link"] != "unseen",
            "the observer saw {}: {v}",
            v["id"]
        );
    }
    assert!(
        !view["plans"].as_array().unwrap().is_empty() && view["server"]["batches"].as_u64() > Some(0),
        "{view}"
    );
    let c = &summary.counters;
    let truth = m.truth(|_| {}).unwrap().expect("a truth");
    assert_eq!(
        c.rejected.values().sum::<u64>(),
        1,
        "only boat-1's garbage on its own key reached the server: {:?}",
        c.rejected
    );
    assert!(
        c.sessions_refused >= 3,
        "the router counted the sessions it refused: {}",
        c.sessions_refused
    );
    let log = std::fs::read_to_string(dir.join("server.log")).unwrap();
    assert!(
        log.contains("a client's password is wrong for its user"),
        "and logged why: {log}"
    );
    assert_eq!(
        c.batches - c.duplicates - 1,
        expected_batches(&m, truth.frames()),
        "the secured fleet ran the whole mission"
    );

    rt.block_on(async {
        let model = format!("{root_key}/model/latest");
        let observer = session_as(&secure, Some("observer"), &endpoint)
            .await
            .expect("the observer gets in");
        assert!(can_get(&observer, &model).await, "the observer reads the model");
        assert!(
            session_as(&secure, None, &endpoint).await.is_none(),
            "no credentials, no session"
        );
        let boat1 = session_as(&secure, Some("boat-1"), &endpoint).await.unwrap();
        assert!(!can_get(&boat1, &model).await, "a vehicle may not query the model");
        // boat-1 replays its first batch (any content under its first seq): a duplicate, not
        // assimilated again, the model unchanged.
        let version = |b: Body| {
            if let Body::Model(u) = b {
                u.version
            } else {
                panic!("not a model")
            }
        };
        let ctx = Context::new(fleet_math::grid::Grid::new(24, 48, 1.0).unwrap());
        let get_version = || async {
            let replies = observer.get(&model).await.unwrap();
            let r = replies.recv_async().await.unwrap();
            version(fleet_net::decode(r.result().unwrap(), &ctx).unwrap())
        };
        let before = get_version().await;
        let status = observer
            .declare_subscriber(format!("{root_key}/server/status"))
            .await
            .unwrap();
        let replay = MeasurementBatch {
            vehicle: "boat-1".parse().unwrap(),
            kind: VehicleKind::Boat,
            seq: 0,
            noise: Noise {
                sigma0: m.team.boat_sigma,
                growth_per_m: 0.0,
            },
            samples: vec![Sample {
                step: 14,
                position: [1.0, 1.0],
                cells: vec![0],
                values: vec![9.0],
                sigma: None,
            }],
        };
        put(
            &boat1,
            &format!("{root_key}/vehicle/boat-1/measurements"),
            protocol::encode(&Body::Batch(replay)),
        )
        .await;
        let mut dup = 0;
        for _ in 0..5 {
            if let Ok(Body::Status(s)) = fleet_net::decode(&status.recv_async().await.unwrap(), &ctx) {
                dup = s.duplicates;
            }
            if dup > c.duplicates {
                break;
            }
        }
        assert_eq!(dup, c.duplicates + 1, "the replay was seen as a duplicate");
        assert_eq!(get_version().await, before, "and not assimilated");
        // A vehicle may not set its own sensor's verdict: the router drops it.
        let trust = fleet_mission::protocol::SensorOverride {
            vehicle: "boat-1".parse().unwrap(),
            from_step: 0,
            set: Some(fleet_mission::protocol::Health::Ok),
        };
        let key = format!("{root_key}/server/sensor/boat-1");
        put(&boat1, &key, protocol::encode(&Body::Override(trust))).await;
        tokio::time::sleep(Duration::from_millis(2500)).await;
        let mut newest = None;
        while let Ok(Some(sample)) = status.try_recv() {
            newest = Some(sample);
        }
        let Ok(Body::Status(s)) = fleet_net::decode(&newest.expect("a status"), &ctx) else {
            panic!("not a status")
        };
        assert_eq!(s.overrides, 0, "a vehicle's override reached the server");
    });
    operator_overrides_a_sensor(mp, &summary);
}

/// The operator, from the ground station's seat (`fleet-operator`, as the gateway's user),
/// excludes boat-1's sensor from step 20: the server takes it and says so in its status, the
/// model is re-fitted (a new version); a vehicle not in the mission is refused (exit 2).
fn operator_overrides_a_sensor(mission: &str, summary: &fleet::mission::report::ServerSummary) {
    let run = |args: &[&str]| {
        std::process::Command::new(bin("fleet-operator"))
            .args(["--mission", mission, "sensor"])
            .args(args)
            .output()
            .unwrap()
    };
    let o = run(&["boat-1", "excluded", "--from-step", "20"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(0), "{out}{}", String::from_utf8_lossy(&o.stderr));
    let version: u64 = out
        .trim()
        .rsplit_once("version ")
        .unwrap()
        .1
        .trim_end_matches(')')
        .parse()
        .unwrap();
    assert!(
        out.contains("its sensor is excluded") && version > summary.model_version,
        "{out}"
    );
    let o = run(&["boat-9", "ok"]);
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn passwords_and_access_control_keep_intruders_out_and_vehicles_in_their_lane() {
    secured_fleet(false);
}

#[test]
fn the_same_over_mutual_tls() {
    secured_fleet(true);
}
