//! The `doefab` command line end to end: the fabrication chain, the single steps, bad input.

use crate::common;

use crate::common::{fails, ok};

use std::path::{Path, PathBuf};

use ndarray::Array2;

use doefab::fabrication::contrast::ContrastCurve;
use doefab::io::npy::write_npy_f64;

fn masks(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("masks").join(name).display().to_string()
}

/// A small design in metres at 4.29 um: a blazed ring pattern reaching 1.5 um, so that it wraps.
fn small_design(dir: &Path) -> PathBuf {
    let n = 150;
    let v = Array2::from_shape_fn((n, n), |(i, j)| {
        let (x, y) = (j as f64 - 74.5, i as f64 - 74.5);
        let r2 = (x * x + y * y) * (4.29e-6f64).powi(2);
        1.5e-6 * r2 / (75.0 * 4.29e-6f64).powi(2)
    });
    let p = dir.join("design.npy");
    write_npy_f64(&p, &v).unwrap();
    p
}

fn read_dir_sorted(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap())
        })
        .collect();
    v.sort();
    v
}

#[test]
fn fab_writes_every_artifact_and_is_byte_identical_when_repeated() {
    let d = common::tempdir();
    let design = small_design(d.path());
    let recipe = masks("binary-3mask-8level.toml");
    let fab = |o: &Path, extra: &[&str]| {
        let mut args =
            vec!["fab", design.to_str().unwrap(), "--pitch", "4.29um", "--unit", "m", "--recipe", &recipe];
        args.extend(["-o", o.to_str().unwrap(), "--quiet"]);
        args.extend(extra);
        ok(&args);
    };
    let (o1, o2) = (d.path().join("o1"), d.path().join("o2"));
    for o in [&o1, &o2] {
        fab(o, &["--intermediates"]);
    }
    let a = read_dir_sorted(&o1);
    let b = read_dir_sorted(&o2);
    let names: Vec<_> = a.iter().map(|(n, _)| n.as_str()).collect();
    for expect in
        ["levels.exr", "mask_set.gds", "mask_set_layer3.png", "report.json", "report.md", "surface.exr"]
    {
        assert!(names.contains(&expect), "{expect} missing from {names:?}");
    }
    assert_eq!(a.len(), b.len());
    for ((na, ba), (nb, bb)) in a.iter().zip(&b) {
        assert_eq!(na, nb);
        // Reports name their output folder, so compare them with the folder name replaced.
        if na.starts_with("report") || na.ends_with(".json") {
            let ta = String::from_utf8_lossy(ba).replace("/o1/", "/oX/");
            let tb = String::from_utf8_lossy(bb).replace("/o2/", "/oX/");
            assert_eq!(ta, tb, "{na} differs");
        } else {
            assert!(ba == bb, "{na} is not byte-identical across runs");
        }
    }
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(o1.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["provenance"]["design_sha256"], doefab::io::file_sha256(&design).unwrap());
    assert_eq!(report["provenance"]["replica_mode"], "master");
    assert_eq!(report["units"]["length"], "m");
    let stl = std::fs::read(o1.join("surface.stl")).unwrap();
    assert!(String::from_utf8_lossy(&stl[..80]).starts_with("doefab STL units=mm part=master "));
    // The paraboloid reaches 3.0 um in the corners: floor(3.0 / 1.2187) = 2 wraps.
    assert_eq!(report["wrap"]["max_wraps"], 2);
    let eta = report["efficiency"][1]["efficiency"].as_f64().unwrap();
    assert!((eta - 0.9496).abs() < 1e-3, "8-level efficiency at 530 nm: {eta}");
    // The input is never modified.
    assert_eq!(doefab::io::file_sha256(&design).unwrap(), report["provenance"]["design_sha256"]);
    // Without --intermediates the maps are not written, the rest is the same.
    let o3 = d.path().join("o3");
    fab(&o3, &[]);
    let c = read_dir_sorted(&o3);
    let without: Vec<_> = c.iter().map(|(n, _)| n.as_str()).collect();
    for gone in ["levels.exr", "surface.exr", "levels_preview.png"] {
        assert!(!without.contains(&gone), "{gone} written without --intermediates");
    }
    for (name, bytes) in &c {
        if !name.ends_with(".json") && !name.ends_with(".md") {
            assert!(a.iter().any(|(n, b)| n == name && b == bytes), "{name} differs without --intermediates");
        }
    }
}

