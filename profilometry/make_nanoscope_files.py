#!/usr/bin/env python3
"""Writes the small Bruker Nanoscope `.spm` test files of this folder from the format's public
layout (Gwyddion's `nanoscope` module, SurfaceTopography's `DI` reader) and prints what
SurfaceTopography and pySPM compute when they read each one back (recorded in README.md).

    python3 -m venv st-venv && st-venv/bin/pip install SurfaceTopography==1.27.1 pySPM==0.6.3
    st-venv/bin/python profilometry/make_nanoscope_files.py profilometry

Files:
- `wave_pedestal.v9.layout.spm`: version 9.3 (0x09300201), 32-bit integers, three channels in the
  order Height Sensor (the surface halved, so that reading the wrong channel shows), Height (the
  surface), Phase (degrees, not a height); `Bytes/pixel: 4`.
- `wave_pedestal.v5.layout.spm`: version 5.31 (0x05310001), 16-bit integers, one Height channel,
  a Latin-1 header (the degree sign of the phase sensitivity), `Bytes/pixel: 2`.

In both, the height of a stored integer n is n / 2^(8 Bytes/pixel) * (the `@2:Z scale` hard
value, volts) * (the `@Sens. ...` soft value, nm/V), and the lines are stored bottom line first.

The surface (i = row, top row of the image; j = column), micrometres:
z = 0.05 + 0.4 sin(2 pi j / 13) cos(2 pi i / 11) + 0.002 j - 0.001 i, plus 0.8 where
10 <= i < 20 and 15 <= j < 30, rounded to a whole count of the file. The Nanoscope format has no
marker for points not measured: every point is measured. Scan size 20 x 12 um for 41 x 29
points: dx = 20/41 um, dy = 12/29 um.
"""
import sys
from pathlib import Path

import numpy as np
from wave_pedestal import surface_um

HEADER = 8192
SENS_Z = 43.91  # nm/V, the Height channel's sensitivity
SENS_ZSENSOR = 9.5  # nm/V, the Height Sensor's
HARD = 440.0  # V, the Z scale's hard value
ROWS, COLS = 29, 41


def counts(z_um, bpp, sens):
    """Integers whose height by the chain is z (um): n = z / (HARD / 2^(8 bpp) * sens nm)."""
    per_count_nm = HARD / 2.0 ** (8 * bpp) * sens
    return np.rint(z_um * 1e3 / per_count_nm).astype(np.int64)


def write(path, version, bpp, channels, latin1_phase, header=HEADER):
    """channels: (name, label, sensitivity key, integers top row first)."""
    rows, cols = channels[0][3].shape
    data_len = rows * cols * bpp
    hard_scale = HARD / 2.0 ** (8 * bpp)
    lines = [
        '\\*File list',
        f'\\Version: {version}',
        '\\Date: 02:15:41 PM Thu Oct 16 2025',
        '\\Start context: OL2',
        f'\\Data length: {header}',
        '\\Text: ',
        '\\*Equipment list',
        '\\Description: Dimension Icon',
        '\\Controller: NanoScope V',
        '\\*Scanner list',
        '\\Scanner type: Icon',
        '\\Serial Number: 4321X',
        f'\\@Sens. Zsens: V {SENS_Z} nm/V',
        '\\*Ciao scan list',
        '\\Scan Size: 20 12 ~m',
        '\\Samps/line: 41',
        '\\Lines: 29',
        '\\Aspect Ratio: 20:12',
        '\\Scan Rate: 0.996',
        f'\\@Sens. ZsensSens: V {SENS_ZSENSOR} nm/V',
        '\\@Sens. Phase: V 18 \u00ba/V',
    ]
    for k, (name, label, sens_key, _) in enumerate(channels):
        lines += [
            '\\*Ciao image list',
            f'\\Data offset: {header + k * data_len}',
            f'\\Data length: {data_len}',
            f'\\Bytes/pixel: {bpp}',
            '\\Start context: OL',
            '\\Line Direction: Trace',
            f'\\Samps/line: {cols}',
            f'\\Number of lines: {rows}',
            '\\Scan Size: 20 12 ~m',
            '\\Aspect Ratio: 20:12',
            f'\\@2:Image Data: S [{name}] "{label}"',
            f'\\@2:Z scale: V [{sens_key}] ({hard_scale:.16f} V/LSB) {HARD} V',
            '\\@2:Z offset: V [Sens. Zsens] (0 V/LSB) 0 V',
        ]
    lines.append('\\*File list end')
    head = ('\r\n'.join(lines) + '\r\n\x1a').encode('latin-1' if latin1_phase else 'utf-8')
    assert len(head) < header
    out = bytearray(head) + bytes(header - len(head))
    dtype = '<i4' if bpp == 4 else '<i2'
    for *_, n in channels:
        assert np.abs(n).max() < 2 ** (8 * bpp - 1)
        out += n[::-1].astype(dtype).tobytes()  # bottom line first
    Path(path).write_bytes(bytes(out))


