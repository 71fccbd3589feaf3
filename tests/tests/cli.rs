//! The `fleet` binary as a user runs it: the bundled example, files, and bad input.

use hetfleet_tests::{bin, root, run};
use std::process::Command;

#[test]
fn fleet_dmd_runs_on_the_bundled_example() {
    let out = run("fleet", &["dmd", "--top", "3"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("general DMD of 501 snapshots on a 10 x 10 grid"), "{stdout}");
    assert!(stdout.contains("relative reconstruction error"), "{stdout}");
}

#[test]
fn fleet_dmd_reads_a_reference_file_and_writes_json() {
    let dir = std::env::temp_dir().join(format!("hetfleet-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("m.json");
    let out = run(
        "fleet",
        &["dmd", "--input", "reference/dmd_case1_Z.npy", "--method", "long-term", "--init", "100", "--out", json.to_str().unwrap()],
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let doc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(doc["model"]["rank"], 100);
    // The long-term operator's top eigenvalue is the reference's (0.8714, from numpy/odmd).
    let top = doc["model"]["eigenvalues"][0][0].as_f64().unwrap();
    let reference: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root().join("reference/dmd_reference.json")).unwrap()).unwrap();
    let want = reference["longterm_g1"]["eigs"][0][0].as_f64().unwrap();
    assert!((top - want).abs() < 1e-8, "{top} vs {want}");
}

#[test]
fn bad_input_gets_a_clear_error_and_a_non_zero_exit() {
    let dir = std::env::temp_dir().join(format!("hetfleet-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let junk = dir.join("junk.npy");
    std::fs::write(&junk, b"\x93NUMPY garbage").unwrap();
    let nan = dir.join("nan.npy");
    fleet::npy::write(&nan, &[4, 2, 2], &[1.0, 2.0, 3.0, f64::NAN, 1.0, 2.0, 3.0, 4.0, 1.0, 2.0, 3.0, 4.0, 1.0, 2.0, 3.0, 4.0]).unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (vec!["--input".into(), junk.display().to_string()], "junk.npy"),
        (vec!["--input".into(), nan.display().to_string()], "not finite"),
        (vec!["--input".into(), dir.join("missing.npy").display().to_string()], "missing.npy"),
        (vec!["--method".into(), "long-term".into(), "--init".into(), "50".into()], "full row rank"),
        (vec!["--rank".into(), "lots".into()], "rank must be"),
        (vec!["--init".into(), "9999".into()], "more than the 500"),
    ];
    for (args, needle) in cases {
        let mut full = vec!["dmd".to_string()];
        full.extend(args.iter().cloned());
        let out = Command::new(bin("fleet")).args(&full).current_dir(root()).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} should fail");
        assert!(!stderr.contains("panicked"), "{args:?} panicked: {stderr}");
        assert!(stderr.contains(needle), "{args:?}: expected {needle:?} in {stderr}");
    }
}
