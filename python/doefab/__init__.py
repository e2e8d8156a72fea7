"""doefab from Python: a diffractive optical element from its design to the fabricated part,
its metrology, its as-fabricated PSF and the decoder tuned to it.

Units are SI: lengths, heights, pitches and wavelengths in metres. Arrays are numpy arrays;
every result the command line prints with ``--json`` comes back as the same dict.

    import doefab
    g = doefab.read_heightmap("design.npy", pitch=4.29e-6, unit="um")
    p = doefab.psf(g, tolerance=1e-3)          # the paper's camera
    p.values.shape                              # (H, W, 3), each channel summing to 1

Errors are ``doefab.Error`` and its subclasses (``FormatError``, ``ParameterError``,
``DataError``, ``ValidityError``, ``RegistrationError``, ``LimitError``, ``OptionsError``),
with the typed cause as attributes; a missing file is ``FileNotFoundError``.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Union

import numpy as np

from . import _doefab
from ._doefab import (
    DataError,
    Error,
    FormatError,
    Grid,
    LimitError,
    OptionsError,
    ParameterError,
    RegistrationError,
    ValidityError,
)

__version__ = _doefab.version()

__all__ = [
    "Grid",
    "Psf",
    "read_heightmap",
    "read_scan",
    "psf",
    "fab",
    "compare",
    "psf_compare",
    "reconstruct",
    "Error",
    "FormatError",
    "ParameterError",
    "DataError",
    "ValidityError",
    "RegistrationError",
    "LimitError",
    "OptionsError",
]

PathLike = Union[str, "os.PathLike[str]"]
Design = Union[Grid, PathLike]
Progress = Callable[[str, int, int], None]

#: The metres of each length unit a string may name ("4.29 um", unit="nm").
_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9, "pm": 1e-12}


def _metres(value: Union[None, float, str], what: str) -> Optional[float]:
    """A length in metres from a number (metres) or a string with its unit ("4.29 um")."""
    if value is None or isinstance(value, (int, float)):
        return None if value is None else float(value)
    text = str(value).strip()
    for unit in sorted(_UNITS, key=len, reverse=True):
        if text.endswith(unit):
            number = text[: -len(unit)].strip()
            try:
                return float(number) * _UNITS[unit]
            except ValueError:
                break
    raise ParameterError(
        f"invalid {what}: '{value}' is not a length (a number in metres, or a number with "
        f"one of the units {', '.join(_UNITS)})"
    )


def _unit(value: Union[None, float, str], what: str) -> Optional[float]:
    """Metres per stored value from a number or a unit name ("um")."""
    if isinstance(value, str) and value.strip() in _UNITS:
        return _UNITS[value.strip()]
    return _metres(value, what)


def _progress(progress: Optional[Progress], what: str) -> Optional[Progress]:
    """The callback given, else a tqdm bar when tqdm is installed and stderr is a terminal."""
    if progress is not None or not sys.stderr.isatty():
        return progress
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    bar = tqdm(desc=what, leave=False)

    def update(message: str, done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.set_postfix_str(message)
        bar.refresh()
        if total and done >= total:
            bar.close()

    return update


def read_heightmap(
    path: PathLike,
    pitch: Union[None, float, str] = None,
    unit: Union[None, float, str] = None,
    z_scale: Union[None, float, str] = None,
    z_offset: Union[None, float, str] = None,
    channel: Optional[str] = None,
    allow_implausible: bool = False,
) -> Grid:
    """A design height map as a Grid of heights in metres.

    path: .npy, .exr, .tif, .png or .csv. pitch: the sample pitch for files that state none,
    metres or a string with its unit ("4.29 um"). unit: metres per stored value of a float
    file, a number or a unit name ("um"). z_scale: metres per count of an integer image.
    z_offset: metres added after scaling. channel: the channel of a multi-channel EXR.
    allow_implausible: skip the plausibility check of the peak-to-valley height.
    """
    return _doefab.read_heightmap(
        os.fspath(path),
        _metres(pitch, "pitch"),
        _unit(unit, "unit"),
        _metres(z_scale, "z_scale"),
        _metres(z_offset, "z_offset"),
        channel,
        allow_implausible,
    )


def read_scan(
    path: PathLike,
    pitch: Union[None, float, str] = None,
    z_unit: Union[None, float, str] = None,
    z_scale: Union[None, float, str] = None,
    z_offset: Union[None, float, str] = None,
    allow_implausible: bool = False,
) -> Grid:
    """A profilometer scan (x3p, gsf, sdf, datx, opd, plu, ... as ``doefab scan-info``) as a
    Grid of heights in metres, unmeasured points invalid.

    pitch: for files that state none (metres, or "0.5 um"). z_unit: metres per stored value
    for files that state no height unit. z_scale: metres per count. z_offset: metres added.
    """
    return _doefab.read_scan(
        os.fspath(path),
        _metres(pitch, "pitch"),
        _unit(z_unit, "z_unit"),
        _metres(z_scale, "z_scale"),
        _metres(z_offset, "z_offset"),
        allow_implausible,
    )


@dataclass(frozen=True)
class Psf:
    """An RGB PSF: ``values`` (H, W, 3) float64, each channel summing to 1; ``pitch`` the
    sensor pixel pitch in metres; ``wavelengths`` per channel in metres (None for a band
    without one); ``report`` the dict ``doefab psf --json`` prints."""

    values: np.ndarray
    pitch: float
    wavelengths: list
    report: dict = field(repr=False)


def _design_arg(design: Design) -> Any:
    return design if isinstance(design, Grid) else os.fspath(design)


def _system_file(system: Union[None, PathLike, dict], folder: str) -> Optional[str]:
    """A system given as a dict (lengths in metres or as strings with units) as a TOML file."""
    if system is None or not isinstance(system, dict):
        return None if system is None else os.fspath(system)
    lines = []
    for key, value in system.items():
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise ParameterError(f"invalid system: field '{key}' is {value!r}; a number or a string")
        if isinstance(value, str):
            text = value
        elif key in ("crop", "subsample"):
            lines.append(f"{key} = {int(value)}")
            continue
        else:
            text = f"{float(value)!r} m"
        lines.append(f"{key} = {json.dumps(text)}")
    path = os.path.join(folder, "system.toml")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    return path


def psf(
    design: Design = "built-in:paper",
    tolerance: float = 1e-3,
    system: Union[None, PathLike, dict] = None,
    material: str = "pdms",
    method: Optional[str] = None,
    subsample: int = 1,
    response: Optional[PathLike] = None,
    allow_invalid: bool = False,
    out: Optional[PathLike] = None,
    progress: Optional[Progress] = None,
) -> Psf:
    """The RGB PSF of a height map in the paper's camera, as ``doefab psf``.

    design: a Grid (heights in metres), a height-map file, or "built-in:paper" /
    "built-in:fresnel". tolerance: the automatic plan's relative L2 error per channel.
    system: the optical system, a TOML file or a dict of its fields (lengths in metres or as
    "5 mm"); unset fields keep the paper's. method: force "matrix_dft", "fresnel",
    "angular_spectrum" or "rayleigh_sommerfeld" at the DOE's pitch, with ``subsample``
    sub-samples per pixel and axis. response: a sensor spectral response CSV (plan only).
    allow_invalid: run a forced method outside its validity conditions (warnings in the report).
    out: also write the files ``doefab psf -o out`` writes. progress: ``progress(message, done,
    total)``, called as the simulation goes.
    """
    with tempfile.TemporaryDirectory(prefix="doefab-") as folder:
        values, pitch, wavelengths, report = _doefab.psf(
            _design_arg(design),
            float(tolerance),
            method,
            int(subsample),
            None if response is None else os.fspath(response),
            _system_file(system, folder),
            material,
            allow_invalid,
            None if out is None else os.fspath(out),
            _progress(progress, "psf"),
        )
    return Psf(values=values, pitch=pitch, wavelengths=list(wavelengths), report=json.loads(report))


def fab(
    design: Design = "built-in:paper",
    recipe: PathLike = "built-in:laser-writer-grayscale",
    out: PathLike = "fab",
    levels: Optional[int] = None,
    fill: bool = False,
    force: bool = False,
    intermediates: bool = False,
    progress: Optional[Progress] = None,
) -> dict:
    """The whole fabrication chain for a recipe into the folder ``out``, as ``doefab fab``;
    returns the dict ``doefab fab --json`` prints (lengths in metres).

    recipe: a recipe TOML or "built-in:NAME" (``masks/``). levels: override the recipe's level
    count. fill: fill unmeasured samples instead of refusing them. force: write a mask above
    its pixel limit. intermediates: also write the wrapped surface and the level map.
    """
    text = _doefab.fab(
        _design_arg(design),
        os.fspath(recipe),
        os.fspath(out),
        levels,
        fill,
        force,
        intermediates,
        _progress(progress, "fab"),
    )
    return json.loads(text)


def compare(
    design: Design,
    scan: Union[Grid, PathLike],
    out: Optional[PathLike] = None,
    recipe: Optional[PathLike] = None,
    levels: Optional[int] = None,
    wavelength: Union[float, str] = 530e-9,
    material: str = "pdms",
    order: int = 1,
    aperture: Union[None, float, str] = None,
    psf_method: str = "matrix_dft",
    allow_invalid: bool = False,
    progress: Optional[Progress] = None,
) -> dict:
    """A scan of the part against its design, as ``doefab compare``: registration, the
    difference over the clear aperture, the fabrication model and the PSFs. Returns the dict
    ``doefab compare --json`` prints (lengths and heights in metres, angles in radians).

    design, scan: Grids or files. out: the folder for the files (surface.exr, the maps); None
    writes none (``files`` is then empty). recipe / levels: compare against the quantized
    part the recipe (or ``levels`` levels at ``wavelength`` in ``material``) makes. aperture:
    the clear aperture's diameter (metres or "5 mm"). psf_method: the PSF comparison's method,
    or "none".
    """
    folder = tempfile.mkdtemp(prefix="doefab-") if out is None else None
    try:
        text = _doefab.compare(
            _design_arg(design),
            scan if isinstance(scan, Grid) else os.fspath(scan),
            os.path.join(folder, "compare") if folder else os.fspath(out),
            None if recipe is None else os.fspath(recipe),
            levels,
            _metres(wavelength, "wavelength"),
            material,
            int(order),
            _metres(aperture, "aperture"),
            psf_method,
            allow_invalid,
            _progress(progress, "compare"),
        )
    finally:
        if folder:
            shutil.rmtree(folder, ignore_errors=True)
    result = json.loads(text)
    if folder:
        result["files"] = []
    return result


def psf_compare(
    a: Union[Psf, PathLike],
    b: Union[Psf, PathLike],
    pitch: Union[None, float, str] = None,
    key: Optional[str] = None,
    radius: Union[None, float, str] = None,
    out: Optional[PathLike] = None,
) -> dict:
    """Two PSFs compared, as ``doefab psf-compare``: per channel the peaks, encircled energy,
    centroids and the relative difference after ``b`` is moved onto ``a``'s centroid. Returns
    the dict ``psf-compare --json`` prints (lengths in metres).

    a, b: ``Psf`` objects (as ``psf`` returns) or files (.npy with psf.json, .exr as ``psf``
    writes, .npz). pitch: for files that state none (metres or "4.29 um"). key: the array of
    an .npz holding several. radius: of the encircled energy and the peak search (metres);
    default the Airy radius at the paper's F/7. out: also save the JSON there.
    """

    def given(p: Union[Psf, PathLike]) -> Any:
        if isinstance(p, Psf):
            return (np.ascontiguousarray(p.values, dtype=np.float64), float(p.pitch), list(p.wavelengths))
        return os.fspath(p)

    text = _doefab.psf_compare(
        given(a),
        given(b),
        _metres(pitch, "pitch"),
        key,
        _metres(radius, "radius"),
        None if out is None else os.fspath(out),
    )
    return json.loads(text)


def capture_values(capture: np.ndarray) -> np.ndarray:
    """An (H, W, 3) capture as the command line reads its file: uint8 / 255, uint16 / 65535,
    floats as they are (units of the clipping level); float32 out."""
    a = np.asarray(capture)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ParameterError(f"invalid capture: shape {a.shape}; an (H, W, 3) RGB array is needed")
    if a.dtype == np.uint8:
        return a.astype(np.float32) / np.float32(255)
    if a.dtype == np.uint16:
        return a.astype(np.float32) / np.float32(65535)
    if np.issubdtype(a.dtype, np.floating):
        return np.ascontiguousarray(a, dtype=np.float32)
    raise ParameterError(f"invalid capture: dtype {a.dtype}; uint8, uint16 or floats")


def reconstruct(
    capture: Union[np.ndarray, PathLike],
    decoder: PathLike = "built-in:doefab-measured-psf",
    keep_negative: bool = False,
    tile: Optional[int] = None,
    overlap: Optional[int] = None,
    border: Optional[int] = None,
    stats: bool = False,
) -> Union[np.ndarray, tuple]:
    """The linear HDR image of a capture through the DOE, as ``doefab reconstruct``: (H, W, 3)
    float32, 1 = the capture's clipping level.

    capture: a PNG/TIFF file or an (H, W, 3) array (uint8 / 255, uint16 / 65535, floats as
    they are). decoder: a decoder file or "built-in:NAME". keep_negative: keep negative
    outputs (the default clamps them to 0). tile, overlap, border: pixels, as the command's
    options (None: its defaults). stats: also return the statistics dict of ``doefab reconstruct --json``.
    """
    given = capture_values(capture) if isinstance(capture, np.ndarray) else os.fspath(capture)
    values, report = _doefab.reconstruct(given, os.fspath(decoder), tile, overlap, border, keep_negative)
    return (values, json.loads(report)) if stats else values
