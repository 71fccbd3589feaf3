//! Criterion benchmarks of the DMD core (the Python side: `bench/peers/`, see docs/benchmarks.md).

#[global_allocator]
static ALLOCATOR: fleet_math::Allocator = fleet_math::Allocator;

use criterion::{criterion_group, criterion_main, Criterion};
use fleet_math::dmd::{pairs_of, Debias, DmdConfig, Method, RankPolicy};
use fleet_math::process::synthetic::smooth_sphere_field;

fn batch_4608x100_r10(c: &mut Criterion) {
    fleet_math::configure_linalg_threads();
    let times: Vec<f64> = (0..101).map(|k| 20.0 * k as f64 / 199.0).collect();
    let field = smooth_sphere_field(&times, 0.01, 42);
    let (x, y) = pairs_of(field.snapshots.as_ref());
    let cfg = DmdConfig {
        method: Method::Batch,
        rank: RankPolicy::Fixed(10),
        debias: Debias::None,
        gamma: 1.0,
        forgetting: Default::default(),
    };
    c.bench_function("batch DMD 4608x100 r10 fit+eig+modes+amplitudes", |b| {
        b.iter(|| {
            let m = cfg.init(x, y).unwrap();
            let modes = m.decompose().unwrap();
            let x0: Vec<f64> = x.col(0).iter().copied().collect();
            std::hint::black_box(modes.model(&x0, 1.0).unwrap());
        })
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30);
    targets = batch_4608x100_r10
}
criterion_main!(benches);
