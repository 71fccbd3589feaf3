//! The claims a fused estimate is held to, checked row by row from the numbers the report
//! already prints (the paired intervals, the steps won, the calibration by decile), so that a
//! reader sees where each holds and, as plainly, where it does not: a table of verdicts
//! rather than a verdict a reader must assemble from four tables.

use super::comparison::{Comparison, AERIAL_ONLY, BOAT_ONLY, HETEROGENEOUS, RANDOM};
use super::stats::{Interval, Outcome};
use serde::Serialize;
use std::collections::BTreeMap;

/// The fused team with the honest-variance placement, and the one fused another way.
const HORIZON: &str = "heterogeneous-horizon";
const INVERSE_VARIANCE: &str = "heterogeneous-inverse-variance";
/// The share of scored steps at which the fused team must be at or below the better single team.
pub const STEPS_WON: f64 = 0.9;
/// The claim counted over rows (it must hold on most, not every one).
pub const HORIZON_OVER_QR: &str = "horizon better than QR (horizon - QR)";
/// Calibration within this band in every decile of reported variance.
pub const DECILE_BAND: std::ops::RangeInclusive<f64> = 0.7..=1.3;

/// One claim on one row: whether it holds, with the number that says so.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Check {
    pub claim: String,
    /// `None`: the row did not run what the claim needs (the team is not in the config).
    pub holds: Option<bool>,
    pub evidence: String,
}

impl Check {
    /// The report's cell: the verdict, then the number.
    pub fn cell(&self) -> String {
        match self.holds {
            Some(true) => format!("holds ({})", self.evidence),
            Some(false) => format!("**not held** ({})", self.evidence),
            None => "not run".into(),
        }
    }
}

/// Of `checks`, how many hold and how many were checked (a claim `not run` is neither).
pub fn tally<'a>(checks: impl IntoIterator<Item = &'a Check>) -> (usize, usize) {
    checks.into_iter().fold((0, 0), |(held, checked), c| match c.holds {
        Some(h) => (held + usize::from(h), checked + 1),
        None => (held, checked),
    })
}

/// What a row's numbers say of each claim, in a fixed order (the report's columns).
pub fn of(
    comparisons: &[Comparison],
    teams: &BTreeMap<String, Interval>,
    steps_won: &BTreeMap<String, f64>,
    reliability: &BTreeMap<String, Vec<Interval>>,
) -> Vec<Check> {
    let relative = Relative { comparisons, teams };
    let mut checks = vec![
        relative.check(
            "fused below aerial-only (fused - aerial-only)",
            HETEROGENEOUS,
            AERIAL_ONLY,
            &[Outcome::Better],
        ),
        relative.check(
            "fused below boat-only (fused - boat-only)",
            HETEROGENEOUS,
            BOAT_ONLY,
            &[Outcome::Better],
        ),
        relative.check(
            "fused below inverse-variance (inverse-variance - fused)",
            INVERSE_VARIANCE,
            HETEROGENEOUS,
            &[Outcome::Worse],
        ),
        steps_check(steps_won.get(HETEROGENEOUS).copied()),
    ];
    for (label, team) in [("QR", HETEROGENEOUS), ("random", RANDOM), ("horizon", HORIZON)] {
        checks.push(decile_check(label, reliability.get(team)));
    }
    let not_worse = [Outcome::Better, Outcome::NotDistinguishable];
    checks.push(relative.check(
        "horizon at least as good as random (horizon - random)",
        HORIZON,
        RANDOM,
        &not_worse,
    ));
    checks.push(relative.check(HORIZON_OVER_QR, HORIZON, HETEROGENEOUS, &[Outcome::Better]));
    checks
}

/// The paired comparisons of a row and the teams' means, to say a difference in percent.
struct Relative<'a> {
    comparisons: &'a [Comparison],
    teams: &'a BTreeMap<String, Interval>,
}

