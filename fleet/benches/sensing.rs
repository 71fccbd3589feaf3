//! Criterion benchmarks of sensor placement (the same cases with pysensors beside them:
//! `fleet bench sensing`).

#[global_allocator]
static ALLOCATOR: fleet_math::Allocator = fleet_math::Allocator;

use criterion::{criterion_group, criterion_main, Criterion};
use fleet_math::grid::Grid;
use fleet_math::process::synthetic::smooth_basis;
use fleet_math::sensing::qr::{block_qr, point_qr};

fn placement(c: &mut Criterion) {
    fleet_math::configure_linalg_threads();
    let grid = Grid::new(48, 96, 1.0).unwrap();
    let phi = smooth_basis(&grid, 10, 7);
    c.bench_function("block QR 48x96 r10 radius 10, 5 boats", |b| {
        b.iter(|| std::hint::black_box(block_qr(phi.as_ref(), &grid, 5, 10.0).unwrap()))
    });
    let pod = fleet::experiment::sensing_timing::pod_basis_48x96(10);
    c.bench_function("point QR 4608x10", |b| {
        b.iter(|| std::hint::black_box(point_qr(pod.as_ref(), 10)))
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30);
    targets = placement
}
criterion_main!(benches);
