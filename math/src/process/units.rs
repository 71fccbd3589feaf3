//! The units a field may come in: the range of magnitudes the estimator holds exactly.
//!
//! Every computation is in the field's own units, and a few guards are absolute (variances
//! floored at 1e-12 so that a flat field's variance of 0 cannot zero a gain; f32 in the
//! report's figures and files). Inside the range below, a field multiplied by any factor gives
//! the same estimate times that factor, and the same calibration (measured: from 1e-4 to 1e6
//! times a field, the MSE over the field's variance the same to 6 digits; tested at 2^13 and
//! 2^-13 times one, which scale without rounding: every per-step MSE 2^52 apart to 1e-9).
//! Outside it the
//! guards are no longer negligible or the squares overflow, so such a field is refused with
//! the factor to rescale it by, rather than estimated wrongly (at 1e-6 the calibration read
//! 0.10 for 1.55; at 1e100 the filter's variances overflowed).

/// Largest magnitude of a value: its square, summed over a grid, fits f64 and the report's f32.
pub const LARGEST: f64 = 1e15;
/// Smallest spread (standard deviation over every value) of a field that varies at all.
pub const SMALLEST_SPREAD: f64 = 1e-5;
/// Smallest sensor noise (standard deviation) other than 0: its variance 1e-10, a hundred times
/// the variance floor.
pub const SMALLEST_NOISE: f64 = 1e-5;

/// The largest magnitude and the spread of a field's values (NaN skipped), made one value at a
/// time (Welford's update), so a truth read frame by frame needs no second pass.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Spread {
    n: u64,
    mean: f64,
    m2: f64,
    largest: f64,
}

impl Spread {
    pub fn of<'a>(values: impl IntoIterator<Item = &'a f64>) -> Self {
        let mut s = Self::default();
        values.into_iter().for_each(|&v| s.add(v));
        s
    }

    pub fn add(&mut self, v: f64) {
        if !v.is_finite() {
            return;
        }
        self.n += 1;
        let d = v - self.mean;
        self.mean += d / self.n as f64;
        self.m2 += d * (v - self.mean);
        self.largest = self.largest.max(v.abs());
    }

    /// The standard deviation of the values (0 for fewer than two).
    pub fn sd(&self) -> f64 {
        if self.n < 2 {
            return 0.0;
        }
        (self.m2 / self.n as f64).max(0.0).sqrt()
    }

    /// Whether the field is in units the estimator holds exactly; if not, why, with the factor
    /// to rescale it by.
    pub fn check(&self) -> Result<(), String> {
        if self.largest > LARGEST {
            return Err(format!(
                "values as large as {:.3e}: beyond {LARGEST:e} the model's sums of squares and the \
                 report's single-precision figures overflow; give the field in larger units (divide it by {})",
                self.largest,
                power_of_ten(self.largest / LARGEST)
            ));
        }
        let sd = self.sd();
        if sd > 0.0 && sd < SMALLEST_SPREAD {
            return Err(format!(
                "values spread by {sd:.3e} (standard deviation): below {SMALLEST_SPREAD:e} the estimator's \
                 variance floor (1e-12) is no longer negligible; give the field in smaller units (multiply it by {})",
                power_of_ten(SMALLEST_SPREAD / sd)
            ));
        }
        Ok(())
    }
}

/// Whether a sensor noise `sigma` (standard deviation, the field's units) is 0 or large enough
/// for the variance floor to be negligible beside it.
pub fn check_noise(sigma: f64) -> Result<(), String> {
    if sigma > 0.0 && sigma < SMALLEST_NOISE {
        return Err(format!(
            "noise {sigma:e}: below {SMALLEST_NOISE:e} (other than 0) the estimator's variance floor (1e-12) \
             is no longer negligible beside it; give the field and its noise in smaller units (multiply both by {})",
            power_of_ten(SMALLEST_NOISE / sigma)
        ));
    }
    Ok(())
}

/// The least power of ten at or above `x` (>= 1), as `1e<k>`.
fn power_of_ten(x: f64) -> String {
    format!("1e{}", x.max(1.0).log10().ceil() as i32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_spread_is_the_population_deviation_and_nan_is_skipped() {
        let s = Spread::of(&[1.0, f64::NAN, 3.0, 5.0, 7.0]);
        assert!((s.sd() - 5f64.sqrt()).abs() < 1e-12, "{}", s.sd());
        assert_eq!(Spread::of(&[2.0]).sd(), 0.0);
    }

    #[test]
    fn fields_outside_the_range_are_refused_with_the_factor_to_rescale_by() {
        assert!(Spread::of(&[0.0, 1e-3, 2e-3]).check().is_ok());
        assert!(
            Spread::of(&[1e12, 1e12 + 1.0]).check().is_ok(),
            "an offset is no spread"
        );
        assert!(Spread::of(&[3.0; 4]).check().is_ok(), "a flat field is not refused");
        let small = Spread::of(&[0.0, 1e-8, 2e-8]).check().unwrap_err();
        assert!(small.contains("multiply it by 1e4"), "{small}");
        let large = Spread::of(&[0.0, 3e17]).check().unwrap_err();
        assert!(large.contains("divide it by 1e3"), "{large}");
        assert!(check_noise(0.0).is_ok() && check_noise(1e-5).is_ok());
        let noise = check_noise(2e-8).unwrap_err();
        assert!(noise.contains("multiply both by 1e3"), "{noise}");
    }
}