#[test]
fn single_steps_chain_to_the_same_mask_as_fab() {
    let d = common::tempdir();
    let design = small_design(d.path());
    let p = |n: &str| d.path().join(n).display().to_string();
    let design_s = design.display().to_string();
    let read = ["--pitch", "4.29um", "--unit", "m"];
    let mut wrap_args = vec!["wrap", design_s.as_str()];
    wrap_args.extend(read);
    let wrapped = p("wrapped.exr");
    wrap_args.extend(["-o", wrapped.as_str(), "--replica", "master", "-q"]);
    ok(&wrap_args);
    let levels = p("levels.exr");
    ok(&["quantize", &wrapped, "-o", &levels, "--levels", "64", "-q"]);
    let mask = p("mask.png");
    let curve = masks("positive-resist-contrast.csv");
    ok(&["mask", &levels, "--curve", &curve, "-o", &mask, "--label", "DOEFAB GRAYSCALE MASTER", "-q"]);
    // The same through the recipe.
    let mut fab = vec!["fab", design_s.as_str()];
    fab.extend(read);
    let out = p("fab");
    let recipe = masks("laser-writer-grayscale.toml");
    fab.extend(["--recipe", recipe.as_str(), "-o", out.as_str(), "-q"]);
    ok(&fab);
    let a = doefab::io::png::read_png(Path::new(&mask)).unwrap();
    let b = doefab::io::png::read_png(&d.path().join("fab/grayscale_mask.png")).unwrap();
    assert_eq!(a.values, b.values, "single steps and fab disagree");
}

#[test]
fn mask_gray_levels_develop_the_target_depths() {
    let d = common::tempdir();
    let out = d.path().join("fab");
    ok(&["fab", "--recipe", &masks("laser-writer-grayscale.toml"), "-o", out.to_str().unwrap(), "-q"]);
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("grayscale_mask.json")).unwrap()).unwrap();
    let curve = ContrastCurve::read_csv(Path::new(&masks("positive-resist-contrast.csv"))).unwrap();
    let n = meta["level_count"].as_u64().unwrap() as usize;
    let period = meta["period_m"].as_f64().unwrap();
    assert_eq!(meta["units"]["pitch"], "m");
    assert_eq!(meta["polarity"], "positive");
    assert_eq!(meta["provenance"]["replica_mode"], "master");
    for (l, row) in meta["levels"].as_array().unwrap().iter().enumerate() {
        let gray = row["gray"].as_f64().unwrap();
        // Develop with the dose this gray level stands for: the depth must be the target
        // within what one gray count changes (the curve's slope is below 2.1 um per unit dose).
        let depth = curve.depth_at(gray / 65535.0);
        let target = (n - 1 - l) as f64 * period / n as f64;
        assert!((depth - target).abs() < 2.1e-6 / 65535.0, "level {l}: {depth} vs {target}");
    }
    // The pattern in the image uses exactly the table's gray values.
    let img = doefab::io::png::read_png(&out.join("grayscale_mask.png")).unwrap();
    let table: Vec<f64> =
        meta["levels"].as_array().unwrap().iter().map(|r| r["gray"].as_f64().unwrap()).collect();
    let [ox, oy] = [
        meta["pattern_offset_px"][0].as_u64().unwrap() as usize,
        meta["pattern_offset_px"][1].as_u64().unwrap() as usize,
    ];
    let [pw, ph] = [
        meta["pattern_size_px"][0].as_u64().unwrap() as usize,
        meta["pattern_size_px"][1].as_u64().unwrap() as usize,
    ];
    for i in (oy..oy + ph).step_by(37) {
        for j in (ox..ox + pw).step_by(41) {
            assert!(
                table.contains(&img.values[[i, j]]),
                "gray {} at ({i},{j}) is no level",
                img.values[[i, j]]
            );
        }
    }
}

