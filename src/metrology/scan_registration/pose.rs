//! The pose of a scan on its design ([`Pose`]): shift, rotation, scale and mirror, and the maps
//! between design and scan positions.

use serde::Serialize;

use crate::error::{Allowed, Error, Result};

/// Placement of the part: scan position `x_s = t + s R(theta) M x_d` of design position `x_d`
/// (both in metres from their grid's centre; `M` mirrors x when `mirror`; rotation
/// counter-clockwise in the (x, y) frame of the grids).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Pose {
    /// The design is mirrored in x (`M = diag(-1, 1)`) before it is rotated: the scan shows it
    /// mirrored (a scan of the master against its cast).
    pub mirror: bool,
    /// `theta`, radians, counter-clockwise.
    pub rotation: f64,
    /// `s`: scan length per design length (dimensionless, 1 = true size).
    pub scale: f64,
    /// `[x, y]`, metres: the scan position of the design's centre.
    pub shift: [f64; 2],
}

impl Default for Pose {
    fn default() -> Self {
        Pose { mirror: false, rotation: 0.0, scale: 1.0, shift: [0.0, 0.0] }
    }
}

impl Pose {
    /// Refuses non-finite values and a scale that is not positive.
    pub fn check(&self) -> Result<()> {
        if !(self.rotation.is_finite() && self.shift.iter().all(|v| v.is_finite())) {
            return Err(Error::param("pose", "rotation and shift must be finite"));
        }
        if !(self.scale.is_finite() && self.scale > 0.0) {
            return Err(Error::param_in(
                "scale",
                Allowed::positive(),
                format!("must be finite and positive, got {}", self.scale),
            ));
        }
        Ok(())
    }

    /// `x_d = M R(-theta) (x_s - t) / s`.
    pub fn scan_to_design(&self, xs: [f64; 2]) -> [f64; 2] {
        let (sn, cs) = self.rotation.sin_cos();
        let u = [(xs[0] - self.shift[0]) / self.scale, (xs[1] - self.shift[1]) / self.scale];
        let v = [cs * u[0] + sn * u[1], -sn * u[0] + cs * u[1]];
        [if self.mirror { -v[0] } else { v[0] }, v[1]]
    }

    /// `x_s = t + s R(theta) M x_d`.
    pub fn design_to_scan(&self, xd: [f64; 2]) -> [f64; 2] {
        let (sn, cs) = self.rotation.sin_cos();
        let m = [if self.mirror { -xd[0] } else { xd[0] }, xd[1]];
        [
            self.shift[0] + self.scale * (cs * m[0] - sn * m[1]),
            self.shift[1] + self.scale * (sn * m[0] + cs * m[1]),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_maps_round_trip() {
        let p = Pose { mirror: true, rotation: 0.7, scale: 1.1, shift: [1e-3, -2e-3] };
        let x = [3e-4, 5e-4];
        let y = p.scan_to_design(p.design_to_scan(x));
        assert!((x[0] - y[0]).abs() < 1e-15 && (x[1] - y[1]).abs() < 1e-15);
        assert!(Pose { scale: 0.0, ..p }.check().is_err());
    }
}
