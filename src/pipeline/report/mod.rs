//! `doefab report`: the sweeps of a design run within one time budget and gathered into
//! one static HTML page (`index.html`) with its charts as SVG and the data beside it as JSON
//! and CSV. It opens in a browser from the folder, without a server.
//!
//! Every number the page shows is a [`Figure`] of `report.json` (its value, unit and the text
//! shown), and the page is written from that list alone: the sentence under each chart, the
//! reading of what to pick and why, is built from figures, never typed in.
//!
//! **The budget is a promise.** Each part (the fabrication sweeps, the registration map, the
//! calibration trials, the tiling sweep, each stability map, the fine-tuning, the PSF
//! sweep) is predicted before it runs: its seconds on the machine that measured them
//! ([`COSTS`]) times the pace, this run's seconds so far over what the same parts (and a probe
//! run first) took there. A part runs only where its prediction fits in what is left of the
//! budget, less what the files need and what the PSF sweep keeps (a fifth of the budget,
//! or its reference's predicted time if more); what does not fit is left out, named on the page
//! and in `report.json` with its prediction and the time it had. The page is always written. A
//! part that runs longer than predicted takes the time of the parts after it; the budget is
//! overrun only by the misprediction of a part run, or of the PSF sweep's reference, which
//! runs whatever its time.

use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use super::sweep::{run_psf_sweep, PsfSweepOptions};
use crate::charts::fabrication::write_fab_sweep_charts;
use crate::charts::failure_maps::{write_calibration_chart, write_registration_chart};
use crate::charts::optics::{write_psf_charts, write_stability_charts};
use crate::charts::tiling::write_tiling_chart;
use crate::charts::training::write_finetune_time_chart;
use crate::error::{Allowed, Error, Result};
use crate::io::atomic::{self, StagedDir};
use crate::sweep::calibration::{self as cal_sweep, CalibrationSweep};
use crate::sweep::fab::{self as fab_sweep, FabSweepOptions, FabSweepResults};
use crate::sweep::finetune_time::{self, TimedFinetune, TimedOptions};
use crate::sweep::psf::{self as psf_sweep, SweepOptions};
use crate::sweep::register::{self as reg_sweep, RegistrationSweep};
use crate::sweep::stability::{self, MapOptions, StabilitySweepResults};
use crate::sweep::tiling::{self as tiling_sweep, TilingOptions, TilingSweep};

mod csv;
use csv::{psf_csv, stability_csv};

/// What `doefab report` runs.
#[derive(Debug, Clone)]
pub struct ReportOptions {
    /// The PSF sweep's design, system and material; its budget is what the rest leaves.
    pub psf: PsfSweepOptions,
    /// Wall-clock seconds for everything.
    pub budget: f64,
    /// The stability maps' sweeps.
    pub maps: MapOptions,
    /// The decoder's fine-tuning against time (its seconds count within `budget`).
    pub finetune: TimedOptions,
}

/// The share of the budget [`ReportOptions::new`] gives the fine-tuning run.
pub const FINETUNE_SHARE: f64 = 0.15;

/// The share of the budget the PSF sweep keeps from the fixed sweeps.
pub const PSF_SHARE: f64 = 0.2;

impl ReportOptions {
    /// The default sweeps within `budget` seconds: the stability maps' defaults, fine-tuning
    /// for [`FINETUNE_SHARE`] of the budget, and what is left for the PSF sweep.
    pub fn new(psf: PsfSweepOptions, budget: f64) -> ReportOptions {
        let psf = PsfSweepOptions { sweep: SweepOptions { budget, ..psf.sweep }, ..psf };
        ReportOptions {
            psf,
            budget,
            maps: MapOptions::default(),
            finetune: TimedOptions::new(FINETUNE_SHARE * budget),
        }
    }
}

/// The seconds each part of the report took on the machine that measured them (two cores,
/// shared with other builds), with the default sweeps on the paper's design: a part's
/// prediction is its figure here times the pace ([`run_report`]). The fabrication sweeps scale
/// with the design's samples, a stability map with its runs.
pub struct Costs {
    /// The probe ([`probe`]).
    pub probe: f64,
    /// The fabrication sweeps on the paper's 1306^2 design.
    pub fabrication: f64,
    /// The registration map.
    pub registration: f64,
    /// The calibration trials.
    pub calibration: f64,
    /// The decoder tiling sweep of the page (a 512^2 capture, tiles 256 and 384, overlaps 0,
    /// 32 and 96).
    pub tiling: f64,
    /// The stability maps of [`stability::MAPS`], in order.
    pub maps: [f64; 8],
    /// The fine-tuning's setup: its least run is this, then `evaluations` steps each with a
    /// validation.
    pub finetune_setup: f64,
    /// One fine-tuning step with its validation.
    pub finetune_step: f64,
    /// The charts and the files of the page.
    pub files: f64,
}

/// The measured [`Costs`]: each part once, on two cores with several builds sharing them (a
/// load of 8 to 10: the probe took 0.12 s there, the parts two to seven times what the README
/// gives for an idle machine, each part its own factor, which is why the pace is followed as
/// the parts run).
pub const COSTS: Costs = Costs {
    probe: 0.12,
    fabrication: 168.0,
    registration: 32.0,
    calibration: 54.0,
    tiling: 26.0,
    maps: [18.6, 31.8, 246.0, 166.0, 2.0, 2.0, 1.9, 1.9],
    finetune_setup: 49.0,
    finetune_step: 13.4,
    files: 5.0,
};

