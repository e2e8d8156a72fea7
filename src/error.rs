//! The library's error type, split by whose fault it is (after `image::ImageError`).
//!
//! Every variant carries a typed cause beside its message, and callers match the cause, never
//! the text (which is for people and may be reworded):
//!
//! * [`Error::Format`]: a file's content is not what its format promises. [`FormatCause`] says
//!   how: [`Truncated`](FormatCause::Truncated) (the file ends before a field it needs; the
//!   offset is where it ends), [`Signature`](FormatCause::Signature) (the magic number or the
//!   identifying name of another format, or none), [`Unsupported`](FormatCause::Unsupported)
//!   (a valid file using a version, encoding or layout this reader does not decode) and
//!   [`Malformed`](FormatCause::Malformed) (content that is inconsistent, out of range or not
//!   parseable); [`Encoding`](FormatCause::Encoding) is the one cause met in writing (an
//!   encoder refused the content). `offset` is the byte offset of the offending field where the reader knows it.
//! * [`Error::Parameter`]: a caller's value is refused; `allowed` states the range or the set
//!   it must lie in ([`Allowed`]) where the check is one.
//! * [`Error::Validity`]: a numerical method would run outside its validity; [`Condition`]
//!   names which condition fails (sampling, aliasing, conditioning, ...).
//! * [`Error::Registration`]: a scan or profile could not be placed on its design;
//!   [`Refusal`] says why (no match, ambiguous, featureless, not trusted, no overlap).
//! * [`Error::Data`]: the data themselves (arrays, images, scans, profiles, PSFs; not the file
//!   that held them) cannot be used. [`DataCause`] says how:
//!   [`NotFinite`](DataCause::NotFinite) (NaN, infinite or unmeasured samples where a value is
//!   needed), [`Empty`](DataCause::Empty) (nothing to work on), [`TooFew`](DataCause::TooFew)
//!   (fewer usable samples than the step needs), [`Shape`](DataCause::Shape) (sizes, channel
//!   counts or pitches that must agree do not), [`OutOfRange`](DataCause::OutOfRange) (values
//!   outside what the step accepts), [`Featureless`](DataCause::Featureless) (no structure to
//!   work with: flat, a single level), [`Singular`](DataCause::Singular) (a fit the data leave
//!   undetermined), [`Diverged`](DataCause::Diverged) (an iteration that did not converge) and
//!   [`Internal`](DataCause::Internal) (an intermediate the library built itself breaks its own
//!   invariant: a bug, not the caller's data).
//! * [`Error::Limit`]: a size limit would be exceeded; [`Resource`] names what is counted
//!   (samples, work, bytes of a record, triangles, vertices, distinct heights, coordinates,
//!   area, relief), `requested` and `limit` its amounts.
//! * [`Error::Options`]: options given together that cannot all be honoured; [`OptionsCause`]
//!   says how (a value refused before any work starts, two options that exclude each other,
//!   one that requires another, two outputs naming the same file) and `options` names them.
//! * [`Error::Io`]: the operating system refused a read or a write (no cause beyond its own
//!   [`std::io::ErrorKind`]).
//!
//! Every variant prints its message alone (`Format` after the file's path, `Parameter`,
//! `Validity` and `Registration` after their fixed prefixes); the causes are not printed.

use std::ops::Bound;
use std::path::PathBuf;

