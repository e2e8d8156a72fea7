#!/usr/bin/env python3
"""Writes the small Bruker Vision64 `.opdx` test file of this folder from the format's public
description (SurfaceTopography's `OPDx.py`, after Gwyddion's `dektakvca` module) and prints
what SurfaceTopography computes when it reads it back (recorded in README.md).

    python3 -m venv opdx-venv && opdx-venv/bin/pip install SurfaceTopography==1.27.1
    opdx-venv/bin/python profilometry/make_opdx_files.py profilometry fuzz/corpus/opdx

The layout (little-endian): the 12-byte magic `VCA DATA\\x01\\x00\\x00\\x55`, then items. An item
is a name (u32 length + UTF-8), a type byte and a payload: containers (0x7d, 0x46, 0x47: a
length, the items, a terminator item (empty name, type 0x7f) and two bytes), strings (0x12: a
length + UTF-8), integers and floats (0x01 bool, 0x04..0x0b, 0x0c f32, 0x0d f64), quantities
(0x13: a length, f64 value, unit name, unit symbol), string lists (0x42), time stamps (0x15: 9
bytes) and matrices (0x00: type name, u32, a name, a length, u32 rows, u32 columns, the f32
values row by row). A length is one byte giving its own size (1, 2 or 4) then the length.
The file ends with a terminator item.

Files:
- `wave_pedestal.layout.opdx`: a Vision64 "Surface Height" file, 26 rows x 35 columns,
  dx = 0.65 um, dy = 0.8 um (the extents are (n - 1) x pitch), heights stored as f32 counts of
  `DataScale` = 0.001 um (nanometres), 6 points NaN (not measured); a second 2-D channel
  (Intensity) not listed as a height channel; instrument metadata.
- `small.layout.opdx` (in the fuzz corpus folder, when a second folder is given): a 3 x 4 map.

The surface (i = row, first row in the file; j = column), micrometres, as in
make_surfalize_files.py: z = 0.05 + 0.4 sin(2 pi j / 13) cos(2 pi i / 11) + 0.002 j - 0.001 i,
plus 0.8 where 10 <= i < 20 and 15 <= j < 30.
"""
import struct
import sys
from pathlib import Path

import numpy as np
from wave_pedestal import surface_um

MAGIC = b'VCA DATA\x01\x00\x00\x55'
ROWS, COLS = 26, 35
DX, DY = 0.65, 0.8  # um
MISSING = [(0, 0), (3, 7), (12, 20), (12, 21), (25, 34), (17, 33)]


def name(s):
    b = s.encode('utf-8')
    return struct.pack('<I', len(b)) + b


def varlen(n):
    if n < 0x100:
        return b'\x01' + struct.pack('<B', n)
    if n < 0x10000:
        return b'\x02' + struct.pack('<H', n)
    return b'\x04' + struct.pack('<I', n)


def item(key, typeid, payload):
    return name(key) + bytes([typeid]) + payload


TERMINATOR = name('') + b'\x7f'


def container(key, items, typeid=0x7D):
    body = b''.join(items) + TERMINATOR + b'\x00\x00'
    return item(key, typeid, varlen(len(body)) + body)


def string(key, s):
    b = s.encode('utf-8')
    return item(key, 0x12, varlen(len(b)) + b)


def u32(key, v):
    return item(key, 0x07, struct.pack('<I', v))


def f64(key, v):
    return item(key, 0x0D, struct.pack('<d', v))


def quantity(key, value, unit_name, symbol):
    body = struct.pack('<d', value) + name(unit_name) + name(symbol)
    return item(key, 0x13, varlen(len(body)) + body)


def string_list(key, values):
    body = b''.join(name(v) for v in values)
    return item(key, 0x42, name('StringList') + varlen(len(body)) + body)


def matrix(key, z):
    rows, cols = z.shape
    body = struct.pack('<II', rows, cols) + z.astype('<f4').tobytes()
    return item(key, 0x00, name('Matrix<float>') + struct.pack('<I', 1) + name('Float') + varlen(len(body)) + body)


def channel(key, kind, z, dx, dy, scale, symbol):
    rows, cols = z.shape
    return container(key, [
        string('DataKind', kind),
        u32('Dimension1Points', rows),
        u32('Dimension2Points', cols),
        quantity('Dimension1Extent', dy * (rows - 1), 'MicroMeter', 'µm'),
        quantity('Dimension2Extent', dx * (cols - 1), 'MicroMeter', 'µm'),
        quantity('DataScale', scale, 'MicroMeter', symbol),
        matrix('Matrix', z),
    ], typeid=0x47)


def opdx(height, intensity, dx, dy):
    meta = container('MetaData', [
        string('DataKind', 'Surface Height'),
        string('PrimaryData2D', 'Height'),
        container('2D_Channels', [string_list('Height', ['Height'])]),
        string('Date', '11/26/2026'),
        string('Time', '10:15:00 AM'),
        item('TimeStamp', 0x15, bytes(range(9))),
        container('MeasurementSettings', [
            string('InstrumentName', 'ContourX-500'),
            string('SerialNumber', 'CX500-0042'),
            string('Objective', '20X'),
            f64('Magnification', 20.0),
            item('VSIMode', 0x01, b'\x01'),
        ]),
    ])
    channels = [channel('Height', 'Height', height, dx, dy, 1e-3, 'µm')]
    if intensity is not None:
        channels.append(channel('Intensity', 'Intensity', intensity, dx, dy, 1.0, ''))
    return MAGIC + meta + container('2D_Data', channels) + TERMINATOR


def stats(path):
    """SurfaceTopography's reading of `path`: size, pitch, non-measured count, Sq (its `Sq`), and
    Sa, Sz from the heights it returns (NaN points left out)."""
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


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else '.')
    z = surface_um(ROWS, COLS) * 1e3  # counts of 0.001 um
    for r, c in MISSING:
        z[r, c] = np.nan
    i, j = np.mgrid[0:ROWS, 0:COLS]
    p = out / 'wave_pedestal.layout.opdx'
    p.write_bytes(opdx(z, (100 + 3 * i + j).astype(float), DX, DY))
    stats(p)
    v = surface_um(ROWS, COLS)
    mask = np.zeros(v.shape, bool)
    for r, c in MISSING:
        mask[r, c] = True
    v = v[~mask]
    print(f'injected surface: {ROWS} rows x {COLS} cols, non-measured {mask.sum()}, '
          f'Sq {v.std():.9g} Sa {np.mean(np.abs(v - v.mean())):.9g} Sz {v.max() - v.min():.9g} um')
    if len(sys.argv) > 2:
        seed = Path(sys.argv[2])
        seed.mkdir(parents=True, exist_ok=True)
        small = np.arange(12, dtype=float).reshape(3, 4) * 10
        small[1, 2] = np.nan
        (seed / 'small.layout.opdx').write_bytes(opdx(small, None, 1.0, 2.0))


if __name__ == '__main__':
    main()
