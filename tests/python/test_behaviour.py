"""What Python users expect of the module: typed exceptions with their causes, the GIL released
during long calls, progress callbacks."""

import threading

import numpy as np
import pytest

import doefab
from conftest import SMALL_SYSTEM, small_design


def test_a_missing_file_is_pythons_own_file_not_found_error(tmp_path):
    missing = tmp_path / "nothing.npy"
    with pytest.raises(FileNotFoundError) as e:
        doefab.read_heightmap(missing, pitch=1e-6)
    assert e.value.filename == str(missing)


def test_a_truncated_file_is_a_format_error_with_its_cause_and_path(tmp_path):
    bad = tmp_path / "cut.npy"
    np.save(bad, np.zeros((64, 64)))
    bad.write_bytes(bad.read_bytes()[:200])
    with pytest.raises(doefab.FormatError) as e:
        doefab.read_heightmap(bad, pitch=1e-6, unit="um")
    assert isinstance(e.value, doefab.Error)
    assert e.value.cause == "truncated" and e.value.path == str(bad)
    assert str(bad) in str(e.value)


def test_a_file_of_another_format_is_a_signature_fault(tmp_path):
    bad = tmp_path / "text.npy"
    bad.write_text("not numpy at all")
    with pytest.raises(doefab.FormatError) as e:
        doefab.read_heightmap(bad, pitch=1e-6)
    assert e.value.cause == "signature"


def test_a_parameter_error_names_the_parameter_and_its_allowed_set():
    with pytest.raises(doefab.ParameterError) as e:
        doefab.psf(doefab.Grid(small_design(), 4.29e-6), system=SMALL_SYSTEM, material="unobtainium")
    assert e.value.name == "material"
    assert isinstance(e.value.allowed, list) and "pdms" in e.value.allowed


def test_options_that_exclude_each_other_are_an_options_error(tmp_path):
    response = tmp_path / "r.csv"
    response.write_text("wavelength_nm,r,g,b\n500,1,1,1\n600,1,1,1\n")
    with pytest.raises(doefab.OptionsError) as e:
        doefab.psf(doefab.Grid(small_design(32), 4.29e-6), method="matrix_dft", response=response)
    assert e.value.cause == "exclusive" and set(e.value.options) == {"response", "method"}


def test_non_finite_design_heights_are_a_data_error():
    h = small_design()
    h[96, 96] = np.inf  # inside the aperture; outside it a missing height changes nothing
    with pytest.raises(doefab.DataError) as e:
        doefab.psf(doefab.Grid(h, 4.29e-6), system=SMALL_SYSTEM, method="matrix_dft")
    assert e.value.cause == "not_finite"


def test_a_bad_length_string_is_a_parameter_error():
    with pytest.raises(doefab.ParameterError):
        doefab.read_heightmap("x.npy", pitch="4.29 furlongs")


def test_a_long_call_releases_the_gil_and_reports_progress():
    g = doefab.Grid(small_design(512), 4.29e-6)
    seen, inside, done, failed = [], threading.Event(), threading.Event(), []
    counted = 0

    def work():
        try:
            inside.set()
            doefab.psf(g, system={"aperture": "2 mm"}, progress=lambda *a: seen.append(a))
        except Exception as e:  # noqa: BLE001 - reported below
            failed.append(e)
        finally:
            inside.clear()
            done.set()

    t = threading.Thread(target=work)
    t.start()
    # This thread counts while the call runs: had the call kept the GIL, it could not take a
    # single step until the call returned.
    while not done.is_set():
        if inside.is_set():
            counted += 1
    t.join()
    assert not failed, failed
    assert counted > 10_000, counted
    assert seen and all(isinstance(m, str) and d <= n for m, d, n in seen)
