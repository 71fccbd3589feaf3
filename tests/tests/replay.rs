//! A mission's recording replays to the same model: the model server's core run again on the
//! recorded operations (`fleet replay`) gives the recorded final model bit for bit, through a
//! killed and restarted server and boat; a recording cut short is one clear line.

use fleet_mission::config::MissionConfig;
use fleet_records::recording::Recording;
use hetfleet_tests::*;

#[test]
fn a_recording_through_kills_replays_to_the_recorded_model_bit_for_bit() {
    let dir = scratch("replay");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = paced_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep), 60);
    let (m, out, state) = (
        mission.to_str().unwrap().to_string(),
        dir.join("out"),
        dir.join("state"),
    );
    let record = dir.join("recording.mcap");
    let server_args = [
        "--mission",
        &m,
        "--out",
        out.to_str().unwrap(),
        "--state-dir",
        state.to_str().unwrap(),
        "--exit-when-done",
        "--record",
        record.to_str().unwrap(),
    ];
    let mut procs = Procs::default();
    let server = start_server(&mut procs, &server_args, &dir.join("server.log"));
    let vehicle_args = |id: &str| {
        vec![
            "--mission".to_string(),
            m.clone(),
            "--id".into(),
            id.into(),
            "--state-dir".into(),
            state.to_str().unwrap().into(),
        ]
    };
    let start = |procs: &mut Procs, id: &str| {
        start_vehicle(
            procs,
            &[],
            &vehicle_args(id).iter().map(String::as_str).collect::<Vec<_>>(),
            &dir.join(format!("{id}.log")),
        )
    };
    let mut boat2 = 0;
    for v in MissionConfig::load(Some(&mission)).unwrap().vehicles() {
        let i = start(&mut procs, &v.id);
        if v.id == "boat-2" {
            boat2 = i;
        }
    }
    // The server dies early and comes back from its journal: its second life records beside
    // the first (recording.1.mcap), starting from what it restored.
    server.epoch(1, 60);
    procs.kill(server.index);
    let server = start_server(&mut procs, &server_args, &dir.join("server.log"));
    // Then a boat dies and comes back from its outbox, re-sending what was not acknowledged.
    server.epoch(3, 60);
    procs.kill(boat2);
    start(&mut procs, "boat-2");
    let summary = server.finished(120);
    procs.wait_all(60);
    assert!(summary.counters.restored > 0, "the server restarted from its journal");

    let second = dir.join("recording.1.mcap");
    let replayed = dir.join("replayed");
    let o = run(
        "fleet",
        &["replay", second.to_str().unwrap(), "--out", replayed.to_str().unwrap()],
    );
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "replay failed: {said}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(said.contains("identical to the recorded one, bit for bit"), "{said}");
    // From a lean recording (the default): of the models published, only the last is in it.
    let models = Recording::read(&second).unwrap().on("/model/latest").count();
    assert_eq!(models, 1, "a lean recording keeps the last model only (of < 50)");
    // The model the server wrote at the end is the recording's last, and the replay's.
    assert_eq!(
        std::fs::read(replayed.join("model.cbor")).unwrap(),
        std::fs::read(out.join("model.cbor")).unwrap(),
        "replayed model.cbor differs from the server's"
    );
    for f in ["estimate.npy", "variance.npy", "plans.json"] {
        assert_eq!(
            std::fs::read(replayed.join(f)).unwrap(),
            std::fs::read(out.join(f)).unwrap(),
            "replayed {f} differs from the server's"
        );
    }

    // In time, to a live view: the recording played onto Zenoh at twice its pace, and the view
    // on it sees the vehicles up and the model advance to the recorded final version.
    let port = free_port();
    let mut live = std::process::Command::new(bin("fleet"))
        .args([
            "replay",
            second.to_str().unwrap(),
            "--out",
            dir.join("live").to_str().unwrap(),
            "--speed",
            "2",
            "--web",
            &format!("127.0.0.1:{port}"),
            "--web-linger-s",
            "30",
        ])
        .current_dir(root())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let version = |s: &serde_json::Value| s["model"]["version"].as_u64().unwrap_or(0);
    eventually(60, "the view has a replayed model", || {
        web_state(port).is_some_and(|s| version(&s) >= 1)
    });
    let first = version(&web_state(port).unwrap());
    eventually(60, "the view sees every vehicle up", || {
        web_state(port).is_some_and(|s| {
            s["vehicles"]
                .as_array()
                .unwrap()
                .iter()
                .all(|v| v["link"] == "up" || v["link"] == "left")
        })
    });
    eventually(60, "the view reaches the recorded final model", || {
        web_state(port).is_some_and(|s| version(&s) == summary.model_version)
    });
    assert!(
        first < summary.model_version,
        "the view saw the model advance ({first} -> {})",
        summary.model_version
    );
    // Ctrl-C during the linger ends it cleanly.
    unsafe { libc::kill(live.id() as i32, libc::SIGINT) };
    let status = live.wait().unwrap();
    assert!(status.success() || status.code() == Some(130), "{status}");

    // The first life's recording ends where the server was killed: refused in one line.
    let o = run(
        "fleet",
        &[
            "replay",
            record.to_str().unwrap(),
            "--out",
            dir.join("cut").to_str().unwrap(),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("recording.mcap: cut short") && err.trim().lines().count() == 1,
        "{err}"
    );
    // Any cut of a finished recording, and a file that is not one, likewise.
    let bytes = std::fs::read(&second).unwrap();
    for (name, b) in [
        ("cut-a.mcap", &bytes[..bytes.len() / 3]),
        ("cut-b.mcap", &bytes[..bytes.len() - 9]),
        ("junk.mcap", &b"not a recording"[..]),
    ] {
        let p = dir.join(name);
        std::fs::write(&p, b).unwrap();
        let o = run(
            "fleet",
            &[
                "replay",
                p.to_str().unwrap(),
                "--out",
                dir.join("cut").to_str().unwrap(),
            ],
        );
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{name}: {err}");
        assert!(err.contains(name) && err.trim().lines().count() == 1, "{name}: {err}");
    }
}