/// One part of the report and its place in the budget.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Part {
    /// What it is (`fabrication sweeps`, `stability map fresnel_wavelength`, ...).
    pub name: String,
    /// Its predicted seconds when it came up.
    pub predicted_seconds: f64,
    /// The seconds then left for it: the budget less the time spent, the files' share and what
    /// the parts after it keep.
    pub left_seconds: f64,
    /// What it took; `None`: left out.
    pub seconds: Option<f64>,
}

/// How the report kept its budget.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BudgetRecord {
    /// The budget, wall-clock seconds for everything ([`ReportOptions::budget`]).
    pub budget_seconds: f64,
    /// The probe's seconds here.
    pub probe_seconds: f64,
    /// The probe's seconds on the machine that measured [`COSTS`].
    pub probe_measured_seconds: f64,
    /// Every part, in the order they came up.
    pub parts: Vec<Part>,
    /// From the start until the page's last file was staged.
    pub spent_seconds: f64,
}

impl BudgetRecord {
    /// The parts left out.
    pub fn left_out(&self) -> impl Iterator<Item = &Part> {
        self.parts.iter().filter(|p| p.seconds.is_none())
    }
}

/// The probe: the matrix DFT PSF of the small scene's DOE ([`psf_sweep::scene`], f64,
/// Gauss-Legendre 8 x 8 pixels) ten times (a few tenths of a second); their seconds and work
/// in the plan's units.
pub fn probe() -> Result<(f64, f64)> {
    use crate::optics::system::{OpticalSystem, PixelRule};
    use crate::optics::{simulate, Method, Options, Precision};
    let system = OpticalSystem { subsample: 8, pixel_rule: PixelRule::GaussLegendre, ..psf_sweep::scene() };
    let doe = psf_sweep::doe()?;
    let t = Instant::now();
    for _ in 0..10 {
        simulate(&system, &doe, Method::MatrixDft, &Options::default())?;
    }
    let work = psf_sweep::Costs::work(Method::MatrixDft, Precision::F64, &system, &doe);
    Ok((t.elapsed().as_secs_f64(), 10.0 * work))
}

/// Keeps the budget (module docs): predicts each part from the pace so far and runs it or
/// leaves it out, recording both.
struct Scheduler {
    start: Instant,
    budget: f64,
    /// Seconds here and on the measuring machine of the parts run so far, the probe included.
    here: f64,
    there: f64,
    parts: Vec<Part>,
}

impl Scheduler {
    /// This machine's time over the measuring machine's, so far.
    fn pace(&self) -> f64 {
        self.here / self.there
    }

    /// The seconds left less `keep`.
    fn left(&self, keep: f64) -> f64 {
        self.budget - self.start.elapsed().as_secs_f64() - keep
    }

    /// Runs `f` with the seconds left less `keep` when the part's least time, `there` seconds on
    /// the measuring machine times the pace, fits in them; records it either way. A part that
    /// takes what it is given (`elastic`: the fine-tuning, the PSF sweep) does not move
    /// the pace.
    fn run<T>(
        &mut self,
        name: &str,
        (there, keep, elastic): (f64, f64, bool),
        f: impl FnOnce(f64) -> Result<T>,
    ) -> Result<Option<T>> {
        let predicted = there * self.pace();
        let left = self.left(keep);
        if predicted > left {
            let left_seconds = left.max(0.0);
            self.parts.push(Part {
                name: name.into(),
                predicted_seconds: predicted,
                left_seconds,
                seconds: None,
            });
            return Ok(None);
        }
        let t = Instant::now();
        let out = f(left)?;
        let seconds = t.elapsed().as_secs_f64();
        if !elastic {
            self.here += seconds;
            self.there += there;
        }
        self.parts.push(Part {
            name: name.into(),
            predicted_seconds: predicted,
            left_seconds: left,
            seconds: Some(seconds),
        });
        Ok(Some(out))
    }
}

/// One number on the page.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Figure {
    /// What it is, in words.
    pub label: String,
    /// The number, in `unit` (`shown` is "n/a" where it is not finite).
    pub value: f64,
    /// Its unit (`s`, `m`, `1` for a pure number).
    pub unit: String,
    /// The text the page shows for it ([`shown`]).
    pub shown: String,
}

/// One section of the page: a heading, its charts, the reading under them, and the figures the
/// reading is made of.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Section {
    /// The heading.
    pub title: String,
    /// Chart files (SVG) beside the page.
    pub charts: Vec<String>,
    /// Data files beside the page.
    pub data: Vec<String>,
    /// The reading: words and figures in turn.
    pub reading: Vec<Piece>,
}

/// A piece of a reading: words, or the figure of that index in [`Page::figures`].
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Piece {
    /// Words of the reading, as they are.
    Words(String),
    /// The figure of this index in [`Page::figures`].
    Figure(usize),
}

/// The page, as `report.json` holds it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Page {
    /// The page's title ("doefab report").
    pub title: String,
    /// The design of the PSF benchmark and the fabrication sweeps: `built-in:NAME` or its
    /// file's path.
    pub design: String,
    /// Every number the page shows; the readings refer to them by index.
    pub figures: Vec<Figure>,
    /// How the budget was kept: every part with its prediction, what it took or that it was
    /// left out.
    pub budget: BudgetRecord,
    /// The sections, in the page's order: the budget first, then the parts.
    pub sections: Vec<Section>,
}

