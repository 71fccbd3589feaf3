//! hetfleet's shared library: the paper's mathematics (no network here) and the pieces the
//! `fleet` CLI, the model server and the vehicle nodes all call.
//!
//! One module per idea: [`grid`] (the workspace raster and sensing disks), [`dmd`] (batch,
//! general online and long-term online DMD), [`process`] (field sources), [`experiment`]
//! (the paper's studies), [`sensing`] (gappy reconstruction, QR placement, coverage,
//! assignment), [`fusion`] (aerial frames and their combination with the boats' estimate),
//! [`npy`] (numpy-compatible files), [`exit`] (every binary's exit codes and one-line errors).

pub mod dmd;
pub mod exit;
pub mod experiment;
pub mod fusion;
pub mod grid;
pub mod mission;
pub mod npy;
pub mod plot;
pub mod process;
pub mod protocol;
pub mod sensing;

/// The allocator hetfleet's binaries and benchmarks use (`#[global_allocator] static A:
/// fleet::Allocator = fleet::Allocator;`): a fit allocates and frees matrices of megabytes,
/// which glibc's malloc maps and unmaps each time (page faults were 60% of a 4608 x 100 batch
/// fit); mimalloc reuses them.
pub use mimalloc::MiMalloc as Allocator;

/// Set faer's parallelism from `HETFLEET_LINALG_THREADS` (default 1). On the 2-core machines
/// we run on, faer's rayon parallelism made the decompositions DMD uses (eig 400 x 400, SVD
/// 400 x 1000, 4608 x 100) 1.3-1.5x *slower* than sequential, and the fleet's nodes run
/// several processes at once anyway. Call once at start-up.
pub fn configure_linalg_threads() -> usize {
    let n = std::env::var("HETFLEET_LINALG_THREADS").ok().and_then(|v| v.parse::<usize>().ok()).unwrap_or(1).max(1);
    faer::set_global_parallelism(if n == 1 { faer::Par::Seq } else { faer::Par::rayon(n) });
    n
}
