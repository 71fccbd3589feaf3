//! Live cross-checks against the Python peers (installed by `scripts/test.sh`): the same field,
//! written by us to .npy, fitted by PyDMD in a real Python process, compared with our fit.
//! Set HETFLEET_SKIP_PYTHON=1 to skip on a machine without them (CI never sets it).

use hetfleet_tests::{bin, root};
use std::process::Command;

fn python_available() -> bool {
    if std::env::var("HETFLEET_SKIP_PYTHON").is_ok_and(|v| v == "1") {
        eprintln!("HETFLEET_SKIP_PYTHON=1: skipping the live PyDMD cross-check");
        return false;
    }
    true
}

#[test]
fn pydmd_and_fleet_agree_on_a_field_we_generate() {
    if !python_available() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("hetfleet-peers-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // A (frames, rows, cols) field: the Fig. 7 field, 201 frames, via the library.
    let f = fleet::process::synthetic::EigStudy::field(0.01, 7);
    let (n, t) = (f.dim(), 201);
    let mut data = Vec::with_capacity(n * t);
    for j in 0..t {
        data.extend(f.snapshots.col(j).iter().copied());
    }
    let npy = dir.join("field.npy");
    fleet::npy::write(&npy, &[t, f.rows, f.cols], &data).unwrap();
    let ours = dir.join("ours.json");
    let out = Command::new(bin("fleet"))
        .args([
            "dmd", "--method", "batch", "--rank", "6", "--init", "200", "--dt", "0.01", "--out",
        ])
        .arg(&ours)
        .arg("--input")
        .arg(&npy)
        .current_dir(root())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let script = r#"
import sys, json, numpy as np
from pydmd import DMD
a = np.load(sys.argv[1]); Z = a.reshape(a.shape[0], -1).T
d = DMD(svd_rank=6, exact=True).fit(Z)
e = d.eigs[np.lexsort((-d.eigs.imag, -np.round(np.abs(d.eigs), 12)))]
print(json.dumps([[float(z.real), float(z.imag)] for z in e]))
"#;
    let py = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(&npy)
        .output()
        .expect("python3 must be installed (scripts/test.sh)");
    assert!(
        py.status.success(),
        "PyDMD failed (run scripts/test.sh to install it): {}",
        String::from_utf8_lossy(&py.stderr)
    );
    let theirs: Vec<[f64; 2]> = serde_json::from_slice(&py.stdout).unwrap();
    let doc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&ours).unwrap()).unwrap();
    let mine: Vec<[f64; 2]> = serde_json::from_value(doc["model"]["eigenvalues"].clone()).unwrap();
    assert_eq!(mine.len(), theirs.len());
    // One to one: the pairing (over all 720 of 6) with the smallest worst relative difference,
    // so two of PyDMD's eigenvalues never match the same one of ours.
    let rel = |m: &[f64; 2], t: &[f64; 2]| {
        ((m[0] - t[0]).powi(2) + (m[1] - t[1]).powi(2)).sqrt() / (t[0].powi(2) + t[1].powi(2)).sqrt().max(1e-3)
    };
    let mut best = f64::INFINITY;
    let mut order: Vec<usize> = (0..mine.len()).collect();
    permutations(&mut order, 0, &mut |p| {
        best = best.min(theirs.iter().zip(p).map(|(t, &j)| rel(&mine[j], t)).fold(0.0, f64::max))
    });
    println!("MEASURED PyDMD vs ours, batch rank 6, one to one: {best:e}");
    // Measured 5.3e-14; two SVD and eigensolver implementations on a 6 x 6 reduced
    // operator: 1e-9 leaves 1e4 for other machines, far below a wrong eigenvalue's 1e-3.
    assert!(best < 1e-9, "PyDMD's eigenvalues {theirs:?} vs ours {mine:?}: {best:e}");
}

/// Call `f` with every permutation of `v[k..]` (Heap's order is not needed: all of them).
fn permutations(v: &mut Vec<usize>, k: usize, f: &mut impl FnMut(&[usize])) {
    if k == v.len() {
        return f(v);
    }
    for i in k..v.len() {
        v.swap(k, i);
        permutations(v, k + 1, f);
        v.swap(k, i);
    }
}
