//! Comparison of a fabricated part's scan with its design: the scan registered
//! ([`crate::metrology::scan_registration`]) and resampled onto the design grid, the difference map with
//! its RMS and PV over the clear aperture, the mean and spread of every quantization level, a
//! fitted fabrication model and the diffraction-efficiency loss its depth error predicts (the
//! design PSF against the as-fabricated PSF, and the outputs of `doefab compare`, are
//! [`crate::pipeline::compare`]'s).
//!
//! # The as-fabricated surface in the design frame
//! Registration gives `z(x_s) = a h(x_d) + b + c . x_s` (see [`crate::metrology::scan_registration`]).
//! For every design sample `x_d`, the scan is read at `x_s = pose.design_to_scan(x_d)` with
//! [`Grid::sample_index`] (Keys bicubic where its 16 taps are measured, else bilinear where its 4
//! taps are, else the nearest sample if it is measured; otherwise the design sample is
//! non-measured), and the surface is `s(x_d) = sign(a) (z(x_s) - b - c . x_s)`: the scan's
//! plane and height reference removed and a complemented part (a cast of the scanned side)
//! turned the right way up, but its depth and shape errors kept, so that `s = |a| h` for a part
//! that is only too shallow.
//!
//! # The master, the cast and the design: one family
//! A recipe makes several surfaces of one design ([`Member`]): the design wrapped modulo the
//! period `P` (and quantized), `w` in `[0, P)`, what a writer makes directly; the master, its
//! complement modulo the period, mirrored, `m(x, y) = (P - w(-x, y)) mod P`; and the cast of the
//! master, `P - m(-x, y)`, which is `w` with its zero heights lifted to the full period (in
//! `(0, P]`). The master is the cast's complement, mirrored: registration's mirror and height
//! sign find it against the cast. But neither is linear in `w` (nor in the unwrapped design):
//! where `w = 0` the master is 0, not `P`. [`compare_family`] therefore registers the scan to
//! each member it is given, keeps the best correlation, judges that registration, and compares
//! the part with that member; the report names it and what the scan shows
//! ([`scan_of`]: the master, the cast, ...).
//!
//! # Fabrication model
//! `z(x_s) = k (G_sigma * h)(x_d) + b + c . x_s`: the design blurred by a Gaussian of standard
//! deviation `sigma` (the writer's and replication's lateral resolution), scaled by the signed
//! depth scale `k` and offset. It is fitted on the scan's own samples (no resampling of the
//! scan, whose interpolation would add a blur of its own), at the registered pose, over a
//! central window of the design: for each `sigma` the linear parameters `(k, b, c)` are exact
//! least squares; `sigma` minimises the residual sum of squares `SSE(sigma)` by golden-section
//! search. Its standard error is the profile-likelihood one, `sqrt(2 s^2 / SSE''(sigma))` with
//! `s^2 = SSE / (n - 5)`; a blur whose standard error exceeds a quarter of its value is
//! reported as not resolved (blurs well below the design's pitch leave the sampled design
//! unchanged, so the data cannot see them). The blur is also checked against the fit's own
//! residual ([`FabModel::blur_doubt`]): one that lowers the residual variance by less than the
//! variance it leaves is a compromise with what the model does not describe, and is named as
//! such rather than taken for the process's resolution.
//!
//! # Efficiency loss
//! A depth scale `k` multiplies every phase step of an `N`-level profile exactly as a detuning
//! does, so the design order's efficiency is Swanson's with `a -> k a`
//! ([`order_efficiency`]; `sinc^2(k a - m)` for a continuous profile).

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::error::{Condition, Error, Refusal, Result};
use crate::fabrication::quantize::{continuous_efficiency, detuning, order_efficiency};
use crate::fabrication::wrap::WrapSpec;
use crate::grid::blur::gaussian_blur;
use crate::grid::{Grid, Interpolation, Unit};
use crate::material::PAPER_WAVELENGTHS;
use crate::metrology::scan_registration::{
    check_registration, check_trust, register_pose, RegisterOptions, Registration, Sampler,
};

/// NaN: a figure a file written before it existed does not hold.
fn nan() -> f64 {
    f64::NAN
}

/// Reads a JSON `null` (how serde_json writes NaN and infinities) back as NaN.
fn null_as_nan<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// The quantization of the design: `count` levels of `step` metres (level `l` at `l step`).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LevelSpec {
    pub count: usize,
    /// Height of one level step, metres.
    pub step: f64,
}

impl LevelSpec {
    /// The levels a surface of these levels whose highest height is `top` holds: `count`, and
    /// one more where `top` reaches `count step` (the cast of the master, whose level 0 lies at
    /// the full period: level `count`).
    pub fn indices(&self, top: f64) -> usize {
        let q = (top / self.step).round();
        if q.is_finite() && q >= self.count as f64 {
            self.count + 1
        } else {
            self.count
        }
    }

    /// The level of height `h` among `indices` levels: the nearest, within range.
    pub fn level_of(&self, h: f64, indices: usize) -> usize {
        (h / self.step).round().clamp(0.0, indices as f64 - 1.0) as usize
    }
}

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
#[derive(Debug, Clone)]
pub struct Reference {
    pub member: Member,
    pub surface: Grid,
    pub levels: Option<LevelSpec>,
}

/// One member a scan was registered to, and the correlation its best pose reached (NaN where
/// the registration found no pose).
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    pub member: Member,
    pub correlation: f64,
}

/// Options of [`compare`] and [`compare_family`].
#[derive(Debug, Clone, Serialize)]
pub struct CompareOptions {
    pub register: RegisterOptions,
    /// Clear-aperture diameter centred on the design, metres (`None`: the largest circle the
    /// design grid holds).
    pub aperture: Option<f64>,
    /// The design's quantization, for the per-level statistics and the efficiency ([`compare`];
    /// [`compare_family`] takes each reference's own).
    pub levels: Option<LevelSpec>,
    /// Design wavelength, material and order, for the efficiency prediction.
    pub optics: WrapSpec,
    /// Smallest fraction of the aperture that the scan's footprint must cover.
    pub min_coverage: f64,
    /// Side of the central design window (samples) on which the fabrication model is fitted.
    pub fit_side: usize,
    /// Most scan samples used by the fabrication-model fit (a stride thins the rest).
    pub fit_points: usize,
}

impl Default for CompareOptions {
    fn default() -> Self {
        CompareOptions {
            register: RegisterOptions::default(),
            aperture: None,
            levels: None,
            optics: WrapSpec::default(),
            min_coverage: 0.99,
            fit_side: 2048,
            fit_points: 150_000,
        }
    }
}

/// Mean and spread of the part's height over one level's terraces.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LevelStat {
    pub level: usize,
    /// Design height `l step`, metres.
    pub design_height: f64,
    /// Samples (terrace interiors: the sample and its four neighbours on this level, measured).
    pub samples: usize,
    /// Mean and standard deviation of the as-fabricated height, metres.
    #[serde(deserialize_with = "null_as_nan")]
    pub mean: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub std: f64,
    /// The level's height fitted with the part's blur over the terrace interiors of the
    /// aperture, metres (see [`LevelHeights`]); `None` where the fit is singular.
    #[serde(default)]
    pub fitted_height: Option<f64>,
    /// Measured terrace-interior samples of this level inside the aperture (the fit's support).
    #[serde(default)]
    pub aperture_samples: usize,
}

