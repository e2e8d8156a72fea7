//! Exact replacements for `f64::round` and `f64::floor` that the compiler inlines.
//!
//! On the baseline x86-64 target (no SSE4.1 `roundsd`) both are calls into the C library,
//! which dominate the per-sample passes over tens of millions of samples. These give the same
//! bits for every input, signed zeros included: below 2^52 in magnitude the truncation
//! `x as i64` is exact and `x - trunc(x)` is exact, so the decision on the fraction is exact;
//! from 2^52 on every finite double is an integer, and those, infinities and NaN go to the
//! library functions.

/// Magnitude from which every finite `f64` is an integer.
const INTEGRAL: f64 = 4_503_599_627_370_496.0; // 2^52

/// Truncation toward zero with the sign of `x` kept (`-0.3 -> -0.0`), for `|x| < 2^52`.
#[inline]
fn trunc_small(x: f64) -> f64 {
    debug_assert!(x.abs() < INTEGRAL);
    // SAFETY: callers pass `|x| < 2^52`, which is finite and inside the range of `i64`, so
    // the conversion is the plain truncation (no saturation or NaN fix-up needed).
    let t = unsafe { x.to_int_unchecked::<i64>() };
    (t as f64).copysign(x)
}

/// `x.round()`: the nearest integer, halves away from zero; bit for bit the same.
#[inline]
pub fn round(x: f64) -> f64 {
    if x.abs() < INTEGRAL {
        let t = trunc_small(x);
        // Without a branch (the fraction is as good as random in a quantizer's pass, and a
        // mispredicted branch costs more than the arithmetic): adding a zero of `x`'s sign
        // leaves `t` (which carries that sign) unchanged, signed zeros included.
        let up = ((x - t).abs() >= 0.5) as u8 as f64;
        t + up.copysign(x)
    } else {
        x.round()
    }
}

/// `x.floor()`: the largest integer not above `x`; bit for bit the same.
#[inline]
pub fn floor(x: f64) -> f64 {
    if x.abs() < INTEGRAL {
        let t = trunc_small(x);
        // Without a branch, as in `round`: subtracting +0 leaves `t` unchanged, signed zeros
        // included.
        t - (t > x) as u8 as f64
    } else {
        x.floor()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn same(a: f64, b: f64) -> bool {
        a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
    }

    #[test]
    fn round_and_floor_equal_the_library_bit_for_bit() {
        let mut x: Vec<f64> = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.5,
            -1.5,
            2.5,
            0.49999999999999994,
            -0.49999999999999994,
            INTEGRAL - 0.5,
            -(INTEGRAL - 0.5),
            INTEGRAL,
            INTEGRAL + 1.0,
            1e300,
            -1e300,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            5e-324,
            -5e-324,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            65535.5,
            65535.49999999999,
        ];
        // Integers, halves and their neighbours, and pseudo-random bit patterns.
        for k in -3000i64..3000 {
            let h = k as f64 * 0.5;
            x.extend([h, f64::from_bits(h.to_bits() + 1), f64::from_bits(h.to_bits().wrapping_sub(1))]);
        }
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        for _ in 0..200_000 {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            let v = f64::from_bits(s);
            // Bit patterns favour huge magnitudes; scale some into the interesting range.
            x.extend([v, v * 1e-300, (s >> 11) as f64 / (1u64 << 40) as f64 - 4096.0]);
        }
        for v in x {
            assert!(same(round(v), v.round()), "round({v:e}): {} vs {}", round(v), v.round());
            assert!(same(floor(v), v.floor()), "floor({v:e}): {} vs {}", floor(v), v.floor());
        }
    }
}