/// Every fallible library function returns this.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The operating system refused a read or a write.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder the operation was on.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },
    /// A file was read but its content is not what its format promises.
    #[error("{path}: {what}")]
    Format {
        /// The file whose content fails.
        path: PathBuf,
        /// The byte offset of the offending field (for [`FormatCause::Truncated`], where the
        /// data end), in the file or in the archive member the message names, where the reader
        /// knows it.
        offset: Option<u64>,
        /// How the content fails its format.
        cause: FormatCause,
        /// What is wrong, for people: the field and what was expected.
        what: String,
    },
    /// A parameter given by the caller is out of range or inconsistent.
    #[error("invalid {name}: {reason}")]
    Parameter {
        /// The parameter as the options' field names it (`pitch`, `level_count`).
        name: String,
        /// Why the value is refused, for people.
        reason: String,
        /// The range or set the value must lie in, where the check is one.
        allowed: Option<Allowed>,
    },
    /// The data themselves (not the file) cannot be used: NaN, implausible values, empty
    /// regions, sizes that disagree; [`DataCause`] says which.
    #[error("{what}")]
    Data {
        /// How the data fail.
        cause: DataCause,
        /// What is wrong and where, for people.
        what: String,
    },
    /// A numerical method would run outside its validity range (sampling, aliasing, conditioning).
    #[error("outside the method's validity: {what}")]
    Validity {
        /// The condition the method would violate.
        condition: Condition,
        /// The condition's figures (the sampling, the limit), for people.
        what: String,
    },
    /// A scan could not be registered to its design: it does not match, the match is
    /// ambiguous (periodic or rotationally symmetric design) or the scan is featureless.
    #[error("registration refused: {what}")]
    Registration {
        /// Why the registration was refused.
        refusal: Refusal,
        /// The correlations or overlap behind the refusal, for people.
        what: String,
    },
    /// A size limit would be exceeded: `requested` of `resource` where at most `limit` can be
    /// made, written or computed (both in the resource's unit, see [`Resource`]).
    #[error("{what}")]
    Limit {
        /// What is counted.
        resource: Resource,
        /// The amount the work would need, in the resource's unit.
        requested: f64,
        /// The most that can be made, written or computed, in the resource's unit.
        limit: f64,
        /// What would exceed the limit, for people.
        what: String,
    },
    /// Options given together that cannot all be honoured; `options` names them as their
    /// fields are named (`response_out`, `response`), and so does the message, in backticks.
    #[error("{what}")]
    Options {
        /// The options involved, as their fields are named.
        options: Vec<String>,
        /// How they conflict.
        cause: OptionsCause,
        /// What cannot be honoured, for people.
        what: String,
    },
}

/// How a file's content fails its format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum FormatCause {
    /// The file ends before a field it needs (cut short in a copy or a download).
    Truncated,
    /// The magic number or identifying name is wrong or absent: another format, or no file of
    /// this kind at all (also a file name whose extension names no readable format).
    Signature,
    /// A valid file of the format, but a version, encoding, layout or sample type this reader
    /// does not decode.
    Unsupported,
    /// Content inconsistent with itself or the format: a field out of range, a missing or
    /// duplicated entry, text that does not parse, sizes that disagree.
    Malformed,
    /// Writing, not reading: the encoder of the format (or of a chart) refused the content.
    Encoding,
}

/// The range or set a parameter must lie in.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Allowed {
    /// A number between `min` and `max`, each end included, excluded or open.
    Range {
        /// The lower end.
        min: Bound<f64>,
        /// The upper end.
        max: Bound<f64>,
    },
    /// One of these names.
    OneOf(Vec<String>),
}

impl Allowed {
    /// `(0, inf)`.
    pub fn positive() -> Self {
        Allowed::Range { min: Bound::Excluded(0.0), max: Bound::Unbounded }
    }
    /// `[min, inf)`.
    pub fn at_least(min: f64) -> Self {
        Allowed::Range { min: Bound::Included(min), max: Bound::Unbounded }
    }
    /// `[min, max]`.
    pub fn between(min: f64, max: f64) -> Self {
        Allowed::Range { min: Bound::Included(min), max: Bound::Included(max) }
    }
    /// Between `min` and `max`, each end as given.
    pub fn within(min: Bound<f64>, max: Bound<f64>) -> Self {
        Allowed::Range { min, max }
    }
    /// One of `names`.
    pub fn one_of<S: AsRef<str>>(names: &[S]) -> Self {
        Allowed::OneOf(names.iter().map(|s| s.as_ref().to_string()).collect())
    }
    /// Whether the number `v` lies in the range (false for a set of names).
    pub fn contains(&self, v: f64) -> bool {
        match self {
            Allowed::Range { min, max } => {
                let above = match *min {
                    Bound::Included(m) => v >= m,
                    Bound::Excluded(m) => v > m,
                    Bound::Unbounded => !v.is_nan(),
                };
                let below = match *max {
                    Bound::Included(m) => v <= m,
                    Bound::Excluded(m) => v < m,
                    Bound::Unbounded => !v.is_nan(),
                };
                above && below
            }
            Allowed::OneOf(_) => false,
        }
    }
}