/// The per-level statistics (`levels` has a level more than `count` for the cast of the
/// master: its level 0 lies at the full period, as level `count`, and level 0 is empty). The
/// means over terrace interiors are biased wherever the blur
/// reaches into the interiors (narrow terraces, and the level next to a phase wrap most of
/// all, whose neighbour is a full period higher); `fitted_height` is not: the surface over the
/// aperture's terrace interiors is fitted as `s(x) = sum_l h_l (G_sigma * chi_l)(x)`, with
/// `chi_l` the indicator of level `l` and `sigma` the fitted blur, by linear least squares in
/// the `h_l` (without blur, the fit is the interior mean).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LevelHeights {
    pub count: usize,
    /// Nominal step, metres.
    pub step: f64,
    pub levels: Vec<LevelStat>,
    /// Differences of consecutive level means (both with samples), metres.
    pub step_heights: Vec<f64>,
    /// Mean and standard deviation of `step_heights`, metres.
    #[serde(deserialize_with = "null_as_nan")]
    pub mean_step: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub step_std: f64,
    /// Largest distance of a design height from its level, in steps (0 for a quantized design).
    #[serde(deserialize_with = "null_as_nan")]
    pub design_off_level: f64,
}

/// The fitted fabrication model (see the module docs).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FabModel {
    /// `|k|`.
    #[serde(deserialize_with = "null_as_nan")]
    pub depth_scale: f64,
    /// `k < 0`: the scan shows the complement.
    pub complement: bool,
    /// `b`, metres.
    #[serde(deserialize_with = "null_as_nan")]
    pub offset: f64,
    /// `sigma`, metres, and its standard error.
    #[serde(deserialize_with = "null_as_nan")]
    pub blur: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub blur_sigma: f64,
    /// The blur is significant (standard error below a quarter of it).
    pub blur_resolved: bool,
    /// RMS of the model's residual, metres: at the fitted blur, and with no blur.
    #[serde(deserialize_with = "null_as_nan")]
    pub rms_residual: f64,
    #[serde(default = "nan", deserialize_with = "null_as_nan")]
    pub rms_residual_unblurred: f64,
    /// The scan's white noise, RMS metres (the registration's estimate), against which the
    /// blur's share of the residual is judged ([`FabModel::blur_doubt`]).
    #[serde(default = "nan", deserialize_with = "null_as_nan")]
    pub noise: f64,
    /// Scan samples in the fit.
    pub points: usize,
    /// Upper end of the blur search, metres.
    #[serde(deserialize_with = "null_as_nan")]
    pub blur_search_max: f64,
}

/// A residual RMS below this (metres) is no residual: below any profilometer's resolution.
const RESIDUAL_FLOOR: f64 = 1e-11;

impl FabModel {
    /// Why the fitted blur is no figure to correct, with the figures (`None`: it is one). The
    /// fit is checked against its own residual: a blur not resolved (its standard error above a
    /// quarter of it: too small for the samples to show), one at the end of its search range
    /// (more than the model follows), one where the model without blur already leaves no
    /// residual, and one that explains less than half of what the model without it leaves above
    /// the scan's white noise `n`: `r_0^2 - r^2 < (r_0^2 - n^2) / 2`, with `r_0` and `r` the
    /// residual RMS without and with the blur (a file without the noise takes `n = 0`). Such a
    /// blur is a compromise with what the model does not describe (a level error, a nonlinear
    /// response, a surface of another member of the design's family), not the process's
    /// resolution; deconvolving it would sharpen the wrong thing.
    pub fn blur_doubt(&self) -> Option<String> {
        let um = |v: f64| v * 1e6;
        if !self.blur_resolved {
            return Some(format!(
                "the lateral blur is not resolved: {:.2} +- {:.2} um",
                um(self.blur),
                um(self.blur_sigma)
            ));
        }
        if self.blur >= 0.98 * self.blur_search_max {
            return Some(format!(
                "the fitted blur sits at the end of its search range ({:.2} um): the part is blurred more than \
                 the model can follow, or does not match the design's shape",
                um(self.blur_search_max)
            ));
        }
        let (r0, r) = (self.rms_residual_unblurred, self.rms_residual);
        if r0.is_nan() || r0 <= RESIDUAL_FLOOR {
            return Some(format!(
                "the model fits the part without a blur to {:.3} nm RMS: there is no blur to see",
                r0 * 1e9
            ));
        }
        let n = if self.noise.is_finite() { self.noise } else { 0.0 };
        if r0 * r0 - r * r < 0.5 * (r0 * r0 - n * n) {
            return Some(format!(
                "the fitted blur of {:.2} um lowers the model's residual only from {:.2} to {:.2} nm RMS, less \
                 than half of what it leaves above the scan's {:.2} nm of noise: it is not the process's \
                 resolution but a compromise with what the model does not describe",
                um(self.blur),
                r0 * 1e9,
                r * 1e9,
                n * 1e9
            ));
        }
        None
    }
}

/// Predicted efficiency of the design order at one wavelength.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EfficiencyLoss {
    /// Metres.
    pub wavelength: f64,
    /// Detuning of the design at this wavelength.
    pub detuning: f64,
    /// With the design's depth, and with the fitted depth scale.
    pub design: f64,
    pub fabricated: f64,
    /// `design - fabricated`.
    pub loss: f64,
}

/// Everything [`compare`] finds; heights and lengths in metres.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    /// The member of the design's family the scan matched best, what the scan shows
    /// ([`scan_of`]), and every member it was registered to.
    pub member: Member,
    pub scan_of: String,
    pub candidates: Vec<Candidate>,
    /// The member's surface the part is compared with (design grid, metres).
    #[serde(skip)]
    pub reference: Grid,
    pub registration: Registration,
    /// Correlation coefficient of the part and the design over the central [`INTERIOR`] of the
    /// aperture (the aperture's edge left out): the confidence that the scan shows this design.
    pub interior_correlation: f64,
    /// The as-fabricated surface on the design grid (invalid: not measured or outside the scan).
    #[serde(skip)]
    pub surface: Grid,
    /// `surface - design` over the aperture (invalid elsewhere).
    #[serde(skip)]
    pub difference: Grid,
    /// Aperture diameter used, metres.
    pub aperture: f64,
    /// Fraction of the aperture's design samples inside the scan's footprint, and measured.
    pub coverage: f64,
    pub measured_fraction: f64,
    /// Mean, RMS and peak-to-valley of the difference over the measured aperture, metres.
    pub mean_error: f64,
    pub rms_error: f64,
    pub pv_error: f64,
    pub levels: Option<LevelHeights>,
    pub model: FabModel,
    pub efficiency: Vec<EfficiencyLoss>,
    pub warnings: Vec<String>,
}

/// Positions (metres from the grid's centre) of sample `(i, j)`.
fn centred(g: &Grid, i: usize, j: usize) -> [f64; 2] {
    let (nr, nc) = g.dim();
    let p = g.pitch();
    [(j as f64 - (nc as f64 - 1.0) * 0.5) * p[0], (i as f64 - (nr as f64 - 1.0) * 0.5) * p[1]]
}

/// Compares `scan` (heights, metres) with `design` (heights, metres) taken as it is
/// ([`Member::Design`], quantized as `opts.levels` says); see [`compare_family`].
pub fn compare(design: &Grid, scan: &Grid, opts: &CompareOptions) -> Result<Comparison> {
    let reference = Reference { member: Member::Design, surface: design.clone(), levels: opts.levels };
    compare_family(std::slice::from_ref(&reference), scan, opts)
}

