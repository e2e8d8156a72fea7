#!/usr/bin/env python3
"""Writes the small Sensofar `.plux` test file of this folder from the format's public layout
(Gwyddion's `sensofarx` module, SurfaceTopography's and surfalize's `plux` readers) and prints
what SurfaceTopography and surfalize compute when they read it back (recorded in README.md).

    python3 -m venv st-venv && st-venv/bin/pip install SurfaceTopography==1.27.1 surfalize==0.19.2
    st-venv/bin/python profilometry/make_plux_file.py profilometry

`wave_pedestal.layout.plux` is a zip archive (deflated members) of
- `LAYER_0.raw`: 27 rows of 37 f32 heights in micrometres, the first row first, NaN at 6 points
  not measured;
- `LAYER_0.stack.raw`: the intensity image (27 x 37 x 3 bytes), not a height;
- `LAYER_1.raw`: a second layer (the surface plus 5 um), which a reader of the first layer skips;
- `index.xml`: root `<xml>`, `GENERAL` (`DATE`, `IMAGE_SIZE_X` = 37, `IMAGE_SIZE_Y` = 27,
  `FOV_X` = 0.65, `FOV_Y` = 0.9: the pitch in micrometres), `LAYER_0` / `LAYER_1` with their
  `FILENAME_Z`, and `INFO` items (Device, Objective, Technique, Measurement Type, Algorithm,
  Comment).

The surface (i = row, first row in the file; j = column), micrometres:
z = 0.05 + 0.4 sin(2 pi j / 13) cos(2 pi i / 11) + 0.002 j - 0.001 i, plus 0.8 where
10 <= i < 20 and 15 <= j < 30.
"""
import sys
import zipfile
from pathlib import Path

import numpy as np
from wave_pedestal import surface_um, surfalize_stats

ROWS, COLS = 27, 37
MISSING = [(0, 0), (4, 9), (12, 20), (12, 21), (26, 36), (19, 3)]


INDEX = """<?xml version="1.0" encoding="UTF-8"?>
<xml>
    <GENERAL>
        <VERSION>1</VERSION>
        <DATE>2025-10-16 14:15:41</DATE>
        <IMAGE_SIZE_X>{cols}</IMAGE_SIZE_X>
        <IMAGE_SIZE_Y>{rows}</IMAGE_SIZE_Y>
        <FOV_X>0.65</FOV_X>
        <FOV_Y>0.9</FOV_Y>
        <NUMBER_LAYERS>2</NUMBER_LAYERS>
    </GENERAL>
    <LAYER_0>
        <FILENAME_Z>LAYER_0.raw</FILENAME_Z>
        <FILENAME_IMAGE>LAYER_0.stack.raw</FILENAME_IMAGE>
    </LAYER_0>
    <LAYER_1>
        <FILENAME_Z>LAYER_1.raw</FILENAME_Z>
    </LAYER_1>
    <INFO>
        <SIZE>6</SIZE>
        <ITEM_0><NAME>Device</NAME><VALUE>S neox</VALUE></ITEM_0>
        <ITEM_1><NAME>Objective</NAME><VALUE>Nikon 50X EPI</VALUE></ITEM_1>
        <ITEM_2><NAME>Technique</NAME><VALUE>Confocal</VALUE></ITEM_2>
        <ITEM_3><NAME>Measurement Type</NAME><VALUE>Topography</VALUE></ITEM_3>
        <ITEM_4><NAME>Algorithm</NAME><VALUE>Confocal Intensity</VALUE></ITEM_4>
        <ITEM_5><NAME>Comment</NAME><VALUE>Built from the PLUx layout</VALUE></ITEM_5>
    </INFO>
</xml>
"""


def stats_surfacetopography(path):
    import SurfaceTopography
    from SurfaceTopography import open_topography

    r = open_topography(str(path))
    t = r.topography(channel_index=0)
    h = np.ma.masked_invalid(t.heights())
    valid = h.compressed()
    dx, dy = (s / n for s, n in zip(t.physical_sizes, t.nb_grid_pts))
    print(f'{path.name}: SurfaceTopography {SurfaceTopography.__version__}, {len(r.channels)} channels, '
          f'channel 0 in {t.unit}: {t.nb_grid_pts[1]} rows x {t.nb_grid_pts[0]} cols, dx {dx!r} dy {dy!r}, '
          f'non-measured {int(h.mask.sum())}, Sq {np.sqrt(np.mean((valid - valid.mean()) ** 2)):.9g} '
          f'Sa {np.mean(np.abs(valid - valid.mean())):.9g} Sz {valid.max() - valid.min():.9g} {t.unit}')


def write(path, rows, cols):
    z = surface_um(rows, cols, MISSING)
    stack = np.repeat((np.nan_to_num(z) * 100).astype(np.uint8)[:, :, None], 3, axis=2)
    with zipfile.ZipFile(path, 'w', compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in [
            ('LAYER_0.raw', z.astype('<f4').tobytes()),
            ('LAYER_0.stack.raw', stack.tobytes()),
            ('LAYER_1.raw', (z + 5).astype('<f4').tobytes()),
            ('index.xml', INDEX.format(rows=rows, cols=cols).encode()),
        ]:
            info = zipfile.ZipInfo(name, date_time=(2025, 10, 16, 14, 15, 40))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data)


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else '.')
    path = out / 'wave_pedestal.layout.plux'
    write(path, ROWS, COLS)
    surfalize_stats(path)
    stats_surfacetopography(path)
    # A small seed for the fuzz target (its inputs are cut at 4 kB): 5 x 4 points.
    seed = out.parent / 'fuzz' / 'corpus' / 'plux'
    if seed.is_dir():
        write(seed / 'seed.plux', 4, 5)


if __name__ == '__main__':
    main()
