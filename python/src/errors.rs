//! `doefab::Error` as Python exceptions: `doefab.Error` and a subclass per variant, the typed
//! cause as attributes beside the message. A file that does not exist is Python's own
//! `FileNotFoundError` (another refused read or write: `PermissionError` or `OSError`), with
//! the path as its `filename`.

use std::ops::Bound as End;

use doefab::{Allowed, Error};
use pyo3::exceptions::{PyException, PyFileNotFoundError, PyOSError, PyPermissionError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

pyo3::create_exception!(
    doefab,
    DoefabError,
    PyException,
    "An error of doefab (the base class of its errors)."
);
pyo3::create_exception!(
    doefab,
    FormatError,
    DoefabError,
    "A file's content is not what its format promises (`path`, `offset`, `cause`)."
);
pyo3::create_exception!(
    doefab,
    ParameterError,
    DoefabError,
    "A parameter is out of range or inconsistent (`name`, `allowed`)."
);
pyo3::create_exception!(doefab, DataError, DoefabError, "The data themselves cannot be used (`cause`).");
pyo3::create_exception!(
    doefab,
    ValidityError,
    DoefabError,
    "A numerical method would run outside its validity range (`condition`)."
);
pyo3::create_exception!(
    doefab,
    RegistrationError,
    DoefabError,
    "A scan could not be registered to its design (`refusal`)."
);
pyo3::create_exception!(
    doefab,
    LimitError,
    DoefabError,
    "A size limit would be exceeded (`resource`, `requested`, `limit`)."
);
pyo3::create_exception!(
    doefab,
    OptionsError,
    DoefabError,
    "Options given together cannot all be honoured (`options`, `cause`)."
);

/// Adds the exception classes to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("Error", py.get_type::<DoefabError>())?;
    m.add("FormatError", py.get_type::<FormatError>())?;
    m.add("ParameterError", py.get_type::<ParameterError>())?;
    m.add("DataError", py.get_type::<DataError>())?;
    m.add("ValidityError", py.get_type::<ValidityError>())?;
    m.add("RegistrationError", py.get_type::<RegistrationError>())?;
    m.add("LimitError", py.get_type::<LimitError>())?;
    m.add("OptionsError", py.get_type::<OptionsError>())?;
    Ok(())
}

/// A cause's variant name in snake case (`NotFinite` -> `not_finite`).
fn snake(debug: impl std::fmt::Debug) -> String {
    let name = format!("{debug:?}");
    let name = name.split('(').next().unwrap_or_default();
    let mut out = String::new();
    for (i, ch) in name.chars().enumerate() {
        if ch.is_ascii_uppercase() {
            if i > 0 {
                out.push('_');
            }
            out.push(ch.to_ascii_lowercase());
        } else {
            out.push(ch);
        }
    }
    out
}

/// `Allowed` as Python sees it: `{"min": .., "max": .., "min_included": .., "max_included": ..}`
/// (None for an open end) or the list of allowed names.
fn allowed(py: Python<'_>, a: &Allowed) -> PyResult<Py<PyAny>> {
    Ok(match a {
        Allowed::Range { min, max } => {
            let d = PyDict::new(py);
            let end = |b: &End<f64>| match b {
                End::Included(v) => (Some(*v), true),
                End::Excluded(v) => (Some(*v), false),
                End::Unbounded => (None, false),
            };
            let (lo, lo_in) = end(min);
            let (hi, hi_in) = end(max);
            d.set_item("min", lo)?;
            d.set_item("min_included", lo_in)?;
            d.set_item("max", hi)?;
            d.set_item("max_included", hi_in)?;
            d.into_any().unbind()
        }
        Allowed::OneOf(names) => names.clone().into_pyobject(py)?.into_any().unbind(),
        _ => py.None(),
    })
}

/// The Python exception of `e`, its typed cause set as attributes.
pub fn to_py(e: Error) -> PyErr {
    let message = e.to_string();
    Python::attach(|py| {
        let attrs = |err: PyErr, items: Vec<(&str, Py<PyAny>)>| -> PyErr {
            let value = err.value(py);
            for (k, v) in items {
                if let Err(set) = value.setattr(k, v) {
                    return set;
                }
            }
            err
        };
        let s = |v: String| -> Py<PyAny> {
            v.into_pyobject(py).map(|o| o.into_any().unbind()).unwrap_or(py.None())
        };
        match &e {
            Error::Io { path, source } => {
                // As Python's own: (errno, strerror, filename), strerror without Rust's
                // " (os error N)".
                let code = source.raw_os_error().unwrap_or(0);
                let text = source.to_string();
                let text = text.strip_suffix(&format!(" (os error {code})")).unwrap_or(&text).to_string();
                let args = (code, text, path.display().to_string());
                match source.kind() {
                    std::io::ErrorKind::NotFound => PyFileNotFoundError::new_err(args),
                    std::io::ErrorKind::PermissionDenied => PyPermissionError::new_err(args),
                    _ => PyOSError::new_err(args),
                }
            }
            Error::Format { path, offset, cause, .. } => attrs(
                FormatError::new_err(message),
                vec![
                    ("path", s(path.display().to_string())),
                    ("offset", offset.into_pyobject(py).map(|o| o.into_any().unbind()).unwrap_or(py.None())),
                    ("cause", s(snake(cause))),
                ],
            ),
            Error::Parameter { name, allowed: a, .. } => {
                let a = match a {
                    Some(a) => allowed(py, a).unwrap_or(py.None()),
                    None => py.None(),
                };
                attrs(ParameterError::new_err(message), vec![("name", s(name.clone())), ("allowed", a)])
            }
            Error::Data { cause, .. } => attrs(DataError::new_err(message), vec![("cause", s(snake(cause)))]),
            Error::Validity { condition, .. } => {
                let refusal = match condition {
                    doefab::Condition::Registration(r) => s(snake(r)),
                    _ => py.None(),
                };
                attrs(
                    ValidityError::new_err(message),
                    vec![("condition", s(snake(condition))), ("refusal", refusal)],
                )
            }
            Error::Registration { refusal, .. } => {
                attrs(RegistrationError::new_err(message), vec![("refusal", s(snake(refusal)))])
            }
            Error::Limit { resource, requested, limit, .. } => {
                let f = |v: f64| v.into_pyobject(py).map(|o| o.into_any().unbind()).unwrap_or(py.None());
                attrs(
                    LimitError::new_err(message),
                    vec![
                        ("resource", s(snake(resource))),
                        ("requested", f(*requested)),
                        ("limit", f(*limit)),
                    ],
                )
            }
            Error::Options { options, cause, .. } => {
                let names =
                    options.clone().into_pyobject(py).map(|o| o.into_any().unbind()).unwrap_or(py.None());
                attrs(OptionsError::new_err(message), vec![("options", names), ("cause", s(snake(cause)))])
            }
            _ => DoefabError::new_err(message),
        }
    })
}

/// `doefab::Result` into `PyResult`, the error as its Python exception.
pub trait OrPy<T> {
    /// The value, or the error as its Python exception.
    fn or_py(self) -> PyResult<T>;
}

impl<T> OrPy<T> for doefab::Result<T> {
    fn or_py(self) -> PyResult<T> {
        self.map_err(to_py)
    }
}