/// Compares `scan` (heights, metres) with the member of `family` it matches best (module
/// docs): registered to each, the best correlation is judged
/// ([`check_registration`]) and the part compared with that member. All members share the
/// design grid. Ties go to the member listed first.
///
/// Errors: a scan whose footprint is smaller than the aperture, or that covers less than
/// `min_coverage` of it once registered; a registration that is refused (no match, ambiguous,
/// featureless, not trusted), or whose part correlates with the member inside the aperture by
/// less than the registration's `min_correlation` or than [`check_trust`] allows, is returned
/// as [`Error::Registration`].
pub fn compare_family(family: &[Reference], scan: &Grid, opts: &CompareOptions) -> Result<Comparison> {
    let first =
        family.first().ok_or_else(|| Error::param("family", "no reference surface to compare with"))?;
    for (name, g) in family.iter().map(|r| ("design", &r.surface)).chain([("scan", scan)]) {
        if g.unit() != Unit::Metre {
            return Err(Error::param(
                name,
                format!("must hold heights in metres, not '{}'", g.unit().symbol()),
            ));
        }
        if name == "design" && (g.dim() != first.surface.dim() || g.pitch() != first.surface.pitch()) {
            return Err(Error::param("family", "the reference surfaces must share the design grid"));
        }
    }
    let design = &first.surface;
    let de = design.extent();
    let aperture = opts.aperture.unwrap_or(de[0].min(de[1]));
    if !(aperture.is_finite() && aperture > 0.0) || aperture > de[0].min(de[1]) * (1.0 + 1e-9) {
        return Err(Error::param(
            "aperture",
            format!(
                "{aperture:e} m: expected a positive diameter within the {:.3} x {:.3} mm design",
                de[0] * 1e3,
                de[1] * 1e3
            ),
        ));
    }
    let se = scan.extent();
    if se[0].min(se[1]) < aperture {
        return Err(Error::Data(format!(
            "the scan ({:.3} x {:.3} mm, {} x {} samples) is smaller than the {:.3} mm aperture it \
             should cover; scan the whole aperture or pass a smaller aperture",
            se[0] * 1e3,
            se[1] * 1e3,
            scan.dim().1,
            scan.dim().0,
            aperture * 1e3
        )));
    }
    let as_registration = |e| match e {
        Error::Validity { condition: Condition::Registration(refusal), what } => {
            Error::Registration { refusal, what }
        }
        other => other,
    };
    let (tried, best, first_error) = register_family(family, scan, &opts.register);
    let Some((k, reg)) = best else {
        return Err(as_registration(
            first_error.unwrap_or_else(|| Error::Data("no reference surface was registered".into())),
        ));
    };
    let named = |m: String| {
        if family.len() > 1 {
            let searched: Vec<String> =
                tried.iter().map(|c| format!("{} {:.3}", c.member.name(), c.correlation)).collect();
            format!("{m} (best of the design's family: {})", searched.join(", "))
        } else {
            m
        }
    };
    check_registration(&reg, &opts.register).map_err(|e| match as_registration(e) {
        Error::Registration { refusal, what } => Error::Registration { refusal, what: named(what) },
        other => other,
    })?;
    let Reference { member, surface: reference, levels } = family[k].clone();
    let design = &reference;
    let mut warnings = Vec::new();
    let (surface, inside, coverage) = design_frame(design, scan, &reg, aperture)?;
    if coverage < opts.min_coverage {
        return Err(Error::Data(format!(
            "the registered scan covers only {:.1}% of the {:.3} mm aperture (at least {:.0}% needed): \
             the scan is smaller than the aperture or off its centre",
            coverage * 100.0,
            aperture * 1e3,
            opts.min_coverage * 100.0
        )));
    }
    let interior_correlation = interior_correlation(design, &surface, aperture);
    if interior_correlation.is_nan() || interior_correlation < opts.register.min_correlation {
        return Err(Error::registration(
            Refusal::NoMatch,
            format!(
            "the scan does not match the design inside the aperture: correlation {interior_correlation:.3} \
             over the central {:.0}% of the aperture is below {:.2} (the registration correlation of {:.3} \
             comes from the aperture's edge or the overall shape, not the design's structure)",
            100.0 * INTERIOR,
            opts.register.min_correlation,
            reg.correlation
        ),
        ));
    }
    check_interior(interior_correlation, reg.noise_ceiling, opts.register.min_correlation_ratio).map_err(
        |e| match e {
            Error::Registration { refusal, what } => Error::Registration { refusal, what: named(what) },
            other => other,
        },
    )?;
    let errors = aperture_errors(design, &surface, &inside)?;
    let model = fit_model(design, scan, &reg, opts)?;
    warnings.extend(model.blur_doubt());
    let levels = levels.map(|l| level_stats(design, &surface, &inside, l, model.blur)).transpose()?;
    if let Some(l) = &levels {
        if l.design_off_level > 0.05 {
            warnings.push(format!(
                "the design is not quantized to {} levels of {:.2} nm (a height lies {:.2} steps from its \
                 level): the level statistics bin a continuous design",
                l.count,
                l.step * 1e9,
                l.design_off_level
            ));
        }
    }
    let efficiency = efficiency_loss(&opts.optics, levels.as_ref().map(|l| l.count), model.depth_scale)?;
    Ok(Comparison {
        member,
        scan_of: scan_of(member, reg.pose.mirror, reg.complement),
        candidates: tried,
        registration: reg,
        interior_correlation,
        surface,
        difference: errors.difference,
        aperture,
        coverage,
        measured_fraction: errors.measured_fraction,
        mean_error: errors.mean,
        rms_error: errors.rms,
        pv_error: errors.pv,
        levels,
        model,
        efficiency,
        warnings,
        reference,
    })
}

