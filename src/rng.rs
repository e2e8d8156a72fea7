//! A small seeded random number generator, so that every stochastic step (test fixtures,
//! synthetic scans, procedural scenes) gives the same numbers for the same seed on every
//! platform and in every version: byte-identical outputs need a generator whose sequence is
//! part of this crate, not of a dependency.
//!
//! The state advances as a 64-bit linear congruential generator with Knuth's MMIX constants
//! (`s <- 6364136223846793005 s + 1442695040888963407 mod 2^64`, Knuth, TAOCP vol. 2, 3.3.4);
//! [`Lcg::uniform`] returns the top 53 bits of the new state as a float in [0, 1).

/// Seeded 64-bit LCG; see the module docs.
#[derive(Debug, Clone)]
pub struct Lcg(pub u64);

impl Lcg {
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal deviate by the Box-Muller transform.
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform(); // (0, 1]: the logarithm stays finite
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moments_of_uniform_and_normal() {
        let mut g = Lcg(1);
        let n = 200_000;
        let u: Vec<f64> = (0..n).map(|_| g.uniform()).collect();
        let mean = u.iter().sum::<f64>() / n as f64;
        assert!((mean - 0.5).abs() < 5e-3 && u.iter().all(|&x| (0.0..1.0).contains(&x)));
        let z: Vec<f64> = (0..n).map(|_| g.normal()).collect();
        let m = z.iter().sum::<f64>() / n as f64;
        let v = z.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n as f64;
        assert!(m.abs() < 0.01 && (v - 1.0).abs() < 0.01, "{m} {v}");
        // The sequence is fixed: the first draw from seed 1.
        assert_eq!(
            Lcg(1).uniform(),
            ((6364136223846793005u64.wrapping_add(1442695040888963407)) >> 11) as f64 / (1u64 << 53) as f64
        );
    }
}
