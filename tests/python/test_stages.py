"""Each function of the module against its command on the same input: equal arrays, equal
JSON (less the paths the two write to)."""

import pickle

import numpy as np
import pytest

import doefab
from conftest import SMALL_SYSTEM, cli, shared, small_design


def without(d, *keys):
    return {k: v for k, v in d.items() if k not in keys}


def test_the_module_is_the_installed_one():
    # `pip install .` put it in the environment's site-packages: it works from any folder.
    assert "site-packages" in doefab.__file__ and doefab.__version__


def test_a_grid_holds_its_values_pitch_and_valid_samples_and_pickles():
    h = small_design(32)
    h[3, 4] = np.nan
    g = doefab.Grid(h, pitch=4.29e-6)
    assert g.shape == (32, 32) and g.pitch == 4.29e-6 and g.pitch_xy == (4.29e-6, 4.29e-6)
    assert g.values.dtype == np.float64 and np.isnan(g.values[3, 4])
    assert not g.valid[3, 4] and g.valid.sum() == 32 * 32 - 1
    np.testing.assert_array_equal(g.values[g.valid], h[~np.isnan(h)])
    back = pickle.loads(pickle.dumps(g))
    np.testing.assert_array_equal(back.values, g.values)
    np.testing.assert_array_equal(back.valid, g.valid)
    assert back.pitch_xy == g.pitch_xy and g.path is None


def test_read_heightmap_reads_the_file_in_metres(design_file):
    g = doefab.read_heightmap(design_file, pitch="4.29 um", unit="um")
    np.testing.assert_array_equal(g.values, np.load(design_file) * 1e-6)
    assert g.pitch == pytest.approx(4.29e-6) and g.path == str(design_file)


def test_psf_equals_the_command_on_the_same_file(design_file, tmp_path):
    system = tmp_path / "system.toml"
    system.write_text('aperture = "0.7 mm"\n')
    out = tmp_path / "cli"
    r = cli("psf", design_file, "--pitch", "4.29um", "--unit", "um", "--system", system, "-o", out)
    g = doefab.read_heightmap(design_file, pitch=4.29e-6, unit="um")
    p = doefab.psf(g, tolerance=1e-3, system=system)
    # The command's NPY holds the channels in float32 (H, W, 1, 3): the arrays agree to
    # float32's precision, the JSON exactly.
    npy = np.load(out / "psf.npy")
    assert npy.shape == (320, 320, 1, 3) and p.values.shape == (320, 320, 3)
    np.testing.assert_array_equal(p.values.astype(npy.dtype), npy[:, :, 0, :])
    assert without(p.report, "files") == without(r, "files") and p.report["files"] == []
    np.testing.assert_allclose(p.values.sum(axis=(0, 1)), 1.0, atol=1e-9)
    assert p.pitch == pytest.approx(4.29e-6)
    assert p.wavelengths == pytest.approx([635e-9, 530e-9, 450e-9])
    # The same heights from an array (a dict for the system) give the same PSF, bit for bit.
    q = doefab.psf(doefab.Grid(g.values, pitch=g.pitch), system=SMALL_SYSTEM)
    np.testing.assert_array_equal(q.values, p.values)
    # With `out`, the files of the command.
    w = doefab.psf(g, system=system, out=tmp_path / "py")
    assert w.report["files"] == r["files"]
    assert (tmp_path / "py" / "psf.npy").read_bytes() == (out / "psf.npy").read_bytes()


def test_fab_equals_the_command(design_file, tmp_path):
    args = ["--pitch", "4.29um", "--unit", "um", "--recipe", "built-in:laser-writer-grayscale"]
    r = cli("fab", design_file, *args, "-o", tmp_path / "cli")
    g = doefab.read_heightmap(design_file, pitch=4.29e-6, unit="um")
    seen = []
    d = doefab.fab(g, recipe="built-in:laser-writer-grayscale", out=tmp_path / "py",
                   progress=lambda *a: seen.append(a))
    assert without(d, "artifacts") == without(r, "artifacts")
    assert [a["kind"] for a in d["artifacts"]] == [a["kind"] for a in r["artifacts"]]
    for a in r["artifacts"]:
        name = a["path"].split("/")[-1]
        if name.endswith((".png", ".tif", ".json")) and "report" not in name:
            assert (tmp_path / "py" / name).read_bytes() == (tmp_path / "cli" / name).read_bytes(), name
    assert seen and seen[-1][1] == seen[-1][2] and all(isinstance(s[0], str) for s in seen)


