//! hetfleet's mathematics, with nothing of the network, the command line or plots: the layer
//! every other crate stands on.
//!
//! One module per idea: [`grid`] (the workspace raster and sensing disks), [`dmd`] (batch,
//! general online and long-term online DMD), [`sensing`] (gappy reconstruction, QR placement,
//! coverage, assignment), [`fusion`] (the sensor model, aerial frames and their combination
//! with the boats' estimate), [`kalman`] (a Kalman filter in a DMD model's modal coordinates:
//! the fused map as a posterior), [`process`] (field sources: the plasma-cloud simulator,
//! synthetic fields, `.npy` datasets), [`npy`] (numpy-compatible files).

pub mod dmd;
pub mod fusion;
pub mod grid;
pub mod kalman;
pub mod npy;
pub mod process;
pub mod sensing;

/// The allocator hetfleet's binaries and benchmarks use (`#[global_allocator] static A:
/// fleet_math::Allocator = fleet_math::Allocator;`): a fit allocates and frees matrices of
/// megabytes, which glibc's malloc maps and unmaps each time (page faults were 60% of a
/// 4608 x 100 batch fit); mimalloc reuses them.
pub use mimalloc::MiMalloc as Allocator;

/// Keep memory the process frees for its next allocations instead of returning it to the
/// system after 10 ms (mimalloc's `purge_delay = -1`). An epoch at 192 x 384 allocates and
/// frees N x r matrices of megabytes in every phase; returned, each came back as fresh pages
/// the kernel zeroed on first touch, 27% of `fleet bench epoch`'s time (`perf`: `clear_page_erms`).
/// The process's resident size is then its peak, which it reaches every epoch anyway. Call once
/// at start-up, with [`configure_linalg_threads`].
pub fn keep_freed_memory() {
    // `mi_option_purge_delay` in mimalloc.h's `mi_option_e` (the same place in v2 and v3);
    // libmimalloc-sys names only the options before it.
    const PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;
    // SAFETY: sets one of mimalloc's option values, which it reads atomically; no pointers.
    unsafe { libmimalloc_sys::mi_option_set(PURGE_DELAY, -1) }
}

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