def read_back(path):
    import SurfaceTopography
    from SurfaceTopography import open_topography
    import pySPM

    r = open_topography(str(path))
    names = [c.name for c in r.channels]
    k = names.index('Height')
    t = r.topography(channel_index=k)
    h = t.heights()
    dx, dy = (s / n for s, n in zip(t.physical_sizes, t.nb_grid_pts))
    print(f'{path.name}: SurfaceTopography {SurfaceTopography.__version__} channels {names}, '
          f'reads channel {k} in {t.unit}: {t.nb_grid_pts[1]} rows x {t.nb_grid_pts[0]} cols, '
          f'dx {dx!r} dy {dy!r}, non-measured {int(np.isnan(h).sum())}, '
          f'Sq {t.rms_height_from_area():.9g} Sa {np.mean(np.abs(h - h.mean())):.9g} '
          f'Sz {h.max() - h.min():.9g} {t.unit}')
    b = pySPM.Bruker(str(path))
    p = b.get_channel('Height')
    z = p.pixels
    print(f'{path.name}: pySPM {pySPM.__version__} channel Height in {p.zscale}: {z.shape[0]} rows x '
          f'{z.shape[1]} cols, size {p.size}, Sq {np.std(z):.9g} Sa {np.mean(np.abs(z - z.mean())):.9g} '
          f'Sz {z.max() - z.min():.9g}')


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else '.')
    z = surface_um(ROWS, COLS)
    v9 = out / 'wave_pedestal.v9.layout.spm'
    write(v9, '0x09300201', 4, [
        ('ZSensor', 'Height Sensor', 'Sens. ZsensSens', counts(z / 2, 4, SENS_ZSENSOR)),
        ('Height', 'Height', 'Sens. Zsens', counts(z, 4, SENS_Z)),
        ('Phase', 'Phase', 'Sens. Phase', np.rint(np.cos(z) * 1e8).astype(np.int64)),
    ], True)
    v5 = out / 'wave_pedestal.v5.layout.spm'
    write(v5, '0x05310001', 2, [('Height', 'Height', 'Sens. Zsens', counts(z, 2, SENS_Z))], True)
    for p in (v9, v5):
        read_back(p)
    # A small seed for the fuzz target (its inputs are cut at 4 kB): 5 x 4 points, a 3 kB header.
    seed = out.parent / 'fuzz' / 'corpus' / 'spm'
    if seed.is_dir():
        z = surface_um(4, 5)
        write(seed / 'seed.spm', '0x09300201', 4, [
            ('ZSensor', 'Height Sensor', 'Sens. ZsensSens', counts(z / 2, 4, SENS_ZSENSOR)),
            ('Height', 'Height', 'Sens. Zsens', counts(z, 4, SENS_Z)),
        ], True, header=3072)


if __name__ == '__main__':
    main()
