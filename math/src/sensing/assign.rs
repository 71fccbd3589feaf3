//! Boats to chosen disks, minimising total travel time (Kuhn-Munkres from `pathfinding`).
//! Travel time is straight-line distance over speed, in integer microseconds (the solver wants
//! integer weights; a microsecond is far below any boat's timing).

use super::SensingError;
use pathfinding::matrix::Matrix;

/// For each boat, the index of its target (or `None` when there are more boats than targets),
/// and the total travel time in seconds. Positions and targets in metres; speed in m/s.
pub fn assign(
    boats: &[(f64, f64)],
    targets: &[(f64, f64)],
    speed: f64,
) -> Result<(Vec<Option<usize>>, f64), SensingError> {
    if !(speed.is_finite() && speed > 0.0) {
        return Err(SensingError::Input(format!("speed must be positive, got {speed}")));
    }
    if boats
        .iter()
        .chain(targets)
        .any(|(x, y)| !(x.is_finite() && y.is_finite()))
    {
        return Err(SensingError::Input("non-finite position".into()));
    }
    if boats.is_empty() || targets.is_empty() {
        return Ok((vec![None; boats.len()], 0.0));
    }
    let micros = |b: &(f64, f64), t: &(f64, f64)| (((b.0 - t.0).hypot(b.1 - t.1) / speed) * 1e6).round() as i64;
    // The solver needs rows <= columns: put the smaller side on the rows.
    let boats_are_rows = boats.len() <= targets.len();
    let (rows, cols) = if boats_are_rows {
        (boats, targets)
    } else {
        (targets, boats)
    };
    let weights = Matrix::from_rows(
        rows.iter()
            .map(|a| cols.iter().map(|b| micros(a, b)).collect::<Vec<_>>()),
    )
    .map_err(|e| SensingError::Numerical(format!("{e:?}")))?;
    let (total, row_to_col) = pathfinding::kuhn_munkres::kuhn_munkres_min(&weights);
    let mut out = vec![None; boats.len()];
    for (r, &c) in row_to_col.iter().enumerate() {
        if boats_are_rows {
            out[r] = Some(c);
        } else {
            out[c] = Some(r);
        }
    }
    Ok((out, total as f64 / 1e6))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// Best total over all injective maps from the smaller side to the larger, by brute force.
    fn brute(boats: &[(f64, f64)], targets: &[(f64, f64)], speed: f64) -> i64 {
        let micros = |b: &(f64, f64), t: &(f64, f64)| (((b.0 - t.0).hypot(b.1 - t.1) / speed) * 1e6).round() as i64;
        type Cost<'a> = &'a dyn Fn(&(f64, f64), &(f64, f64)) -> i64;
        fn go(i: usize, used: &mut Vec<bool>, a: &[(f64, f64)], b: &[(f64, f64)], f: Cost<'_>) -> i64 {
            if i == a.len() {
                return 0;
            }
            let mut best = i64::MAX;
            for j in 0..b.len() {
                if !used[j] {
                    used[j] = true;
                    best = best.min(f(&a[i], &b[j]) + go(i + 1, used, a, b, f));
                    used[j] = false;
                }
            }
            best
        }
        let (a, b) = if boats.len() <= targets.len() {
            (boats, targets)
        } else {
            (targets, boats)
        };
        go(0, &mut vec![false; b.len()], a, b, &micros)
    }

    #[test]
    fn equals_brute_force_for_every_small_instance() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for nb in 1..=6 {
            for nt in 1..=6 {
                for _ in 0..20 {
                    let pts = |n: usize, rng: &mut rand_chacha::ChaCha8Rng| -> Vec<(f64, f64)> {
                        (0..n)
                            .map(|_| (rng.random_range(0.0..500.0), rng.random_range(0.0..300.0)))
                            .collect()
                    };
                    let (b, t) = (pts(nb, &mut rng), pts(nt, &mut rng));
                    let (a, total) = assign(&b, &t, 1.5).unwrap();
                    let best = brute(&b, &t, 1.5);
                    assert_eq!((total * 1e6).round() as i64, best, "{nb} boats, {nt} targets");
                    // Every target used at most once; exactly min(nb, nt) boats assigned.
                    let mut used: Vec<usize> = a.iter().flatten().copied().collect();
                    assert_eq!(used.len(), nb.min(nt));
                    used.sort_unstable();
                    used.dedup();
                    assert_eq!(used.len(), nb.min(nt));
                }
            }
        }
        assert!(assign(&[(0.0, 0.0)], &[(1.0, 1.0)], 0.0).is_err());
        assert!(assign(&[(f64::NAN, 0.0)], &[(1.0, 1.0)], 1.0).is_err());
    }
}
