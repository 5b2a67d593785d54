//! Elementary functions on the servo tick's hot path, where libm's general-purpose versions
//! cost more than the accuracy they buy.

/// tanh through a single `exp`: 1 − 2/(e^{2a} + 1). It agrees with `f64::tanh` to a few
/// 1e-16 absolute (what the simulator's friction curve needs) at about half the cost: libm's
/// tanh goes through `expm1`. Saturates cleanly (e^{2a} = ∞ gives 1, 0 gives −1). The
/// networks' hidden layers use `tanh_in_place`.
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

/// tanh of every element in place: a hidden layer's units at once. One `exp` per unit through
/// libm was a sixth of the servo tick; this is the same tanh with an exp of its own, without
/// calls or branches, so the units run side by side in vector registers. It agrees with
/// `f64::tanh` to a few 1e-16 absolute, and gives the same bits on every machine (plain IEEE
/// adds, multiplies and one divide; no fused multiply-add, no libm).
pub(crate) fn tanh_in_place(a: &mut [f64]) {
    for x in a {
        *x = tanh_by_table(*x);
    }
}

/// tanh|a| = (1 − e)/(1 + e) with e = e^{−2|a|} ∈ (0, 1]: nothing overflows, and the sign is
/// put back last. e^{−x} = 2^k · 2^{j/64} · e^r with 64k + j = n = round(−x·64/ln2) and
/// |r| ≤ ln2/128, where a degree-5 Taylor polynomial is exact to 4e-17 relative.
#[inline(always)]
fn tanh_by_table(a: f64) -> f64 {
    let x = 2.0 * a.abs();
    // Past 2|a| = 40, e < 2⁻⁵⁴ and the quotient is exactly 1; the clamp keeps 2^k a normal
    // number. A NaN fails the compare and stays NaN.
    let x = if x > 40.0 { 40.0 } else { x };
    // Adding 1.5·2⁵² rounds −x·64/ln2 to the integer n and leaves n in the low mantissa bits.
    let shifted = -x * LN2_64_INV + ROUNDER;
    let n = shifted - ROUNDER;
    let bits = shifted.to_bits();
    let j = (bits & 63) as usize;
    // (bits >> 6) is ROUNDER's bits / 64 (low 12 bits zero) + floor(n/64) = k ∈ [−58, 0]:
    // its low 12 bits plus the bias are 2^k's exponent field.
    let two_k = f64::from_bits(((bits >> 6) + 1023) << 52);
    // n·LN2_64_HI is exact (|n| < 2¹², HI has 40 significant bits): Cody–Waite reduction.
    let r = (-x - n * LN2_64_HI) - n * LN2_64_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0)))));
    let e = EXP2_J64[j] * p * two_k;
    ((1.0 - e) / (1.0 + e)).copysign(a)
}

/// 64/ln2, rounded.
const LN2_64_INV: f64 = 92.33248261689366;
/// ln2/64 to 40 significant bits, and the rest.
const LN2_64_HI: f64 = 0.010830424696237628;
const LN2_64_LO: f64 = 1.1517191508074686e-14;
/// 1.5·2⁵²: adding it rounds to an integer, in the default rounding mode.
const ROUNDER: f64 = 6755399441055744.0;

