//! `doefab report`: one static page from the benchmarks, within its budget.

use doefab::decoder::FinetuneConfig;
use doefab::design::{paper_example, ExampleParams, PAPER_PITCH};
use doefab::fabrication::recipe_run::DesignSource;
use doefab::io::heightmap::ReadOptions;
use doefab::pipeline::report::{run_report, shown, ReportOptions, COSTS};
use doefab::pipeline::sweep::PsfSweepOptions;
use doefab::sweep::finetune_time::TimedOptions;
use doefab::sweep::psf::SweepOptions;
use doefab::sweep::stability::{MapOptions, MAPS};

/// `html` without the elements from `open` to `close`.
fn without(html: &str, open: &str, close: &str) -> String {
    let mut out = String::new();
    let mut rest = html;
    while let Some(i) = rest.find(open) {
        out.push_str(&rest[..i]);
        rest = rest[i..].find(close).map_or("", |j| &rest[i + j + close.len()..]);
    }
    out.push_str(rest);
    out
}

/// The numbers in `html`'s text: digits (with a point, an exponent, a sign) not glued to a
/// letter or an underscore (so `f32` is a name, not a number), outside tags, `<style>` and
/// `<code>` (which holds the design's name).
fn numbers_in_text(html: &str) -> Vec<String> {
    let text = without(&without(html, "<style>", "</style>"), "<code>", "</code>");
    let mut plain = String::new();
    let mut in_tag = false;
    for c in text.chars() {
        match c {
            '<' => in_tag = true,
            '>' => {
                in_tag = false;
                plain.push(' ');
            }
            _ if !in_tag => plain.push(c),
            _ => {}
        }
    }
    let c: Vec<char> = plain.chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < c.len() {
        let glued = i > 0 && (c[i - 1].is_alphanumeric() || c[i - 1] == '_');
        if !c[i].is_ascii_digit() || glued {
            i += 1;
            continue;
        }
        let start = if i > 0 && c[i - 1] == '-' { i - 1 } else { i };
        let next_digit = |j: usize| j + 1 < c.len() && c[j + 1].is_ascii_digit();
        let mut j = i;
        while j < c.len()
            && (c[j].is_ascii_digit()
                || (c[j] == '.' && next_digit(j))
                || (c[j] == 'e' && (next_digit(j) || (j + 1 < c.len() && c[j + 1] == '-')))
                || (c[j] == '-' && c[j - 1] == 'e'))
        {
            j += 1;
        }
        out.push(c[start..j].iter().collect());
        i = j;
    }
    out
}

