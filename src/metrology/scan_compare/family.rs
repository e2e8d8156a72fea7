//! The surfaces one recipe makes of a design ([`Member`]: the design wrapped, the master, the
//! cast), what a scan of each shows ([`scan_of`]), and the registration of a scan to each member
//! it is given (the module docs' "one family").

use serde::{Deserialize, Serialize};

use crate::error::Error;
use crate::grid::Grid;
use crate::metrology::scan_registration::{register_pose, RegisterOptions, Registration};

use super::levels::LevelSpec;

/// Which surface of a design's fabrication family a reference is (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Member {
    /// The design's surface as given, taken as it is.
    Design,
    /// The design wrapped modulo the period (and quantized) as the recipe makes it, heights in
    /// `[0, P)`: what a writer makes directly, and the frame `precompensate` commands in.
    Wrapped,
    /// The cast of the master the recipe writes: the wrapped design with its zero heights at
    /// the full period, heights in `(0, P]`. A scan of the master matches it mirrored and
    /// complemented.
    Replica,
}

impl Member {
    /// A short name.
    pub fn name(self) -> &'static str {
        match self {
            Member::Design => "the design as given",
            Member::Wrapped => "the wrapped design",
            Member::Replica => "the cast of the master",
        }
    }
}

/// What a scan registered to `member` with `mirror` and height sign `complement` shows: the
/// member itself (not mirrored, not complemented), its replica (both; a scan of the master is
/// the replica of the master's cast), or an unexpected mix named as such.
pub fn scan_of(member: Member, mirror: bool, complement: bool) -> String {
    match (member, mirror, complement) {
        (Member::Replica, true, true) => "the master".into(),
        (Member::Replica, false, false) => "the cast of the master".into(),
        (m, false, false) => m.name().into(),
        (m, true, true) => format!("a cast (mirrored, complemented) of {}", m.name()),
        (m, mirror, _) => {
            format!(
                "{} {}, which no replication makes",
                m.name(),
                if mirror { "mirrored" } else { "complemented" }
            )
        }
    }
}

/// A candidate surface of [`compare_family`]: a member of the design's family on the design
/// grid (metres), with its quantization (`None` for a continuous surface).
///
/// [`compare_family`]: super::compare_family
#[derive(Debug, Clone)]
pub struct Reference {
    /// Which surface of the family it is.
    pub member: Member,
    /// Its heights on the design grid, metres.
    pub surface: Grid,
    /// Its quantization; `None` for a continuous surface.
    pub levels: Option<LevelSpec>,
}

/// One member a scan was registered to, and the correlation its best pose reached (NaN where
/// the registration found no pose).
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    /// The member registered to.
    pub member: Member,
    /// Correlation coefficient of the scan and the member at its best pose
    /// ([`Registration::correlation`]); NaN (`null` in JSON) where the registration was refused.
    pub correlation: f64,
}

/// Every member of `family` registered onto `scan` (module docs): the candidates with their
/// correlations (NaN where refused), the member with the best correlation (the first on a
/// tie) and its registration, and the first refusal.
pub(super) fn register_family(
    family: &[Reference],
    scan: &Grid,
    opts: &RegisterOptions,
) -> (Vec<Candidate>, Option<(usize, Registration)>, Option<Error>) {
    let mut tried = Vec::with_capacity(family.len());
    let mut best: Option<(usize, Registration)> = None;
    let mut first_error = None;
    for (k, r) in family.iter().enumerate() {
        match register_pose(&r.surface, scan, opts) {
            Ok(reg) => {
                tried.push(Candidate { member: r.member, correlation: reg.correlation });
                if best.as_ref().is_none_or(|(_, b)| reg.correlation > b.correlation) {
                    best = Some((k, reg));
                }
            }
            Err(e) => {
                tried.push(Candidate { member: r.member, correlation: f64::NAN });
                first_error.get_or_insert(e);
            }
        }
    }
    (tried, best, first_error)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::design::PAPER_PITCH;
    use crate::error::Refusal;
    use crate::fabrication::wrap::WrapSpec;
    use crate::metrology::scan_compare::compare::compare_family;
    use crate::metrology::scan_compare::compare::tests::paper;
    use crate::metrology::scan_compare::options::CompareOptions;
    use crate::metrology::synthetic_scan::{simulate_scan, SimulateParams};

    /// The design's family on the built-in design (heights 0..1.55 um, wrapped at 1.22 um): a
    /// scan of the master, of its cast and of the wrapped design each registers to the member
    /// it shows, named; against the wrapped design alone the master is not trusted (it is not
    /// linear in it: where the wrapped design is 0, outside the aperture, the master is 0 too).
    #[test]
    fn each_member_of_the_family_is_found_and_named() {
        use crate::fabrication::wrap::{cast_of_master, to_master, wrap};
        let d = paper(300);
        let spec = WrapSpec::default();
        let period = spec.period().unwrap();
        let (w, _) = wrap(&d, &spec).unwrap();
        let cast = cast_of_master(&w, period).unwrap();
        let master = to_master(&w, period).unwrap();
        let family = [
            Reference { member: Member::Wrapped, surface: w.clone(), levels: None },
            Reference { member: Member::Replica, surface: cast.clone(), levels: None },
        ];
        let opts = CompareOptions { aperture: Some(0.8 * 300.0 * PAPER_PITCH), ..Default::default() };
        let sp = SimulateParams { noise: 5e-9, seed: 2, ..Default::default() };
        for (surface, member, shows) in [
            (&master, Member::Replica, "the master"),
            (&cast, Member::Replica, "the cast of the master"),
            (&w, Member::Wrapped, "the wrapped design"),
        ] {
            let c = compare_family(&family, &simulate_scan(surface, &sp).unwrap(), &opts).unwrap();
            assert_eq!((c.member, c.scan_of.as_str()), (member, shows), "{:?}", c.candidates);
            assert!(c.rms_error < 6e-9 && c.registration.correlation > 0.9999, "{}", c.rms_error);
        }
        let scan = simulate_scan(&master, &sp).unwrap();
        match compare_family(&family[..1], &scan, &opts) {
            Err(Error::Registration { refusal: Refusal::NotTrusted, .. }) => {}
            other => panic!("expected a refusal, got {other:?}"),
        }
    }
}
