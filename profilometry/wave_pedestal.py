"""The surface every instrument test file of this folder carries (imported by the make_*.py
scripts beside it, with the reading back by surfalize that four of them print), micrometres;
i = row (the first row in the file unless a format says otherwise), j = column:

z = 0.05 + 0.4 sin(2 pi j / 13) cos(2 pi i / 11) + 0.002 j - 0.001 i, plus 0.8 where
10 <= i < 20 and 15 <= j < 30; the points `missing` (row, column) within the map are NaN.
"""
import numpy as np


def surface_um(rows, cols, missing=()):
    i, j = np.mgrid[0:rows, 0:cols].astype(float)
    z = 0.05 + 0.4 * np.sin(2 * np.pi * j / 13) * np.cos(2 * np.pi * i / 11) + 0.002 * j - 0.001 * i
    z[10:20, 15:30] += 0.8
    for r, c in missing:
        if r < rows and c < cols:
            z[r, c] = np.nan
    return z


def surfalize_stats(path, label=None, unit='um'):
    """Prints what surfalize reads from `path`: size, steps, non-measured points, Sq, Sa, Sz (in
    `unit`, the unit the file's numbers are in for surfalize). surfalize computes the height
    parameters on the valid points once the non-measured ones are masked (it refuses NaN in
    the data itself)."""
    import surfalize
    from surfalize import Surface
    s = Surface.load(path)
    nan = np.isnan(s.data)
    m = Surface(np.where(nan, 0.0, s.data), s.step_x, s.step_y, mask=nan)
    p = m.height_parameters()
    print(f'{label or path.name}: surfalize {surfalize.__version__}: {s.size.y} rows x {s.size.x} cols, '
          f'step_x {s.step_x!r} step_y {s.step_y!r} ({unit}), non-measured {int(nan.sum())}, '
          f'Sq {p["Sq"]:.9g} Sa {p["Sa"]:.9g} Sz {p["Sz"]:.9g} {unit}')