/// The text a figure shows: three significant digits, in positional notation from 0.01 to
/// 10,000 and in scientific notation outside (`0.394`, `1.68`, `42`, `2.5e-4`).
pub fn shown(v: f64) -> String {
    if !v.is_finite() {
        return "n/a".into();
    }
    let a = v.abs();
    if a == 0.0 {
        "0".into()
    } else if (1e-2..1e4).contains(&a) {
        let digits = (2 - a.log10().floor() as i32).max(0) as usize;
        let t = format!("{v:.digits$}");
        if t.contains('.') {
            t.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            t
        }
    } else {
        let t = format!("{v:.1e}");
        t.replace(".0e", "e")
    }
}

/// Builds readings from words and figures.
struct Builder {
    figures: Vec<Figure>,
}

impl Builder {
    fn fig(&mut self, label: &str, value: f64, unit: &str) -> Piece {
        self.figures.push(Figure { label: label.into(), value, unit: unit.into(), shown: shown(value) });
        Piece::Figure(self.figures.len() - 1)
    }
}

fn words(w: &str) -> Piece {
    Piece::Words(w.into())
}

/// The tiling sweep of the page: a 512^2 capture, tiles of 256 and 384, overlaps 0, 32 and 96
/// (about 10 s on two cores).
fn report_tiling() -> TilingOptions {
    TilingOptions { tiles: vec![256, 384], overlaps: vec![0, 32, 96], ..TilingOptions::default() }
}

/// How many progress steps [`run_report`] takes.
pub fn steps(opts: &ReportOptions) -> usize {
    stability::steps(&opts.maps)
        + reg_sweep::steps()
        + fab_sweep::steps(&FabSweepOptions::default())
        + cal_sweep::steps()
        + tiling_sweep::steps(&report_tiling())
        + finetune_time::steps(&opts.finetune)
        + psf_sweep::steps(&opts.psf.sweep)
}

