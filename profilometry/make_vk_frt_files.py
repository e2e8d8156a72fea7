#!/usr/bin/env python3
"""Writes the small Keyence .vk4/.vk6 and FRT MicroProf .frt test files of this folder from the
public layouts, and prints what surfalize and SurfaceTopography compute when they read each one
back (recorded in README.md).

    python3 -m venv vk-venv && vk-venv/bin/pip install surfalize==0.19.2 SurfaceTopography==1.27.1
    vk-venv/bin/python profilometry/make_vk_frt_files.py profilometry

Neither program writes these formats, so the files are built here, field by field, from the
layouts that Gwyddion's `keyence` and `microprof` modules, SurfaceTopography's `VK` and `FRT`
readers and surfalize's `vk.py` describe (see src/io/scan/vk.rs and frt.rs for the tables):

- `wave_pedestal.layout.vk4`: the VK4 byte stream: 12-byte header, 72-byte offset table, 336
  bytes of measurement conditions (more than the 304 described, as newer software writes), a
  24-bit colour peak image, a 16-bit light image, the 32-bit height image (counts of 10 pm,
  pitch 1.25 x 1.6 um), a second height layer, and the strings (title, lens name; UTF-16).
- `wave_pedestal.layout.vk6`: the same stream as the zip entry `Vk4File`, after `VK6`, a u32
  length and a BMP preview of that length.
- `wave_pedestal.layout.frt`: version 1.00 (u32 block sizes): blocks 0x0065 description,
  0x0066 size, 0x0067 ranges, 0x006c z scale, 0x0070 valid range, 0x0072 time, 0x0077 parameter
  set, 0x000b the heights (i32 counts of 1 pm, the first stored row the bottom of the image,
  the count 1 for points not measured).
- `wave_pedestal_multi.layout.frt`: version 1.01 (u64 block sizes), no 0x000b: the multi-image
  block 0x007d with an intensity image first and the topography second (u16 counts of 50 pm).

The surface (i = row from the top of the image; j = column), micrometres:
z = 0.05 + 0.4 sin(2 pi j / 13) cos(2 pi i / 11) + 0.002 j - 0.001 i, plus 0.8 where
10 <= i < 20 and 15 <= j < 30; in the .frt files a few points are non-measured (VK4 has no
marker for them).
"""
import io
import struct
import sys
import zipfile
from pathlib import Path

import numpy as np
from wave_pedestal import surface_um, surfalize_stats

ROWS, COLS = 23, 31
MISSING = [(3, 4), (12, 20), (22, 30), (0, 17)]


# ---- Keyence VK4 ----------------------------------------------------------------------------

VK_PX, VK_PY, VK_PZ = 1_250_000, 1_600_000, 10  # picometres


def vk4_counts():
    """The surface as u32 counts of VK_PZ pm, shifted up by 1 um (the counts are unsigned)."""
    z = surface_um(ROWS, COLS, [])
    return np.round((z + 1.0) * 1e6 / VK_PZ).astype('<u4')


