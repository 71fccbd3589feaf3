//! `fleet simulate` and `fleet render` as a user runs them: files numpy can load, a sidecar of
//! every parameter, pictures, and clear errors.

use hetfleet_tests::{bin, root, run};
use std::process::Command;

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("hetfleet-sim-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn plasma_cloud_writes_npy_and_sidecar_then_renders() {
    let dir = tmp("plasma");
    let npy = dir.join("cloud.npy");
    let out = run(
        "fleet",
        &[
            "simulate",
            "plasma-cloud",
            "--preset",
            "cloud10",
            "--grid",
            "24x96",
            "--frames",
            "4",
            "--seed",
            "3",
            "--out",
            npy.to_str().unwrap(),
        ],
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let a = fleet_math::npy::read(&npy).unwrap();
    assert_eq!(a.shape, vec![4, 24, 96]);
    assert!(a.data.iter().all(|v| v.is_finite() && *v > 0.0));
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("cloud.json")).unwrap()).unwrap();
    assert_eq!(side["preset"], "cloud10");
    assert_eq!(side["params"]["seed"], 3);
    assert_eq!(side["params"]["n_b"], 0.2);
    assert_eq!(side["shape"], serde_json::json!([4, 24, 96]));
    assert!(side["solver"]["solves"].as_u64().unwrap() > 0);
    // Same seed, same field.
    let again = dir.join("again.npy");
    let out = run(
        "fleet",
        &[
            "simulate",
            "--process",
            "plasma-cloud",
            "--preset",
            "cloud10",
            "--grid",
            "24x96",
            "--frames",
            "4",
            "--seed",
            "3",
            "--out",
            again.to_str().unwrap(),
        ],
    );
    assert!(out.status.success());
    assert_eq!(fleet_math::npy::read(&again).unwrap().data, a.data);

    let png = dir.join("f.png");
    let out = run(
        "fleet",
        &[
            "render",
            npy.to_str().unwrap(),
            "--frame",
            "3",
            "--out",
            png.to_str().unwrap(),
        ],
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(&std::fs::read(&png).unwrap()[..4], b"\x89PNG");
    let gif = dir.join("f.gif");
    let out = run(
        "fleet",
        &["render", npy.to_str().unwrap(), "--gif", "--out", gif.to_str().unwrap()],
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(&std::fs::read(&gif).unwrap()[..3], b"GIF");
}

#[test]
fn synthetic_processes_are_written_with_their_shapes() {
    let dir = tmp("synth");
    for (args, shape) in [
        (vec!["table1", "--case", "3"], vec![1001, 20, 20]),
        (vec!["eig-study", "--noise", "0.01"], vec![1001, 20, 20]),
        (vec!["plume", "--grid", "12x30", "--frames", "7"], vec![7, 12, 30]),
    ] {
        let out_path = dir.join(format!("{}.npy", args[0]));
        let mut full = vec!["simulate"];
        full.extend(&args);
        full.extend(["--out", out_path.to_str().unwrap()]);
        let out = run("fleet", &full);
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_eq!(fleet_math::npy::read(&out_path).unwrap().shape, shape, "{args:?}");
    }
}

#[test]
fn bad_simulate_and_render_input_is_a_clear_error() {
    let dir = tmp("bad");
    let o = |n: &str| dir.join(n).display().to_string();
    let flat = dir.join("flat.npy");
    fleet_math::npy::write(&flat, &[4, 6], &[0.0; 24]).unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "simulate".into(),
                "plasma-cloud".into(),
                "--grid".into(),
                "96by384".into(),
                "--out".into(),
                o("a.npy"),
            ],
            "ROWSxCOLS",
        ),
        (
            vec![
                "simulate".into(),
                "plasma-cloud".into(),
                "--grid".into(),
                "2x2".into(),
                "--out".into(),
                o("a.npy"),
            ],
            "at least 4 x 4",
        ),
        (
            vec![
                "simulate".into(),
                "table1".into(),
                "--case".into(),
                "9".into(),
                "--out".into(),
                o("a.npy"),
            ],
            "1-4",
        ),
        (
            vec![
                "simulate".into(),
                "plume".into(),
                "--noise=-1".into(),
                "--out".into(),
                o("a.npy"),
            ],
            "variance",
        ),
        (
            vec![
                "simulate".into(),
                "plume".into(),
                "--process".into(),
                "table1".into(),
                "--out".into(),
                o("a.npy"),
            ],
            "two different",
        ),
        (
            vec!["render".into(), flat.display().to_string(), "--out".into(), o("x.png")],
            "(frames, rows, cols)",
        ),
        (
            vec!["render".into(), o("missing.npy"), "--out".into(), o("x.png")],
            "missing.npy",
        ),
    ];
    for (args, needle) in cases {
        let out = Command::new(bin("fleet"))
            .args(&args)
            .current_dir(root())
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} should fail");
        assert!(!stderr.contains("panicked"), "{args:?} panicked: {stderr}");
        assert!(stderr.contains(needle), "{args:?}: expected {needle:?} in {stderr}");
    }
}
