//! hetfleet's mathematics, with nothing of the network, the command line or plots: the layer
//! every other crate stands on.
//!
//! One module per idea: [`grid`] (the workspace raster and sensing disks), [`dmd`] (batch,
//! general online and long-term online DMD), [`sensing`] (gappy reconstruction, QR placement,
//! coverage, assignment), [`fusion`] (the sensor model, aerial frames and their combination
//! with the boats' estimate), [`kalman`] (a Kalman filter in a DMD model's modal coordinates:
//! the fused map as a posterior), [`process`] (field sources: the plasma-cloud simulator,
//! synthetic fields, `.npy` datasets), [`npy`] (numpy-compatible files), [`par`] and [`simd`]
//! (both cores, and the CPU's wider vectors, for loops of our own, to the same bits).

pub mod dmd;
pub mod fusion;
pub mod grid;
pub mod kalman;
pub mod longitude;
pub mod npy;
pub mod par;
pub mod process;
pub mod sensing;
pub mod simd;

/// The allocator hetfleet's binaries and benchmarks use (`#[global_allocator] static A:
/// fleet_math::Allocator = fleet_math::Allocator;`): a fit allocates and frees matrices of
/// megabytes, which glibc's malloc maps and unmaps each time (page faults were 60% of a
/// 4608 x 100 batch fit); mimalloc reuses them.
pub use mimalloc::MiMalloc as Allocator;

/// Set faer's parallelism from `HETFLEET_LINALG_THREADS` (default 1). On the 2-core machines
/// we run on, faer's rayon parallelism made the decompositions DMD uses (eig 400 x 400, SVD
/// 400 x 1000, 4608 x 100) 1.3-1.5x *slower* than sequential, and the fleet's nodes run
/// several processes at once anyway. Call once at start-up.
pub fn configure_linalg_threads() -> usize {
    let n = std::env::var("HETFLEET_LINALG_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .unwrap_or(1)
        .max(1);
    faer::set_global_parallelism(if n == 1 { faer::Par::Seq } else { faer::Par::rayon(n) });
    n
}