def false_colour_image(a, bits):
    h, w = a.shape
    dtype = {16: '<u2', 32: '<u4'}[bits]
    head = struct.pack('<7I', w, h, bits, 0, w * h * bits // 8, int(a.min()), int(a.max()))
    return head + bytes(768) + a.astype(dtype).tobytes()


def vk4_bytes():
    counts = vk4_counts()
    out = bytearray(b'VK4_' + bytes([0, 0, 1, 2]) + bytes(4))
    table_at = len(out)
    out += bytes(72)
    table = [0] * 18
    table[0] = len(out)
    mc = bytearray(336)

    def put(off, fmt, *v):
        struct.pack_into(fmt, mc, off, *v)

    put(0, '<I', len(mc))
    put(4, '<6Ii', 2023, 11, 7, 9, 41, 3, 60)
    put(48, '<2I', 1, 2)          # run mode, peak mode
    put(72, '<I', 10)             # optical zoom 1.0
    put(96, '<I', 500)            # lens magnification 50.0
    put(168, '<3I', VK_PX, VK_PY, VK_PZ)
    put(224, '<I', 950)           # numerical aperture 0.95
    put(300, '<I', 32)
    out += mc
    # Colour peak image: 24-bit, no palette.
    table[1] = len(out)
    rgb = np.zeros((ROWS, COLS, 3), np.uint8)
    rgb[..., 1] = (counts % 256).astype(np.uint8)
    out += struct.pack('<5I', COLS, ROWS, 24, 0, ROWS * COLS * 3) + rgb.tobytes()
    table[3] = len(out)
    out += false_colour_image((counts % 65536).astype(np.uint32), 16)
    table[6] = len(out)
    out += false_colour_image(counts, 32)
    table[7] = len(out)
    out += false_colour_image(counts + 500, 32)
    table[16] = len(out)
    for s in ['wave pedestal', 'CF IC EPI Plan 50X']:
        u = s.encode('utf-16-le')
        out += struct.pack('<I', len(u) // 2) + u
    struct.pack_into('<18I', out, table_at, *table)
    return bytes(out)


def vk6_bytes(vk4):
    bmp = bytearray(b'BM' + struct.pack('<I', 70) + bytes(64))
    zbuf = io.BytesIO()
    # A fixed entry date, so that the same script writes the same bytes.
    entry = lambda name: zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
    with zipfile.ZipFile(zbuf, 'w', zipfile.ZIP_DEFLATED) as z:
        z.writestr(entry('MeasureCondition'), '<Condition/>', zipfile.ZIP_DEFLATED)
        z.writestr(entry('Vk4File'), vk4, zipfile.ZIP_DEFLATED)
    return b'VK6' + struct.pack('<I', len(bmp)) + bytes(bmp) + zbuf.getvalue()


# ---- FRT MicroProf --------------------------------------------------------------------------

FRT_DX, FRT_DY = 2.5e-6, 2.0e-6  # metres


def frt_counts(zscale, dtype, shift_um):
    """Counts of `zscale` metres (rows from the top of the image; NaN as the count 1)."""
    z = surface_um(ROWS, COLS, MISSING)
    c = np.round((z + shift_um) * 1e-6 / zscale)
    assert not np.any(c == 1), 'a measured point would read as the marker'
    c[np.isnan(z)] = 1
    return c.astype(dtype)


def frt_block(tag, payload, wide):
    return struct.pack('<HQ' if wide else '<HI', tag, len(payload)) + payload


def frt_bytes(version, zscale, counts, multi):
    wide = version == b'1.01'
    # The first stored row is the bottom of the image.
    stored = counts[::-1]
    bits = 8 * counts.dtype.itemsize
    blocks = [
        frt_block(0x0065, b'wave pedestal from the FRT layout', wide),
        frt_block(0x0066, struct.pack('<3I', COLS, ROWS, bits), wide),
        frt_block(0x0067, struct.pack('<5dI', COLS * FRT_DX, ROWS * FRT_DY, 1e-4, -2e-4,
                                      (ROWS * FRT_DY) / (COLS * FRT_DX), 1), wide),
        frt_block(0x006c, struct.pack('<Id', 5, zscale), wide),
        frt_block(0x0070, struct.pack('<2I', 2, 0xFFFFFFFF), wide),
        frt_block(0x0072, struct.pack('<3I', 1700000000, 1700000123, 123), wide),
        frt_block(0x0077, b'CWL 300um', wide),
    ]
    if multi:
        intensity = (np.arange(ROWS * COLS).reshape(ROWS, COLS) % 4000 + 100).astype(counts.dtype)
        images = struct.pack('<4H', 0, 0, 0, 0)
        images += struct.pack('<4I', 0x00000002, COLS, ROWS, bits) + intensity[::-1].tobytes()
        images += struct.pack('<4I', 0x00000004, COLS, ROWS, bits) + stored.tobytes()
        blocks.append(frt_block(0x007d, images, wide))
    else:
        blocks.append(frt_block(0x000b, stored.tobytes(), wide))
    return b'FRTM_GLIDERV' + version + struct.pack('<H', len(blocks)) + b''.join(blocks)


# ---- Reading back ---------------------------------------------------------------------------

def topography_stats(path):
    import SurfaceTopography
    r = SurfaceTopography.open_topography(str(path))
    t = r.topography()
    h = t.heights()  # (nx, ny), masked where undefined
    v = np.ma.compressed(h)
    nx, ny = t.nb_grid_pts
    sx, sy = t.physical_sizes
    sa = np.mean(np.abs(v - v.mean()))
    print(f'{path.name}: SurfaceTopography {SurfaceTopography.__version__}: {ny} rows x {nx} cols, '
          f'step {sx / nx!r}, {sy / ny!r} {t.unit}, non-measured {h.size - v.size}, '
          f'Sq {t.Sq():.9g} (its Sq), Sa {sa:.9g} Sz {np.ptp(v):.9g} (numpy on its heights) {t.unit}')


def main(folder):
    folder = Path(folder)
    vk4 = vk4_bytes()
    files = {
        'wave_pedestal.layout.vk4': vk4,
        'wave_pedestal.layout.vk6': vk6_bytes(vk4),
        'wave_pedestal.layout.frt': frt_bytes(b'1.00', 1e-12, frt_counts(1e-12, '<i4', 0.0), False),
        'wave_pedestal_multi.layout.frt':
            frt_bytes(b'1.01', 5e-11, frt_counts(5e-11, '<u2', 1.0), True),
    }
    for name, data in files.items():
        (folder / name).write_bytes(data)
        print(f'wrote {name}: {len(data)} bytes')
    for name in files:
        if name.endswith(('.vk4', '.vk6')):
            surfalize_stats(folder / name)
        topography_stats(folder / name)


if __name__ == '__main__':
    main(sys.argv[1] if len(sys.argv) > 1 else '.')