/// Every member of `family` registered onto `scan` (module docs): the candidates with their
/// correlations (NaN where refused), the member with the best correlation (the first on a
/// tie) and its registration, and the first refusal.
fn register_family(
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

/// The part's error over the aperture: `surface - design` where the surface is measured inside
/// the aperture (`inside`), and its statistics.
struct ApertureErrors {
    /// The difference, metres (invalid outside the aperture and where not measured).
    difference: Grid,
    /// Measured samples over the aperture's samples.
    measured_fraction: f64,
    /// Mean, RMS and peak-to-valley of the difference, metres.
    mean: f64,
    rms: f64,
    pv: f64,
}

/// The difference of `surface` and `design` over the measured samples `inside` the aperture
/// (module docs); none measured there is refused.
fn aperture_errors(design: &Grid, surface: &Grid, inside: &Array2<bool>) -> Result<ApertureErrors> {
    let (nr, nc) = design.dim();
    let mut diff = Array2::zeros((nr, nc));
    let mut dvalid = Array2::from_elem((nr, nc), false);
    let (mut n, mut s, mut ss, mut lo, mut hi, mut n_ap) =
        (0.0, 0.0, 0.0, f64::INFINITY, f64::NEG_INFINITY, 0.0);
    for i in 0..nr {
        for j in 0..nc {
            if !inside[[i, j]] {
                continue;
            }
            n_ap += 1.0;
            if surface.is_valid(i, j) {
                let d = surface.values()[[i, j]] - design.values()[[i, j]];
                diff[[i, j]] = d;
                dvalid[[i, j]] = true;
                n += 1.0;
                s += d;
                ss += d * d;
                lo = lo.min(d);
                hi = hi.max(d);
            }
        }
    }
    if n == 0.0 {
        return Err(Error::Data("no measured scan sample falls inside the aperture".into()));
    }
    let difference = design.map_values(diff, Unit::Metre)?.with_mask(dvalid)?;
    Ok(ApertureErrors {
        difference,
        measured_fraction: n / n_ap,
        mean: s / n,
        rms: (ss / n).sqrt(),
        pv: hi - lo,
    })
}

/// Fraction of the aperture's diameter over which [`Comparison::interior_correlation`] runs.
pub const INTERIOR: f64 = 0.9;

/// [`check_trust`] on the part's correlation with the reference over the aperture's interior,
/// against the ceiling the scan's noise sets (`compare`, and `precompensate` on a model it reads
/// back). The reference is not blurred here, so a blur of many samples lowers the correlation
/// too: it is refused with the poses the rule exists for. A part blurred by up to 4 pitches
/// still passes (0.975 on the built-in design, `tests`); against the reference blurred by the
/// fitted blur a scan of the unwrapped design, blurred by 2 or 4 pitches, would pass as the
/// wrapped design (0.972, 0.984, where the sharp wrapped design gives 0.931, 0.917): its blur
/// fit is a compromise that [`FabModel::blur_doubt`] does not always catch.
pub fn check_interior(correlation: f64, noise_ceiling: f64, fraction: f64) -> Result<()> {
    let what = format!("the part over the central {:.0}% of the aperture", 100.0 * INTERIOR);
    check_trust(&what, correlation, noise_ceiling, fraction)
}

/// Pearson correlation of `surface` and `design` over the measured samples within
/// `INTERIOR * aperture / 2` of the centre (NaN when there are none or either is constant).
fn interior_correlation(design: &Grid, surface: &Grid, aperture: f64) -> f64 {
    let r2 = (0.5 * INTERIOR * aperture).powi(2);
    let (nr, nc) = design.dim();
    let mut m = [0.0f64; 6];
    for i in 0..nr {
        for j in 0..nc {
            let x = centred(design, i, j);
            if x[0] * x[0] + x[1] * x[1] <= r2 && design.is_valid(i, j) && surface.is_valid(i, j) {
                let (a, b) = (surface.values()[[i, j]], design.values()[[i, j]]);
                for (k, v) in [1.0, a, b, a * a, b * b, a * b].iter().enumerate() {
                    m[k] += v;
                }
            }
        }
    }
    let [n, sa, sb, saa, sbb, sab] = m;
    let cov = sab / n - sa * sb / (n * n);
    cov / ((saa / n - (sa / n).powi(2)) * (sbb / n - (sb / n).powi(2))).sqrt()
}

/// The scan on the design grid (module docs), the aperture mask and the fraction of the
/// aperture inside the scan's footprint.
fn design_frame(
    design: &Grid,
    scan: &Grid,
    reg: &Registration,
    aperture: f64,
) -> Result<(Grid, Array2<bool>, f64)> {
    use rayon::prelude::*;
    let (nr, nc) = design.dim();
    let (sr, sc) = scan.dim();
    let ps = scan.pitch();
    let sign = if reg.complement { -1.0 } else { 1.0 };
    let r2 = (0.5 * aperture).powi(2);
    // Per design row: heights, measured, inside the aperture, aperture and covered counts.
    type Row = (Vec<f64>, Vec<bool>, Vec<bool>, usize, usize);
    let rows: Vec<Row> = (0..nr)
        .into_par_iter()
        .map(|i| {
            let (mut v, mut ok, mut ins) = (vec![0.0; nc], vec![false; nc], vec![false; nc]);
            let (mut n_ap, mut n_cov) = (0, 0);
            for j in 0..nc {
                let xd = centred(design, i, j);
                let xs = reg.pose.design_to_scan(xd);
                let fi = xs[1] / ps[1] + (sr as f64 - 1.0) * 0.5;
                let fj = xs[0] / ps[0] + (sc as f64 - 1.0) * 0.5;
                let in_scan = fi >= -0.5 && fj >= -0.5 && fi <= sr as f64 - 0.5 && fj <= sc as f64 - 0.5;
                if xd[0] * xd[0] + xd[1] * xd[1] <= r2 && design.is_valid(i, j) {
                    ins[j] = true;
                    n_ap += 1;
                    n_cov += usize::from(in_scan);
                }
                if !in_scan {
                    continue;
                }
                let z = [Interpolation::Bicubic, Interpolation::Bilinear, Interpolation::Nearest]
                    .iter()
                    .find_map(|&m| scan.sample_index(fi, fj, m));
                if let Some(z) = z {
                    let plane = reg.offset + reg.tilt[0] * xs[0] + reg.tilt[1] * xs[1];
                    v[j] = sign * (z - plane);
                    ok[j] = true;
                }
            }
            (v, ok, ins, n_ap, n_cov)
        })
        .collect();
    let (n_ap, n_cov) = rows.iter().fold((0, 0), |(a, c), r| (a + r.3, c + r.4));
    let shape = |e: ndarray::ShapeError| Error::Data(format!("design frame: {e}"));
    let values = Array2::from_shape_vec((nr, nc), rows.iter().flat_map(|r| r.0.iter().copied()).collect())
        .map_err(shape)?;
    let valid = Array2::from_shape_vec((nr, nc), rows.iter().flat_map(|r| r.1.iter().copied()).collect())
        .map_err(shape)?;
    let inside = Array2::from_shape_vec((nr, nc), rows.iter().flat_map(|r| r.2.iter().copied()).collect())
        .map_err(shape)?;
    let surface =
        Grid::new(values, design.pitch(), Unit::Metre)?.with_mask(valid)?.with_origin(design.origin());
    Ok((surface, inside, n_cov as f64 / n_ap.max(1) as f64))
}

fn level_stats(
    design: &Grid,
    surface: &Grid,
    inside: &Array2<bool>,
    spec: LevelSpec,
    blur: f64,
) -> Result<LevelHeights> {
    if spec.count < 2 || !(spec.step.is_finite() && spec.step > 0.0) {
        return Err(Error::param(
            "levels",
            format!(
                "{} levels of {:e} m: expected at least 2 levels of a positive step",
                spec.count, spec.step
            ),
        ));
    }
    let (nr, nc) = design.dim();
    let count = spec.indices(design.min_max().map_or(0.0, |m| m.1));
    let mut off = 0.0f64;
    let level = Array2::from_shape_fn((nr, nc), |(i, j)| {
        let h = design.values()[[i, j]];
        let l = spec.level_of(h, count);
        if inside[[i, j]] {
            off = off.max((h / spec.step - l as f64).abs());
        }
        l
    });
    let mut acc = vec![(0usize, 0.0f64, 0.0f64); count];
    for i in 1..nr.saturating_sub(1) {
        for j in 1..nc.saturating_sub(1) {
            let l = level[[i, j]];
            let nb = [(i, j), (i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)];
            if nb.iter().all(|&(a, b)| level[[a, b]] == l && inside[[a, b]] && surface.is_valid(a, b)) {
                let z = surface.values()[[i, j]];
                acc[l].0 += 1;
                acc[l].1 += z;
                acc[l].2 += z * z;
            }
        }
    }
    let (fitted, area) = fit_level_heights(design, surface, inside, &level, count, blur)?;
    let levels: Vec<LevelStat> = acc
        .iter()
        .enumerate()
        .map(|(l, &(n, s, ss))| {
            let mean = if n > 0 { s / n as f64 } else { f64::NAN };
            let var = if n > 1 { (ss - s * s / n as f64) / (n as f64 - 1.0) } else { f64::NAN };
            LevelStat {
                level: l,
                design_height: l as f64 * spec.step,
                samples: n,
                mean,
                std: var.max(0.0).sqrt(),
                fitted_height: fitted[l],
                aperture_samples: area[l],
            }
        })
        .collect();
    let step_heights: Vec<f64> = levels
        .windows(2)
        .filter(|w| w[0].samples > 0 && w[1].samples > 0)
        .map(|w| w[1].mean - w[0].mean)
        .collect();
    let m = step_heights.len() as f64;
    let mean_step = step_heights.iter().sum::<f64>() / m;
    let step_std = (step_heights.iter().map(|d| (d - mean_step).powi(2)).sum::<f64>() / (m - 1.0)).sqrt();
    Ok(LevelHeights {
        count: spec.count,
        step: spec.step,
        levels,
        step_heights,
        mean_step,
        step_std,
        design_off_level: off,
    })
}

/// Most levels whose heights are fitted with the blur (a fit for the few levels of a
/// multi-level part, not for the 65,536 "levels" of a continuous 16-bit surface).
pub const MAX_FITTED_LEVELS: usize = 256;

/// The level heights of [`LevelHeights`]'s blurred-indicator fit, of the levels the design
/// holds (`None` for a level it does not hold, and for every level where the fit is singular:
/// a level held with no measured sample in the aperture), and each level's measured samples
/// there.
fn fit_level_heights(
    design: &Grid,
    surface: &Grid,
    inside: &Array2<bool>,
    level: &Array2<usize>,
    count: usize,
    blur: f64,
) -> Result<(Vec<Option<f64>>, Vec<usize>)> {
    // Terrace interiors, as for the means: a sample next to a level change also carries the
    // resampling of the scan onto the design grid, which no blur of the design models.
    let (nr, nc) = level.dim();
    let used = |i: usize, j: usize| {
        let l = level[[i, j]];
        i > 0
            && j > 0
            && i + 1 < nr
            && j + 1 < nc
            && [(i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)].iter().all(|&(a, b)| level[[a, b]] == l)
            && inside[[i, j]]
            && surface.is_valid(i, j)
    };
    let mut area = vec![0usize; count];
    let mut held = vec![false; count];
    for ((i, j), &l) in level.indexed_iter() {
        held[l] = true;
        if used(i, j) {
            area[l] += 1;
        }
    }
    // The unknowns: the levels the design holds (a level it does not hold has no indicator).
    let index: Vec<Option<usize>> =
        held.iter().scan(0, |k, &h| Some(h.then(|| std::mem::replace(k, *k + 1)))).collect();
    let unknowns = held.iter().filter(|h| **h).count();
    let singular = (0..count).any(|l| held[l] && area[l] == 0);
    if singular || unknowns > MAX_FITTED_LEVELS {
        return Ok((vec![None; count], area));
    }
    // The blurred indicators at each used sample, from the sample's window of the design's
    // levels (the blur reaches across the aperture's edge as it does on the part): the same
    // truncated, border-normalised separable kernel as [`gaussian_blur`]. Rows are summed in
    // fixed chunks, in order, so the sums do not depend on the thread count.
    use rayon::prelude::*;
    let kernel = |s: f64| -> Vec<f64> {
        if s <= 0.0 {
            return vec![1.0];
        }
        let r = (4.0 * s).ceil() as isize;
        (-r..=r).map(|k| (-0.5 * (k as f64 / s).powi(2)).exp()).collect()
    };
    let kx = kernel(blur / design.pitch()[0]);
    let ky = kernel(blur / design.pitch()[1]);
    let (rx, ry) = ((kx.len() / 2) as isize, (ky.len() / 2) as isize);
    let scale = 1e-6;
    const ROWS: usize = 16;
    let n = unknowns;
    let chunks: Vec<(Vec<f64>, Vec<f64>)> = (0..nr.div_ceil(ROWS))
        .into_par_iter()
        .map(|c| {
            let (mut a, mut r) = (vec![0.0; n * n], vec![0.0; n]);
            let mut f = vec![0.0; n];
            let mut seen = vec![false; n];
            let mut touched = Vec::with_capacity(n);
            for i in c * ROWS..((c + 1) * ROWS).min(nr) {
                for j in 0..nc {
                    if !used(i, j) {
                        continue;
                    }
                    let (i0, i1) = ((i as isize - ry).max(0), (i as isize + ry).min(nr as isize - 1));
                    let (j0, j1) = ((j as isize - rx).max(0), (j as isize + rx).min(nc as isize - 1));
                    let wy: f64 = (i0..=i1).map(|a| ky[(a - i as isize + ry) as usize]).sum();
                    let wx: f64 = (j0..=j1).map(|b| kx[(b - j as isize + rx) as usize]).sum();
                    for a in i0..=i1 {
                        let gy = ky[(a - i as isize + ry) as usize];
                        for b in j0..=j1 {
                            // Every level read here is held, so it has an index.
                            let Some(l) = index[level[[a as usize, b as usize]]] else { continue };
                            if !seen[l] {
                                seen[l] = true;
                                touched.push(l);
                            }
                            f[l] += gy * kx[(b - j as isize + rx) as usize];
                        }
                    }
                    let z = surface.values()[[i, j]] / scale;
                    for &p in &touched {
                        let fp = f[p] / (wx * wy);
                        r[p] += fp * z;
                        for &q in &touched {
                            a[p * n + q] += fp * f[q] / (wx * wy);
                        }
                    }
                    for &p in &touched {
                        f[p] = 0.0;
                        seen[p] = false;
                    }
                    touched.clear();
                }
            }
            (a, r)
        })
        .collect();
    let (mut a, mut r) = (vec![0.0; n * n], vec![0.0; n]);
    for (ca, cr) in &chunks {
        a.iter_mut().zip(ca).for_each(|(x, y)| *x += y);
        r.iter_mut().zip(cr).for_each(|(x, y)| *x += y);
    }
    match crate::linalg::solve(a, r, n) {
        Ok(h) => Ok((index.iter().map(|k| k.map(|k| h[k] * scale)).collect(), area)),
        Err(_) => Ok((vec![None; count], area)),
    }
}

/// Residual sum of squares of the linear fit `z = k h + b + c . x` at one blur, and `(k, b)`.
struct LinFit {
    sse: f64,
    k: f64,
    b: f64,
    n: usize,
}

fn fit_at_blur(window: &Grid, pts: &[([f64; 2], f64, [f64; 2])], sigma: f64) -> Result<LinFit> {
    let blurred = gaussian_blur(window, sigma)?;
    let sampler = Sampler::new(&blurred);
    let hs: Vec<Option<f64>> = pts.iter().map(|(xd, _, _)| sampler.at_position(*xd)).collect();
    // Columns scaled to order 1 (heights per micrometre, positions per millimetre) so that the
    // normal equations stay well conditioned.
    let (hu, xu) = (1e-6, 1e-3);
    let mut a = [0.0; 16];
    let mut r = [0.0; 4];
    for ((_, z, xs), h) in pts.iter().zip(&hs) {
        let Some(h) = *h else { continue };
        let f = [h / hu, 1.0, xs[0] / xu, xs[1] / xu];
        for p in 0..4 {
            r[p] += f[p] * z;
            for q in 0..4 {
                a[p * 4 + q] += f[p] * f[q];
            }
        }
    }
    let x = crate::linalg::solve(a.to_vec(), r.to_vec(), 4)?;
    let x = [x[0] / hu, x[1], x[2] / xu, x[3] / xu];
    // The residuals summed directly (z.z - x.F^T z would cancel catastrophically).
    let (mut sse, mut n) = (0.0, 0usize);
    for ((_, z, xs), h) in pts.iter().zip(&hs) {
        if let Some(h) = *h {
            sse += (z - x[0] * h - x[1] - x[2] * xs[0] - x[3] * xs[1]).powi(2);
            n += 1;
        }
    }
    Ok(LinFit { sse, k: x[0], b: x[1], n })
}

/// Fits the fabrication model of the module docs on a central window of the design.
fn fit_model(design: &Grid, scan: &Grid, reg: &Registration, opts: &CompareOptions) -> Result<FabModel> {
    let pd = design.pitch();
    let (nr, nc) = design.dim();
    let pmax = pd[0].max(pd[1]);
    let hi_sigma = (3.0 * reg.blur).max(2.0 * pmax);
    let margin = (4.0 * hi_sigma / pd[0].min(pd[1])).ceil() as usize + 2;
    let side = opts.fit_side.max(2 * margin + 16);
    let (h0, w0) = (nr.min(side), nc.min(side));
    let (r0, c0) = ((nr - h0) / 2, (nc - w0) / 2);
    let window = design.crop(r0..r0 + h0, c0..c0 + w0)?;
    // The window's centre relative to the design's centre, metres.
    let wc = [
        ((c0 as f64 + (w0 as f64 - 1.0) * 0.5) - (nc as f64 - 1.0) * 0.5) * pd[0],
        ((r0 as f64 + (h0 as f64 - 1.0) * 0.5) - (nr as f64 - 1.0) * 0.5) * pd[1],
    ];
    let half = [
        ((w0 as f64 - 1.0) * 0.5 - margin as f64) * pd[0],
        ((h0 as f64 - 1.0) * 0.5 - margin as f64) * pd[1],
    ];
    if half[0] <= 0.0 || half[1] <= 0.0 {
        return Err(Error::Data("the design is too small for the fabrication-model fit".into()));
    }
    let (sr, sc) = scan.dim();
    let stride = ((scan.valid_count() as f64 / opts.fit_points.max(1) as f64).sqrt().ceil() as usize).max(1);
    let mut pts = Vec::new();
    for i in (0..sr).step_by(stride) {
        for j in (0..sc).step_by(stride) {
            if !scan.is_valid(i, j) {
                continue;
            }
            let xs = centred(scan, i, j);
            let xd = reg.pose.scan_to_design(xs);
            let xw = [xd[0] - wc[0], xd[1] - wc[1]];
            if xw[0].abs() <= half[0] && xw[1].abs() <= half[1] {
                pts.push((xw, scan.values()[[i, j]], xs));
            }
        }
    }
    if pts.len() < 100 {
        return Err(Error::Data(format!(
            "only {} scan samples fall in the central {h0} x {w0} design window: nothing to fit the \
             fabrication model on",
            pts.len()
        )));
    }
    // Golden-section search of SSE(sigma) on [0, hi_sigma] to 0.01 design pitches.
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut b) = (0.0, hi_sigma);
    let mut x1 = b - g * (b - a);
    let mut x2 = a + g * (b - a);
    let mut f1 = fit_at_blur(&window, &pts, x1)?.sse;
    let mut f2 = fit_at_blur(&window, &pts, x2)?.sse;
    while b - a > 0.01 * pmax {
        if f1 <= f2 {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - g * (b - a);
            f1 = fit_at_blur(&window, &pts, x1)?.sse;
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + g * (b - a);
            f2 = fit_at_blur(&window, &pts, x2)?.sse;
        }
    }
    let sigma = 0.5 * (a + b);
    let best = fit_at_blur(&window, &pts, sigma)?;
    // Profile curvature by central differences (one-sided at the lower end).
    let h = 0.05 * pmax;
    let sse = |s: f64| fit_at_blur(&window, &pts, s).map(|f| f.sse);
    let curv = if sigma > h {
        (sse(sigma + h)? - 2.0 * best.sse + sse(sigma - h)?) / (h * h)
    } else {
        (sse(sigma + 2.0 * h)? - 2.0 * sse(sigma + h)? + best.sse) / (h * h)
    };
    let s2 = best.sse / (best.n as f64 - 5.0).max(1.0);
    let blur_sigma = if curv > 0.0 { (2.0 * s2 / curv).sqrt() } else { f64::INFINITY };
    let unblurred = fit_at_blur(&window, &pts, 0.0)?;
    Ok(FabModel {
        depth_scale: best.k.abs(),
        complement: best.k < 0.0,
        offset: best.b,
        blur: sigma,
        blur_sigma,
        blur_resolved: blur_sigma < 0.25 * sigma,
        rms_residual: (best.sse / best.n as f64).sqrt(),
        rms_residual_unblurred: (unblurred.sse / unblurred.n.max(1) as f64).sqrt(),
        noise: reg.noise,
        points: best.n,
        blur_search_max: hi_sigma,
    })
}

