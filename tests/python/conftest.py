"""Shared fixtures of the Python module's tests: the command-line binary they compare against,
and small designs that run in seconds."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


def binary() -> Path:
    """The `doefab` binary of this checkout (`cargo build --release` makes it), or
    `$DOEFAB_BIN`."""
    path = Path(os.environ.get("DOEFAB_BIN", ROOT / "target" / "release" / "doefab"))
    if not path.exists():
        pytest.fail(f"{path} is missing: build it with `cargo build --release` (or set DOEFAB_BIN)")
    return path


def cli(*args, json_out=True):
    """Runs the binary with `args` (and `--json --quiet`); its JSON result, or the process."""
    flags = ["--json", "--quiet"] if json_out else ["--quiet"]
    p = subprocess.run([str(binary()), *flags, *map(str, args)], capture_output=True, text=True)
    if not json_out:
        return p
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


def shared() -> Path:
    """The shared data set beside the checkout, or `$DOEFAB_SHARED`."""
    path = Path(os.environ.get("DOEFAB_SHARED", ROOT.parent / "shared"))
    if not path.exists():
        pytest.fail(f"the shared data set is missing at {path} (set DOEFAB_SHARED)")
    return path


def small_design(n=192, pitch=4.29e-6):
    """A smooth DOE of n x n heights in metres: a grating of 12 samples' period, 0..1.2 um,
    on a weak lens of 0.5 um sag at the grid's edge."""
    y, x = (np.mgrid[0:n, 0:n] - (n - 1) / 2) * pitch
    edge = (n - 1) / 2 * pitch
    h = 0.6e-6 * (1 + np.sin(2 * np.pi * x / (12 * pitch))) + 0.5e-6 * (x**2 + y**2) / edge**2
    return h - h.min()


@pytest.fixture
def design_file(tmp_path):
    """`small_design()` as .npy in micrometres (read with pitch 4.29 um, unit um)."""
    path = tmp_path / "design.npy"
    np.save(path, small_design() * 1e6)
    return path


#: The camera of the small designs: the paper's, with a 0.7 mm aperture inside their grid.
SMALL_SYSTEM = {"aperture": "0.7 mm"}