impl Relative<'_> {
    /// The claim holds when `first - second`'s verdict is one of `wanted`; the evidence is the
    /// difference in percent of `second`'s mean with its interval (the claim's words name the
    /// difference).
    fn check(&self, claim: &str, first: &str, second: &str, wanted: &[Outcome]) -> Check {
        let found = self.comparisons.iter().find(|c| c.first == first && c.second == second);
        let (Some(c), Some(base)) = (found, self.teams.get(second)) else {
            return Check {
                claim: claim.into(),
                holds: None,
                evidence: String::new(),
            };
        };
        let pct = |x: f64| 100.0 * x / base.mean;
        Check {
            claim: claim.into(),
            holds: Some(wanted.contains(&c.verdict)),
            evidence: format!(
                "{:+.2}% [{:+.2}, {:+.2}]",
                pct(c.difference.mean),
                pct(c.difference.lo),
                pct(c.difference.hi)
            ),
        }
    }
}

fn steps_check(won: Option<f64>) -> Check {
    Check {
        claim: format!(
            "fused at or below the better single team at {:.0}% of steps",
            100.0 * STEPS_WON
        ),
        holds: won.map(|w| w >= STEPS_WON),
        evidence: won.map_or(String::new(), |w| format!("{:.1}%", 100.0 * w)),
    }
}

fn decile_check(placement: &str, by_decile: Option<&Vec<Interval>>) -> Check {
    let by_decile = by_decile.filter(|d| !d.is_empty());
    let in_band = by_decile.map(|d| d.iter().filter(|i| DECILE_BAND.contains(&i.mean)).count());
    Check {
        claim: format!("deciles in 0.7-1.3 under {placement}"),
        holds: by_decile.zip(in_band).map(|(d, n)| n == d.len()),
        evidence: by_decile
            .zip(in_band)
            .map_or(String::new(), |(d, n)| format!("{n}/{}", d.len())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn interval(mean: f64, lo: f64, hi: f64) -> Interval {
        Interval { mean, lo, hi, n: 10 }
    }

    fn compare(first: &str, second: &str, d: Interval) -> Comparison {
        Comparison {
            first: first.into(),
            second: second.into(),
            difference: d,
            verdict: Outcome::of(&d),
        }
    }

    #[test]
    fn each_claim_is_read_from_its_own_number_and_a_team_not_run_is_said_so() {
        let teams: BTreeMap<String, Interval> = [HETEROGENEOUS, AERIAL_ONLY, BOAT_ONLY, RANDOM]
            .iter()
            .map(|t| (t.to_string(), interval(2.0, 1.9, 2.1)))
            .collect();
        let comparisons = vec![
            // Below aerial-only by 5% [2.5, 7.5]: holds; boat-only not distinguishable: not held.
            compare(HETEROGENEOUS, AERIAL_ONLY, interval(-0.1, -0.15, -0.05)),
            compare(HETEROGENEOUS, BOAT_ONLY, interval(-0.1, -0.3, 0.1)),
            // Inverse-variance worse than the fused team: the fused team is below it.
            compare(INVERSE_VARIANCE, HETEROGENEOUS, interval(0.2, 0.1, 0.3)),
        ];
        let won: BTreeMap<String, f64> = [(HETEROGENEOUS.to_string(), 0.899)].into();
        let mut deciles = vec![interval(1.0, 0.9, 1.1); 10];
        let reliability: BTreeMap<String, Vec<Interval>> = [
            (HETEROGENEOUS.to_string(), deciles.clone()),
            (RANDOM.to_string(), {
                deciles[9] = interval(1.31, 1.2, 1.4);
                deciles
            }),
        ]
        .into();
        let checks = of(&comparisons, &teams, &won, &reliability);
        let holds: Vec<Option<bool>> = checks.iter().map(|c| c.holds).collect();
        assert_eq!(
            holds,
            [
                Some(true),
                Some(false),
                Some(true),
                Some(false),
                Some(true),
                Some(false),
                None,
                None,
                None
            ]
        );
        assert_eq!(checks[0].evidence, "-5.00% [-7.50, -2.50]");
        assert_eq!(
            (checks[3].evidence.as_str(), checks[5].evidence.as_str()),
            ("89.9%", "9/10")
        );
        assert_eq!(checks[6].cell(), "not run");
        assert!(checks[1].cell().starts_with("**not held**"));
        assert_eq!(tally(&checks), (3, 6));
    }
}