/// Efficiency of order `m` at detuning `a`: Swanson's for `n` levels, `sinc^2(a - m)` for a
/// continuous profile.
fn efficiency(levels: Option<usize>, a: f64, m: i64) -> f64 {
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
    use crate::design::{paper_example, ExampleParams, PAPER_PITCH};
    use crate::metrology::scan_registration::Pose;
    use crate::metrology::synthetic_scan::{simulate_scan, SimulateParams};

    /// The built-in design at its real pitch and grating period, `n` samples, aperture 0.9 n.
    fn paper(n: usize) -> Grid {
        let p = ExampleParams { samples: n, aperture: 0.9 * n as f64 * PAPER_PITCH, ..Default::default() };
        paper_example(&p).unwrap()
    }

    /// Level heights of a blurred staircase (8 levels of 5 samples, a bowed response, blur of
    /// two samples): the blurred-indicator fit recovers them to round-off, where the interior
    /// means are pulled towards the neighbours (level 0 most, next to the wrap).
    #[test]
    fn the_blurred_indicator_fit_recovers_level_heights_that_means_miss() {
        let (n, pitch) = (120, 4e-6);
        let level = Array2::from_shape_fn((n, n), |(_, j)| (j % 40) / 5);
        let h: Vec<f64> = (0..8).map(|l| l as f64 * 150e-9 * (1.0 + 0.04 * l as f64)).collect();
        let design = Grid::new(level.mapv(|l| l as f64 * 150e-9), [pitch; 2], Unit::Metre).unwrap();
        let made = Grid::new(level.mapv(|l| h[l]), [pitch; 2], Unit::Metre).unwrap();
        let part = gaussian_blur(&made, 2.0 * pitch).unwrap();
        let inside = Array2::from_elem((n, n), true);
        let (fit, area) = fit_level_heights(&design, &part, &inside, &level, 8, 2.0 * pitch).unwrap();
        let fit: Vec<f64> = fit.iter().map(|h| h.unwrap()).collect();
        assert!(area.iter().all(|&a| a > 1000), "{area:?}");
        for (l, (f, h)) in fit.iter().zip(&h).enumerate() {
            assert!((f - h).abs() < 1e-12, "level {l}: {f} vs {h}");
        }
        let spec = LevelSpec { count: 8, step: 150e-9 };
        let r = level_stats(&design, &part, &inside, spec, 2.0 * pitch).unwrap();
        assert!(r.levels[0].mean - h[0] > 50e-9, "{:?}", r.levels[0]);
        assert_eq!(r.levels[0].fitted_height, Some(fit[0]));
        // Without the blur in the fit the same samples give the means' bias back.
        let (plain, _) = fit_level_heights(&design, &part, &inside, &level, 8, 0.0).unwrap();
        assert!((plain[0].unwrap() - r.levels[0].mean).abs() < 1e-15);
        // The same staircase with level 0 lifted to the period (as the cast of a master holds
        // it): 9 level indices, level 0 held nowhere, the others fitted as before.
        let lifted = level.mapv(|l| if l == 0 { 8 } else { l });
        let hl = |l: usize| if l == 8 { h[0] + 8.0 * 150e-9 } else { h[l] };
        let made = Grid::new(lifted.mapv(hl), [pitch; 2], Unit::Metre).unwrap();
        let part = gaussian_blur(&made, 2.0 * pitch).unwrap();
        let (fit, area) = fit_level_heights(&design, &part, &inside, &lifted, 9, 2.0 * pitch).unwrap();
        assert_eq!((fit[0], area[0]), (None, 0));
        for (l, f) in fit.iter().enumerate().skip(1) {
            assert!((f.unwrap() - hl(l)).abs() < 1e-12, "level {l}: {f:?} vs {}", hl(l));
        }
    }

    fn goals_params(seed: u64) -> SimulateParams {
        SimulateParams { offset: 0.2e-6, seed, ..SimulateParams::typical_cast() }
    }

    /// The accuracy goals on a synthetic cast (20 nm noise, 2 um blur, 10% missing):
    /// shift <= 0.02 px, rotation <= 0.01 deg, depth scale <= 0.5%; the fabrication model
    /// recovers the blur within 0.15 um and the depth scale within 0.5%.
    #[test]
    fn a_synthetic_cast_is_recovered_within_the_accuracy_goals() {
        let d = paper(300);
        let sp = goals_params(9);
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.8 * 300.0 * PAPER_PITCH), ..Default::default() };
        let c = compare(&d, &scan, &opts).unwrap();
        let r = &c.registration;
        let e = [(r.pose.shift[0] - 3.2e-6) / PAPER_PITCH, (r.pose.shift[1] + 1.7e-6) / PAPER_PITCH];
        assert!(e[0].abs() <= 0.02 && e[1].abs() <= 0.02, "shift error {e:?} px");
        assert!((r.pose.rotation.to_degrees() - 0.3).abs() <= 0.01, "{r:?}");
        assert!((r.depth_scale / 0.95 - 1.0).abs() <= 0.005, "{r:?}");
        let m = &c.model;
        assert!(m.complement, "{m:?}");
        assert!((m.depth_scale / 0.95 - 1.0).abs() <= 0.005, "{m:?}");
        assert!((m.blur - 2e-6).abs() <= 0.15e-6, "{m:?}");
        assert!(m.blur_resolved && m.blur_sigma < 0.1e-6, "{m:?}");
        // Offset of the complement: z = -k h + k max(h) + b.
        let hmax = d.min_max().unwrap().1;
        assert!((m.offset - (0.2e-6 + 0.95 * hmax)).abs() < 5e-9, "{m:?}");
        // Residual: the noise (20 nm) and nothing else.
        assert!((m.rms_residual / 20e-9 - 1.0).abs() < 0.05, "{m:?}");
        assert!(c.coverage > 0.999 && c.warnings.is_empty(), "{:?}", c.warnings);
    }

    /// A quantized design (8 levels of 150 nm, a 2-D staircase) made 10% too shallow, with an
    /// offset and 5 nm noise, no blur and no misplacement.
    fn staircase() -> (Grid, LevelSpec) {
        let n = 240;
        let step = 150e-9;
        let c = (n as f64 - 1.0) * 0.5;
        let v = Array2::from_shape_fn((n, n), |(i, j)| {
            let (x, y) = (j as f64 - c, i as f64 - c);
            let t = (x * 0.7 + y * 0.3) / 23.0 + (x * y / 900.0).sin() * 1.5 + (y / 17.0).cos();
            (t.rem_euclid(8.0)).floor() * step
        });
        (Grid::new(v, [PAPER_PITCH; 2], Unit::Metre).unwrap(), LevelSpec { count: 8, step })
    }

    #[test]
    fn difference_and_level_statistics_of_a_shallow_staircase() {
        let (d, levels) = staircase();
        let sp =
            SimulateParams { depth_scale: 0.9, offset: 40e-9, noise: 5e-9, seed: 3, ..Default::default() };
        let scan = simulate_scan(&d, &sp).unwrap();
        let aperture = 0.9 * d.extent()[0];
        let opts = CompareOptions { aperture: Some(aperture), levels: Some(levels), ..Default::default() };
        let c = compare(&d, &scan, &opts).unwrap();
        // The difference is -0.1 h plus noise: its RMS over the aperture follows from the design.
        let (mut n, mut s2, mut lo, mut hi) = (0.0, 0.0, f64::INFINITY, f64::NEG_INFINITY);
        for ((i, j), h) in d.values().indexed_iter() {
            let x = [
                d.x(j) - d.x(0) - 0.5 * (d.extent()[0] - d.pitch()[0]),
                d.y(i) - d.y(0) - 0.5 * (d.extent()[1] - d.pitch()[1]),
            ];
            if x[0] * x[0] + x[1] * x[1] <= 0.25 * aperture * aperture {
                let e = -0.1 * h;
                n += 1.0;
                s2 += e * e;
                lo = lo.min(e);
                hi = hi.max(e);
            }
        }
        let want = (s2 / n + 5e-9f64.powi(2)).sqrt();
        assert!((c.rms_error / want - 1.0).abs() < 0.02, "{} vs {want}", c.rms_error);
        assert!((c.pv_error - (hi - lo)).abs() < 50e-9, "{} vs {}", c.pv_error, hi - lo);
        assert!(c.measured_fraction > 0.999);
        let l = c.levels.as_ref().unwrap();
        assert_eq!(l.design_off_level, 0.0);
        assert_eq!(l.step_heights.len(), 7);
        for st in &l.levels {
            assert!(st.samples > 200, "{st:?}");
            // Means at 0.9 l step (the fitted offset takes the 40 nm), spread = the noise.
            assert!((st.mean - 0.9 * st.design_height).abs() < 2e-9, "{st:?}");
            assert!((st.std / 5e-9 - 1.0).abs() < 0.15, "{st:?}");
        }
        assert!((l.mean_step / (0.9 * 150e-9) - 1.0).abs() < 0.01 && l.step_std < 2e-9, "{l:?}");
        assert!((c.model.depth_scale - 0.9).abs() < 0.002, "{:?}", c.model);
    }

    /// A blur well below the design's pitch leaves the sampled design as it is: reported as not
    /// resolved, with a warning; 2 um (0.47 pitch) is resolved (the other test).
    #[test]
    fn an_unresolvable_blur_is_reported() {
        let d = paper(200);
        let sp = SimulateParams { blur: 0.3e-6, noise: 20e-9, seed: 5, ..Default::default() };
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.8 * d.extent()[0]), ..Default::default() };
        let c = compare(&d, &scan, &opts).unwrap();
        assert!(!c.model.blur_resolved, "{:?}", c.model);
        assert!(c.model.blur < 1.2e-6, "{:?}", c.model);
        assert!(c.warnings.iter().any(|w| w.contains("not resolved")), "{:?}", c.warnings);
    }

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
            Err(Error::Registration { refusal: Refusal::NotTrusted, what: m }) => {
                assert!(m.contains("not trusted"), "{m}")
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
    }

    /// The blur is checked against the fit's own residual: on a scan of the master before
    /// quantization, compared with the 64-level master's cast, the samples just above a wrap
    /// (which the quantizer puts a period lower) pull the fit to a blur of about 2 um that
    /// lowers the residual by a few percent of what it leaves: doubted. A true blur of 2
    /// pitches brings the residual down to the noise: used (and so is the 2 um blur under 20 nm
    /// of noise of the test above, 21.6 -> 20.1 nm: what it leaves is the noise). And a fit
    /// without residual has no blur to show.
    #[test]
    fn a_blur_that_explains_less_than_it_leaves_is_doubted() {
        use crate::fabrication::quantize::{quantize, QuantizeMethod};
        use crate::fabrication::wrap::{cast_of_master, to_master, wrap};
        let d = paper(300);
        let spec = WrapSpec::default();
        let period = spec.period().unwrap();
        let (w, _) = wrap(&d, &spec).unwrap();
        let wq = quantize(&w, period, 64, QuantizeMethod::Round).unwrap().heights().unwrap();
        let family = [Reference {
            member: Member::Replica,
            surface: cast_of_master(&wq, period).unwrap(),
            levels: Some(LevelSpec { count: 64, step: period / 64.0 }),
        }];
        let opts = CompareOptions { aperture: Some(0.8 * 300.0 * PAPER_PITCH), ..Default::default() };
        let unquantized = simulate_scan(&to_master(&w, period).unwrap(), &SimulateParams::default()).unwrap();
        let c = compare_family(&family, &unquantized, &opts).unwrap();
        let m = &c.model;
        let doubt = m.blur_doubt().unwrap_or_default();
        assert!(doubt.contains("lowers the model's residual only"), "{doubt}; {m:?}");
        assert!(m.blur_resolved && m.rms_residual > 0.9 * m.rms_residual_unblurred, "{m:?}");
        assert!(c.warnings.contains(&doubt), "{:?}", c.warnings);
        let sp = SimulateParams { blur: 2.0 * PAPER_PITCH, noise: 5e-9, ..Default::default() };
        let blurred = simulate_scan(&to_master(&wq, period).unwrap(), &sp).unwrap();
        let c = compare_family(&family, &blurred, &opts).unwrap();
        assert_eq!(c.model.blur_doubt(), None, "{:?}", c.model);
        assert!((c.model.blur / (2.0 * PAPER_PITCH) - 1.0).abs() < 0.02, "{:?}", c.model);
        let exact = FabModel { rms_residual: 0.0, rms_residual_unblurred: 0.0, ..c.model.clone() };
        assert!(exact.blur_doubt().is_some_and(|d| d.contains("no blur to see")));
    }

    #[test]
    fn a_scan_smaller_than_the_aperture_is_refused() {
        let d = paper(200);
        let sp = SimulateParams { size: Some((120, 120)), ..Default::default() };
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.9 * d.extent()[0]), ..Default::default() };
        match compare(&d, &scan, &opts) {
            Err(Error::Data(m)) => assert!(m.contains("smaller than the") && m.contains("aperture"), "{m}"),
            other => panic!("expected a refusal, got {other:?}"),
        }
        // Large enough but off centre: the registered footprint misses part of the aperture.
        // (A 190-sample scan 25 samples off centre degrades the registration itself, 0.14
        // samples and 0.03 deg off at a correlation of 0.85 on a noise-free scan, and is refused
        // as not trusted.)
        let sp = SimulateParams {
            size: Some((200, 200)),
            pose: Pose { shift: [25.0 * PAPER_PITCH, 0.0], ..Default::default() },
            ..Default::default()
        };
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.85 * d.extent()[0]), ..Default::default() };
        match compare(&d, &scan, &opts) {
            Err(Error::Data(m)) => assert!(m.contains("covers only"), "{m}"),
            other => panic!("expected a refusal, got {other:?}"),
        }
    }

    #[test]
    fn a_scan_of_another_part_is_a_registration_error() {
        let mut rng = crate::rng::Lcg(11);
        let v = Array2::from_shape_fn((200, 200), |_| 0.3e-6 * rng.normal());
        let other = Grid::new(v, [PAPER_PITCH; 2], Unit::Metre).unwrap();
        let other = gaussian_blur(&other, 3.0 * PAPER_PITCH).unwrap();
        match compare(&paper(200), &other, &CompareOptions::default()) {
            Err(Error::Registration { refusal: Refusal::NoMatch, what: m }) => {
                assert!(m.contains("does not match"), "{m}")
            }
            other => panic!("expected a registration error, got {other:?}"),
        }
    }

    /// A Fresnel lens in the same circular aperture registers on the aperture's edge alone: the
    /// registration's noise ceiling refuses it (correlation 0.62 where 5 nm of noise allow
    /// 0.998), and with that test off, the interior correlation does.
    #[test]
    fn a_part_matching_only_at_the_aperture_edge_is_refused() {
        let d = paper(300);
        let aperture = 0.9 * 300.0 * PAPER_PITCH;
        let c = (300.0 - 1.0) * 0.5;
        let f = Array2::from_shape_fn((300, 300), |(i, j)| {
            let r2 = ((i as f64 - c).powi(2) + (j as f64 - c).powi(2)) * PAPER_PITCH * PAPER_PITCH;
            if r2 <= 0.25 * aperture * aperture {
                1.2e-6 * (r2 / 4.2e-8).fract()
            } else {
                0.0
            }
        });
        let f = Grid::new(f, [PAPER_PITCH; 2], Unit::Metre).unwrap();
        let scan = simulate_scan(&f, &SimulateParams { noise: 5e-9, ..Default::default() }).unwrap();
        let opts = CompareOptions { aperture: Some(aperture), ..Default::default() };
        match compare(&d, &scan, &opts) {
            Err(Error::Registration { refusal: Refusal::NotTrusted, what: m }) => {
                assert!(m.contains("not trusted"), "{m}")
            }
            other => panic!("expected a registration error, got {other:?}"),
        }
        let mut lenient = opts.clone();
        lenient.register.min_correlation_ratio = 0.0;
        match compare(&d, &scan, &lenient) {
            Err(Error::Registration { refusal: Refusal::NoMatch, what: m }) => {
                assert!(m.contains("inside the aperture"), "{m}")
            }
            other => panic!("expected a registration error, got {other:?}"),
        }
        // The design's own scan passes the same check.
        let own = simulate_scan(&d, &SimulateParams { noise: 5e-9, ..Default::default() }).unwrap();
        let c = compare(&d, &own, &opts).unwrap();
        assert!(c.interior_correlation > 0.99, "{}", c.interior_correlation);
    }

    /// The interior is judged against the sharp design: a part blurred by 2 and 4 pitches
    /// (5 nm of noise) still passes, its correlation falling with the blur (measured: 0.998 and
    /// 0.975, where the noise allows 0.9994), and the fit recovers the blur.
    #[test]
    fn a_part_blurred_by_several_pitches_passes_the_interior_check() {
        let d = paper(300);
        let opts = CompareOptions { aperture: Some(0.8 * 300.0 * PAPER_PITCH), ..Default::default() };
        for (pitches, lo, hi) in [(2.0, 0.99, 0.999), (4.0, 0.96, 0.98)] {
            let sp = SimulateParams { blur: pitches * PAPER_PITCH, noise: 5e-9, ..Default::default() };
            let scan = simulate_scan(&d, &sp).unwrap();
            let c = compare(&d, &scan, &opts).unwrap();
            assert!(c.model.blur_doubt().is_none(), "{:?}", c.model);
            assert!((c.model.blur / (pitches * PAPER_PITCH) - 1.0).abs() < 0.05, "{:?}", c.model);
            let r = c.interior_correlation;
            assert!(r > lo && r < hi, "{pitches} pitches: {r}");
        }
    }

    /// Different x and y pitches (a stage that steps 3.5 um in x and 5 um in y) are supported.
    #[test]
    fn a_scan_with_different_x_and_y_pitches_is_compared() {
        let d = paper(300);
        let sp = SimulateParams { pitch: Some([3.5e-6, 5e-6]), ..goals_params(2) };
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.8 * 300.0 * PAPER_PITCH), ..Default::default() };
        let c = compare(&d, &scan, &opts).unwrap();
        let r = &c.registration;
        let e = [(r.pose.shift[0] - 3.2e-6) / PAPER_PITCH, (r.pose.shift[1] + 1.7e-6) / PAPER_PITCH];
        assert!(e[0].abs() <= 0.02 && e[1].abs() <= 0.02, "shift error {e:?} px");
        assert!((r.pose.rotation.to_degrees() - 0.3).abs() <= 0.01, "{r:?}");
        assert!((c.model.depth_scale / 0.95 - 1.0).abs() <= 0.005, "{:?}", c.model);
        assert!((c.model.blur - 2e-6).abs() <= 0.15e-6, "{:?}", c.model);
    }

    /// Over a 4 x 4 aperture less one corner, one sample not measured: the difference of the
    /// other 14 (`i - j` nm on a flat design) has mean -2/14 nm, RMS sqrt(30/14) nm and a
    /// peak-to-valley of 5 nm.
    #[test]
    fn aperture_errors_are_the_measured_differences_statistics() {
        let design = Grid::new(Array2::from_elem((4, 4), 1e-7), [1e-6; 2], Unit::Metre).unwrap();
        let mut valid = Array2::from_elem((4, 4), true);
        valid[[0, 1]] = false;
        let surface = design
            .map_values(
                Array2::from_shape_fn((4, 4), |(i, j)| 1e-7 + (i as f64 - j as f64) * 1e-9),
                Unit::Metre,
            )
            .unwrap()
            .with_mask(valid)
            .unwrap();
        let mut inside = Array2::from_elem((4, 4), true);
        inside[[3, 0]] = false;
        let e = aperture_errors(&design, &surface, &inside).unwrap();
        let close = |a: f64, b: f64| (a - b).abs() < 1e-20;
        assert!(
            close(e.mean, -2e-9 / 14.0) && close(e.rms, (30.0f64 / 14.0).sqrt() * 1e-9),
            "{} {}",
            e.mean,
            e.rms
        );
        assert!(close(e.pv, 5e-9), "{}", e.pv);
        assert_eq!(e.measured_fraction, 14.0 / 15.0);
        assert!(!e.difference.is_valid(0, 1) && !e.difference.is_valid(3, 0) && e.difference.is_valid(3, 3));
        let nothing = Array2::from_elem((4, 4), false);
        assert!(aperture_errors(&design, &surface, &nothing).is_err());
    }
}