/// Runs the sweeps within `opts.budget` (module docs) and writes the page, its charts and
/// data into the folder `output`, all or nothing; the parts left out are named on the page.
pub fn run_report(
    opts: &ReportOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<Page> {
    if !(opts.budget > 0.0 && opts.budget.is_finite()) {
        return Err(Error::param_in(
            "budget",
            Allowed::positive(),
            format!("must be a positive time, got {} s", opts.budget),
        ));
    }
    let start = Instant::now();
    let total = steps(opts) as u64;
    let mut done = 0u64;
    let loaded = crate::fabrication::recipe_run::load_design(&opts.psf.design)?;
    let (probe_seconds, probe_work) = probe()?;
    let mut plan =
        Scheduler { start, budget: opts.budget, here: probe_seconds, there: COSTS.probe, parts: Vec::new() };
    // The PSF sweep's least time: its reference, two matrix DFTs (module docs of psf_sweep).
    let psf_least = psf_reference_work(opts, &loaded.heights)? / probe_work * COSTS.probe;
    let keep_files = |plan: &Scheduler| COSTS.files * plan.pace();
    let keep_psf = |plan: &Scheduler| (PSF_SHARE * opts.budget).max(psf_least * plan.pace());
    let fixed = |plan: &Scheduler, there: f64| (there, keep_files(plan) + keep_psf(plan), false);
    let mut tick = |what: &str, done: &mut u64| {
        progress(what, *done, total);
        *done += 1;
    };

    // The tiling sweep first: a short part, whose time sets the pace for the longer ones.
    let decoder = std::path::Path::new("built-in:paper-measured-psf");
    let tiling = plan.run("decoder tiling sweep", fixed(&plan, COSTS.tiling), |_| {
        tiling_sweep::run(decoder, &report_tiling(), |w| tick(w, &mut done))
    })?;
    if tiling.is_none() {
        done += tiling_sweep::steps(&report_tiling()) as u64;
    }
    let (rows, cols) = loaded.heights.dim();
    let fab_cost = COSTS.fabrication * (rows * cols) as f64 / (1306.0 * 1306.0);
    let fab = plan.run("fabrication sweeps", fixed(&plan, fab_cost), |_| {
        fab_sweep::run_sweep(&loaded.heights, &loaded.name, &FabSweepOptions::default(), |w| {
            tick(w, &mut done)
        })
    })?;
    if fab.is_none() {
        done += fab_sweep::steps(&FabSweepOptions::default()) as u64;
    }
    let registration = plan.run("registration map", fixed(&plan, COSTS.registration), |_| {
        reg_sweep::run(|w| tick(w, &mut done))
    })?;
    if registration.is_none() {
        done += reg_sweep::steps() as u64;
    }
    let measured_psf = crate::optics::Psf::paper_measured()?;
    let calibration = plan.run("calibration trials", fixed(&plan, COSTS.calibration), |_| {
        cal_sweep::run(&measured_psf, "built-in:paper-measured-psf", |w| tick(w, &mut done))
    })?;
    if calibration.is_none() {
        done += cal_sweep::steps() as u64;
    }
    let defaults = MapOptions::default();
    // The cheapest maps first, so that a short budget leaves out the fewest (on the page they
    // keep the order of stability::MAPS).
    let there: Vec<f64> = (stability::MAPS.iter().enumerate())
        .map(|(k, &kind)| {
            let runs = stability::map_steps(&opts.maps, kind);
            COSTS.maps[k] * runs as f64 / stability::map_steps(&defaults, kind).max(1) as f64
        })
        .collect();
    let mut order: Vec<usize> = (0..stability::MAPS.len()).collect();
    order.sort_by(|&a, &b| there[a].total_cmp(&there[b]));
    let mut maps = Vec::new();
    let mut maps_left_out = Vec::new();
    for k in order {
        let kind = stability::MAPS[k];
        let name = format!("stability map {}", kind.name());
        match plan.run(&name, fixed(&plan, there[k]), |_| {
            stability::run_map(&opts.maps, kind, |w| tick(w, &mut done))
        })? {
            Some(m) => maps.push((k, m)),
            None => {
                done += stability::map_steps(&opts.maps, kind) as u64;
                maps_left_out.push((k, kind.name()));
            }
        }
    }
    maps.sort_by_key(|m| m.0);
    maps_left_out.sort_by_key(|m| m.0);
    let maps = stability::report(
        &opts.maps,
        maps.into_iter().map(|m| m.1).collect(),
        maps_left_out.into_iter().map(|m| m.1).collect(),
    );
    let least = COSTS.finetune_setup + COSTS.finetune_step * opts.finetune.evaluations as f64;
    let keep = keep_files(&plan) + keep_psf(&plan);
    let finetune = plan.run("decoder fine-tuning", (least, keep, true), |left| {
        let timed = TimedOptions { seconds: opts.finetune.seconds.min(left), ..opts.finetune.clone() };
        finetune_time::run(&timed, &measured_psf, "built-in:paper-measured-psf", |w| tick(w, &mut done))
    })?;
    if finetune.is_none() {
        done += finetune_time::steps(&opts.finetune) as u64;
    }
    let keep = keep_files(&plan);
    let psf = plan.run("PSF benchmark", (psf_least, keep, true), |left| {
        let psf_opts = PsfSweepOptions {
            sweep: SweepOptions { budget: opts.psf.sweep.budget.min(left), ..opts.psf.sweep.clone() },
            ..opts.psf.clone()
        };
        run_psf_sweep(&psf_opts, &loaded.heights, |w| tick(w, &mut done))
    })?;

    let mut stage = StagedDir::new(output)?;
    let measured = Measured {
        psf: psf.as_ref(),
        maps: &maps,
        registration: registration.as_ref(),
        fab: fab.as_ref(),
        calibration: calibration.as_ref(),
        tiling: tiling.as_ref(),
        finetune: finetune.as_ref(),
    };
    let charts = stage_parts(&mut stage, &measured)?;
    let budget = BudgetRecord {
        budget_seconds: opts.budget,
        probe_seconds,
        probe_measured_seconds: COSTS.probe,
        parts: plan.parts,
        spent_seconds: start.elapsed().as_secs_f64(),
    };
    let page = page(&loaded.name, measured, charts, budget);
    atomic::write_json(&stage.stage_path("report.json"), &page)?;
    atomic::write_bytes(&stage.stage_path("index.html"), html(&page).as_bytes())?;
    stage.commit()?;
    progress("", total, total);
    Ok(page)
}

/// The PSF sweep's least work, real multiply-adds: its reference, two matrix DFTs of the
/// design in its system at the bench's largest sub-sampling plus 2 and plus 4 (module docs of
/// psf_sweep).
fn psf_reference_work(opts: &ReportOptions, heights: &crate::grid::Grid) -> Result<f64> {
    let system = super::sweep::design_system(&opts.psf, heights)?;
    Ok([2, 4]
        .map(|extra| {
            let sys = crate::optics::system::OpticalSystem {
                subsample: opts.psf.sweep.max_subsample + extra,
                pixel_rule: crate::optics::system::PixelRule::GaussLegendre,
                ..system.clone()
            };
            let f64 = crate::optics::Precision::F64;
            psf_sweep::Costs::work(crate::optics::Method::MatrixDft, f64, &sys, heights)
        })
        .iter()
        .sum())
}

/// Writes each measured part's charts and data into `stage` (the parts left out write none);
/// returns the SVG charts by section.
fn stage_parts(stage: &mut StagedDir, m: &Measured) -> Result<Charts> {
    let svg = |names: Vec<String>, prefix: &str| -> Vec<String> {
        names.into_iter().filter(|n| n.ends_with(".svg")).map(|n| format!("{prefix}{n}")).collect()
    };
    let mut charts = Charts::default();
    if let Some(psf) = m.psf {
        charts.psf = svg(write_psf_charts(|n| stage.stage_path(&format!("psf_{n}")), psf)?, "psf_");
        atomic::write_json(&stage.stage_path("bench_psf.json"), psf)?;
        atomic::write_bytes(&stage.stage_path("bench_psf.csv"), psf_csv(psf).as_bytes())?;
    }
    charts.maps = svg(write_stability_charts(|n| stage.stage_path(n), m.maps)?, "");
    atomic::write_json(&stage.stage_path("stability.json"), m.maps)?;
    atomic::write_bytes(&stage.stage_path("stability.csv"), stability_csv(m.maps).as_bytes())?;
    if let Some(r) = m.registration {
        charts.registration = svg(write_registration_chart(|n| stage.stage_path(n), r)?, "");
        atomic::write_json(&stage.stage_path("register.json"), r)?;
    }
    if let Some(f) = m.fab {
        charts.fab = svg(write_fab_sweep_charts(|n| stage.stage_path(&format!("fab_{n}")), f)?, "fab_");
        atomic::write_json(&stage.stage_path("bench_fab.json"), f)?;
    }
    if let Some(c) = m.calibration {
        charts.calibration = svg(write_calibration_chart(|n| stage.stage_path(n), c)?, "");
        atomic::write_json(&stage.stage_path("calibration.json"), c)?;
    }
    if let Some(t) = m.tiling {
        charts.tiling = svg(write_tiling_chart(|n| stage.stage_path(n), t)?, "");
        atomic::write_json(&stage.stage_path("tiling.json"), t)?;
    }
    if let Some(f) = m.finetune {
        charts.finetune = svg(write_finetune_time_chart(|n| stage.stage_path(n), f)?, "");
        atomic::write_json(&stage.stage_path("finetune_time.json"), f)?;
    }
    Ok(charts)
}

/// The chart files of each section.
#[derive(Default)]
struct Charts {
    psf: Vec<String>,
    maps: Vec<String>,
    registration: Vec<String>,
    fab: Vec<String>,
    calibration: Vec<String>,
    tiling: Vec<String>,
    finetune: Vec<String>,
}

/// What the sweeps of the page measured.
struct Measured<'a> {
    psf: Option<&'a psf_sweep::PsfSweepResults>,
    maps: &'a StabilitySweepResults,
    registration: Option<&'a RegistrationSweep>,
    fab: Option<&'a FabSweepResults>,
    calibration: Option<&'a CalibrationSweep>,
    tiling: Option<&'a TilingSweep>,
    finetune: Option<&'a TimedFinetune>,
}