/// The validity condition a numerical method would violate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Condition {
    /// A propagation method's own conditions (lens and defocus sampling, transfer-function
    /// bandwidth, phase gradient, the Fresnel approximation, the output window), each violated
    /// one named in the message; no method of the planner meets them all.
    Propagation,
    /// The spectral bands or the pixel integration cannot be sampled finely enough for the
    /// tolerance within the allowed number of samples.
    Sampling,
    /// A periodic replica (of a propagator or a spectrum) would overlap the result.
    Aliasing,
    /// The geometry leaves nothing to compute: an imaging configuration (B = 0), a crop larger
    /// than the window, a simulated scan off its design.
    Geometry,
    /// An input outside the range where the model holds (a wavelength outside a dispersion
    /// formula's range, a depth scale that is a unit error rather than a process error).
    Domain,
    /// The equations are singular or leave the unknowns unconstrained.
    Conditioning,
    /// Too few usable samples or pixels support the estimate.
    Coverage,
    /// The data do not follow the method's model (a motion that is not affine).
    Model,
    /// A registration's own conditions fail (see [`Refusal`]); [`Error::Registration`] carries
    /// the same refusal where the caller reports it as such.
    Registration(Refusal),
}

/// Why a scan or profile was not registered to its design.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Refusal {
    /// The best correlation is below the required one: another design, scan or part.
    NoMatch,
    /// A second placement correlates nearly as well (a periodic or rotationally symmetric
    /// design): the shift or rotation is not determined.
    Ambiguous,
    /// The scan or the design has no structure to correlate (flat, or white noise).
    Featureless,
    /// The correlation is far below what the scan's own noise allows: the design does not
    /// describe the part, or the pose is wrong.
    NotTrusted,
    /// The scan and the design barely overlap at the placement found.
    NoOverlap,
}

/// Why data (not the file that held them) cannot be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum DataCause {
    /// A value is NaN or infinite, or a sample is not measured (masked), where the step needs
    /// a finite value at every sample (the message says where the first one is).
    NotFinite,
    /// Nothing to work on: no valid sample, no channel, no point, no run, no light.
    Empty,
    /// Some usable samples, but fewer than the step needs (points for a fit, matched tiles,
    /// cells, terrace levels, samples inside an aperture).
    TooFew,
    /// Sizes that must agree do not: array shapes, channel counts, pitches.
    Shape,
    /// Values outside the range the step accepts: a level that is not an integer in range,
    /// heights not wrapped into one period, a peak too close to its window's border, a curve
    /// that does not cover the depth needed, a relief implausible for the part.
    OutOfRange,
    /// The data have no structure the step can use: a flat surface or profile, a single level
    /// or levels the histogram does not resolve, a line that misses the design's structure.
    Featureless,
    /// A fit the data leave undetermined: too few or collinear points, a singular map, a
    /// parameter without effect (the data's side of [`Condition::Conditioning`]).
    Singular,
    /// An iteration did not converge, or diverged (a loss that became NaN or grew).
    Diverged,
    /// Not the caller's data: an intermediate the library built itself breaks its own
    /// invariant (a mesh, a reshaped array, a tensor read back, a worker that panicked, a
    /// built-in entry missing). A bug to report with the message.
    Internal,
}