#[test]
fn bad_input_gets_a_clear_error_and_leaves_nothing_behind() {
    let d = common::tempdir();
    let design = small_design(d.path());
    let design_s = design.display().to_string();
    let recipe = masks("binary-3mask-8level.toml");
    let out = d.path().join("out");
    let out_s = out.display().to_string();
    // No pitch in an .npy file: refuse, name the parameter.
    let e = fails(&["fab", &design_s, "--unit", "m", "--recipe", &recipe, "-o", &out_s]);
    assert!(e.contains("pass `pitch`") && e.contains("design.npy"), "{e}");
    // Heights ~1e-6 declared in um: implausible, suggest metres.
    let e =
        fails(&["fab", &design_s, "--pitch", "4.29um", "--unit", "um", "--recipe", &recipe, "-o", &out_s]);
    assert!(e.contains("did you mean `unit` m?"), "{e}");
    // Level count out of range.
    let e = fails(&[
        "fab", &design_s, "--pitch", "4.29um", "--unit", "m", "--recipe", &recipe, "--levels", "300", "-o",
        &out_s,
    ]);
    assert!(e.contains("2..=256"), "{e}");
    // A truncated file names itself.
    let bytes = std::fs::read(&design).unwrap();
    let cut = d.path().join("cut.npy");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let e = fails(&[
        "fab",
        cut.to_str().unwrap(),
        "--pitch",
        "4.29um",
        "--unit",
        "m",
        "--recipe",
        &recipe,
        "-o",
        &out_s,
    ]);
    assert!(e.contains("cut.npy"), "{e}");
    // NaN heights: count and first location, or `fill`.
    let mut v = doefab::io::npy::read_npy_2d(&design).unwrap();
    v[[3, 7]] = f64::NAN;
    v[[90, 2]] = f64::NAN;
    let nan = d.path().join("nan.npy");
    write_npy_f64(&nan, &v).unwrap();
    let nan_s = nan.display().to_string();
    let e = fails(&["fab", &nan_s, "--pitch", "4.29um", "--unit", "m", "--recipe", &recipe, "-o", &out_s]);
    assert!(e.contains("2 samples") && e.contains("row 3, column 7") && e.contains("set `fill`"), "{e}");
    assert!(!out.exists(), "a failed run left {out:?}");
    // A contrast curve too shallow for the design: fails late, after files were staged.
    let shallow = d.path().join("shallow.csv");
    std::fs::write(&shallow, "dose,depth_nm\n0,0\n1,500\n").unwrap();
    let r = std::fs::read_to_string(masks("laser-writer-grayscale.toml")).unwrap().replace(
        "contrast_curve = \"positive-resist-contrast.csv\"",
        &format!("contrast_curve = {:?}", shallow.display().to_string()),
    );
    let rp = d.path().join("shallow.toml");
    std::fs::write(&rp, r).unwrap();
    let e = fails(&[
        "fab",
        &nan_s,
        "--fill",
        "--pitch",
        "4.29um",
        "--unit",
        "m",
        "--recipe",
        rp.to_str().unwrap(),
        "-o",
        &out_s,
    ]);
    assert!(e.contains("covers 0.0..500.0 nm"), "{e}");
    assert!(!out.exists(), "a failed run left {out:?}");
    let leftovers: Vec<_> = std::fs::read_dir(d.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .filter(|n| n.to_string_lossy().starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "staging debris: {leftovers:?}");
    // With --fill and a good recipe it goes through.
    ok(&[
        "fab", &nan_s, "--fill", "--pitch", "4.29um", "--unit", "m", "--recipe", &recipe, "-o", &out_s, "-q",
    ]);
    assert!(out.join("mask_set.gds").exists());
}

#[test]
fn json_output_is_machine_readable() {
    let d = common::tempdir();
    let design = small_design(d.path());
    let wrapped = d.path().join("w.exr");
    let s = ok(&[
        "wrap",
        design.to_str().unwrap(),
        "--pitch",
        "4.29um",
        "--unit",
        "m",
        "-o",
        wrapped.to_str().unwrap(),
        "--json",
    ]);
    let v: serde_json::Value = serde_json::from_str(&s).unwrap();
    let period = v["wrap"]["period"].as_f64().unwrap();
    assert!((period - 530e-9 / 0.4349).abs() < 1e-15);
    let s = ok(&[
        "quantize",
        wrapped.to_str().unwrap(),
        "-o",
        d.path().join("l.exr").to_str().unwrap(),
        "-n",
        "4",
        "--json",
    ]);
    let v: serde_json::Value = serde_json::from_str(&s).unwrap();
    let eta = v["efficiency"][1]["efficiency"].as_f64().unwrap();
    assert!((eta - 0.8106).abs() < 1e-3, "{eta}");
}

#[test]
fn a_mask_above_the_size_limit_needs_force() {
    let d = common::tempdir();
    let design = small_design(d.path());
    let p = |n: &str| d.path().join(n).display().to_string();
    let (wrapped, levels, mask) = (p("w.exr"), p("l.exr"), p("m.png"));
    ok(&["wrap", design.to_str().unwrap(), "--pitch", "4.29um", "--unit", "m", "-o", &wrapped, "-q"]);
    ok(&["quantize", &wrapped, "-o", &levels, "-n", "8", "-q"]);
    let curve = masks("positive-resist-contrast.csv");
    // 643.5 um of pattern at 30 nm: 21450^2 = 4.6e8 pixels, above the limit of 2e8.
    let e = fails(&[
        "mask",
        &levels,
        "--curve",
        &curve,
        "-o",
        &mask,
        "--writer-pitch",
        "30nm",
        "--border",
        "0um",
    ]);
    assert!(e.contains("above the limit") && e.contains("set `force`"), "{e}");
    assert!(!Path::new(&mask).exists());
    ok(&["mask", &levels, "--curve", &curve, "-o", &mask, "--writer-pitch", "0.5um", "-q"]);
    assert!(Path::new(&mask).exists());
}

#[test]
fn stl_command_meshes_level_maps_and_heights() {
    let d = common::tempdir();
    let design = small_design(d.path());
    let p = |n: &str| d.path().join(n).display().to_string();
    let (wrapped, levels) = (p("w.exr"), p("l.exr"));
    ok(&["wrap", design.to_str().unwrap(), "--pitch", "4.29um", "--unit", "m", "-o", &wrapped, "-q"]);
    ok(&["quantize", &wrapped, "-o", &levels, "-n", "16", "-q"]);
    for (input, name, surface) in [(&levels, "t.stl", "Terraces"), (&wrapped, "h.stl", "Heightfield")] {
        let out = p(name);
        let s =
            ok(&["stl", input, "-o", &out, "--unit", "um", "--base", "20um", "--max-error", "5nm", "--json"]);
        let r: serde_json::Value = serde_json::from_str(&s).unwrap();
        assert_eq!(r["surface"], surface.to_ascii_lowercase());
        let triangles = r["triangles"].as_u64().unwrap();
        let bytes = std::fs::read(&out).unwrap();
        assert_eq!(bytes.len() as u64, 84 + 50 * triangles);
        assert!(String::from_utf8_lossy(&bytes[..80]).starts_with("doefab STL units=um"));
        assert!(r["max_height_error"].as_f64().unwrap() <= 5e-9 * (1.0 + 1e-9));
    }
    let e = fails(&["stl", &levels, "-o", &p("x.stl"), "--unit", "inch"]);
    assert!(e.contains("inch"), "{e}");
}

/// Every file below `dir` (relative path, bytes), sorted by path.
fn read_tree(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(dir).unwrap().to_string_lossy().into_owned();
                out.push((rel, std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

/// The demo from a folder outside the checkout, on 1 and on 7 threads: every stage runs, and
/// every file it writes is byte-identical between the two (parallel work is split and summed
/// the same way whatever the thread count).
#[test]
fn demo_runs_every_stage_on_the_built_in_design() {
    let d = common::tempdir();
    let mut runs = Vec::new();
    for threads in ["1", "7"] {
        let cwd = d.path().join(format!("threads-{threads}"));
        std::fs::create_dir_all(&cwd).unwrap();
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_doefab"))
            .args(["demo", "-o", "demo", "--json"])
            .current_dir(&cwd)
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "demo on {threads} threads failed:\n{}",
            String::from_utf8_lossy(&o.stderr)
        );
        runs.push((cwd.join("demo"), String::from_utf8(o.stdout).unwrap()));
    }
    let (a, b) = (read_tree(&runs[0].0), read_tree(&runs[1].0));
    let names = |t: &[(String, Vec<u8>)]| t.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
    assert_eq!(names(&a), names(&b), "the two runs wrote different files");
    let differ: Vec<&str> = a.iter().zip(&b).filter(|(x, y)| x.1 != y.1).map(|(x, _)| x.0.as_str()).collect();
    assert!(differ.is_empty(), "not byte-identical on 1 and 7 threads: {differ:?}");
    assert_eq!(runs[0].1, runs[1].1, "the JSON reports differ between 1 and 7 threads");
    let out = runs[0].0.clone();
    let all: serde_json::Value = serde_json::from_str(&runs[0].1).unwrap();
    let reports = all["fabrication"].as_array().unwrap();
    assert_eq!(reports.len(), 3);
    let psf = &all["psf"];
    assert_eq!(psf["channels"].as_array().unwrap().len(), 3);
    for f in psf["files"].as_array().unwrap() {
        assert!(out.join("psf").join(f.as_str().unwrap()).exists(), "{f} missing");
    }
    let kinds: Vec<&str> = reports
        .iter()
        .flat_map(|r| r["artifacts"].as_array().unwrap())
        .map(|a| a["kind"].as_str().unwrap())
        .collect();
    for k in ["grayscale_mask", "gds_mask_set", "stl", "report_markdown"] {
        assert!(kinds.contains(&k), "the demo wrote no {k}");
    }
    // The metrology stage: the simulated 8-level cast (5% shallow, 2 um blur) is recovered.
    let m = &all["metrology"];
    for f in m["files"].as_array().unwrap() {
        assert!(out.join("metrology/compare").join(f.as_str().unwrap()).exists(), "{f} missing");
    }
    assert!(out.join("metrology/scan.x3p").exists());
    let depth = m["model"]["depth_scale"].as_f64().unwrap();
    assert!((depth / 0.95 - 1.0).abs() < 0.005, "{depth}");
    assert!((m["model"]["blur"].as_f64().unwrap() - 2e-6).abs() < 0.1e-6, "{}", m["model"]);
    let step = m["levels"]["mean_step"].as_f64().unwrap() / m["levels"]["step"].as_f64().unwrap();
    assert!((step / 0.95 - 1.0).abs() < 0.005, "{step}");
    assert_eq!(m["psf"]["channels"].as_array().unwrap().len(), 3);
    // The calibration stage: the synthetic pinhole bracket gives the simulated PSF back.
    for l2 in all["calibration"]["relative_l2_to_simulated"].as_array().unwrap() {
        assert!(l2.as_f64().unwrap() < 0.02, "{l2}");
    }
    // The decoder stage: two fine-tuning steps and a reconstruction, written where it says.
    let dec = &all["decoder"];
    assert_eq!(dec["history"].as_array().unwrap().iter().filter(|h| h["loss"].is_number()).count(), 2);
    let cwd = out.parent().unwrap();
    assert!(cwd.join(dec["decoder"].as_str().unwrap()).exists());
    for k in ["exr", "png"] {
        assert!(cwd.join(dec["reconstruction"][k].as_str().unwrap()).exists(), "{k} missing");
    }
    for r in reports {
        assert_eq!(r["provenance"]["design"], "built-in:paper");
        for a in r["artifacts"].as_array().unwrap() {
            let path = cwd.join(a["path"].as_str().unwrap());
            assert!(path.exists(), "{} listed but missing", path.display());
        }
    }
}

#[test]
fn a_terrace_mesh_larger_than_a_pixel_mesh_is_reported() {
    let d = common::tempdir();
    let mut g = doefab::rng::Lcg(9);
    let v = Array2::from_shape_fn((60, 60), |_| g.uniform() * 1.2e-6);
    let noise = d.path().join("noise.npy");
    write_npy_f64(&noise, &v).unwrap();
    let out = d.path().join("o");
    let args = ["fab", noise.to_str().unwrap(), "--pitch", "4.29um", "--unit", "m"];
    let recipe = masks("binary-3mask-8level.toml");
    let s = ok(&[&args[..], &["--recipe", &recipe, "-o", out.to_str().unwrap(), "--json"]].concat());
    let r: serde_json::Value = serde_json::from_str(&s).unwrap();
    assert!(r["stl"]["triangle_ratio"].as_f64().unwrap() > 1.0);
    let w: Vec<&str> = r["warnings"].as_array().unwrap().iter().map(|w| w.as_str().unwrap()).collect();
    assert!(w.iter().any(|w| w.contains("two-per-pixel")), "{w:?}");
}
