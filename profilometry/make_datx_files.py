#!/usr/bin/env python3
"""Writes the small Zygo Mx `.datx` test files of this folder with h5py, in the layout Zygo's Mx
software writes (as SurfaceTopography's DATX reader, prysm's `read_zygo_datx` and Gwyddion's
DATX module describe it), and prints what SurfaceTopography computes when it reads each one
back (recorded in README.md).

    python3 -m venv datx-venv && datx-venv/bin/pip install h5py==3.16.0 SurfaceTopography==1.27.1
    datx-venv/bin/python profilometry/make_datx_files.py profilometry fuzz/corpus/datx

The layout written (HDF5):
- `/MetaData`: a table (compound of three variable-length strings `Source`, `Link`,
  `Destination`) linking `Root` -> `Measurement` -> {guid}, {guid} -> `Surface` -> {guid2},
  {guid2} -> `Path` -> `/Measurement/Surface`: where the height map is.
- `/Measurement/Surface`: the heights (rows along y, the first row first), with the attributes
  `Unit` (one string: `NanoMeters`, `MicroMeters`, ..., or `Fringes`), `No Data` (one f64, the
  marker of non-measured points), `Wavelength` (m), `Interferometric Scale Factor`,
  `Obliquity Factor`, and `X Converter`, `Y Converter`, `Z Converter`: compounds of `Category`,
  `BaseUnit` (variable-length strings) and `Parameters` (f64; the lateral pitch in metres is
  `Parameters[1]` of a `LateralCat` / `Pixels` converter).
- `/Measurement/Intensity`: a u16 camera intensity map (another channel, skipped by doefab).
- `/Measurement` and `/Attributes/{guid}` group attributes: instrument metadata
  (`Data Context.Data Attributes.System Type`, `... System Serial Number`, `...Objective`, ...).

Files:
- `wave_pedestal.h5py.datx`: f32 nanometres in a chunked (8 x 16, edge chunks partial), deflated
  and shuffled dataset; 26 rows x 35 columns, dx = 0.65 um, dy = 0.8 um; 6 points at `No Data`
  (the f32 maximum), converter parameters variable-length sequences. Read by SurfaceTopography.
- `wave_pedestal_fringes.h5py.datx`: the same surface as f64 fringes in a contiguous dataset
  (height = fringes x wavelength x scale factor x obliquity), `No Data` = f64 maximum, converter
  parameters fixed arrays of 4 f64, no `/MetaData` table (the older files prysm reads, where the
  map is the one dataset of `/Data/Surface`). SurfaceTopography refuses `Fringes` (not a length
  unit) and files without `/MetaData`, so this one is checked against the injected surface only.
- `small.h5py.datx` (in the fuzz corpus folder, when a second folder is given): a 3 x 4 map in
  under 2 kB (the fuzzer cuts inputs at 4 kB elsewhere): fixed-length strings, fixed-array
  converters, a contiguous f32 dataset with one `No Data` point, the newer HDF5 object layout.

The surface (i = row, first row in the file; j = column), micrometres, as in
make_surfalize_files.py: z = 0.05 + 0.4 sin(2 pi j / 13) cos(2 pi i / 11) + 0.002 j - 0.001 i,
plus 0.8 where 10 <= i < 20 and 15 <= j < 30.
"""
import sys
from pathlib import Path

import h5py
import numpy as np
from wave_pedestal import surface_um

ROWS, COLS = 26, 35
DX, DY = 0.65e-6, 0.8e-6
MISSING = [(0, 0), (3, 7), (12, 20), (12, 21), (25, 34), (17, 33)]
WAVELENGTH = 632.8e-9
SCALE_FACTOR = 0.5
OBLIQUITY = 1.02


VSTR = h5py.string_dtype('ascii')


def converter_type(vlen_parameters):
    params = h5py.vlen_dtype(np.float64) if vlen_parameters else np.dtype((np.float64, (4,)))
    return np.dtype([('Category', VSTR), ('BaseUnit', VSTR), ('Parameters', params)])


def converter(category, unit, params, vlen_parameters):
    t = converter_type(vlen_parameters)
    a = np.empty(1, dtype=t)
    a[0]['Category'] = category
    a[0]['BaseUnit'] = unit
    a[0]['Parameters'] = np.asarray(params, dtype=np.float64)
    return a


def strings(*values):
    return np.array(values, dtype=VSTR)


def f64(*values):
    return np.array(values, dtype=np.float64)


def surface_attrs(ds, unit, no_data, vlen_parameters):
    ds.attrs['Unit'] = strings(unit)
    ds.attrs['No Data'] = f64(no_data)
    ds.attrs['Wavelength'] = f64(WAVELENGTH)
    ds.attrs['Interferometric Scale Factor'] = f64(SCALE_FACTOR)
    ds.attrs['Obliquity Factor'] = f64(OBLIQUITY)
    ds.attrs.create('X Converter', converter('LateralCat', 'Pixels', [0.0, DX, 0.0, 0.0], vlen_parameters))
    ds.attrs.create('Y Converter', converter('LateralCat', 'Pixels', [0.0, DY, 0.0, 0.0], vlen_parameters))
    ds.attrs.create(
        'Z Converter',
        converter('HeightCat', unit, [0.0, WAVELENGTH, SCALE_FACTOR, OBLIQUITY], vlen_parameters),
    )


def instrument_attrs(obj):
    p = 'Data Context.Data Attributes.'
    obj.attrs[p + 'System Type'] = strings('NexView NX2')
    obj.attrs[p + 'System Serial Number'] = strings('12345')
    obj.attrs[p + 'Objective'] = strings('50X Mirau')
    obj.attrs[p + 'Time Stamp'] = strings('2026-11-26 10:15:00')
    obj.attrs[p + 'Lateral Resolution:Value'] = f64(DX)
    obj.attrs[p + 'Lateral Resolution:Unit'] = strings('Meters')