/// What a [`Error::Limit`] counts; `requested` and `limit` are in the unit given here.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Resource {
    /// Samples (pixels) of a map, raster, scan, mask, preview or canvas: all of them, or
    /// along the longer side where the limit is a side's (a raster to trace, a canvas).
    Samples,
    /// Elementary operations of a method (kernel products of a direct integration).
    Work,
    /// Bytes of one record of a file format (a GDSII record's length).
    RecordBytes,
    /// Triangles of a mesh file.
    Triangles,
    /// Vertices of one polygon (a GDSII boundary).
    Vertices,
    /// Distinct heights of a terrace mesh.
    Heights,
    /// The magnitude of a coordinate in a file's integer range, in nanometres.
    Coordinate,
    /// The magnitude of an area in an integer range, in square nanometres.
    Area,
    /// The relief a process can make from its commands, in metres.
    Relief,
}

/// How options given together fail.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum OptionsCause {
    /// One option's value is refused before any work starts, in the command's own wording
    /// (a library function's refused argument is an [`Error::Parameter`]).
    Value,
    /// Two options exclude each other.
    Exclusive,
    /// An option needs another one given, or given otherwise.
    Requires,
    /// Two outputs name the same file.
    SameFile,
}

impl Error {
    /// The operating system refused a read or a write of `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }
    fn format(
        path: impl Into<PathBuf>,
        offset: Option<u64>,
        cause: FormatCause,
        what: impl Into<String>,
    ) -> Self {
        Error::Format { path: path.into(), offset, cause, what: what.into() }
    }
    /// The file ends at `offset` (its length) before the field `what` needs.
    pub fn truncated(path: impl Into<PathBuf>, offset: u64, what: impl Into<String>) -> Self {
        Error::format(path, Some(offset), FormatCause::Truncated, what)
    }
    /// A wrong or absent magic number or identifier: not a file of this format.
    pub fn signature(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        Error::format(path, None, FormatCause::Signature, what)
    }
    /// A version, encoding or layout this reader does not decode.
    pub fn unsupported(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        Error::format(path, None, FormatCause::Unsupported, what)
    }
    /// Content inconsistent, out of range or not parseable.
    pub fn malformed(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        Error::format(path, None, FormatCause::Malformed, what)
    }
    /// The encoder of the file's format refused the content being written.
    pub fn encoding(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        Error::format(path, None, FormatCause::Encoding, what)
    }
    /// This error with the byte offset of the offending field, for a [`Error::Format`] (any
    /// other error is returned unchanged).
    #[must_use]
    pub fn at(mut self, at: u64) -> Self {
        if let Error::Format { offset, .. } = &mut self {
            *offset = Some(at);
        }
        self
    }
    /// This error with its message passed through `f` (to name the file or scene it concerns
    /// before it, or add a note after it), its variant and cause kept. The message is the
    /// whole text of [`Error::Data`], [`Error::Limit`] and [`Error::Options`]; of the other
    /// variants it is the part after their fixed prefix or their file (for [`Error::Io`] the
    /// operating system's message, its [`std::io::ErrorKind`] kept).
    #[must_use]
    pub fn reworded(mut self, f: impl FnOnce(String) -> String) -> Self {
        let text = match &mut self {
            Error::Data { what, .. }
            | Error::Limit { what, .. }
            | Error::Options { what, .. }
            | Error::Format { what, .. }
            | Error::Validity { what, .. }
            | Error::Registration { what, .. } => what,
            Error::Parameter { reason, .. } => reason,
            Error::Io { source, .. } => {
                *source = std::io::Error::new(source.kind(), f(source.to_string()));
                return self;
            }
        };
        *text = f(std::mem::take(text));
        self
    }
    /// A refused parameter without a stated range.
    pub fn param(name: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::Parameter { name: name.into(), reason: reason.into(), allowed: None }
    }
    /// A parameter refused for lying outside `allowed`.
    pub fn param_in(name: impl Into<String>, allowed: Allowed, reason: impl Into<String>) -> Self {
        Error::Parameter { name: name.into(), reason: reason.into(), allowed: Some(allowed) }
    }
    /// A method refused for violating `condition`.
    pub fn validity(condition: Condition, what: impl Into<String>) -> Self {
        Error::Validity { condition, what: what.into() }
    }
    /// A registration refused for `refusal`.
    pub fn registration(refusal: Refusal, what: impl Into<String>) -> Self {
        Error::Registration { refusal, what: what.into() }
    }
    /// Data that cannot be used, for `cause`.
    pub fn data(cause: DataCause, what: impl Into<String>) -> Self {
        Error::Data { cause, what: what.into() }
    }
    /// A bug: an intermediate the library built breaks its own invariant.
    pub fn internal(what: impl Into<String>) -> Self {
        Error::data(DataCause::Internal, what)
    }
    /// `requested` of `resource` where at most `limit` can be made.
    pub fn limit(resource: Resource, requested: f64, limit: f64, what: impl Into<String>) -> Self {
        Error::Limit { resource, requested, limit, what: what.into() }
    }
    /// Options `options` refused together for `cause`.
    pub fn options<S: AsRef<str>>(options: &[S], cause: OptionsCause, what: impl Into<String>) -> Self {
        Error::Options {
            options: options.iter().map(|s| s.as_ref().to_string()).collect(),
            cause,
            what: what.into(),
        }
    }
    /// This error with the byte offset where serde_json stopped in `text` (the whole file the
    /// [`Error::Format`] names), where it reports one: where the text ends for a JSON text cut
    /// short, else the byte it could not take.
    #[must_use]
    pub fn at_json(self, text: &str, e: &serde_json::Error) -> Self {
        // serde_json's column counts the bytes of the line it has taken: at the end of the text
        // they are all taken; a byte it refuses is the last one it looked at.
        let past = usize::from(e.classify() == serde_json::error::Category::Eof);
        match e.line() {
            0 => self,
            line => self.at(byte_offset(text, line, e.column() + past)),
        }
    }
    /// A TOML file at `path` that does not parse or does not hold the fields its reader
    /// needs: [`FormatCause::Malformed`] at the start of the span the parser reports, with
    /// the parser's message.
    pub fn toml(path: impl Into<PathBuf>, e: &toml::de::Error) -> Self {
        let offset = e.span().map(|s| s.start as u64);
        Error::format(path, offset, FormatCause::Malformed, e.to_string())
    }
}