/// The page's sections and figures from the reports and the budget's record.
fn page(design: &str, m: Measured, charts: Charts, budget: BudgetRecord) -> Page {
    let Measured { psf, maps, registration, fab, calibration, tiling, finetune } = m;
    let mut b = Builder { figures: Vec::new() };
    let budget_section = budget_section(&mut b, &budget);
    let psf_section = match psf {
        Some(psf) => psf_section(&mut b, psf, charts.psf),
        None => left_out(&mut b, "PSF: speed against accuracy", &budget, "PSF benchmark"),
    };
    let map_section = map_section(&mut b, maps, charts.maps);
    let registration_section = match registration {
        Some(r) => registration_section(&mut b, r, charts.registration),
        None => left_out(&mut b, REGISTRATION_TITLE, &budget, "registration map"),
    };
    let fab_section = match fab {
        Some(f) => fab_section(&mut b, f, charts.fab),
        None => left_out(&mut b, FAB_TITLE, &budget, "fabrication sweeps"),
    };
    let calibration_section = match calibration {
        Some(c) => calibration_section(&mut b, c, charts.calibration),
        None => left_out(&mut b, CALIBRATION_TITLE, &budget, "calibration trials"),
    };
    let tiling_section = match tiling {
        Some(t) => tiling_section(&mut b, t, charts.tiling),
        None => left_out(&mut b, TILING_TITLE, &budget, "decoder tiling sweep"),
    };
    let finetune_section = match finetune {
        Some(f) => finetune_section(&mut b, f, charts.finetune),
        None => left_out(&mut b, FINETUNE_TITLE, &budget, "decoder fine-tuning"),
    };
    Page {
        title: "doefab report".into(),
        design: design.into(),
        figures: b.figures,
        budget,
        sections: vec![
            budget_section,
            fab_section,
            registration_section,
            psf_section,
            map_section,
            calibration_section,
            tiling_section,
            finetune_section,
        ],
    }
}

const REGISTRATION_TITLE: &str = "Metrology: where scan registration fails";
const FAB_TITLE: &str = "Fabrication: quantization, STL and GDSII against their truths";
const CALIBRATION_TITLE: &str = "Calibration: the measured PSF from a pinhole bracket";
const TILING_TITLE: &str = "Decoder: tiles and precision";
const FINETUNE_TITLE: &str = "Decoder: fine-tuning against time";

/// The budget's section: what it was, what was spent, and every part left out with its
/// prediction and the time it had.
fn budget_section(b: &mut Builder, budget: &BudgetRecord) -> Section {
    let mut reading = vec![
        words("The budget:"),
        b.fig("budget", budget.budget_seconds, "s"),
        words("s; spent"),
        b.fig("spent", budget.spent_seconds, "s"),
        words("s until the page was written. Each part was predicted before it ran, from what it took where it was measured times this machine's pace (the probe took"),
        b.fig("probe seconds", budget.probe_seconds, "s"),
        words("s here against"),
        b.fig("probe seconds where measured", budget.probe_measured_seconds, "s"),
        words("s there, and the pace follows the parts run), and ran only where that fit."),
    ];
    let left_out: Vec<&Part> = budget.left_out().collect();
    if left_out.is_empty() {
        reading.push(words(" Every part ran."));
    } else {
        reading.push(words(" Left out:"));
        for (k, p) in left_out.iter().enumerate() {
            reading.push(words(&format!("{}{} (predicted", if k > 0 { "; " } else { " " }, p.name)));
            reading.push(b.fig("left out: predicted", p.predicted_seconds, "s"));
            reading.push(words("s,"));
            reading.push(b.fig("left out: seconds left", p.left_seconds, "s"));
            reading.push(words("s left)"));
        }
        reading.push(words("."));
    }
    Section { title: "Budget".into(), charts: Vec::new(), data: vec!["report.json".into()], reading }
}

