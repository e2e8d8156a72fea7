//! `doefab compare-profile` and the stylus-profile library: simulated profiles of the built-in
//! design with a known model (recovered within the reported uncertainty), the complement, the
//! refusals, and a line of a Gwyddion-written surface with known steps read as a profile.

use std::io::Write;
use std::path::Path;

use serde_json::Value;

use crate::common::{self, doefab, fails, ok, shared_data};

use doefab::fabrication::recipe::Recipe;
use doefab::fabrication::recipe_run::{load_design, ChainParams, DesignSource};
use doefab::io::profile::ProfileReadOptions;
use doefab::io::scan::{read_scan, ScanOptions};
use doefab::metrology::{simulate_profile, LineSpec, Profile, ProfileLevel, ProfileOptions, SimulateProfile};
use doefab::pipeline::compare::reference_surface;
use doefab::pipeline::compare_profile::{compare_profile_file, ProfileDesign};

const RECIPE: &str = "built-in:binary-3mask-8level";

/// The built-in design as the 8-level recipe quantizes it (design side).
fn quantized_paper() -> (doefab::Grid, ChainParams) {
    let d = load_design(&DesignSource::BuiltIn("paper".into())).unwrap();
    let chain = ChainParams::of_recipe(&Recipe::read(Path::new(RECIPE)).unwrap(), false);
    let (g, _, _) = reference_surface(&d, Some(&chain)).unwrap();
    (g, chain)
}

/// Writes a profile as a Dektak-like export: metadata pairs, a column header with the units,
/// positions in um and heights in angstrom (Latin-1 "Å"), NaN where not measured, a footer.
fn write_dektak(path: &Path, p: &Profile) {
    let mut f = std::fs::File::create(path).unwrap();
    f.write_all(
        b"Meta Data\nDate,01/02/2025\nScan Length,1000.0,um\nStylus Type,Radius: 2.0 um\n\nScan Data\n",
    )
    .unwrap();
    f.write_all(b"Lateral(um),Raw(\xc5)\n").unwrap();
    for k in 0..p.len() {
        if p.is_valid(k) {
            writeln!(f, "{:.5},{:.4}", p.x()[k] * 1e6, p.z()[k] * 1e10).unwrap();
        } else {
            writeln!(f, "{:.5},NaN", p.x()[k] * 1e6).unwrap();
        }
    }
    f.write_all(b"End of data\n").unwrap();
}

fn truth(a: f64) -> SimulateProfile {
    SimulateProfile {
        line: LineSpec::Angle { angle: 17f64.to_radians() },
        length: 1.2e-3,
        step: 0.5e-6,
        x_origin: 35e-6,
        along_shift: 7.3e-6,
        across_offset: -2.9e-6,
        depth_scale: a,
        offset: 60e-9,
        tilt: 1.5e-4,
        blur: 2e-6,
        noise: 5e-9,
        seed: 11,
    }
}

/// A profile simulated with depth scale `a`, written as a Dektak export `name` in a temporary
/// folder, and compared through the library against the quantized built-in design.
fn simulated_comparison(
    a: f64,
    name: &str,
) -> (
    SimulateProfile,
    doefab::pipeline::compare_profile::CompareProfileOutcome,
    tempfile::TempDir,
    std::path::PathBuf,
) {
    let (design, chain) = quantized_paper();
    let sp = truth(a);
    let prof = simulate_profile(&design, &sp).unwrap();
    let dir = common::tempdir();
    let csv = dir.path().join(name);
    write_dektak(&csv, &prof);
    let pd = ProfileDesign {
        source: DesignSource::BuiltIn("paper".into()),
        chain: Some(chain),
        line: sp.line,
        options: ProfileOptions::default(),
    };
    let r = compare_profile_file(&csv, &ProfileReadOptions::default(), ProfileLevel::Line, Some(&pd), None)
        .unwrap();
    (sp, r, dir, csv)
}

fn num(v: &Value, k: &str) -> f64 {
    v[k].as_f64().unwrap_or_else(|| panic!("{k} missing in {v}"))
}

/// Recovered within 4 standard errors and within `tol`.
fn check(name: &str, got: f64, want: f64, sigma: f64, tol: f64) {
    eprintln!("{name}: {got:.6e} (true {want:.6e}), sigma {sigma:.3e}");
    assert!(
        (got - want).abs() <= 4.0 * sigma && (got - want).abs() <= tol,
        "{name}: {got:e} against {want:e} (sigma {sigma:e}, tolerance {tol:e})"
    );
}

