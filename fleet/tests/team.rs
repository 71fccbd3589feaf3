//! A tiny configuration of the paper's loop (DESIGN.md "The loop") on a simulated cloud:
//! the relations the paper reports, and determinism.

use fleet::experiment::team::{run, Placement, TeamConfig};
use fleet_math::process::plasma::{PlasmaCloud, Preset};
use fleet_math::process::FieldSeries;

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
        rank: fleet_math::dmd::RankPolicy::Fixed(8),
        init_steps: 10,
        boat_period: 5,
        ..TeamConfig::default()
    }
}

/// The paper's relations as claims over seeds: every team of a seed sees the same truth and
/// noise, each verdict is read from the 95% interval of the paired difference (10 seeds).
/// With either fusion the fused team beats both single-kind teams. QR disks beat random ones
/// with inverse-variance fusion; with the Kalman filter they are not distinguishable on this
/// tiny cloud (the filter's detail takes most of what the disks' placement used to decide:
/// docs/results/README.md, "Where they hold"), so that verdict is asserted for inverse-variance only.
#[test]
fn over_ten_seeds_the_heterogeneous_team_beats_both_single_kind_teams() {
    use fleet::experiment::stats::{Interval, Outcome};
    use fleet_math::fusion::Scheme;
    let truth = tiny_cloud();
    for fusion in [Scheme::InverseVariance, Scheme::Kalman] {
        let (mut het, mut aerial, mut boat, mut random) = (vec![], vec![], vec![], vec![]);
        for seed in 1..=10 {
            let cfg = TeamConfig {
                seed,
                fusion,
                ..tiny_config()
            };
            let qr = run(&cfg, &truth, |_, _| {}).unwrap();
            let rnd = run(
                &TeamConfig {
                    placement: Placement::Random,
                    ..cfg.clone()
                },
                &truth,
                |_, _| {},
            )
            .unwrap();
            assert_eq!(qr.heterogeneous.len(), 60);
            assert_eq!(
                qr.scored_from, 14,
                "scored from the boats' first sample (step 10 + 5 - 1)"
            );
            assert!(
                qr.boat_only[..14].iter().all(Option::is_none) && qr.boat_only[14..].iter().all(Option::is_some),
                "the boat-only team has no estimate before its first sample"
            );
            het.push(qr.mean_heterogeneous);
            aerial.push(qr.mean_aerial_only);
            boat.push(qr.mean_boat_only);
            random.push(rnd.mean_heterogeneous);
        }
        let (a, b, q) = (
            Interval::paired(&het, &aerial),
            Interval::paired(&het, &boat),
            Interval::paired(&het, &random),
        );
        println!(
            "{fusion}, 10 seeds, paired differences [95%]: heterogeneous - aerial-only {a:?}; heterogeneous - \
            boat-only {b:?}; QR - random {q:?} ({})",
            Outcome::of(&q).words()
        );
        assert_eq!(Outcome::of(&a), Outcome::Better, "{fusion}: against aerial-only");
        assert_eq!(Outcome::of(&b), Outcome::Better, "{fusion}: against boat-only");
        if fusion == Scheme::InverseVariance {
            assert_eq!(Outcome::of(&q), Outcome::Better, "QR disks against random ones");
        }
    }
}

#[test]
fn same_seed_same_numbers() {
    let truth = tiny_cloud();
    let cfg = tiny_config();
    let a = serde_json::to_string(&run(&cfg, &truth, |_, _| {}).unwrap()).unwrap();
    let b = serde_json::to_string(&run(&cfg, &truth, |_, _| {}).unwrap()).unwrap();
    assert_eq!(a, b);
}

/// The oracle's disk choice on a known error map: two hot spots, the hotter first, the third
/// disk where what is left is largest, none overlapping and none on excluded cells.
#[test]
fn the_oracle_puts_disks_where_the_error_is() {
    use fleet::experiment::team::where_the_error_is;
    use fleet_math::grid::{Cell, Grid};
    let grid = Grid::new(20, 40, 1.0).unwrap();
    let mut err2 = vec![0.001; grid.len()];
    err2[grid.index(Cell::new(5, 30))] = 7.0;
    err2[grid.index(Cell::new(14, 8))] = 4.0;
    err2[grid.index(Cell::new(15, 8))] = 4.0; // the second spot, hotter than the first summed over a disk
    err2[grid.index(Cell::new(2, 2))] = 1.0;
    let mut excluded = vec![false; grid.len()];
    let disks = where_the_error_is(&grid, &err2, 3, 2.0, &excluded);
    let centres: Vec<(usize, usize)> = disks.iter().map(|d| d.1).collect();
    assert!(
        disks[0].0.contains(&grid.index(Cell::new(14, 8))) && disks[0].0.contains(&grid.index(Cell::new(15, 8))),
        "the disk with most error first: {centres:?}"
    );
    assert!(disks[1].0.contains(&grid.index(Cell::new(5, 30))), "{centres:?}");
    assert!(disks[2].0.contains(&grid.index(Cell::new(2, 2))), "{centres:?}");
    let mut seen = std::collections::BTreeSet::new();
    assert!(
        disks.iter().flat_map(|d| &d.0).all(|c| seen.insert(*c)),
        "disks overlap"
    );
    // Fenced off, the hottest spot is not taken; and no more disks than fit.
    for r in 0..20 {
        for c in 20..40 {
            excluded[grid.index(Cell::new(r, c))] = true;
        }
    }
    let fenced = where_the_error_is(&grid, &err2, 3, 2.0, &excluded);
    assert!(fenced.iter().flat_map(|d| &d.0).all(|&c| !excluded[c]));
    assert!(!fenced.iter().any(|d| d.0.contains(&grid.index(Cell::new(5, 30)))));
    assert_eq!(
        where_the_error_is(&Grid::new(3, 3, 1.0).unwrap(), &[1.0; 9], 4, 5.0, &[]).len(),
        1,
        "one disk covers the grid"
    );
}

/// The oracle (boats sent where a copy of the fleet, boats idle, is furthest from the truth)
/// does at least as well as QR on the tiny cloud, paired over 10 seeds. (It beat QR with
/// intervals excluding 0 until the filter's skill between the lattice was learned from the
/// boats, issue 37: disks where the error is are also where the filter is at its worst, so the
/// skill they measure is lower, and the margin fell to -6e-4 [-1.3e-3, 4e-5].)
#[test]
fn boats_sent_where_the_error_is_do_at_least_as_well_as_qr() {
    use fleet::experiment::stats::{Interval, Outcome};
    use fleet::experiment::team::run_oracle;
    let truth = tiny_cloud();
    let (mut qr, mut oracle) = (vec![], vec![]);
    for seed in 1..=10 {
        let cfg = TeamConfig { seed, ..tiny_config() };
        let q = run(&cfg, &truth, |_, _| {}).unwrap();
        let o = run_oracle(&cfg, &truth).unwrap();
        assert_eq!(o.scored_from, q.scored_from);
        assert_ne!(o.disks, q.disks, "seed {seed}: the oracle's disks are QR's");
        qr.push(q.mean_heterogeneous);
        oracle.push(o.mean_heterogeneous);
    }
    let d = Interval::paired(&oracle, &qr);
    println!("oracle - QR, 10 seeds [95%]: {d:?}");
    assert!(d.mean < 0.0 && Outcome::of(&d) != Outcome::Worse, "{d:?}");
}