/// A section whose part `part` the budget left out: its title and why.
fn left_out(b: &mut Builder, title: &str, budget: &BudgetRecord, part: &str) -> Section {
    let mut reading = vec![words("Left out by the budget")];
    if let Some(p) = budget.parts.iter().find(|p| p.name == part) {
        reading.push(words(": predicted"));
        reading.push(b.fig("left out: predicted", p.predicted_seconds, "s"));
        reading.push(words("s,"));
        reading.push(b.fig("left out: seconds left", p.left_seconds, "s"));
        reading.push(words("s left"));
    }
    reading.push(words(". Give more time (a larger budget) to see it."));
    Section { title: title.into(), charts: Vec::new(), data: Vec::new(), reading }
}

/// The PSF sweep's section.
fn psf_section(b: &mut Builder, psf: &psf_sweep::PsfSweepResults, charts: Vec<String>) -> Section {
    let mut reading = vec![
        words("The PSF of the design by every method, precision, FFT padding and pixel sub-sampling, timed and scored against a reference (matrix DFT, Gauss-Legendre pixels) that differs from its own refinement by"),
        b.fig("reference self-difference", psf.reference.difference, "1"),
        words(". The automatic plan:"),
    ];
    for p in &psf.plans {
        reading.push(words(" at tolerance"));
        reading.push(b.fig("plan tolerance", p.tolerance, "1"));
        reading.push(words(&format!(" it takes {} {} with", p.method, p.precision)));
        reading.push(b.fig("plan sub-samples per pixel", p.subsample as f64, "1"));
        reading.push(words("sub-samples per pixel, in"));
        reading.push(b.fig("plan run time", p.seconds, "s"));
        reading.push(words("s, error"));
        reading.push(b.fig("plan error", p.error, "1"));
        match p.time_ratio {
            Some(t) => {
                reading.push(words(if p.meets_tolerance { "(meets it;" } else { "(MISSES it;" }));
                reading.push(b.fig("plan time over the cheapest adequate run", t, "1"));
                reading.push(words("times the time of the cheapest run of the sweep that meets it)."));
            }
            None => reading.push(words(if p.meets_tolerance {
                "(meets it; no run of the sweep does)."
            } else {
                "(MISSES it; no run of the sweep meets it either)."
            })),
        }
    }
    reading.push(words(
        " Plans over their tolerance (silent failures: the plan runs only what its guard accepts):",
    ));
    reading.push(b.fig("PSF plan silent failures", psf.silent_failures as f64, "1"));
    reading.push(words("."));
    reading.push(words(" Pick the leftmost point below your tolerance; the plan should sit on it or just right of it. A hollow point is a run its guard refuses: trust only filled ones."));
    if !psf.skipped.is_empty() {
        reading.push(words(" The budget left out"));
        reading.push(b.fig("PSF runs left out", psf.skipped.len() as f64, "1"));
        reading.push(words("runs and plans (named in bench_psf.json)."));
    }
    Section {
        title: "PSF: speed against accuracy".into(),
        charts,
        data: vec!["bench_psf.json".into(), "bench_psf.csv".into()],
        reading,
    }
}

/// The stability maps' section, naming the maps the budget left out.
fn map_section(b: &mut Builder, maps: &StabilitySweepResults, charts: Vec<String>) -> Section {
    if maps.maps.is_empty() {
        let reading = vec![words(&format!(
            "Left out by the budget: {} (their predictions and the time they had are in report.json). Give \
             more time (a larger budget) to see them.",
            maps.left_out.join(", ")
        ))];
        let data = vec!["stability.json".into()];
        return Section { title: "PSF: where each method fails".into(), charts, data, reading };
    }
    let mut reading = vec![
        words("Each PSF method against a truth, over pupil sampling and Fresnel number, and over pupil sampling and wavelength (the two-step Fresnel method against the matrix DFT of the same sampled pupil; the angular spectrum against direct Rayleigh-Sommerfeld integration of the same samples; the matrix DFT against itself on the surface between the DOE's samples, and on a wrapped and a quantized DOE against the piecewise-constant part they are, whose steps away from the wrap's wavelength are real); at tolerance"),
        b.fig("stability tolerance", maps.tolerance, "1"),
        words(":"),
    ];
    for m in &maps.maps {
        let refused = m.cells.iter().filter(|c| !c.violations.is_empty()).count();
        let on = if m.design == "smooth" { String::new() } else { format!(" on the {} DOE", m.design) };
        reading.push(words(&format!(
            " {}{on} over {},",
            m.method.replace('_', " "),
            m.y_axis.replace('_', " ")
        )));
        reading.push(b.fig("runs", m.cells.len() as f64, "1"));
        reading.push(words("runs,"));
        reading.push(b.fig("silent failures", m.silent_failures as f64, "1"));
        reading.push(words("silent failures (accepted by the guard, over the tolerance),"));
        reading.push(b.fig("refused by the guard", refused as f64, "1"));
        reading.push(words("refused, of which"));
        reading.push(b.fig("refused within the tolerance", m.refused_within_tolerance as f64, "1"));
        reading.push(words("within the tolerance."));
    }
    reading.push(words(" Trust a dot; a cross names the condition that failed in stability.json. The paper's own sampling is drawn in blue: right of the black line of the transfer-function methods' maps the lens phase is undersampled, so use the matrix DFT there, at the DOE's own pitch (a coarser pupil is refused where it reads the surface too sparsely)."));
    if !maps.left_out.is_empty() {
        reading.push(words(&format!(" Left out by the budget: {}.", maps.left_out.join(", "))));
    }
    Section {
        title: "PSF: where each method fails".into(),
        charts,
        data: vec!["stability.json".into(), "stability.csv".into()],
        reading,
    }
}