#[test]
fn a_simulated_profile_of_the_built_in_design_is_recovered_by_library_and_cli() {
    // Library.
    let (sp, r, dir, csv) = simulated_comparison(0.9, "scan01.csv");
    assert_eq!((r.x_unit, r.z_unit), (1e-6, 1e-10));
    let c = r.comparison.as_ref().unwrap();
    check("along shift", c.along_shift, sp.along_shift, c.along_shift_sigma, 0.1e-6);
    check("across offset", c.across_offset, sp.across_offset, c.across_offset_sigma, 0.3e-6);
    check("depth scale", c.depth_scale, 0.9, c.depth_scale_sigma, 0.009);
    check("blur", c.blur, sp.blur, c.blur_sigma, 0.2e-6);
    assert!(!c.complement && !c.across_fixed && c.blur_resolved, "{:?}", c.warnings);
    check("offset", c.offset, sp.offset, c.offset_sigma, 2e-9);
    check("tilt", c.tilt, sp.tilt, c.tilt_sigma, 2e-6);
    assert!((c.rms_residual - 5e-9).abs() < 0.5e-9, "{}", c.rms_residual);
    let l = c.levels.as_ref().unwrap();
    assert!(l.levels.len() >= 3, "{l:#?}");
    let mut per_level = 0;
    for s in &l.levels {
        if let (Some(d), Some(ds)) = (s.depth_scale, s.depth_scale_sigma) {
            eprintln!("level {}: {} points, depth scale {d:.4} +- {ds:.4}", s.level, s.points);
            if s.points >= 30 {
                assert!((d - 0.9).abs() <= (4.0 * ds).max(0.01), "level {}: {d} +- {ds}", s.level);
                per_level += 1;
            }
        }
    }
    assert!(per_level >= 2, "{l:#?}");

    // Command line: the same figures in its JSON, the files in the output folder.
    let out = dir.path().join("cmp");
    let json = ok(&[
        "compare-profile",
        csv.to_str().unwrap(),
        "built-in:paper",
        "--recipe",
        RECIPE,
        "--angle",
        "17deg",
        "-o",
        out.to_str().unwrap(),
        "--json",
    ]);
    let v: Value = serde_json::from_str(&json).unwrap();
    let cv = &v["comparison"];
    assert_eq!(num(cv, "along_shift"), c.along_shift);
    assert_eq!(num(cv, "depth_scale"), c.depth_scale);
    for f in ["profile.json", "profile_fit.csv", "profile.svg"] {
        assert!(out.join(f).exists(), "{f}");
    }
    let written: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("profile.json")).unwrap()).unwrap();
    assert_eq!(written["comparison"]["blur"], cv["blur"]);
    assert!(written["units"].as_str().unwrap().contains("metres"));
    // The human summary names the figures.
    let text = ok(&[
        "compare-profile",
        csv.to_str().unwrap(),
        "built-in:paper",
        "--recipe",
        RECIPE,
        "--angle",
        "17deg",
    ]);
    eprintln!("{text}");
    assert!(text.contains("depth scale 0.9") && text.contains("registered: along"), "{text}");
}

