//! The `fleet` binary as a user runs it: the bundled example, files, and bad input.

use hetfleet_tests::{bin, root, run};
use std::process::Command;

#[test]
fn fleet_dmd_runs_on_the_bundled_example() {
    let out = run("fleet", &["dmd", "--top", "3"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("general DMD of 501 snapshots on a 10 x 10 grid"),
        "{stdout}"
    );
    assert!(stdout.contains("relative reconstruction error"), "{stdout}");
}

#[test]
fn fleet_dmd_reads_a_reference_file_and_writes_json() {
    let dir = std::env::temp_dir().join(format!("hetfleet-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("m.json");
    let out = run(
        "fleet",
        &[
            "dmd",
            "--input",
            "reference/dmd_case1_Z.npy",
            "--method",
            "long-term",
            "--init",
            "100",
            "--out",
            json.to_str().unwrap(),
        ],
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
    fleet_math::npy::write(
        &nan,
        &[4, 2, 2],
        &[
            1.0,
            2.0,
            3.0,
            f64::NAN,
            1.0,
            2.0,
            3.0,
            4.0,
            1.0,
            2.0,
            3.0,
            4.0,
            1.0,
            2.0,
            3.0,
            4.0,
        ],
    )
    .unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (vec!["--input".into(), junk.display().to_string()], "junk.npy"),
        (vec!["--input".into(), nan.display().to_string()], "not finite"),
        (
            vec!["--input".into(), dir.join("missing.npy").display().to_string()],
            "missing.npy",
        ),
        (
            vec!["--method".into(), "long-term".into(), "--init".into(), "50".into()],
            "full row rank",
        ),
        (vec!["--rank".into(), "lots".into()], "rank must be"),
        (vec!["--init".into(), "9999".into()], "more than the 500"),
    ];
    for (args, needle) in cases {
        let mut full = vec!["dmd".to_string()];
        full.extend(args.iter().cloned());
        let out = Command::new(bin("fleet"))
            .args(&full)
            .current_dir(root())
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: bad input is exit 2: {stderr}");
        // (clap's usage errors add its "try --help" line, as every clap program does.)
        let usage = stderr.contains("try '--help'");
        assert!(
            usage || stderr.trim().lines().count() == 1,
            "{args:?}: one line: {stderr}"
        );
        assert!(!stderr.contains("panicked"), "{args:?} panicked: {stderr}");
        assert!(stderr.contains(needle), "{args:?}: expected {needle:?} in {stderr}");
    }
}

/// Exit status and stderr of a workspace binary run with `args`.
fn status_and_stderr(binary: &str, args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(bin(binary))
        .args(args)
        .current_dir(root())
        .output()
        .unwrap();
    (out.status.code(), String::from_utf8_lossy(&out.stderr).to_string())
}

/// Refused as bad input: exit 2, one line `<binary>: ...` containing `needle`, no panic.
fn assert_refused(binary: &str, args: &[&str], needle: &str) {
    let (code, err) = status_and_stderr(binary, args);
    assert_eq!(code, Some(2), "{args:?}: exit 2 for bad input, got {code:?}: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{args:?}: one line: {err}");
    assert!(
        lines[0].starts_with(&format!("{binary}: ")) && lines[0].contains(needle),
        "{args:?}: expected {needle:?} in {err}"
    );
    assert!(
        !err.contains("panicked") && !err.contains("{ ") && !err.contains("Os {"),
        "{args:?}: no panic, no debug formatting: {err}"
    );
}

/// `fleet up` of mission `m` into `out` refused as bad input ([`assert_refused`]).
fn up_refused(m: &std::path::Path, out: &std::path::Path, needle: &str) {
    assert_refused(
        "fleet",
        &["up", m.to_str().unwrap(), "--out", out.to_str().unwrap()],
        needle,
    );
}

#[test]
fn configurations_that_cannot_run_are_refused_up_front_naming_the_field() {
    let dir = hetfleet_tests::scratch("configs");
    let cases = [
        (
            "aerial_stride = 3",
            "aerial_stride = 12\naerials = 10",
            "aerials = 10: the aerial lattice has only 8 cells",
        ),
        (
            "radius = 3.0",
            "radius = 500.0",
            "radius = 500: 3 boats' disks of that radius do not fit",
        ),
        (
            "seed = 5",
            "seed = 5\ngamma = 0.9",
            "gamma = 0.9: the forgetting factor applies to method = \"long-term\" only",
        ),
        (
            "boats = 3",
            "boats = \"three\"",
            "invalid type: string \"three\", expected usize (at [team] boats, line",
        ),
        ("rank = \"6\"", "rank = -6", "rank: give \"full\""),
        (
            "seed = 5",
            "seed = 5\nmethod = \"long-term\"",
            "method = \"long-term\": its operator has every one of the grid's N modes",
        ),
    ];
    for (i, (from, to, needle)) in cases.into_iter().enumerate() {
        let m = hetfleet_tests::tiny_mission(&dir, &["tcp/127.0.0.1:7461".into()], &["tcp/127.0.0.1:7461".into()]);
        hetfleet_tests::edit(&m, from, to);
        if to.contains("aerials = 10") {
            hetfleet_tests::edit(&m, "aerials = 2\n", "");
        }
        let out = dir.join(format!("run-{i}"));
        up_refused(&m, &out, needle);
        assert!(!out.join("state").exists(), "{to}: nothing started");
    }
    // A NetCDF-4 (HDF5) truth cut short, whatever its name: one line naming it, before
    // anything starts.
    let h5 = dir.join("sst.nc");
    std::fs::write(&h5, b"\x89HDF\r\n\x1a\n\0\0\0\0").unwrap();
    let m = hetfleet_tests::tiny_mission(&dir, &["tcp/127.0.0.1:7461".into()], &["tcp/127.0.0.1:7461".into()]);
    let dataset = format!("dataset = {:?}\nvariable = \"sst\"", h5.to_str().unwrap());
    hetfleet_tests::edit(&m, "preset = \"cloud2\"\ngrid = [48, 96]", &dataset);
    let out = dir.join("run-netcdf4");
    assert_refused(
        "fleet",
        &["up", m.to_str().unwrap(), "--out", out.to_str().unwrap()],
        "sst.nc: not a readable NetCDF file (HDF5 error",
    );
    // Latitudes not evenly spaced (tests/py/netcdf4.py): the site is not placed from them in
    // silence (it was put at the default origin) but refused, naming the coordinate.
    // A time coordinate without units: refused, not read as seconds (issue 82).
    for (variant, needle) in [
        ("uneven", "coordinate \"ocean/lat\" is not evenly spaced: value 4"),
        ("unitless", "time coordinate \"time\" has units \"\", not CF's"),
    ] {
        let nc = dir.join(format!("{variant}.nc"));
        let o = Command::new("python3")
            .args(["tests/py/netcdf4.py", "write", nc.to_str().unwrap(), variant])
            .current_dir(root())
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let dataset = format!("dataset = {:?}\nvariable = \"ocean/sst\"", nc.to_str().unwrap());
        let m = hetfleet_tests::tiny_mission(&dir, &["tcp/127.0.0.1:7461".into()], &["tcp/127.0.0.1:7461".into()]);
        hetfleet_tests::edit(&m, "preset = \"cloud2\"\ngrid = [48, 96]", &dataset);
        hetfleet_tests::edit(&m, "frames = 40\naverage = 2", "frames = 30\naverage = 1");
        let out = dir.join(format!("run-{variant}"));
        assert_refused(
            "fleet",
            &["up", m.to_str().unwrap(), "--out", out.to_str().unwrap()],
            needle,
        );
    }
    assert!(!out.join("state").exists(), "a NetCDF-4 truth: nothing started");
    // An integer rank is a rank.
    let m = hetfleet_tests::tiny_mission(&dir, &[], &["tcp/127.0.0.1:7461".into()]);
    hetfleet_tests::edit(&m, "rank = \"6\"", "rank = 6");
    assert_eq!(
        fleet_mission::config::MissionConfig::load(Some(&m)).unwrap().team.rank,
        fleet_math::dmd::RankPolicy::Fixed(6)
    );
}

#[test]
fn a_truth_that_is_not_the_missions_and_oversized_or_misnamed_outputs_are_refused() {
    let dir = hetfleet_tests::scratch("truths");
    let m = hetfleet_tests::tiny_mission(&dir, &["tcp/127.0.0.1:7461".into()], &["tcp/127.0.0.1:7461".into()]);
    let small = dir.join("small.npy");
    fleet_math::npy::write(&small, &[40, 24, 24], &vec![0.5; 40 * 24 * 24]).unwrap();
    for node in ["vehicle", "model-server"] {
        let mut args = vec![
            "--mission",
            m.to_str().unwrap(),
            "--truth",
            small.to_str().unwrap(),
            "--state-dir",
            dir.to_str().unwrap(),
        ];
        if node == "vehicle" {
            args.extend(["--id", "boat-1"]);
        }
        assert_refused(
            node,
            &args,
            "is 24 x 24 cells for 40 steps, but mission \"tiny\" senses 24 x 48 cells for 40 steps",
        );
    }
    assert_refused(
        "vehicle",
        &[
            "--mission",
            m.to_str().unwrap(),
            "--id",
            "boat-9",
            "--state-dir",
            dir.to_str().unwrap(),
        ],
        "--id boat-9: no such vehicle",
    );
    let out = dir.join("f.npy");
    assert_refused(
        "fleet",
        &[
            "simulate",
            "plume",
            "--frames",
            "100000000",
            "--out",
            out.to_str().unwrap(),
        ],
        "--grid/--frames",
    );
    assert_refused(
        "fleet",
        &[
            "simulate",
            "plume",
            "--grid",
            "100000x100000",
            "--out",
            out.to_str().unwrap(),
        ],
        "--grid/--frames",
    );
    assert_refused(
        "fleet",
        &[
            "simulate",
            "plasma-cloud",
            "--grid",
            "100000x100000",
            "--out",
            out.to_str().unwrap(),
        ],
        "--grid/--frames",
    );
    assert!(!out.exists());
    assert_refused(
        "fleet",
        &[
            "render",
            small.to_str().unwrap(),
            "--gif",
            "--out",
            dir.join("x.png").to_str().unwrap(),
        ],
        "--gif writes a GIF, name it .gif",
    );
    assert!(!dir.join("x.png").exists());
    assert_refused(
        "fleet",
        &["dmd", "--gamma", "0.9"],
        "--gamma 0.9: forgetting applies to --method long-term only",
    );
    // float32 data is widened, not refused.
    let f32_path = dir.join("f32.npy");
    let text =
        "import numpy as np, sys; np.save(sys.argv[1], np.random.default_rng(1).random((30, 4, 5)).astype(np.float32))";
    if Command::new("python3")
        .args(["-c", text, f32_path.to_str().unwrap()])
        .status()
        .is_ok_and(|s| s.success())
    {
        let (code, err) = status_and_stderr("fleet", &["dmd", "--input", f32_path.to_str().unwrap(), "--top", "2"]);
        assert_eq!(code, Some(0), "{err}");
    }
}

#[test]
fn fleet_dmd_saves_the_model_for_numpy() {
    let dir = hetfleet_tests::scratch("dmd-save");
    let save = dir.join("model");
    let (code, err) = status_and_stderr(
        "fleet",
        &[
            "dmd",
            "--input",
            "reference/dmd_case1_Z.npy",
            "--method",
            "batch",
            "--rank",
            "10",
            "--save",
            save.to_str().unwrap(),
        ],
    );
    assert_eq!(code, Some(0), "{err}");
    // The guide's three lines (docs/guide/after.md): the record rebuilt in numpy from what was saved, with the error
    // fleet reported.
    let script = r#"
import json, sys, numpy as np
d, z = sys.argv[1], np.load(sys.argv[2])
lam, phi, b = np.load(d + "/eigenvalues.npy"), np.load(d + "/modes.npy"), np.load(d + "/amplitudes.npy")
x = (phi @ (b[:, None] * lam[:, None] ** np.arange(z.shape[1]))).real
assert lam.dtype == np.complex128 and phi.shape == (100, 10) and b.shape == (10,)
print(abs(np.linalg.norm(x - z) / np.linalg.norm(z) - json.load(open(d + "/summary.json"))["relative_reconstruction_error"]))
"#;
    let o = Command::new("python3")
        .args([
            "-c",
            script,
            save.to_str().unwrap(),
            root().join("reference/dmd_case1_Z.npy").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let diff: f64 = String::from_utf8_lossy(&o.stdout).trim().parse().unwrap();
    // Both sums run over the same 50,100 values in float64: rounding differences only.
    assert!(
        diff < 1e-12,
        "numpy's reconstruction error differs from fleet's by {diff:e}"
    );
}
