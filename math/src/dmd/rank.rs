//! How many singular values a DMD keeps (the same choices PyDMD offers).

use std::fmt;
use std::str::FromStr;

/// Truncation rank of the SVD of the snapshot matrix.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RankPolicy {
    /// Keep every singular value above the numerical-rank tolerance (no truncation).
    Full,
    /// Keep at most this many (fewer if the data has lower numerical rank).
    Fixed(usize),
    /// Keep the fewest singular values whose squares reach this fraction of the total energy.
    Energy(f64),
    /// Gavish & Donoho's optimal hard threshold for unknown noise (PyDMD's `svd_rank=0`).
    Optimal,
}

impl RankPolicy {
    /// The rank for singular values `s` (non-increasing) of a `rows x cols` matrix. Never more
    /// than the numerical rank, and at least 1 when the matrix is not zero.
    pub fn select(&self, s: &[f64], rows: usize, cols: usize) -> usize {
        let numerical = numerical_rank(s, rows, cols);
        if numerical == 0 {
            return 0;
        }
        let r = match *self {
            RankPolicy::Full => numerical,
            RankPolicy::Fixed(r) => r,
            RankPolicy::Energy(f) => {
                let total: f64 = s.iter().map(|x| x * x).sum();
                let mut acc = 0.0;
                let mut r = s.len();
                for (i, x) in s.iter().enumerate() {
                    acc += x * x;
                    if acc / total >= f {
                        r = i + 1;
                        break;
                    }
                }
                r
            }
            RankPolicy::Optimal => {
                let (a, b) = (rows.min(cols) as f64, rows.max(cols) as f64);
                let beta = a / b;
                let omega = 0.56 * beta.powi(3) - 0.95 * beta.powi(2) + 1.82 * beta + 1.43;
                let tau = median(s) * omega;
                s.iter().filter(|&&x| x > tau).count()
            }
        };
        r.clamp(1, numerical)
    }
}

/// Count of singular values above `max(rows, cols) * eps * s[0]` (numpy's `matrix_rank`).
pub fn numerical_rank(s: &[f64], rows: usize, cols: usize) -> usize {
    let Some(&s0) = s.first() else { return 0 };
    if !(s0 > 0.0) {
        return 0;
    }
    let tol = rows.max(cols) as f64 * f64::EPSILON * s0;
    s.iter().filter(|&&x| x > tol).count()
}

fn median(s: &[f64]) -> f64 {
    let mut v = s.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

impl fmt::Display for RankPolicy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            RankPolicy::Full => write!(f, "full"),
            RankPolicy::Fixed(r) => write!(f, "{r}"),
            RankPolicy::Energy(e) => write!(f, "energy:{e}"),
            RankPolicy::Optimal => write!(f, "optimal"),
        }
    }
}

/// In files: `"full"`, `"optimal"`, `"energy:<f>"`, or an integer (`6` or `"6"`).
impl schemars::JsonSchema for RankPolicy {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "RankPolicy".into()
    }

    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({
            "description": "How many singular values the DMD keeps: an integer (at most that many), \"full\" (every one above the numerical-rank tolerance), \"optimal\" (Gavish and Donoho's hard threshold) or \"energy:<fraction>\" (the fewest reaching that fraction of the energy).",
            "anyOf": [
                {"type": "integer", "minimum": 1},
                {"type": "string", "pattern": "^(full|optimal|energy:[0-9.eE+-]+|[1-9][0-9]*)$"}
            ]
        })
    }
}

impl serde::Serialize for RankPolicy {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> serde::Deserialize<'de> for RankPolicy {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(serde::Deserialize)]
        #[serde(untagged)]
        enum Rank {
            Text(String),
            Number(u64),
        }
        const WHAT: &str = "rank: give \"full\", \"optimal\", \"energy:<fraction>\" or a positive integer";
        let text = match Rank::deserialize(d).map_err(|_| serde::de::Error::custom(WHAT))? {
            Rank::Text(t) => t,
            Rank::Number(n) => n.to_string(),
        };
        text.parse().map_err(|e| serde::de::Error::custom(format!("rank: {e}")))
    }
}

impl FromStr for RankPolicy {
    type Err = String;
    /// `full`, `optimal`, an integer, or `energy:<fraction in (0, 1]>`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "full" => Ok(RankPolicy::Full),
            "optimal" => Ok(RankPolicy::Optimal),
            t if t.starts_with("energy:") => {
                let f: f64 = t[7..].parse().map_err(|_| format!("bad energy fraction in {t:?}"))?;
                if f > 0.0 && f <= 1.0 {
                    Ok(RankPolicy::Energy(f))
                } else {
                    Err(format!("energy fraction must be in (0, 1], got {f}"))
                }
            }
            t => match t.parse::<usize>() {
                Ok(0) => Err("rank must be at least 1".into()),
                Ok(r) => Ok(RankPolicy::Fixed(r)),
                Err(_) => Err(format!(
                    "rank must be full, optimal, energy:<f> or an integer, got {t:?}"
                )),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_prints() {
        for s in ["full", "optimal", "7", "energy:0.99"] {
            assert_eq!(s.parse::<RankPolicy>().unwrap().to_string(), s);
        }
        assert!("0".parse::<RankPolicy>().is_err());
        assert!("energy:1.5".parse::<RankPolicy>().is_err());
        assert!("many".parse::<RankPolicy>().is_err());
    }

    #[test]
    fn selects() {
        let s = [10.0, 5.0, 1.0, 0.1, 1e-20];
        assert_eq!(RankPolicy::Full.select(&s, 5, 10), 4);
        assert_eq!(RankPolicy::Fixed(2).select(&s, 5, 10), 2);
        assert_eq!(RankPolicy::Fixed(9).select(&s, 5, 10), 4);
        // energies: 100, 125, 126, 126.01 of 126.01
        assert_eq!(RankPolicy::Energy(0.99).select(&s, 5, 10), 2);
        assert_eq!(RankPolicy::Energy(0.9999).select(&s, 5, 10), 3);
        assert_eq!(RankPolicy::Energy(0.99995).select(&s, 5, 10), 4);
        assert_eq!(RankPolicy::Full.select(&[0.0, 0.0], 2, 2), 0);
    }

    #[test]
    fn optimal_threshold_matches_pydmd_formula() {
        // square matrix: beta = 1, omega = 0.56 - 0.95 + 1.82 + 1.43 = 2.86; median = 3
        let s = [20.0, 10.0, 3.0, 2.9, 2.8];
        assert_eq!(RankPolicy::Optimal.select(&s, 5, 5), 2);
    }
}