#[test]
fn the_complement_is_detected_and_bad_lines_and_files_are_refused() {
    let (sp, r, dir, csv) = simulated_comparison(-0.9, "cast.csv");
    let c = r.comparison.unwrap();
    assert!(c.complement, "{c:?}");
    check("depth scale (complement)", c.depth_scale, 0.9, c.depth_scale_sigma, 0.009);
    check("along shift (complement)", c.along_shift, sp.along_shift, c.along_shift_sigma, 0.1e-6);

    // A line outside the aperture sees one level (the design is 0 there).
    let e = fails(&[
        "compare-profile",
        csv.to_str().unwrap(),
        "built-in:paper",
        "--recipe",
        RECIPE,
        "--line",
        "-2.75mm,-2.7mm,-1.55mm,-2.7mm",
    ]);
    assert!(e.contains("crosses 1 level"), "{e}");
    // A design without a line, a line without a design.
    let e = fails(&["compare-profile", csv.to_str().unwrap(), "built-in:paper"]);
    assert!(e.contains("--line") && e.contains("--angle"), "{e}");
    let e = fails(&["compare-profile", csv.to_str().unwrap(), "--angle", "10deg"]);
    assert!(e.contains("need a DESIGN"), "{e}");
    // The profile at the wrong angle does not match: exit status 3. (At 17 + 60 degrees it
    // would: the design's three gratings repeat every 60 degrees.)
    let o = doefab(&[
        "compare-profile",
        csv.to_str().unwrap(),
        "built-in:paper",
        "--recipe",
        RECIPE,
        "--angle",
        "47deg",
    ]);
    assert_eq!(
        o.status.code(),
        Some(3),
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    // A file without units needs them on the command line.
    let bare = dir.path().join("bare.txt");
    std::fs::write(&bare, "0 10\n1 12\n2 11\n").unwrap();
    let e = fails(&["compare-profile", bare.to_str().unwrap()]);
    assert!(e.contains("bare.txt") && e.contains("no position unit") && e.contains("pass `x_unit`"), "{e}");
}

/// Row 100 of Gwyddion's S1 surface (1 um pitch; 1.0 um pedestal over columns 50..150, a
/// further 0.5 um over 80..120; tilt 2 nm per column) as a stylus export.
fn s1_line(dir: &Path) -> (std::path::PathBuf, doefab::Grid) {
    let scan =
        read_scan(&shared_data("surfaces/gwyddion/s1_tilt_pedestal.gsf"), &ScanOptions::default()).unwrap();
    let g = scan.grid;
    let (_, nc) = g.dim();
    assert_eq!(g.pitch(), [1e-6, 1e-6]);
    let path = dir.join("s1_row100.txt");
    let mut f = std::fs::File::create(&path).unwrap();
    // A P-series-like tab-separated export with the micro sign in UTF-8.
    writeln!(f, "Profile from s1_tilt_pedestal.gsf, row 100\nX (µm)\tZ (nm)").unwrap();
    for j in 0..nc {
        writeln!(f, "{}\t{}", j as f64, g.values()[[100, j]] * 1e9).unwrap();
    }
    (path, g)
}

#[test]
fn a_line_of_a_real_surface_file_gives_its_known_step_heights() {
    let dir = common::tempdir();
    let (path, g) = s1_line(dir.path());
    let out = dir.path().join("s1");
    let json = ok(&[
        "compare-profile",
        path.to_str().unwrap(),
        "--level",
        "substrate",
        "-o",
        out.to_str().unwrap(),
        "--json",
    ]);
    let v: Value = serde_json::from_str(&json).unwrap();
    let slope = num(&v["levelling"], "slope");
    eprintln!("S1 substrate slope {slope:e} (true 2e-3), terraces {}", v["terraces"]);
    assert!((slope - 2e-3).abs() < 1e-6, "{slope}");
    let t = v["terraces"].as_array().unwrap();
    assert_eq!(t.len(), 3, "{t:?}");
    // The README's stated steps: 1.0 um, and 0.5 um further (1.5 um above the base).
    assert!((num(&t[1], "height") - 1.0e-6).abs() < 1e-9, "{t:?}");
    assert!((num(&t[2], "height") - 1.5e-6).abs() < 1e-9, "{t:?}");
    assert!(out.join("profile.svg").exists());
    eprintln!("{}", ok(&["compare-profile", path.to_str().unwrap(), "--level", "substrate"]));

    // Against the surface's ideal design (the pedestal without tilt), given as a height map:
    // the line at row 100 is y = +0.5 um from the centre; across it the design is flat.
    let design = g
        .map_values(
            ndarray::Array2::from_shape_fn(g.dim(), |(i, j)| {
                let p = |lo: usize, hi: usize| (lo..hi).contains(&i) && (lo..hi).contains(&j);
                if p(80, 120) {
                    1.5e-6
                } else if p(50, 150) {
                    1.0e-6
                } else {
                    0.0
                }
            }),
            doefab::grid::Unit::Metre,
        )
        .unwrap();
    let dfile = dir.path().join("s1_design.csv");
    doefab::io::csv::write_csv(
        &dfile,
        design.values(),
        &doefab::io::raw_map::Metadata::heights([1e-6, 1e-6]),
    )
    .unwrap();
    let json = ok(&[
        "compare-profile",
        path.to_str().unwrap(),
        dfile.to_str().unwrap(),
        "--line",
        "-99.5um,0.5um,99.5um,0.5um",
        "--level",
        "substrate",
        "--json",
    ]);
    let v: Value = serde_json::from_str(&json).unwrap();
    let c = &v["comparison"];
    eprintln!("S1 against its design: {c}");
    assert!(num(c, "along_shift").abs() < 0.05e-6, "{c}");
    assert!(c["across_fixed"].as_bool().unwrap(), "{c}");
    assert!((num(c, "depth_scale") - 1.0).abs() < 1e-3, "{c}");
    let steps: Vec<(f64, f64)> = c["levels"]["levels"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|s| Some((s["step_height"].as_f64()?, s["design_step"].as_f64()?)))
        .collect();
    assert_eq!(steps.len(), 2, "{c}");
    assert!((steps[0].0 - 1.0e-6).abs() < 2e-9 && (steps[1].0 - 1.5e-6).abs() < 2e-9, "{steps:?}");
    assert!(v["comparison"]["warnings"]
        .as_array()
        .unwrap()
        .iter()
        .any(|w| w.as_str().unwrap().contains("unobservable")));
}
