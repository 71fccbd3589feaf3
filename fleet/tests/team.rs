//! A tiny configuration of the paper's loop (DESIGN.md "The loop") on a simulated cloud:
//! the relations the paper reports, and determinism.

use fleet::experiment::team::{run, Placement, TeamConfig};
use fleet::process::plasma::{PlasmaCloud, Preset};
use fleet::process::FieldSeries;

fn tiny_cloud() -> FieldSeries {
    let mut p = Preset::Cloud10.params();
    (p.ny, p.nx) = (24, 96);
    p.out_dt = 0.3;
    let mut sim = PlasmaCloud::new(p).unwrap();
    sim.run(60, |_| {}).unwrap()
}

/// The paper's Table 2 first row, scaled down: aerials every step at a third of the boats'
/// spatial resolution (AV/MV space rates 12/4), boats every 5 steps, the same noise (0.15) on
/// both; 4 boats of radius 3 on a 24 x 96 grid.
fn tiny_config() -> TeamConfig {
    TeamConfig {
        aerial_stride: 3,
        aerial_sigma0: 0.15,
        aerial_growth_per_cell: 0.0,
        boat_sigma: 0.15,
        radius: 3.0,
        boats: 4,
        rank: "8".into(),
        init_steps: 10,
        boat_period: 5,
        ..TeamConfig::default()
    }
}

#[test]
fn heterogeneous_team_beats_homogeneous_ones_and_qr_beats_random() {
    let truth = tiny_cloud();
    let cfg = tiny_config();
    let het = run(&cfg, &truth, |_, _| {}).unwrap();
    let random = run(&TeamConfig { placement: Placement::Random, ..cfg.clone() }, &truth, |_, _| {}).unwrap();
    println!(
        "time-averaged MSE: heterogeneous {:.3e}, aerial-only {:.3e}, boat-only {:.3e}; random placement {:.3e}",
        het.mean_heterogeneous, het.mean_aerial_only, het.mean_boat_only, random.mean_heterogeneous
    );
    assert_eq!(het.heterogeneous.len(), 60);
    assert!(het.mean_heterogeneous < het.mean_aerial_only);
    assert!(het.mean_heterogeneous < het.mean_boat_only);
    assert!(het.mean_heterogeneous < random.mean_heterogeneous);
}

#[test]
fn same_seed_same_numbers() {
    let truth = tiny_cloud();
    let cfg = tiny_config();
    let a = serde_json::to_string(&run(&cfg, &truth, |_, _| {}).unwrap()).unwrap();
    let b = serde_json::to_string(&run(&cfg, &truth, |_, _| {}).unwrap()).unwrap();
    assert_eq!(a, b);
}