def write_nm(path):
    z = surface_um(ROWS, COLS) * 1e3  # nanometres
    no_data = float(np.finfo(np.float32).max)
    for r, c in MISSING:
        z[r, c] = no_data
    z = z.astype(np.float32)
    with h5py.File(path, 'w', libver='earliest') as f:
        meas = f.create_group('Measurement')
        instrument_attrs(meas)
        ds = meas.create_dataset('Surface', data=z, chunks=(8, 16), compression='gzip',
                                 compression_opts=6, shuffle=True)
        surface_attrs(ds, 'NanoMeters', no_data, True)
        i, j = np.mgrid[0:ROWS, 0:COLS]
        inten = meas.create_dataset('Intensity', data=(1000 + 7 * i + 3 * j).astype(np.uint16),
                                    chunks=(8, 16), compression='gzip')
        inten.attrs['Unit'] = strings('')
        attrs = f.create_group('Attributes').create_group('{6d1f2c4e-0000-4000-8000-000000000001}')
        instrument_attrs(attrs)
        guid1 = '{6d1f2c4e-0000-4000-8000-000000000002}'
        guid2 = '{6d1f2c4e-0000-4000-8000-000000000003}'
        guid3 = '{6d1f2c4e-0000-4000-8000-000000000004}'
        rows = [
            ('Root', 'Measurement', guid1),
            (guid1, 'Surface', guid2),
            (guid1, 'Intensity', guid3),
            (guid2, 'Path', '/Measurement/Surface'),
            (guid3, 'Path', '/Measurement/Intensity'),
        ]
        t = np.dtype([('Source', VSTR), ('Link', VSTR), ('Destination', VSTR)])
        f.create_dataset('MetaData', data=np.array(rows, dtype=t))


def write_fringes(path):
    z = surface_um(ROWS, COLS) * 1e-6 / (WAVELENGTH * SCALE_FACTOR * OBLIQUITY)  # fringes
    no_data = float(np.finfo(np.float64).max)
    for r, c in MISSING:
        z[r, c] = no_data
    with h5py.File(path, 'w', libver='earliest') as f:
        ds = f.create_group('Data').create_group('Surface').create_dataset(
            '{6d1f2c4e-0000-4000-8000-000000000005}', data=z)
        surface_attrs(ds, 'Fringes', no_data, False)
        attrs = f.create_group('Attributes').create_group('{6d1f2c4e-0000-4000-8000-000000000006}')
        instrument_attrs(attrs)


def write_seed(path):
    z = np.arange(12, dtype=np.float32).reshape(3, 4) * 10
    z[1, 2] = np.finfo(np.float32).max
    s = np.dtype('S12')
    conv = np.dtype([('Category', s), ('BaseUnit', s), ('Parameters', np.float64, (4,))])
    with h5py.File(path, 'w', libver='latest') as f:
        ds = f.create_group('Measurement').create_dataset('Surface', data=z)
        ds.attrs['Unit'] = np.array([b'MicroMeters'], dtype=s)
        ds.attrs['No Data'] = f64(float(np.finfo(np.float32).max))
        ds.attrs['X Converter'] = np.array([(b'LateralCat', b'Pixels', [0, 1e-6, 0, 0])], dtype=conv)
        ds.attrs['Y Converter'] = np.array([(b'LateralCat', b'Pixels', [0, 2e-6, 0, 0])], dtype=conv)
        ds.attrs['Z Converter'] = np.array([(b'HeightCat', b'MicroMeters', [0, WAVELENGTH, 0.5, 1])], dtype=conv)


def stats(path):
    """SurfaceTopography's reading of `path`: size, pitch, non-measured count, Sq (its `Sq`), and
    Sa, Sz from the heights it returns (masked points left out)."""
    import SurfaceTopography
    from SurfaceTopography import read_topography
    t = read_topography(str(path))
    h = t.heights()  # (x, y) order: SurfaceTopography transposes the (rows, columns) dataset
    nx, ny = t.nb_grid_pts
    sx, sy = t.physical_sizes
    valid = np.ma.compressed(h)
    sa = np.mean(np.abs(valid - valid.mean()))
    print(f'{path.name}: SurfaceTopography {SurfaceTopography.__version__}, {ny} rows x {nx} cols, '
          f'pitch x {sx / nx!r} y {sy / ny!r} ({t.unit}), non-measured {int(np.ma.count_masked(h))}, '
          f'Sq {t.Sq():.9g} Sa {sa:.9g} Sz {valid.max() - valid.min():.9g} {t.unit}')


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else '.')
    nm = out / 'wave_pedestal.h5py.datx'
    write_nm(nm)
    stats(nm)
    fr = out / 'wave_pedestal_fringes.h5py.datx'
    write_fringes(fr)
    if len(sys.argv) > 2:
        seed = Path(sys.argv[2])
        seed.mkdir(parents=True, exist_ok=True)
        write_seed(seed / 'small.h5py.datx')
    z = surface_um(ROWS, COLS)
    mask = np.zeros(z.shape, bool)
    for r, c in MISSING:
        mask[r, c] = True
    v = z[~mask]
    print(f'injected surface: {ROWS} rows x {COLS} cols, non-measured {mask.sum()}, '
          f'Sq {v.std():.9g} Sa {np.mean(np.abs(v - v.mean())):.9g} Sz {v.max() - v.min():.9g} um')


if __name__ == '__main__':
    main()
