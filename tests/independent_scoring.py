"""A second, independent registration of a scene's reference onto its capture, and scores on it.

Used by the integration tests to check `doefab evaluate`: the registration here shares no code
and no method with doefab's (tile NCC, RANSAC affine, Gaussian-weighted field). It is OpenCV's:

1. the reference is predicted through the PSF (scipy FFT convolution, the reference extended by
   its edge values) and compressed by a square root of the channel mean, as is the capture;
2. a homography by enhanced correlation coefficient maximisation (cv2.findTransformECC,
   Evangelidis and Psarakis 2008) over a four-level pyramid;
3. the residual (parallax) from template matching (cv2.matchTemplate, normalised correlation
   coefficient) of 48 px tiles of the capture every 16 px within +-12 px, sub-pixel by a
   parabola, kept where the peak exceeds 0.7, is sharp, and agrees within 2 px with the median
   of its neighbours; interpolated linearly between the kept tiles (scipy griddata) and
   smoothed (Gaussian, sigma 4 px); pixels outside the kept tiles' hull are not covered;
4. the gain is the median capture / prediction over covered samples exposed between 0.05 and
   0.9 in every channel.

Every image is then scored, with PSNR-gamma as doefab defines it, against this registration's
reference and against doefab's (`evaluate --registered`), over the pixels both cover and over
those of them doefab counts saturated. Prints JSON.
"""

import argparse
import json

import cv2
import numpy as np
import OpenEXR
from scipy.interpolate import griddata
from scipy.ndimage import gaussian_filter
from scipy.signal import fftconvolve


def read_exr(path):
    channels = OpenEXR.File(path, separate_channels=True).channels()
    rgb = np.stack([channels[c].pixels for c in "RGB"], -1).astype(np.float64)
    return rgb, {k: v.pixels for k, v in channels.items()}


def predict(reference, psf):
    pad = psf.shape[0] // 2 + 1
    return np.stack(
        [
            fftconvolve(np.pad(reference[..., c], pad, mode="edge"), psf[..., c], mode="same")[pad:-pad, pad:-pad]
            for c in range(3)
        ],
        -1,
    )


def compress(image):
    return np.sqrt(np.clip(image.mean(-1), 0, 1)).astype(np.float32)