/// The registration map's section.
fn registration_section(b: &mut Builder, registration: &RegistrationSweep, charts: Vec<String>) -> Section {
    let registered = registration.trials.iter().filter(|t| t.outcome == "registered");
    let worst = registered.map(|t| t.shift_error).fold(0.0, f64::max);
    let reading = vec![
        words("Scans of a known pose, one trouble at a time pushed past where registration can work:"),
        b.fig("registration trials", registration.trials.len() as f64, "1"),
        words("trials,"),
        b.fig("registration silent failures", registration.silent_failures as f64, "1"),
        words("accepted with a wrong pose (silent failures),"),
        b.fig("registration refusals", registration.refused as f64, "1"),
        words("refused; the worst accepted shift error"),
        b.fig("worst accepted shift error", worst, "design samples"),
        words("design samples, against the bound of"),
        b.fig("wrong-pose bound", registration.wrong_shift, "design samples"),
        words(". Read each panel left to right: green dots are poses found, black crosses at the top are refusals (the reason is in register.json); a part beyond the crosses needs a better scan, not a looser registration."),
    ];
    Section { title: REGISTRATION_TITLE.into(), charts, data: vec!["register.json".into()], reading }
}

/// The fabrication sweeps' section.
fn fab_section(b: &mut Builder, fab: &FabSweepResults, charts: Vec<String>) -> Section {
    let stl_bounded = fab.stl.points.iter().filter(|p| p.within_bound).count();
    let reading = vec![
        words("Quantization: the predicted design-order efficiency (Swanson, with detuning) against a simulated grating's, largest difference"),
        b.fig("quantization max difference", fab.quantization.max_difference, "1"),
        words(". STL heightfield: the measured height error within its bound at"),
        b.fig("STL points within bound", stl_bounded as f64, "1"),
        words("of"),
        b.fig("STL points", fab.stl.points.len() as f64, "1"),
        words("settings. GDSII: polygon area against the bitmap, largest difference"),
        b.fig("GDS max area difference", fab.gds.max_area_difference as f64, "nm^2"),
        words("square nanometres (exact: zero). Pick the level count where the efficiency curve flattens for your shortest wavelength, the largest max_error your part tolerates (triangles fall fast with it), and any vertex limit your mask shop accepts (size and time level off above the design's largest polygon)."),
    ];
    Section { title: FAB_TITLE.into(), charts, data: vec!["bench_fab.json".into()], reading }
}

/// The calibration trials' section.
fn calibration_section(b: &mut Builder, calibration: &CalibrationSweep, charts: Vec<String>) -> Section {
    let calibrated = calibration.trials.iter().filter(|t| t.outcome == "calibrated");
    let fewest = calibrated.filter(|t| t.axis == "frames").map(|t| t.value).fold(f64::INFINITY, f64::min);
    let mut reading = vec![
        words("Pinhole brackets of the paper's measured PSF simulated with one trouble at a time (frames, read noise, black level), merged and calibrated as calibrate-psf does:"),
        b.fig("calibration trials", calibration.trials.len() as f64, "1"),
        words("trials against the tolerance of"),
        b.fig("calibration tolerance", calibration.tolerance, "1"),
        words("(relative L2, largest channel);"),
        b.fig("calibration silent failures", calibration.silent_failures as f64, "1"),
        words("over it with nothing said (silent failures),"),
        b.fig("calibration warned", calibration.warned as f64, "1"),
        words("over it and warned by the calibration's own error estimate,"),
        b.fig("calibration refusals", calibration.refused as f64, "1"),
        words("refused."),
    ];
    if fewest.is_finite() {
        reading.push(words(" The fewest frames one stop apart that meet the tolerance:"));
        reading.push(b.fig("fewest frames within tolerance", fewest, "frames"));
        reading.push(words("."));
    }
    reading.push(words(" Grey rings are the calibration's own estimate of its error (printed as a warning when over the tolerance): bracket until it is below your tolerance; where it is far above, the bracket cannot give the PSF."));
    Section { title: CALIBRATION_TITLE.into(), charts, data: vec!["calibration.json".into()], reading }
}