/// 2^{j/64}, j = 0..63, each correctly rounded (computed to 200 bits; the tests check them
/// against libm's exp2).
#[rustfmt::skip]
const EXP2_J64: [f64; 64] = [
    1.0, 1.0108892860517005, 1.0218971486541166, 1.0330248790212284,
    1.0442737824274138, 1.0556451783605572, 1.0671404006768237, 1.0787607977571199,
    1.0905077326652577, 1.102382583307841, 1.1143867425958924, 1.1265216186082418,
    1.1387886347566916, 1.1511892299529827, 1.1637248587775775, 1.1763969916502812,
    1.189207115002721, 1.202156731452703, 1.215247359980469, 1.22848053610687,
    1.241857812073484, 1.255380757024691, 1.2690509571917332, 1.2828700160787783,
    1.2968395546510096, 1.3109612115247644, 1.3252366431597413, 1.339667524053303,
    1.3542555469368927, 1.3690024229745905, 1.383909881963832, 1.3989796725383112,
    std::f64::consts::SQRT_2, 1.42961333839197, 1.4451808069770467, 1.460917794180647,
    1.4768261459394993, 1.4929077282912648, 1.5091644275934228, 1.5255981507445384,
    1.5422108254079407, 1.559004400237837, 1.5759808451078865, 1.593142151342267,
    1.6104903319492543, 1.6280274218573478, 1.645755478153965, 1.6636765803267364,
    1.681792830507429, 1.7001063537185235, 1.718619298122478, 1.7373338352737062,
    1.7562521603732995, 1.7753764925265212, 1.7947090750031072, 1.8142521755003989,
    1.8340080864093424, 1.8539791250833855, 1.8741676341103, 1.8945759815869656,
    1.9152065613971474, 1.9360617934922943, 1.9571441241754002, 1.978456026387951,
];

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

    fn by_table(a: f64) -> f64 {
        let mut v = [a];
        tanh_in_place(&mut v);
        v[0]
    }

    #[test]
    fn the_layer_tanh_matches_libm_to_rounding() {
        let mut worst: f64 = 0.0;
        let mut worst_rel: f64 = 0.0;
        for i in -400_000..=400_000 {
            let a = i as f64 * 5e-5 + 1.3e-7; // −20 … 20, off the grid of table points
            let (mine, libm) = (by_table(a), a.tanh());
            worst = worst.max((mine - libm).abs());
            if a.abs() > 0.5 {
                worst_rel = worst_rel.max(((mine - libm) / libm).abs());
            }
        }
        assert!(worst < 4e-16, "worst absolute error {worst:e}");
        assert!(
            worst_rel < 1e-15,
            "worst relative error above |a| = 0.5: {worst_rel:e}"
        );
    }

    #[test]
    fn the_layer_tanh_does_each_element_and_keeps_odd_symmetry() {
        let mut v: Vec<f64> = (0..37).map(|i| (i as f64 - 18.0) * 0.37).collect();
        let before = v.clone();
        tanh_in_place(&mut v);
        for (y, a) in v.iter().zip(&before) {
            assert!((y - a.tanh()).abs() < 4e-16, "a = {a}");
            assert_eq!(by_table(-a).to_bits(), (-y).to_bits(), "a = {a}");
        }
    }

    #[test]
    fn the_layer_tanh_saturates_and_passes_nan_and_signed_zero() {
        for a in [20.0, 40.0, 1e6, 1e300, f64::INFINITY] {
            assert_eq!(by_table(a), 1.0, "a = {a}");
            assert_eq!(by_table(-a), -1.0, "a = {a}");
        }
        assert!(by_table(19.0) <= 1.0 && by_table(18.0) < 1.0);
        assert!(by_table(f64::NAN).is_nan());
        assert_eq!(by_table(0.0).to_bits(), 0.0f64.to_bits());
        assert_eq!(by_table(-0.0).to_bits(), (-0.0f64).to_bits());
        // The smallest arguments: the absolute error stays at the rounding of 1 − e.
        for a in [1e-300, 1e-12, 1e-8] {
            assert!((by_table(a) - a).abs() < 2.3e-16, "a = {a}");
        }
    }

    #[test]
    fn the_table_is_two_to_the_sixty_fourths() {
        for (j, t) in EXP2_J64.iter().enumerate() {
            let libm = (j as f64 / 64.0).exp2();
            // within one ulp of libm's (itself within one ulp of the true value)
            assert!(
                (t - libm).abs() <= f64::EPSILON * libm,
                "j = {j}: {t} vs {libm}"
            );
        }
    }

    #[test]
    fn the_reduction_constants_split_ln2_over_64_exactly() {
        let ln2_64 = std::f64::consts::LN_2 / 64.0;
        assert!((LN2_64_HI + LN2_64_LO - ln2_64).abs() <= f64::EPSILON * ln2_64);
        // 40 significant bits: n·HI is exact for the |n| < 2¹² the reduction meets.
        assert_eq!(LN2_64_HI.to_bits() & 0xFFF, 0);
        assert!((LN2_64_INV * ln2_64 - 1.0).abs() <= f64::EPSILON);
        assert_eq!(ROUNDER, 1.5 * 2f64.powi(52));
    }

    #[test]
    fn tanh_slope_is_one_minus_square() {
        // The networks' backward pass uses 1 − h²: check it against a central difference, for
        // the scalar tanh and the layer's.
        for (name, f) in [("scalar", tanh as fn(f64) -> f64), ("layer", by_table)] {
            for &a in &[-3.0, -0.7, 0.0, 0.2, 1.5, 4.0] {
                let h = 1e-6;
                let fd = (f(a + h) - f(a - h)) / (2.0 * h);
                let y = f(a);
                assert!((fd - (1.0 - y * y)).abs() < 1e-9, "{name}, a = {a}");
            }
        }
    }
}
