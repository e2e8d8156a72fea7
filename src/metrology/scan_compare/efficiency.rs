//! The diffraction-efficiency loss a fitted depth scale predicts ([`EfficiencyLoss`]): the
//! design order's efficiency with every phase step scaled by `k`.

use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::fabrication::quantize::{continuous_efficiency, detuning, order_efficiency};
use crate::fabrication::wrap::WrapSpec;
use crate::material::PAPER_WAVELENGTHS;

/// Predicted efficiency of the design order at one wavelength.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EfficiencyLoss {
    /// Wavelength, metres.
    pub wavelength: f64,
    /// Detuning of the design at this wavelength.
    pub detuning: f64,
    /// Efficiency of the design order with the design's depth, fraction of the energy (0..1).
    pub design: f64,
    /// Efficiency of the design order with every phase step scaled by the fitted depth scale
    /// (`a -> k a`), fraction of the energy (0..1).
    pub fabricated: f64,
    /// Efficiency lost, `design - fabricated`, fraction of the energy (negative where the
    /// fabricated depth does better).
    pub loss: f64,
}

/// Efficiency of order `m` at detuning `a`: Swanson's for `n` levels, `sinc^2(a - m)` for a
/// continuous profile.
pub(super) fn efficiency(levels: Option<usize>, a: f64, m: i64) -> f64 {
    match levels {
        Some(n) => order_efficiency(n, a, m),
        None => continuous_efficiency(a, m),
    }
}

/// The design order's efficiency at the paper's wavelengths with the design's depth and with
/// `depth_scale` times it (module docs).
pub fn efficiency_loss(
    spec: &WrapSpec,
    levels: Option<usize>,
    depth_scale: f64,
) -> Result<Vec<EfficiencyLoss>> {
    let n0 = spec.index()?;
    let m = spec.order as i64;
    PAPER_WAVELENGTHS
        .iter()
        .map(|&l| {
            let a = detuning(spec.order, spec.wavelength, n0, l, spec.material.index(l)?);
            let design = efficiency(levels, a, m);
            let fabricated = efficiency(levels, depth_scale * a, m);
            Ok(EfficiencyLoss { wavelength: l, detuning: a, design, fabricated, loss: design - fabricated })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Swanson's efficiency with a depth scale against the first Fourier coefficient of the
    /// scaled N-level staircase, integrated step by step (an independent computation).
    #[test]
    fn efficiency_loss_matches_the_staircase_fourier_coefficient() {
        let spec = WrapSpec::default();
        for (n, k) in [(8usize, 0.93), (4, 1.05), (16, 0.8)] {
            let rows = efficiency_loss(&spec, Some(n), k).unwrap();
            for r in &rows {
                // c_1 = sum_l exp(i 2 pi a k l / N) int_{l/N}^{(l+1)/N} exp(-i 2 pi x) dx.
                let (mut re, mut im) = (0.0, 0.0);
                for l in 0..n {
                    let phi = 2.0 * std::f64::consts::PI * r.detuning * k * l as f64 / n as f64;
                    let (x0, x1) = (l as f64 / n as f64, (l + 1) as f64 / n as f64);
                    let tau = 2.0 * std::f64::consts::PI;
                    // int exp(-i tau x) dx = (exp(-i tau x1) - exp(-i tau x0)) / (-i tau).
                    let (dr, di) =
                        ((tau * x1).cos() - (tau * x0).cos(), -(tau * x1).sin() + (tau * x0).sin());
                    let (ir, ii) = (-di / tau, dr / tau);
                    re += phi.cos() * ir - phi.sin() * ii;
                    im += phi.cos() * ii + phi.sin() * ir;
                }
                assert!((r.fabricated - (re * re + im * im)).abs() < 1e-12, "N {n} k {k}: {r:?}");
            }
            let green = &rows[1];
            assert!((green.detuning - 1.0).abs() < 1e-12 && green.loss > 0.0, "{green:?}");
        }
        let cont = efficiency_loss(&spec, None, 0.9).unwrap();
        let x = std::f64::consts::PI * (0.9 - 1.0);
        let s = x.sin() / x;
        assert!((cont[1].fabricated - s * s).abs() < 1e-12 && cont[1].design == 1.0);
    }
}