/// The tiling sweep's section.
fn tiling_section(b: &mut Builder, tiling: &TilingSweep, charts: Vec<String>) -> Section {
    let mut reading = Vec::new();
    if let Some(one) = tiling.runs.iter().find(|r| r.tile.is_none()) {
        reading.push(words("The paper's measured-PSF decoder on a simulated capture of"));
        reading.push(b.fig("tiling capture side", tiling.options.size as f64, "px"));
        reading.push(words("px. In f32 in one pass it is"));
        reading.push(b.fig("f32 against f64, one pass", one.relative_l2, "1"));
        reading.push(words("(relative L2) from the same network in f64, in"));
        reading.push(b.fig("f32 one-pass time", one.seconds, "s"));
        reading.push(words("s against"));
        reading.push(b.fig("f64 one-pass time", tiling.reference_seconds, "s"));
        reading.push(words("s."));
        let exact = tiling
            .runs
            .iter()
            .filter(|r| r.tile.is_some() && r.relative_l2 <= 1.05 * one.relative_l2)
            .filter_map(|r| r.overlap)
            .min();
        if let Some(o) = exact {
            reading.push(words(" Tiles equal one pass from an overlap of"));
            reading.push(b.fig("smallest exact overlap", o as f64, "px"));
            reading.push(words("px (the receptive-field bound is"));
            reading.push(b.fig("receptive radius", tiling.receptive_radius as f64, "px"));
            reading.push(words("px);"));
        }
        let worst = tiling.runs.iter().map(|r| r.relative_l2).fold(0.0, f64::max);
        reading.push(words(" without overlap the seams reach"));
        reading.push(b.fig("worst tiled error", worst, "1"));
        reading.push(words(". Keep the overlap at the receptive radius (the default) and pick the largest tile your memory holds; f32 is enough."));
    }
    Section { title: TILING_TITLE.into(), charts, data: vec!["tiling.json".into()], reading }
}

/// Escapes text for HTML.
fn escape(t: &str) -> String {
    t.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// The page as HTML: every number from [`Page::figures`], every chart an `<img>` of a file
/// beside it.
pub fn html(page: &Page) -> String {
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title>\n<style>\
         body{{font-family:sans-serif;max-width:1050px;margin:2em auto;line-height:1.45}}\
         img{{max-width:100%;border:1px solid #ccc;margin:0.5em 0}} .fig{{font-weight:bold}}\
         </style></head><body>\n<h1>{}</h1>\n<p>Design: <code>{}</code>. Data: report.json (every number \
         on this page, with its unit).</p>\n",
        escape(&page.title),
        escape(&page.title),
        escape(&page.design)
    );
    for s in &page.sections {
        let _ = writeln!(h, "<h2>{}</h2>", escape(&s.title));
        for c in &s.charts {
            let _ = writeln!(h, "<img src=\"{}\" alt=\"{}\">", escape(c), escape(c));
        }
        h.push_str("<p>");
        for (k, p) in s.reading.iter().enumerate() {
            let text = match p {
                Piece::Words(w) => escape(w.trim()),
                Piece::Figure(i) => {
                    let f = &page.figures[*i];
                    format!("<span class=\"fig\" title=\"{}\">{}</span>", escape(&f.label), escape(&f.shown))
                }
            };
            // One space between pieces, none before punctuation.
            if k > 0 && !text.starts_with(['.', ',', ':', ';', ')']) {
                h.push(' ');
            }
            h.push_str(&text);
        }
        h.push_str("</p>\n<p>Data: ");
        let links: Vec<String> =
            s.data.iter().map(|d| format!("<a href=\"{0}\">{0}</a>", escape(d))).collect();
        h.push_str(&links.join(", "));
        h.push_str("</p>\n");
    }
    h.push_str("</body></html>\n");
    h
}

/// The fine-tuning section: the validation PSNR from the start to the best, the time, and when
/// half the gain was in.
fn finetune_section(b: &mut Builder, r: &TimedFinetune, charts: Vec<String>) -> Section {
    let (start, best) = r.start_and_best();
    let last = r.points.last().map_or(0.0, |p| p.seconds);
    let mut reading = vec![
        words("The paper's simulated-PSF decoder fine-tuned for the paper's measured PSF with doefab finetune's settings on procedural scenes, in batches of"),
        b.fig("fine-tuning batch", r.batch as f64, "crops"),
        words("crops"),
        b.fig("fine-tuning crop side", r.crop as f64, "px"),
        words("px a side:"),
        b.fig("fine-tuning steps", r.steps as f64, "1"),
        words("steps in"),
        b.fig("fine-tuning training time", last / 60.0, "min"),
        words("minutes of training on"),
        b.fig("fine-tuning threads", r.threads as f64, "threads"),
        words("threads ("),
        b.fig("fine-tuning seconds per step", r.seconds_per_step, "s"),
        words("s a step). The held-out validation PSNR went from"),
        b.fig("validation PSNR at the start", start, "dB"),
        words("dB to a best of"),
        b.fig("best validation PSNR", best, "dB"),
        words("dB"),
    ];
    match r.half_gain_seconds() {
        Some(s) => {
            reading.push(words(", half of that gain within"));
            reading.push(b.fig("training time to half the gain", s, "s"));
            reading.push(words("s. Stop where the curve flattens: later minutes buy less."));
        }
        None => reading
            .push(words(": no gain in this time; give the run more minutes or real HDR images to train on.")),
    }
    reading.push(words(" These are simulated captures of simulated scenes: score the result on real captures with bench decoder before trusting it there, and fine-tune on real HDR images for a decoder to keep."));
    Section { title: FINETUNE_TITLE.into(), charts, data: vec!["finetune_time.json".into()], reading }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_are_shown_with_three_significant_digits() {
        for (v, t) in [
            (0.394123, "0.394"),
            (1.6789, "1.68"),
            (42.0, "42"),
            (2.5e-4, "2.5e-4"),
            (1e-2, "0.01"),
            (0.0, "0"),
            (12345.0, "1.2e4"),
            (3.0, "3"),
            (-0.5, "-0.5"),
        ] {
            assert_eq!(shown(v), t, "{v}");
        }
    }
}