/// On a small design and camera (0.5 mm aperture, 40^2 crop) and a budget that holds every part: the page links only files
/// that exist, every number on it is a figure of report.json shown as [`shown`] writes it, and
/// the figures hold what the benchmarks' own JSON say.
#[test]
fn the_report_page_links_what_exists_and_every_number_comes_from_its_json() {
    let dir = tempfile::tempdir().unwrap();
    let sys = dir.path().join("small.toml");
    std::fs::write(
        &sys,
        "aperture = \"0.5 mm\"\nfocal_length = \"3.5 mm\"\nlens_to_sensor = \"3.5 mm\"\ndoe_to_lens = \"1 mm\"\n\
         crop = 40\nsensor_pitch = \"3 um\"\npupil_window = \"0.6 mm\"\n",
    )
    .unwrap();
    // The paper's design on 140 samples (0.6 mm), for the fabrication sweeps to be quick.
    let design = dir.path().join("design.npy");
    let p = ExampleParams { samples: 140, aperture: 0.55e-3, ..Default::default() };
    doefab::io::npy::write_npy_f64(&design, paper_example(&p).unwrap().values()).unwrap();
    let read = ReadOptions { pitch: Some([PAPER_PITCH; 2]), unit: Some(1.0), ..Default::default() };
    let opts = ReportOptions {
        psf: PsfSweepOptions {
            design: DesignSource::File(design, read),
            system: Some(sys),
            material: "pdms".into(),
            sweep: SweepOptions { budget: 60.0, max_subsample: 3, ..Default::default() },
        },
        // Room for every part, whatever else shares the machine; the PSF benchmark keeps to
        // its own minute.
        budget: 3600.0,
        // Two rows a map, two pupil samplings a row: the page, not the maps, is tested here.
        maps: MapOptions {
            subsamples: vec![1, 2],
            asm_subsamples: vec![1, 2],
            mdft_pitches: vec![3e-6, 9e-6],
            stepped_pitches: vec![2e-6, 4.5e-6],
            focal_lengths: vec![2e-3, 4e-3],
            wavelengths: vec![450e-9, 650e-9],
            ..MapOptions::default()
        },
        // Small crops, for the test's time; the page is tested here, not the settings.
        finetune: TimedOptions {
            config: FinetuneConfig { batch: 1, crop: 64, validation: 2, ..FinetuneConfig::recommended() },
            ..TimedOptions::new(10.0)
        },
    };
    let out = dir.path().join("report");
    let page = run_report(&opts, &out, &mut |_, _, _| {}).unwrap();
    assert_eq!(page.budget.left_out().count(), 0, "{:?}", page.budget);
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    // Every linked file exists, and every chart of the sections is linked.
    let mut linked = 0;
    for attr in ["src=\"", "href=\""] {
        for part in html.split(attr).skip(1) {
            let name = &part[..part.find('"').unwrap()];
            assert!(out.join(name).is_file(), "{name} is linked but not written");
            linked += 1;
        }
    }
    for s in &page.sections {
        for c in &s.charts {
            assert!(html.contains(&format!("src=\"{c}\"")), "{c} not on the page");
        }
    }
    assert!(linked >= 18, "{linked}");
    assert_eq!(page.sections.len(), 8);
    // Every number on the page is one of report.json's figures, as shown() writes its value.
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let figures = json["figures"].as_array().unwrap();
    let texts: Vec<&str> = figures.iter().map(|f| f["shown"].as_str().unwrap()).collect();
    for f in figures {
        assert_eq!(f["shown"].as_str().unwrap(), shown(f["value"].as_f64().unwrap()), "{f}");
        assert!(!f["unit"].as_str().unwrap().is_empty(), "{f}");
    }
    let numbers = numbers_in_text(&html);
    assert!(numbers.len() >= 20, "{numbers:?}");
    for n in &numbers {
        assert!(texts.contains(&n.as_str()), "{n} on the page is no figure of report.json: {texts:?}");
    }
    // The figures say what the benchmarks measured.
    let maps: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("stability.json")).unwrap()).unwrap();
    let silent: Vec<f64> = figures
        .iter()
        .filter(|f| f["label"] == "silent failures")
        .map(|f| f["value"].as_f64().unwrap())
        .collect();
    let in_json: Vec<f64> =
        maps["maps"].as_array().unwrap().iter().map(|m| m["silent_failures"].as_f64().unwrap()).collect();
    assert_eq!(in_json.len(), 8);
    assert_eq!(silent, in_json);
    let psf: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("bench_psf.json")).unwrap()).unwrap();
    let errors: Vec<f64> =
        figures.iter().filter(|f| f["label"] == "plan error").map(|f| f["value"].as_f64().unwrap()).collect();
    let want: Vec<f64> =
        psf["plans"].as_array().unwrap().iter().map(|p| p["error"].as_f64().unwrap()).collect();
    assert_eq!(errors, want);
    let cal: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("calibration.json")).unwrap()).unwrap();
    let figure =
        |label: &str| figures.iter().find(|f| f["label"] == label).unwrap()["value"].as_f64().unwrap();
    assert_eq!(figure("calibration silent failures"), cal["silent_failures"].as_f64().unwrap());
    assert_eq!(figure("calibration trials"), cal["trials"].as_array().unwrap().len() as f64);
    let tiling: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("tiling.json")).unwrap()).unwrap();
    assert_eq!(figure("f32 against f64, one pass"), tiling["runs"][0]["relative_l2"].as_f64().unwrap());
    let finetune: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("finetune_time.json")).unwrap()).unwrap();
    let points = finetune["points"].as_array().unwrap();
    assert_eq!(points.len(), 9);
    assert_eq!(figure("validation PSNR at the start"), points[0]["val_psnr"].as_f64().unwrap());
    let best = points.iter().map(|p| p["val_psnr"].as_f64().unwrap()).fold(f64::MIN, f64::max);
    assert_eq!(figure("best validation PSNR"), best);
    assert_eq!(figure("fine-tuning steps"), finetune["steps"].as_f64().unwrap());
}

