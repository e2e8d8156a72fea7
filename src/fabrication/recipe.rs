//! Process recipes: TOML files in `masks/` that fix the writer, the level count, the resist
//! and which artifacts to produce. Lengths are strings with units ("1 um", "500 nm"), parsed
//! here; paths (the contrast curve) are relative to the recipe file.
//!
//! The recipes and the contrast curve of `masks/` are also compiled into the binary
//! ([`BUNDLED`](super::built_in::BUNDLED)): `built-in:NAME` names one of them wherever a recipe or curve path is taken,
//! so an installed binary needs no source tree beside it.

use crate::fabrication::gds::{MAX_BOUNDARY_VERTICES, SIGNED_LENGTH_MAX_VERTICES};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::fabrication::built_in::{read_text, BUILT_IN};
use crate::fabrication::mask::Polarity;
use crate::fabrication::quantize::{check_level_count, QuantizeMethod};
use crate::fabrication::stl::StlUnit;
use crate::fabrication::ReplicaMode;
use crate::units::parse_length;

/// Artifacts a recipe can ask for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Output {
    /// Grayscale mask as PNG (with a JSON sidecar).
    GrayscalePng,
    /// Grayscale mask as TIFF (with a JSON sidecar).
    GrayscaleTiff,
    /// Multi-level binary mask set as one GDSII file, with a PNG preview per layer.
    Gds,
    /// Binary STL of the surface.
    Stl,
}

/// The TOML form, lengths still as text.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RecipeFile {
    name: String,
    #[serde(default)]
    description: String,
    writer: WriterFile,
    process: ProcessFile,
    #[serde(default)]
    design: DesignFile,
    #[serde(default)]
    mask: MaskFile,
    #[serde(default)]
    stl: StlFile,
    #[serde(default)]
    gds: GdsFile,
    outputs: Vec<Output>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct WriterFile {
    address_grid: String,
    min_feature: String,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ProcessFile {
    level_count: usize,
    #[serde(default)]
    quantization: QuantizeMethod,
    #[serde(default)]
    replica_mode: ReplicaMode,
    #[serde(default)]
    polarity: Polarity,
    contrast_curve: Option<String>,
}

#[derive(Debug, Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct DesignFile {
    wavelength: Option<String>,
    material: Option<String>,
    order: Option<u32>,
}

#[derive(Debug, Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct MaskFile {
    bits: Option<u8>,
    mirror: Option<bool>,
    border: Option<String>,
    label: Option<String>,
}

#[derive(Debug, Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct StlFile {
    unit: Option<String>,
    base_thickness: Option<String>,
    max_error: Option<String>,
}

#[derive(Debug, Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct GdsFile {
    max_vertices: Option<usize>,
}

/// A parsed, validated recipe (SI units).
#[derive(Debug, Clone, Serialize)]
pub struct Recipe {
    /// The recipe's name (`name`).
    pub name: String,
    /// What the recipe is for, in words (`description`; empty when absent).
    pub description: String,
    /// The recipe file, or `built-in:NAME` for a bundled one.
    pub path: PathBuf,
    /// Writer address grid, metres.
    pub address_grid: f64,
    /// Smallest feature the writer resolves, metres.
    pub min_feature: f64,
    /// Number of height levels per period (`process.level_count`; a power of two for GDSII).
    pub level_count: usize,
    /// How heights are mapped onto levels (default: nearest level).
    pub quantization: QuantizeMethod,
    /// Whether the outputs show the design or the master that casts it (default: design).
    pub replica_mode: ReplicaMode,
    /// Resist polarity of the grayscale mask (default: positive).
    pub polarity: Polarity,
    /// The resist's contrast curve (dose -> depth CSV), relative paths resolved against the
    /// recipe's folder; needed by grayscale outputs, `None` when the recipe names none.
    pub contrast_curve: Option<PathBuf>,
    /// Design wavelength, metres (default 530 nm).
    pub wavelength: f64,
    /// DOE material name (default `pdms`).
    pub material: String,
    /// Multi-order factor p: the wrap period is `p * h_2pi` (default 1).
    pub order: u32,
    /// Bits per grayscale mask pixel, 8 or 16 (default 16).
    pub mask_bits: u8,
    /// Mirror the mask pattern left-right, for writing through the substrate (default off).
    pub mask_mirror: bool,
    /// Frame width around the mask pattern, metres (default 0.5 mm).
    pub mask_border: f64,
    /// Text drawn in the mask's frame below the pattern (empty for none).
    pub mask_label: String,
    /// Length unit of the STL coordinates (default mm).
    pub stl_unit: StlUnit,
    /// Thickness of the STL's solid base below the lowest surface point, metres (default 1 mm).
    pub stl_base_thickness: f64,
    /// Largest height error of a simplified STL heightfield, metres (default 5 nm).
    pub stl_max_error: f64,
    /// Most vertices per GDSII polygon, 4..=8190 (default 4094: every reader takes it without
    /// a warning; see [`crate::fabrication::gds`]).
    pub gds_max_vertices: usize,
    /// The artifacts to produce.
    pub outputs: Vec<Output>,
}

