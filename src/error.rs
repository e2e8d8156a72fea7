//! The library's error type, split by whose fault it is (after `image::ImageError`).

use std::path::PathBuf;

/// Every fallible library function returns this.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The operating system refused a read or a write.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file was read but its content is not what its format promises.
    #[error("{path}: {what}")]
    Format { path: PathBuf, what: String },
    /// A parameter given by the caller is out of range or inconsistent.
    #[error("invalid {name}: {reason}")]
    Parameter { name: String, reason: String },
    /// The data itself (not the file) cannot be used: NaN, implausible values, empty regions.
    #[error("{0}")]
    Data(String),
    /// A numerical method would run outside its validity range (sampling, aliasing, conditioning).
    #[error("outside the method's validity: {0}")]
    Validity(String),
    /// A scan could not be registered to its design: it does not match, the match is
    /// ambiguous (periodic or rotationally symmetric design) or the scan is featureless.
    #[error("registration refused: {0}")]
    Registration(String),
    /// A size limit would be exceeded.
    #[error("{0}")]
    Limit(String),
    /// Options given together that cannot all be honoured (a value refused before any work
    /// starts, two options that exclude each other, two outputs naming the same file); the
    /// message names the options as their fields are named, in backticks.
    #[error("{0}")]
    Options(String),
}

impl Error {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }
    pub fn format(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        Error::Format { path: path.into(), what: what.into() }
    }
    pub fn param(name: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::Parameter { name: name.into(), reason: reason.into() }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
