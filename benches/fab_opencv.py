"""The OpenCV reference of `cargo bench --bench fab`: a height map (.npy, metres) wrapped at
the period, quantized to N levels, mapped to 16-bit gray through a linear table and written
with cv2.imwrite as a 16-bit PNG, timed inside this script (reading included, the
interpreter's start not). Prints "opencv SECONDS".

    python fab_opencv.py design.npy out.png PERIOD_M LEVELS
"""
import sys
import time

import cv2
import numpy as np

path, out, period, levels = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
t = time.perf_counter()
h = np.load(path)
wrapped = np.mod(h, period)
q = np.rint(wrapped * (levels / period)).astype(np.int64) % levels
lut = np.round(np.linspace(65535, 0, levels)).astype(np.uint16)
gray = lut[q]
if not cv2.imwrite(out, gray):
    sys.exit("cv2.imwrite failed")
print(f"opencv {time.perf_counter() - t:.4f}")
