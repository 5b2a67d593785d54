//! Elementary functions on the servo tick's hot path, where libm's general-purpose versions
//! cost more than the accuracy they buy.

/// tanh through a single `exp`: 1 − 2/(e^{2a} + 1). It agrees with `f64::tanh` to a few
/// 1e-16 absolute (what a hidden unit or a friction curve needs) at about half the cost:
/// libm's tanh goes through `expm1`. Saturates cleanly (e^{2a} = ∞ gives 1, 0 gives −1).
#[inline]
pub(crate) fn tanh(a: f64) -> f64 {
    // Beyond |a| = 19.1 the formula rounds to exactly ±1 (2/(e^{2a}+1) < 2⁻⁵⁴ above, e^{2a} <
    // 2⁻⁵³ below), so skip the exp: the simulator's friction curve (a = q̇ / 0.01 rad/s) is
    // out there whenever a joint moves faster than 0.2 rad/s.
    if a.abs() > SATURATED {
        return 1.0f64.copysign(a);
    }
    by_exp(a)
}

/// Where `by_exp` has already saturated to ±1 in double precision.
const SATURATED: f64 = 19.1;

#[inline(always)]
fn by_exp(a: f64) -> f64 {
    1.0 - 2.0 / ((2.0 * a).exp() + 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tanh_matches_libm_to_rounding() {
        let mut worst: f64 = 0.0;
        for i in -200_000..=200_000 {
            let a = i as f64 * 1e-4; // −20 … 20, through both tails and the origin
            worst = worst.max((tanh(a) - a.tanh()).abs());
        }
        assert!(worst < 1e-15, "worst absolute error {worst:e}");
    }

    #[test]
    fn the_saturation_shortcut_changes_no_bit() {
        // Every value the shortcut returns is what the exp formula gives there, from just past
        // the threshold out to where e^{2a} overflows.
        let mut a = SATURATED;
        while a < 400.0 {
            for x in [a, -a] {
                assert_eq!(tanh(x).to_bits(), by_exp(x).to_bits(), "a = {x}");
            }
            a = a * (1.0 + 1e-6) + 1e-12;
        }
        // and the threshold is not needlessly far out: just inside it the formula is not ±1 yet.
        assert!(by_exp(18.0) < 1.0 && by_exp(-18.0) > -1.0);
    }

    #[test]
    fn tanh_saturates_and_passes_nan() {
        assert_eq!(tanh(1e6), 1.0);
        assert_eq!(tanh(-1e6), -1.0);
        assert_eq!(tanh(f64::INFINITY), 1.0);
        assert_eq!(tanh(f64::NEG_INFINITY), -1.0);
        assert!(tanh(f64::NAN).is_nan());
    }

    #[test]
    fn tanh_slope_is_one_minus_square() {
        // The networks' backward pass uses 1 − h²: check it against a central difference.
        for &a in &[-3.0, -0.7, 0.0, 0.2, 1.5, 4.0] {
            let h = 1e-6;
            let fd = (tanh(a + h) - tanh(a - h)) / (2.0 * h);
            let y = tanh(a);
            assert!((fd - (1.0 - y * y)).abs() < 1e-9, "a = {a}");
        }
    }
}