impl Recipe {
    /// The grayscale mask files the recipe asks for, by extension (`png`, `tif`).
    pub fn grayscale_extensions(&self) -> Vec<&'static str> {
        self.outputs
            .iter()
            .filter_map(|o| match o {
                Output::GrayscalePng => Some("png"),
                Output::GrayscaleTiff => Some("tif"),
                _ => None,
            })
            .collect()
    }

    /// The grayscale mask's options: the recipe's writer and mask settings, alignment marks on.
    pub fn mask_options(&self, force: bool) -> crate::fabrication::mask::MaskOptions {
        crate::fabrication::mask::MaskOptions {
            writer_pitch: self.address_grid,
            bits: self.mask_bits,
            polarity: self.polarity,
            mirror: self.mask_mirror,
            border: self.mask_border,
            marks: true,
            label: self.mask_label.clone(),
            force,
            ..Default::default()
        }
    }

    /// The STL options of the recipe (the mesher chosen by the surface).
    pub fn stl_options(&self) -> crate::fabrication::stl::StlOptions {
        crate::fabrication::stl::StlOptions {
            unit: self.stl_unit,
            base_thickness: self.stl_base_thickness,
            max_error: self.stl_max_error,
            surface: crate::fabrication::stl::SurfaceChoice::Auto,
        }
    }

    /// Reads and validates a recipe (a file, or `built-in:NAME` for a bundled one);
    /// errors name the file and the field.
    pub fn read(path: &Path) -> Result<Recipe> {
        let text = read_text(path, ".toml")?;
        let f: RecipeFile = toml::from_str(&text).map_err(|e| Error::toml(path, &e))?;
        let len = |field: &str, v: &str| {
            parse_length(v).map_err(|e| Error::malformed(path, format!("field '{field}': {e}")))
        };
        let positive = |field: &str, v: f64| {
            if v > 0.0 {
                Ok(v)
            } else {
                Err(Error::malformed(path, format!("field '{field}' must be positive")))
            }
        };
        check_level_count(f.process.level_count)
            .map_err(|e| Error::malformed(path, format!("field 'process.level_count': {e}")))?;
        let bundled = path.to_str().is_some_and(|p| p.starts_with(BUILT_IN));
        let dir = path.parent().unwrap_or(Path::new("."));
        let contrast_curve = f.process.contrast_curve.map(|c| match bundled {
            true => PathBuf::from(format!("{BUILT_IN}{c}")),
            false => dir.join(c),
        });
        let needs_curve = f.outputs.iter().any(|o| matches!(o, Output::GrayscalePng | Output::GrayscaleTiff));
        if needs_curve && contrast_curve.is_none() {
            return Err(Error::malformed(path, "grayscale outputs need 'process.contrast_curve'"));
        }
        if f.outputs.contains(&Output::Gds) && !f.process.level_count.is_power_of_two() {
            return Err(Error::malformed(
                path,
                format!("a binary mask set needs a power-of-two level_count, got {}", f.process.level_count),
            ));
        }
        let stl_unit = match &f.stl.unit {
            Some(u) => {
                StlUnit::parse(u).map_err(|e| Error::malformed(path, format!("field 'stl.unit': {e}")))?
            }
            None => StlUnit::Millimetre,
        };
        Ok(Recipe {
            name: f.name,
            description: f.description,
            path: path.to_path_buf(),
            address_grid: positive(
                "writer.address_grid",
                len("writer.address_grid", &f.writer.address_grid)?,
            )?,
            min_feature: positive("writer.min_feature", len("writer.min_feature", &f.writer.min_feature)?)?,
            level_count: f.process.level_count,
            quantization: f.process.quantization,
            replica_mode: f.process.replica_mode,
            polarity: f.process.polarity,
            contrast_curve,
            wavelength: match &f.design.wavelength {
                Some(w) => positive("design.wavelength", len("design.wavelength", w)?)?,
                None => 530e-9,
            },
            material: f.design.material.unwrap_or_else(|| "pdms".into()),
            order: f.design.order.unwrap_or(1),
            mask_bits: f.mask.bits.unwrap_or(16),
            mask_mirror: f.mask.mirror.unwrap_or(false),
            mask_border: match &f.mask.border {
                Some(b) => len("mask.border", b)?,
                None => 500e-6,
            },
            mask_label: f.mask.label.unwrap_or_default(),
            stl_unit,
            stl_base_thickness: match &f.stl.base_thickness {
                Some(b) => positive("stl.base_thickness", len("stl.base_thickness", b)?)?,
                None => 1e-3,
            },
            stl_max_error: match &f.stl.max_error {
                Some(b) => positive("stl.max_error", len("stl.max_error", b)?)?,
                None => 5e-9,
            },
            gds_max_vertices: match f.gds.max_vertices {
                Some(n) if (4..=MAX_BOUNDARY_VERTICES).contains(&n) => n,
                Some(n) => {
                    return Err(Error::malformed(
                        path,
                        format!("field 'gds.max_vertices': {n} is outside 4..={MAX_BOUNDARY_VERTICES}"),
                    ))
                }
                None => SIGNED_LENGTH_MAX_VERTICES,
            },
            outputs: f.outputs,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::FormatCause;
    use crate::fabrication::built_in::BUNDLED;

    fn write(dir: &Path, text: &str) -> PathBuf {
        let p = dir.join("r.toml");
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn the_gds_vertex_limit_defaults_to_what_every_reader_takes_and_is_checked() {
        let d = tempfile::tempdir().unwrap();
        let r = Recipe::read(&write(d.path(), GOOD)).unwrap();
        assert_eq!(r.gds_max_vertices, SIGNED_LENGTH_MAX_VERTICES);
        let r = Recipe::read(&write(d.path(), &format!("{GOOD}\n[gds]\nmax_vertices = 100\n"))).unwrap();
        assert_eq!(r.gds_max_vertices, 100);
        for bad in [3, MAX_BOUNDARY_VERTICES + 1] {
            let e = Recipe::read(&write(d.path(), &format!("{GOOD}\n[gds]\nmax_vertices = {bad}\n")))
                .unwrap_err()
                .to_string();
            assert!(e.contains("r.toml") && e.contains("gds.max_vertices"), "{e}");
        }
    }

    const GOOD: &str = r#"
name = "t"
outputs = ["gds"]
[writer]
address_grid = "1 um"
min_feature = "2um"
[process]
level_count = 8
"#;

    #[test]
    fn parses_lengths_and_defaults() {
        let d = tempfile::tempdir().unwrap();
        let r = Recipe::read(&write(d.path(), GOOD)).unwrap();
        assert_eq!(r.address_grid, 1e-6);
        assert_eq!(r.min_feature, 2e-6);
        assert_eq!(r.wavelength, 530e-9);
        assert_eq!(r.replica_mode, ReplicaMode::Design);
    }

    #[test]
    fn errors_name_the_field() {
        let d = tempfile::tempdir().unwrap();
        let e = Recipe::read(&write(d.path(), &GOOD.replace("\"1 um\"", "\"1\""))).unwrap_err().to_string();
        assert!(e.contains("writer.address_grid") && e.contains("no unit"), "{e}");
        let e =
            Recipe::read(&write(d.path(), &GOOD.replace("level_count = 8", "level_count = 6"))).unwrap_err();
        assert!(e.to_string().contains("power-of-two"), "{e}");
        let e = Recipe::read(&write(d.path(), &GOOD.replace("level_count = 8", "level_count = 300")))
            .unwrap_err();
        assert!(e.to_string().contains("process.level_count"), "{e}");
        let text = GOOD.replace("[process]", "[process]\nlevels = 3");
        let e = Recipe::read(&write(d.path(), &text)).unwrap_err();
        let at = text.find("levels").unwrap() as u64;
        assert!(
            matches!(e, Error::Format { cause: FormatCause::Malformed, offset: Some(o), .. } if o == at),
            "{e:?}"
        );
        assert!(e.to_string().contains("unknown field"), "{e}");
        let e =
            Recipe::read(&write(d.path(), &GOOD.replace("[\"gds\"]", "[\"grayscale_png\"]"))).unwrap_err();
        assert!(e.to_string().contains("contrast_curve"), "{e}");
    }

    #[test]
    fn bundled_recipes_parse_and_equal_the_files_in_masks() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("masks");
        let mut n = 0;
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_str().unwrap().to_string();
            let bundled = BUNDLED.iter().find(|(b, _)| *b == name);
            let (_, text) = bundled.unwrap_or_else(|| panic!("masks/{name} is not bundled"));
            assert_eq!(
                *text,
                std::fs::read_to_string(&p).unwrap(),
                "masks/{name} differs from its bundled copy"
            );
            if name.ends_with(".toml") {
                for path in
                    [p.clone(), PathBuf::from(format!("{BUILT_IN}{}", name.trim_end_matches(".toml")))]
                {
                    let r = Recipe::read(&path).unwrap_or_else(|e| panic!("{e}"));
                    if let Some(c) = &r.contrast_curve {
                        crate::fabrication::contrast::ContrastCurve::read_csv(c).unwrap();
                    }
                }
                n += 1;
            }
        }
        assert!(n >= 3, "expected at least three bundled recipes, found {n}");
        let e = Recipe::read(Path::new("built-in:nothing")).unwrap_err().to_string();
        assert!(e.contains("built-in:laser-writer-grayscale"), "{e}");
    }
}
