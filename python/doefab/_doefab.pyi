"""Type stubs of doefab's native module (the functions are called through ``doefab``)."""

from typing import Any, Callable, Optional, Union

import numpy as np

class Grid:
    """A sampled surface: heights in metres on a regular grid with its pitch (metres), and
    which samples were measured. A grid read from a file remembers the file."""

    def __init__(
        self,
        values: np.ndarray,
        pitch: float,
        valid: Optional[np.ndarray] = None,
        pitch_y: Optional[float] = None,
    ) -> None:
        """values: (H, W) float64 heights in metres (NaN: unmeasured); pitch: metres along x
        (``pitch_y`` along y when it differs); valid: (H, W) bool of measured samples."""
    @property
    def values(self) -> np.ndarray:
        """Heights in metres, (H, W) float64; unmeasured samples NaN."""
    @property
    def valid(self) -> np.ndarray:
        """Measured samples, (H, W) bool."""
    @property
    def pitch(self) -> float:
        """Sample pitch along x, metres."""
    @property
    def pitch_xy(self) -> tuple[float, float]:
        """Sample pitch (x, y), metres."""
    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns)."""
    @property
    def path(self) -> Optional[str]:
        """The file the grid was read from; None for one made from an array."""

class Error(Exception):
    """An error of doefab (the base class of its errors)."""

class FormatError(Error):
    """A file's content is not what its format promises."""
    path: str
    offset: Optional[int]
    cause: str

class ParameterError(Error):
    """A parameter is out of range or inconsistent."""
    name: str
    allowed: Any

class DataError(Error):
    """The data themselves cannot be used."""
    cause: str

class ValidityError(Error):
    """A numerical method would run outside its validity range."""
    condition: str
    refusal: Optional[str]

class RegistrationError(Error):
    """A scan could not be registered to its design."""
    refusal: str

class LimitError(Error):
    """A size limit would be exceeded."""
    resource: str
    requested: float
    limit: float

class OptionsError(Error):
    """Options given together cannot all be honoured."""
    options: list[str]
    cause: str

def version() -> str: ...
def read_heightmap(
    path: str,
    pitch: Optional[float],
    unit: Optional[float],
    z_scale: Optional[float],
    z_offset: Optional[float],
    channel: Optional[str],
    allow_implausible: bool,
) -> Grid: ...
def read_scan(
    path: str,
    pitch: Optional[float],
    z_unit: Optional[float],
    z_scale: Optional[float],
    z_offset: Optional[float],
    allow_implausible: bool,
) -> Grid: ...
def psf(
    design: Union[Grid, str],
    tolerance: float,
    method: Optional[str],
    subsample: int,
    response: Optional[str],
    system: Optional[str],
    material: str,
    allow_invalid: bool,
    out: Optional[str],
    progress: Optional[Callable[[str, int, int], None]],
) -> tuple[np.ndarray, float, list[Optional[float]], str]: ...
def fab(
    design: Union[Grid, str],
    recipe: str,
    out: str,
    levels: Optional[int],
    fill: bool,
    force: bool,
    intermediates: bool,
    progress: Optional[Callable[[str, int, int], None]],
) -> str: ...
def compare(
    design: Union[Grid, str],
    scan: Union[Grid, str],
    out: str,
    recipe: Optional[str],
    levels: Optional[int],
    wavelength: float,
    material: str,
    order: int,
    aperture: Optional[float],
    psf_method: str,
    allow_invalid: bool,
    progress: Optional[Callable[[str, int, int], None]],
) -> str: ...
def reconstruct(
    capture: Union[np.ndarray, str],
    decoder: str,
    tile: Optional[int],
    overlap: Optional[int],
    border: Optional[int],
    keep_negative: bool,
) -> tuple[np.ndarray, str]: ...
def psf_compare(
    a: Union[str, tuple[np.ndarray, float, list[Optional[float]]]],
    b: Union[str, tuple[np.ndarray, float, list[Optional[float]]]],
    pitch: Optional[float],
    key: Optional[str],
    radius: Optional[float],
    out: Optional[str],
) -> str: ...
