#!/usr/bin/env python3
"""Writes the small Alicona .al3d and TrueMap .tmd test files of this folder and prints the
statistics surfalize computes when it reads each one back (recorded in README.md).

    python3 -m venv surfalize-venv && surfalize-venv/bin/pip install surfalize==0.19.2
    surfalize-venv/bin/python profilometry/make_surfalize_files.py profilometry

Files:
- `wave_pedestal.surfalize.al3d`: written by surfalize's AL3D writer.
- `wave_pedestal.surfalize.tmd`: written by surfalize's TMD writer. The TrueMap format stores
  lengths and heights in millimetres (TrueMap / GelSight `readtmd`, SurfaceTopography);
  surfalize writes and reads whatever numbers its surface holds, which it takes for
  micrometres. The surface is therefore handed to surfalize in millimetres, so that the file
  is what the format says, and surfalize's statistics of it are millimetres.
- `quality_map.layout.al3d`: built here from the AL3D layout (not by surfalize's writer), for
  what surfalize's writer never produces: more tags in another order, a comment, an odd column
  count (rows padded to 8 bytes), texture planes after the depth image, and a repeatability
  plane (`DepthImageResPtr`) whose points above `DepthResFilterVal` are not valid.

The surface (i = row, first row in the file; j = column), micrometres:
z = 0.05 + 0.4 sin(2 pi j / 13) cos(2 pi i / 11) + 0.002 j - 0.001 i, plus 0.8 where
10 <= i < 20 and 15 <= j < 30; a few points are non-measured (NaN).
"""
import struct
import sys
from pathlib import Path

import numpy as np
import surfalize
from surfalize import Surface
from wave_pedestal import surface_um, surfalize_stats as stats


def tag(key, value):
    return struct.pack('20s30s2s', key.encode('latin-1'), str(value).encode('latin-1'), b'\r\n')


def layout_al3d(path):
    """An AL3D file from the format's layout: 17-byte magic, 52-byte tags (Version, TagCount,
    then TagCount tags in any order), a 256-byte comment ending in CR LF, the depth image (f32
    metres, rows padded to 8 bytes), then the texture planes (u8, rows padded to 8 bytes)."""
    rows, cols = 9, 13
    z = surface_um(rows + 10, cols + 15, [(12, 17)])[10:, 15:] * 1e-6  # the pedestal corner
    z[2, 5] = np.nan
    invalid = np.float32(3.0e15)
    stride = -(-cols * 4 // 8) * 8
    tstride = -(-cols // 8) * 8
    tags = [
        ('Rows', rows), ('Cols', cols), ('NumberOfPlanes', 2), ('PixelSizeXMeter', '2.5e-06'),
        ('PixelSizeYMeter', '2e-06'), ('InvalidPixelValue', float(invalid)), ('IconOffset', 0),
        ('DepthImageResPtr', 1), ('DepthResMinVal', '1e-07'), ('DepthResShiftVal', '1e-08'),
        ('DepthResFilterVal', '1.5e-06'), ('DepthImageOffset', 0), ('TextureImageOffset', 0),
    ]
    header_len = 17 + 52 * (2 + len(tags)) + 256
    depth_offset = header_len
    texture_offset = depth_offset + stride * rows
    tags[-2] = ('DepthImageOffset', depth_offset)
    tags[-1] = ('TextureImageOffset', texture_offset)
    out = bytearray(b'AliconaImaging\x00\r\n')
    out += tag('Version', 1) + tag('TagCount', len(tags))
    for k, v in tags:
        out += tag(k, v)
    out += b'Built from the AL3D layout'.ljust(254, b'\x00') + b'\r\n'
    depth = np.zeros((rows, stride // 4), '<f4')
    depth[:, :cols] = np.where(np.isnan(z), invalid, z)
    out += depth.tobytes()
    # Every row padded, the last one too: the texture planes follow the full depth image.
    assert len(out) == texture_offset
    plane0 = np.zeros((rows, tstride), np.uint8)
    plane0[:, :cols] = np.arange(rows * cols).reshape(rows, cols) % 251
    codes = np.zeros((rows, tstride), np.uint8)
    codes[:, :cols] = 20
    # repeatability code * 1e-8 + 1e-7 > 1.5e-6 where code > 140: three points.
    codes[0, 0] = 200
    codes[4, 7] = 141
    codes[8, 12] = 255
    codes[6, 3] = 140  # exactly at the filter value: kept
    out += plane0.tobytes() + codes.tobytes()
    Path(path).write_bytes(bytes(out))


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else '.')
    print(f'surfalize {surfalize.__version__}, numpy {np.__version__}')
    al3d = out / 'wave_pedestal.surfalize.al3d'
    z = surface_um(30, 41, [(0, 0), (3, 7), (12, 20), (12, 21), (29, 40), (17, 33), (25, 2)])
    Surface(z, 1.5, 2.0).save(al3d)
    stats(al3d, al3d.name, 'um')
    tmd = out / 'wave_pedestal.surfalize.tmd'
    z = surface_um(29, 37, [(1, 1), (5, 30), (14, 22), (28, 36), (20, 4)])
    # Millimetres (see the module docs): 0.8 um and 1.25 um pitch.
    Surface(z * 1e-3, 0.8e-3, 1.25e-3).save(tmd)
    stats(tmd, tmd.name, 'mm')
    layout = out / 'quality_map.layout.al3d'
    layout_al3d(layout)
    stats(layout, layout.name, 'um')


if __name__ == '__main__':
    main()
