#!/usr/bin/env python3
"""Writes the small Wyko / Bruker Vision `.opd` test files of this folder from the format's
public description (Gwyddion's `opdfile` module, SurfaceTopography's `OPD.py`) and prints what
SurfaceTopography computes when it reads each one back (recorded in README.md).

    python3 -m venv opd-venv && opd-venv/bin/pip install SurfaceTopography==1.27.1
    opd-venv/bin/python profilometry/make_opd_files.py profilometry

The layout (little-endian): two bytes 01 00, then a directory of 24-byte entries (16-byte name,
u16 type, u32 size of the data, u16 flags), the first being the directory itself (`Directory`,
type 1, flags 0xffff), then each entry's data in the entries' order. Types: 3 array (u16
columns, rows, bytes per element, then the elements column by column, each from the last row
up), 5 text, 6 short, 7 float, 8 double, 12 long, 15 serialised structures of later Vision
versions. Heights = value x Wavelength (nm) / Mult; i16 values of 32766 and above and f32
values of 1e38 and above are not measured; Pixel_size in mm, the y pitch Aspect x Pixel_size.

Files (the surface of wave_pedestal.py, 26 rows x 35 columns, 6 points not measured):
- `wave_pedestal.raw.layout.opd`: a later Vision version's directory, as in the file that
  surfalize stops on: the heights in an i16 array named `Raw` (Wavelength 632.8 nm, Mult
  2048: 0.309 nm per count; 3 points 32766 and 3 points 32767), an `Image` intensity array
  before it, type-15 entries (one among the numbers, the `ExtendedKeys` table at the end, its
  name in Latin-1 as Gwyddion quotes it), `AdjustVSI_Gain` a float entry of 2 bytes (a short),
  `NumFrames` a short entry of 4 bytes (a long), `ImageModificat~0` a float entry of 40 bytes
  before the heights; Pixel_size 0.65 um, Aspect 1.25.
- `wave_pedestal.opd_f32.layout.opd`: the heights as f32 counts of the wavelength (550 nm, no
  Mult) in an array named `OPD`; the non-measured points 1e38, 3e38, +inf and NaN; an
  `Intensity` array after it; Pixel_size 0.8 um, no Aspect.
"""
import struct
import sys
from pathlib import Path

import numpy as np
from wave_pedestal import surface_um

ROWS, COLS = 26, 35
MISSING = [(0, 0), (3, 7), (12, 20), (12, 21), (25, 34), (17, 33)]


def directory(entries):
    """The file: prelude, directory, the entries' data. `entries`: (name bytes, type, data)."""
    def entry(name, kind, size, flags):
        return struct.pack('<16sHIH', name, kind, size, flags)
    out = b'\x01\x00' + entry(b'Directory', 1, 24 * (len(entries) + 1), 0xFFFF)
    out += b''.join(entry(n, t, len(d), 0) for n, t, d in entries)
    return out + b''.join(d for _, _, d in entries)


def array(values, dtype):
    """An array entry's data: `values` (rows x cols, row 0 first) column by column, each
    column from the last row up."""
    rows, cols = values.shape
    head = struct.pack('<3H', cols, rows, np.dtype(dtype).itemsize)
    return head + np.ascontiguousarray(values[::-1, :].T).astype(dtype).tobytes()


def raw_layout():
    wavelength, mult = 632.8, 2048
    unit_nm = np.float32(wavelength) / mult
    z = surface_um(ROWS, COLS) * 1e3 / unit_nm
    counts = np.round(z).astype('<i2')
    for k, (r, c) in enumerate(MISSING):
        counts[r, c] = 32766 + k % 2
    i, j = np.mgrid[0:ROWS, 0:COLS]
    intensity = (40 + 5 * i + j).astype('u1')
    return directory([
        (b'Image', 3, array(intensity, 'u1')),
        (b'ImageModificat~0', 7, struct.pack('<f', 2.0) + bytes(range(36))),
        (b'Raw', 3, array(counts, '<i2')),
        (b'Wavelength', 7, struct.pack('<f', wavelength)),
        (b'Mult', 6, struct.pack('<h', mult)),
        (b'StageState', 15, b'\x02\x00\x00\x00' + struct.pack('<3d', 1.5, -2.0, 0.25)),
        (b'Pixel_size', 7, struct.pack('<f', 0.65e-3)),
        (b'Aspect', 7, struct.pack('<f', 1.25)),
        (b'AdjustVSI_Gain', 7, struct.pack('<h', 3)),
        (b'NumFrames', 6, struct.pack('<i', 70000)),
        (b'Date', 5, b'11/26/2026\x00\x00'),
        (b'Time', 5, b'10:15:00'),
        (b'Title', 5, b'later Vision layout\x00'),
        (b'\xcaxtendedKe\xfds', 15,
         b'ImageModificat~0\x00ImageModificationType\x00'),
    ])


def f32_layout():
    wavelength = 550.0
    z = (surface_um(ROWS, COLS) * 1e3 / wavelength).astype('<f4')
    for (r, c), bad in zip(MISSING, [1e38, 3e38, np.inf, np.nan, 1e38, np.inf]):
        z[r, c] = bad
    i, j = np.mgrid[0:ROWS, 0:COLS]
    return directory([
        (b'OPD', 3, array(z, '<f4')),
        (b'Intensity', 3, array((100 + 3 * i + j).astype('<f4'), '<f4')),
        (b'Wavelength', 7, struct.pack('<f', wavelength)),
        (b'Pixel_size', 7, struct.pack('<f', 0.8e-3)),
        (b'Title', 5, b'f32 OPD array\x00\x00\x00'),
    ])


def topography_stats(path):
    """SurfaceTopography's reading of `path`: size, pitch, non-measured count, Sq, Sa, Sz of
    the heights it returns (non-measured points left out)."""
    import SurfaceTopography
    from SurfaceTopography import read_topography
    t = read_topography(str(path))
    h = np.ma.masked_invalid(t.heights())
    nx, ny = t.nb_grid_pts
    sx, sy = t.physical_sizes
    v = np.ma.compressed(h)
    sq = np.sqrt(np.mean((v - v.mean()) ** 2))
    print(f'{path.name}: SurfaceTopography {SurfaceTopography.__version__}, {ny} rows x {nx} cols, '
          f'pitch x {sx / nx!r} y {sy / ny!r} ({t.unit}), non-measured {int(np.ma.count_masked(h))}, '
          f'Sq {sq:.9g} (its Sq: {t.Sq():.9g}) Sa {np.mean(np.abs(v - v.mean())):.9g} '
          f'Sz {v.max() - v.min():.9g} {t.unit}')


def main(folder):
    folder = Path(folder)
    files = {
        'wave_pedestal.raw.layout.opd': raw_layout(),
        'wave_pedestal.opd_f32.layout.opd': f32_layout(),
    }
    for name, data in files.items():
        (folder / name).write_bytes(data)
        print(f'wrote {name}: {len(data)} bytes')
    for name in files:
        topography_stats(folder / name)


if __name__ == '__main__':
    main(sys.argv[1] if len(sys.argv) > 1 else '.')
