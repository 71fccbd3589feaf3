//! Timings of sensor placement and gappy reconstruction (issue 3's benchmarks), with pysensors'
//! `QR.fit` timed on the very same basis in the same run when Python and pysensors are there.

use super::eig_study::median;
use faer::Mat;
use fleet_math::dmd::linalg::thin_svd;
use fleet_math::grid::Grid;
use fleet_math::kalman::{ModalFilter, Scheduled};
use fleet_math::process::synthetic::{smooth_basis, smooth_sphere_field};
use fleet_math::sensing::gappy::reconstruct;
use fleet_math::sensing::horizon::{plan, Boat, Forecast};
use fleet_math::sensing::qr::{block_dopt, block_qr, point_qr};
use serde::Serialize;
use std::time::Instant;

#[derive(Debug, Clone, Serialize)]
pub struct Timing {
    pub what: String,
    pub median_ms: f64,
    pub min_ms: f64,
    /// The same operation in the peer library, when measured.
    pub peer: Option<String>,
    pub peer_median_ms: Option<f64>,
}

fn time_ms(repeats: usize, mut f: impl FnMut()) -> (f64, f64) {
    f();
    let mut ts: Vec<f64> = (0..repeats.max(1))
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    let min = ts.iter().copied().fold(f64::INFINITY, f64::min);
    (median(&mut ts), min)
}

/// POD basis (first `r` left singular vectors of the mean-removed snapshots) of the 48 x 96
/// smooth field of the peers' `sensors_qr.py`, 200 snapshots on t in [0, 20].
pub fn pod_basis_48x96(r: usize) -> Mat<f64> {
    let times: Vec<f64> = (0..200).map(|k| 20.0 * k as f64 / 199.0).collect();
    let mut z = smooth_sphere_field(&times, 0.01, 42).snapshots;
    for i in 0..z.nrows() {
        let mean = z.row(i).iter().sum::<f64>() / z.ncols() as f64;
        z.row_mut(i).iter_mut().for_each(|v| *v -= mean);
    }
    thin_svd(z.as_ref()).expect("svd of a finite field").truncate(r).u
}