def test_compare_equals_the_command(design_file, tmp_path):
    scan = tmp_path / "scan.x3p"
    cli("simulate-scan", design_file, "--pitch", "4.29um", "--unit", "um", "-o", scan)
    args = ["--pitch", "4.29um", "--unit", "um", "--aperture", "0.6mm", "--psf-method", "none"]
    r = cli("compare", scan, "--design", design_file, *args, "-o", tmp_path / "cli")
    g = doefab.read_heightmap(design_file, pitch=4.29e-6, unit="um")
    s = doefab.read_scan(scan)
    c = doefab.compare(g, s, aperture="0.6 mm", psf_method="none")
    assert without(c, "files") == without(r, "files") and c["files"] == []
    assert c["scan"] == str(scan) and 0 < c["rms_error"] < 1e-6


def test_reconstruct_equals_the_command_from_a_file_and_from_its_array(tmp_path):
    import cv2

    capture = shared() / "data/deepoptics-hdr/captures/Fruit/wPSF_0_stop.png"
    full = cv2.imread(str(capture), cv2.IMREAD_UNCHANGED)[..., ::-1]  # BGR -> RGB
    crop = np.ascontiguousarray(full[200:296, 300:396])
    path = tmp_path / "crop.png"
    cv2.imwrite(str(path), crop[..., ::-1])
    r = cli("reconstruct", path, "--decoder", "built-in:doefab-measured-psf", "-o", tmp_path / "y.exr")
    y, stats = doefab.reconstruct(path, stats=True)
    assert y.dtype == np.float32 and y.shape == (96, 96, 3)
    for k in ("rows", "cols", "tiles", "values_below_zero", "min_raw", "max"):
        assert stats[k] == r[k], k
    np.testing.assert_array_equal(doefab.reconstruct(crop), y)
    assert (doefab.reconstruct(crop, keep_negative=True).min() <= 0) == (r["min_raw"] <= 0)


def test_the_readme_python_example_runs(capsys):
    from conftest import ROOT

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = text.split("```python\n")[1:]
    assert blocks, "the README has no Python example"
    for block in blocks:
        exec(compile(block.split("```")[0], "README.md", "exec"), {})
    printed = capsys.readouterr().out
    assert "(320, 320, 3)" in printed and "material ['pdms'" in printed


def test_psf_compare_equals_the_command_on_files_and_on_psf_objects(design_file, tmp_path):
    measured = shared() / "data/deepoptics-hdr/measured_psf.npz"
    cli("psf", "built-in:paper", "-o", tmp_path / "design")
    ours = tmp_path / "design" / "psf.exr"
    r = cli("psf-compare", ours, measured, "--key", "psf_val", "--pitch", "4.29um")
    c = doefab.psf_compare(ours, measured, key="psf_val", pitch="4.29 um")
    assert c == r
    # Two PSFs in memory: equal to the command on the files that hold them, as far as the
    # files' float32 holds them.
    g = doefab.read_heightmap(design_file, pitch=4.29e-6, unit="um")
    p = doefab.psf(g, system=SMALL_SYSTEM, out=tmp_path / "a")
    q = doefab.psf(g, method="matrix_dft", system=SMALL_SYSTEM, out=tmp_path / "b")
    r = cli("psf-compare", tmp_path / "a" / "psf.exr", tmp_path / "b" / "psf.exr")
    c = doefab.psf_compare(p, q)
    for name in ("a", "b"):
        assert c[name] == "array" and r[name].endswith("psf.exr")
    for mine, theirs in zip(c["channels"], r["channels"]):
        assert mine["name"] == theirs["name"]
        assert mine["relative_l2"] == pytest.approx(theirs["relative_l2"], rel=1e-4, abs=1e-7)
