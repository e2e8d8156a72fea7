"""The OpenCV reference of `cargo bench --bench register`: the shift of a scan against its design
by cv2.phaseCorrelate (translation only), timed inside this script from arrays in memory (the
.npy reads and the interpreter's start not timed), best of RUNS.

What it does, as a user of OpenCV would: the design resampled to the scan's pitch
(cv2.resize, INTER_AREA), placed centred on a canvas of the scan's size, the scan's
non-measured points (NaN) filled with its mean, both windowed (Hanning), cv2.phaseCorrelate.
Prints "opencv SECONDS DX_M DY_M": the scan position of the design's centre, metres from the
scan's centre (x along columns, y along rows).

    python register_opencv.py design.npy DESIGN_PITCH_M scan.npy SCAN_PITCH_M RUNS
"""
import sys
import time

import cv2
import numpy as np

design = np.load(sys.argv[1]).astype(np.float64)
pd = float(sys.argv[2])
scan = np.load(sys.argv[3]).astype(np.float64)
ps = float(sys.argv[4])
runs = int(sys.argv[5])


def shift_of(design, scan):
    f = pd / ps
    d = cv2.resize(design, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)
    rows, cols = scan.shape
    canvas = np.zeros_like(scan)
    dr, dc = d.shape
    # Centre the resampled design on the canvas (cropped where it is larger).
    r0, c0 = (rows - dr) // 2, (cols - dc) // 2
    src = d[max(0, -r0):max(0, -r0) + min(dr, rows), max(0, -c0):max(0, -c0) + min(dc, cols)]
    canvas[max(0, r0):max(0, r0) + src.shape[0], max(0, c0):max(0, c0) + src.shape[1]] = src
    # Where the design's centre lands: cv2.resize maps source x to (x + 0.5) f - 0.5, so the
    # centre (n - 1) / 2 of n samples lands on n f / 2 - 0.5, then r0 on the canvas, whose own
    # centre is (rows - 1) / 2.
    n_r, n_c = design.shape
    off = (r0 + n_r * f / 2 - 0.5 - (rows - 1) / 2, c0 + n_c * f / 2 - 0.5 - (cols - 1) / 2)
    s = scan.copy()
    bad = ~np.isfinite(s)
    s[bad] = s[~bad].mean()
    win = cv2.createHanningWindow((cols, rows), cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(canvas - canvas.mean(), s - s.mean(), win)
    return (dx + off[1]) * ps, (dy + off[0]) * ps


best = float("inf")
for _ in range(runs):
    t = time.perf_counter()
    dx, dy = shift_of(design, scan)
    best = min(best, time.perf_counter() - t)
print(f"opencv {best:.4f} {dx:.9e} {dy:.9e}")