/// pysensors' `QR().fit(basis)` (which pivots the QR of `basis.T`, N columns) median milliseconds
/// on `basis`, or `None` when Python or pysensors is missing (the reason goes to stderr).
pub fn pysensors_qr_ms(basis: &Mat<f64>, repeats: usize) -> Option<f64> {
    let dir = std::env::temp_dir().join(format!("hetfleet-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).ok()?;
    let path = dir.join("basis.npy");
    let data: Vec<f64> = (0..basis.nrows())
        .flat_map(|i| (0..basis.ncols()).map(move |j| (i, j)))
        .map(|(i, j)| basis[(i, j)])
        .collect();
    fleet_math::npy::write(&path, &[basis.nrows(), basis.ncols()], &data).ok()?;
    let script = format!(
        "import time, numpy as np, pysensors as ps\n\
         b = np.load(r'{}')\n\
         ps.optimizers.QR().fit(b)\n\
         ts = []\n\
         for _ in range({repeats}):\n    t = time.perf_counter(); ps.optimizers.QR().fit(b); \
         ts.append(time.perf_counter() - t)\n\
         print(sorted(ts)[len(ts) // 2] * 1e3)\n",
        path.display()
    );
    let out = std::process::Command::new("python3")
        .arg("-c")
        .arg(script)
        .env("OPENBLAS_NUM_THREADS", "1")
        .output();
    let _ = std::fs::remove_dir_all(&dir);
    match out {
        Ok(o) if o.status.success() => String::from_utf8_lossy(&o.stdout).trim().parse().ok(),
        Ok(o) => {
            eprintln!(
                "pysensors timing skipped: {}",
                String::from_utf8_lossy(&o.stderr).lines().last().unwrap_or("")
            );
            None
        }
        Err(e) => {
            eprintln!("pysensors timing skipped: {e}");
            None
        }
    }
}

/// Every sensing timing: point QR at r = 10 and 20 (beside pysensors), block QR and D-optimal
/// at 48 x 96 (r 10, radius 10, 5 boats) and 96 x 384 (radius 15), horizon placement at 48 x 96
/// and 192 x 384, gappy reconstruction at
/// 48 x 96 from 5 disks.
pub fn run(repeats: usize, peers: bool, mut progress: impl FnMut(&str)) -> Vec<Timing> {
    let mut out = vec![];
    let mut push = |what: String, (median_ms, min_ms): (f64, f64), peer: Option<(&str, f64)>| {
        out.push(Timing {
            what,
            median_ms,
            min_ms,
            peer: peer.map(|p| p.0.to_string()),
            peer_median_ms: peer.map(|p| p.1),
        });
    };
    for r in [10, 20] {
        progress(&format!("point QR r{r}"));
        let phi = pod_basis_48x96(r);
        let t = time_ms(repeats, || {
            std::hint::black_box(point_qr(phi.as_ref(), r));
        });
        let peer = if peers { pysensors_qr_ms(&phi, repeats) } else { None };
        push(format!("point QR 4608 x {r}"), t, peer.map(|p| ("pysensors QR.fit", p)));
    }
    for (rows, cols, radius) in [(48, 96, 10.0), (96, 384, 15.0)] {
        let grid = Grid::new(rows, cols, 1.0).expect("valid grid");
        let phi = smooth_basis(&grid, 10, 7);
        progress(&format!("block QR {rows}x{cols}"));
        let t = time_ms(repeats, || {
            std::hint::black_box(block_qr(phi.as_ref(), &grid, 5, radius).expect("placement"));
        });
        push(
            format!("block QR {rows} x {cols}, r 10, radius {radius}, 5 boats"),
            t,
            None,
        );
        progress(&format!("D-optimal {rows}x{cols}"));
        let t = time_ms(repeats, || {
            std::hint::black_box(block_dopt(phi.as_ref(), &grid, 5, radius).expect("placement"));
        });
        push(
            format!("D-optimal blocks {rows} x {cols}, r 10, radius {radius}, 5 boats"),
            t,
            None,
        );
    }
    // Horizon placement (issue 19's targets: under 50 ms at 48 x 96 with 5 boats, under 1 s
    // at 192 x 384): a forecast over 10 modes, 3 epochs of 5 steps, boats spread over the grid
    // reaching a quarter of its width, the aerials seeing every 4th cell (the look ahead timed
    // with the plan); 192 x 384 at the same physical radius (40) and at 10.
    for (rows, cols, radius) in [(48, 96, 10.0), (192, 384, 40.0), (192, 384, 10.0)] {
        progress(&format!("horizon {rows}x{cols} radius {radius}"));
        let t = time_horizon(rows, cols, radius, repeats);
        push(
            format!("horizon placement {rows} x {cols}, r 10, radius {radius}, 5 boats, 3 epochs"),
            t,
            None,
        );
    }
    progress("gappy 48x96");
    let grid = Grid::new(48, 96, 1.0).expect("valid grid");
    let phi = smooth_basis(&grid, 10, 7);
    let disks = block_qr(phi.as_ref(), &grid, 5, 10.0).expect("placement");
    let cells: Vec<usize> = disks.iter().flat_map(|d| d.cells.iter().copied()).collect();
    let values: Vec<f64> = cells.iter().map(|&c| (0..10).map(|j| phi[(c, j)]).sum()).collect();
    let t = time_ms(repeats, || {
        std::hint::black_box(reconstruct(phi.as_ref(), &cells, &values, 0.01).expect("reconstruction"));
    });
    push(
        format!("gappy reconstruction + variance 48 x 96, r 10, {} cells", cells.len()),
        t,
        None,
    );
    out
}

/// Horizon placement on a `rows x cols` grid, as the assimilator plans: a forecast over 10
/// modes, 3 epochs of 5 steps, boats spread over the grid reaching a quarter of its width, the
/// aerials seeing every 4th cell; the look ahead timed with the plan. Median and min ms.
fn time_horizon(rows: usize, cols: usize, radius: f64, repeats: usize) -> (f64, f64) {
    let grid = Grid::new(rows, cols, 1.0).expect("valid grid");
    let phi = smooth_basis(&grid, 10, 7);
    let q = phi.ncols();
    let a = Mat::<f64>::from_fn(q, q, |i, j| {
        if i == j {
            0.97
        } else if j == i + 1 {
            0.05
        } else {
            0.0
        }
    });
    let p = Mat::<f64>::from_fn(q, q, |i, j| if i == j { 0.1 } else { 0.0 });
    let filter = ModalFilter::new(phi.clone(), a, vec![0.0; q], p, 1e-3, 0.01)
        .expect("a filter")
        .with_persistence(0.9);
    // The aerials' lattice every 4 cells, and their estimate everywhere.
    let strided = grid.strided(4).expect("a lattice");
    let lattice: Vec<usize> = (0..strided.rows * strided.cols)
        .map(|k| grid.index(strided.fine_cell(k)))
        .collect();
    let (noise, everywhere) = (vec![1e-3; lattice.len()], vec![5e-3; grid.len()]);
    let aerials = Scheduled {
        cells: &lattice,
        variance: &noise,
        everywhere: &everywhere,
    };
    let boats: Vec<Boat> = (0..5)
        .map(|b| Boat {
            position: ((b as f64 + 0.5) * cols as f64 / 5.0, rows as f64 / 2.0),
            reach_m: cols as f64 / 4.0,
        })
        .collect();
    // As the assimilator plans: the forecast at the sampling step, the look ahead, and the
    // unmodelled displacement's variance from the forecast's squared gradient.
    time_ms(repeats, || {
        let (mean, _) = filter.ahead(5).field();
        let ahead = filter.look_ahead(5, 15, &aerials, 1e-4).expect("a look ahead");
        let unmodelled: Vec<f64> = grid
            .squared_gradient(&mean)
            .expect("one value per cell")
            .iter()
            .map(|g2| 0.5 * g2)
            .collect();
        std::hint::black_box(
            plan(
                &grid,
                &Forecast::of(phi.as_ref(), &ahead).with_unmodelled(&unmodelled),
                &boats,
                radius,
                1e-4,
            )
            .expect("placement"),
        );
    })
}