/// The byte offset of 1-based `line` and `column` (the column's byte, 0 before the line's
/// first byte), clamped to the text.
fn byte_offset(text: &str, line: usize, column: usize) -> u64 {
    let start: usize = text.split_inclusive('\n').take(line - 1).map(str::len).sum();
    (start + column.saturating_sub(1)).min(text.len()) as u64
}

/// The result of every fallible library function.
pub type Result<T, E = Error> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::io::npy::{decode_npy, header_bytes};

    /// A 2 x 2 f8 `.npy` file as numpy writes it.
    fn npy() -> Vec<u8> {
        let mut b = header_bytes("<f8", &[2, 2]);
        b.extend([1.0f64, 2.0, 3.0, 4.0].iter().flat_map(|v| v.to_le_bytes()));
        b
    }

    fn format_error(bytes: &[u8]) -> (FormatCause, Option<u64>, String) {
        match decode_npy(Path::new("a.npy"), bytes) {
            Err(Error::Format { cause, offset, what, .. }) => (cause, offset, what),
            other => panic!("expected a format error, got {other:?}"),
        }
    }

    #[test]
    fn a_reader_states_how_a_file_fails() {
        let good = npy();
        assert!(decode_npy(Path::new("a.npy"), &good).is_ok());
        // Cut inside the data: truncated where the bytes end.
        let cut = &good[..good.len() - 5];
        let (cause, offset, what) = format_error(cut);
        assert_eq!((cause, offset), (FormatCause::Truncated, Some(cut.len() as u64)), "{what}");
        assert!(what.starts_with("truncated data"), "{what}");
        // Another format's bytes.
        let (cause, _, what) = format_error(b"PK\x03\x04 a zip archive, not an array");
        assert_eq!(cause, FormatCause::Signature, "{what}");
        // A format version numpy has not written.
        let mut v9 = good.clone();
        v9[6] = 9;
        let (cause, _, what) = format_error(&v9);
        assert_eq!(cause, FormatCause::Unsupported, "{what}");
        // A header dictionary that does not parse.
        let mut broken = good.clone();
        let at = broken.iter().position(|&b| b == b'{').unwrap();
        broken[at] = b'[';
        let (cause, _, what) = format_error(&broken);
        assert_eq!(cause, FormatCause::Malformed, "{what}");
    }

    #[test]
    fn a_refused_parameter_states_its_range() {
        let g = crate::Grid::new(ndarray::Array2::zeros((4, 4)), [1e-6, 1e-6], crate::Unit::Metre).unwrap();
        match crate::grid::blur::gaussian_blur(&g, -1e-6) {
            Err(Error::Parameter { name, allowed: Some(range), .. }) => {
                assert!(
                    name == "blur" && !range.contains(-1e-6) && range.contains(0.0) && range.contains(2e-6)
                )
            }
            other => panic!("expected a refused blur with its range, got {other:?}"),
        }
        let e = crate::units::length_unit("furlong").unwrap_err();
        match &e {
            Error::Parameter { allowed: Some(Allowed::OneOf(units)), .. } => {
                assert!(units.iter().any(|u| u == "nm"))
            }
            other => panic!("expected the allowed units, got {other:?}"),
        }
    }

    #[test]
    fn a_line_and_column_become_a_byte_offset() {
        assert_eq!(byte_offset("ab\ncd\n", 2, 2), 4);
        assert_eq!(byte_offset("ab", 1, 0), 0);
    }

    #[test]
    fn data_limits_and_options_carry_their_cause_and_print_their_message_alone() {
        let e = crate::Grid::new(ndarray::Array2::zeros((0, 3)), [1e-6; 2], crate::Unit::Metre).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::Empty, .. }), "{e:?}");
        assert_eq!(e.to_string(), "a grid needs at least 1 x 1 samples, got 0 x 3");
        let e = Error::limit(Resource::Triangles, 5e9, u32::MAX as f64, "5e9 triangles");
        assert_eq!(e.to_string(), "5e9 triangles");
        let e = Error::options(&["ev"], OptionsCause::Value, "`ev` must be finite");
        assert!(
            matches!(&e, Error::Options { options, cause: OptionsCause::Value, .. } if options == &["ev"])
        );
        assert_eq!(e.to_string(), "`ev` must be finite");
        // Reworded: the cause is kept, the text changes where the message is.
        let e = Error::data(DataCause::Diverged, "loss is NaN").reworded(|m| format!("{m} at step 3"));
        assert!(
            matches!(&e, Error::Data { cause: DataCause::Diverged, what } if what == "loss is NaN at step 3")
        );
        let e = Error::param("blend", "2 is above 1").reworded(|m| format!("{m}; see the checkpoint"));
        assert_eq!(e.to_string(), "invalid blend: 2 is above 1; see the checkpoint");
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "gone");
        let e = Error::io("a.exr", io).reworded(|m| format!("{m}; see the checkpoint"));
        assert!(matches!(&e, Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound));
        assert_eq!(e.to_string(), "a.exr: gone; see the checkpoint");
    }

    #[test]
    fn a_method_names_the_condition_it_would_violate() {
        let pdms = crate::material::Material::by_name("pdms").unwrap();
        assert!(pdms.index(550e-9).is_ok());
        let e = pdms.index(2e-6).unwrap_err();
        assert!(matches!(e, Error::Validity { condition: Condition::Domain, .. }), "{e:?}");
        assert!(
            e.to_string().starts_with("outside the method's validity: pdms: wavelength 2000.0 nm"),
            "{e}"
        );
    }
}