/// A budget of 3 s on the small design and camera: most parts cannot fit, and the page is
/// written all the same. Every part is in `report.json`'s budget: each one that ran was
/// predicted to fit in the time it had, each one left out was not, and the page names each left
/// out (the recorded plan, not the clock, is what is checked).
#[test]
fn a_small_budget_leaves_parts_out_and_names_them_on_the_page() {
    let dir = tempfile::tempdir().unwrap();
    let sys = dir.path().join("small.toml");
    std::fs::write(
        &sys,
        "aperture = \"0.5 mm\"\nfocal_length = \"3.5 mm\"\nlens_to_sensor = \"3.5 mm\"\ndoe_to_lens = \"1 mm\"\n\
         crop = 40\nsensor_pitch = \"3 um\"\npupil_window = \"0.6 mm\"\n",
    )
    .unwrap();
    let design = dir.path().join("design.npy");
    let p = ExampleParams { samples: 140, aperture: 0.55e-3, ..Default::default() };
    doefab::io::npy::write_npy_f64(&design, paper_example(&p).unwrap().values()).unwrap();
    let read = ReadOptions { pitch: Some([PAPER_PITCH; 2]), unit: Some(1.0), ..Default::default() };
    let psf = PsfSweepOptions {
        design: DesignSource::File(design, read),
        system: Some(sys),
        material: "pdms".into(),
        sweep: SweepOptions { max_subsample: 2, ..Default::default() },
    };
    let opts = ReportOptions::new(psf, 3.0);
    let out = dir.path().join("report");
    let page = run_report(&opts, &out, &mut |_, _, _| {}).unwrap();
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let b = &page.budget;
    // Every part came up: the fabrication sweeps, registration, calibration, tiling, eight maps,
    // the fine-tuning and the PSF benchmark.
    assert_eq!(b.parts.len(), 14, "{b:?}");
    assert_eq!(json["budget"]["parts"].as_array().unwrap().len(), 14);
    for p in &b.parts {
        match p.seconds {
            Some(_) => assert!(p.predicted_seconds <= p.left_seconds, "{p:?}"),
            None => {
                assert!(p.predicted_seconds > p.left_seconds, "{p:?}");
                assert!(html.contains(&p.name), "{} is not named on the page", p.name);
            }
        }
    }
    // The stability maps come up cheapest first: a short budget leaves out the costly ones.
    let maps: Vec<&str> =
        b.parts.iter().map(|p| p.name.as_str()).filter(|n| n.starts_with("stability map ")).collect();
    let mut cheapest_first: Vec<usize> = (0..MAPS.len()).collect();
    cheapest_first.sort_by(|&a, &b| COSTS.maps[a].total_cmp(&COSTS.maps[b]));
    let expected: Vec<String> =
        cheapest_first.iter().map(|&k| format!("stability map {}", MAPS[k].name())).collect();
    assert_eq!(maps, expected);
    // The angular spectrum's maps (the slowest part) cannot fit in 3 s.
    let left_out: Vec<&str> = b.left_out().map(|p| p.name.as_str()).collect();
    assert!(left_out.contains(&"stability map angular_spectrum_fresnel_number"), "{left_out:?}");
    assert_eq!(json["budget"]["budget_seconds"], 3.0);
    for attr in ["src=\"", "href=\""] {
        for part in html.split(attr).skip(1) {
            let name = &part[..part.find('"').unwrap()];
            assert!(out.join(name).is_file(), "{name} is linked but not written");
        }
    }
    assert_eq!(page.sections.len(), 8);
}

#[test]
fn the_report_refuses_a_budget_it_cannot_keep() {
    let opts = ReportOptions {
        psf: PsfSweepOptions {
            design: DesignSource::BuiltIn("paper".into()),
            system: None,
            material: "pdms".into(),
            sweep: SweepOptions::default(),
        },
        budget: 0.0,
        maps: MapOptions::default(),
        finetune: TimedOptions::new(0.0),
    };
    let dir = tempfile::tempdir().unwrap();
    let e = run_report(&opts, &dir.path().join("r"), &mut |_, _, _| {}).unwrap_err();
    assert!(matches!(e, doefab::Error::Parameter { ref name, .. } if name == "budget"), "{e:?}");
    assert!(!dir.path().join("r").exists());
}