def ecc_homography(moving, fixed):
    """The homography W with moving(W q) ~ fixed(q), coarse to fine."""
    warp = np.eye(3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)
    for level in [3, 2, 1, 0]:
        f = 2**level
        s = np.diag([1 / f, 1 / f, 1]).astype(np.float32)
        m = cv2.resize(moving, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
        x = cv2.resize(fixed, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
        _, ws = cv2.findTransformECC(x, m, (s @ warp @ np.linalg.inv(s)).astype(np.float32), cv2.MOTION_HOMOGRAPHY, criteria, None, 5)
        warp = (np.linalg.inv(s) @ ws @ s).astype(np.float32)
    return warp.astype(np.float64)


def remap(image, mx, my):
    return np.stack(
        [
            cv2.remap(image[..., c].astype(np.float32), mx.astype(np.float32), my.astype(np.float32), cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
            for c in range(image.shape[2])
        ],
        -1,
    ).astype(np.float64)


def residual_field(moving, fixed, tile=48, step=16, radius=12):
    h, w = fixed.shape
    centres, shifts = [], []
    texture = 0.02 * fixed.std()
    for y in range(radius, h - tile - radius + 1, step):
        for x in range(radius, w - tile - radius + 1, step):
            t = fixed[y:y + tile, x:x + tile]
            if t.std() < texture:
                continue
            ncc = cv2.matchTemplate(moving[y - radius:y + tile + radius, x - radius:x + tile + radius], t, cv2.TM_CCOEFF_NORMED)
            _, peak, _, (lx, ly) = cv2.minMaxLoc(ncc)
            if peak < 0.7 or not (0 < lx < 2 * radius and 0 < ly < 2 * radius):
                continue

            def vertex(m, c, p):
                d = m + p - 2 * c
                return 0.5 * (m - p) / d if d < -1e-3 else None

            fx = vertex(ncc[ly, lx - 1], peak, ncc[ly, lx + 1])
            fy = vertex(ncc[ly - 1, lx], peak, ncc[ly + 1, lx])
            if fx is None or fy is None:
                continue
            centres.append((x + tile / 2 - 0.5, y + tile / 2 - 0.5))
            shifts.append((lx - radius + fx, ly - radius + fy))
    centres, shifts = np.array(centres), np.array(shifts)
    keep = np.ones(len(centres), bool)
    for _ in range(5):
        nxt = keep.copy()
        for i, c in enumerate(centres):
            d = np.abs(centres[keep] - c).max(1)
            near = (d <= 2 * step + 0.1) & (d > 0)
            nxt[i] = near.sum() >= 3 and np.hypot(*(shifts[i] - np.median(shifts[keep][near], 0))) <= 2
        keep = nxt
    yy, xx = np.mgrid[0:h, 0:w]
    fields = [griddata(centres[keep], shifts[keep, k], (xx, yy), method="linear") for k in range(2)]
    covered = np.isfinite(fields[0]) & np.isfinite(fields[1])
    weight = gaussian_filter(covered.astype(float), 4)
    smooth = [np.where(covered, gaussian_filter(np.nan_to_num(f), 4) / np.maximum(weight, 1e-9), 0) for f in fields]
    return smooth, covered, int(keep.sum()), len(centres)


def psnr_gamma(reference, image, mask):
    x, y = reference[mask], image[mask]
    return float(10 * np.log10(x.max() / np.mean((np.sqrt(np.clip(y, 0, None)) - np.sqrt(np.clip(x, 0, None))) ** 2)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--reference", required=True)
    ap.add_argument("--capture", required=True)
    ap.add_argument("--psf", required=True)
    ap.add_argument("--psf-key", default="psf_val")
    ap.add_argument("--ours", required=True, help="doefab evaluate --registered output")
    ap.add_argument("--image", action="append", default=[], help="NAME=PATH.exr")
    a = ap.parse_args()
    reference, _ = read_exr(a.reference)
    capture = cv2.imread(a.capture, cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64) / 255
    psf = np.load(a.psf)[a.psf_key].reshape(-1, *np.load(a.psf)[a.psf_key].shape[-3:])[0] if False else np.load(a.psf)[a.psf_key]
    psf = psf.reshape(psf.shape[0], psf.shape[1], -1)
    psf = psf / psf.sum(axis=(0, 1))
    ours, ours_channels = read_exr(a.ours)
    scored, saturated = ours_channels["scored"] > 0.5, ours_channels["saturated"] > 0.5
    h, w = capture.shape[:2]

    prediction = predict(reference, psf)
    gain0 = np.median((capture / np.maximum(prediction, 1e-12))[(capture > 0.05).all(-1) & (capture < 0.9).all(-1)])
    fixed = compress(capture)
    homography = ecc_homography(compress(np.clip(gain0 * prediction, 0, 1)), fixed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    den = homography[2, 0] * xx + homography[2, 1] * yy + homography[2, 2]
    hx = (homography[0, 0] * xx + homography[0, 1] * yy + homography[0, 2]) / den
    hy = (homography[1, 0] * xx + homography[1, 1] * yy + homography[1, 2]) / den
    moved = compress(np.clip(gain0 * np.nan_to_num(remap(prediction, hx, hy)), 0, 1))
    (fx, fy), covered, kept, tiles = residual_field(moved, fixed)
    qx, qy = (xx + fx).astype(np.float32), (yy + fy).astype(np.float32)
    mx = cv2.remap(hx.astype(np.float32), qx, qy, cv2.INTER_LINEAR)
    my = cv2.remap(hy.astype(np.float32), qx, qy, cv2.INTER_LINEAR)
    registered, registered_prediction = remap(reference, mx, my), remap(prediction, mx, my)
    covered &= np.isfinite(registered).all(-1) & np.isfinite(registered_prediction).all(-1)
    exposed = covered & (capture > 0.05).all(-1) & (capture < 0.9).all(-1)
    gain = float(np.median(capture[exposed] / np.maximum(registered_prediction[exposed], 1e-12)))
    target = gain * np.nan_to_num(registered)

    both = covered & scored
    both_saturated = both & saturated
    images = {"capture": capture}
    for spec in a.image:
        name, path = spec.split("=", 1)
        images[name] = read_exr(path)[0]
    out = {
        "tiles_kept": kept,
        "tiles": tiles,
        "coverage": float(covered.mean()),
        "coverage_both": float(both.mean()),
        "saturated_both": int(both_saturated.sum()),
        "saturated_ours": int(saturated.sum()),
        "gain": gain,
        "scores": {
            name: {
                "independent": [psnr_gamma(target, img, both), psnr_gamma(target, img, both_saturated)],
                "doefab": [psnr_gamma(ours, img, both), psnr_gamma(ours, img, both_saturated)],
            }
            for name, img in images.items()
        },
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
