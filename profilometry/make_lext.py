#!/usr/bin/env python3
"""Writes the small Olympus LEXT (.lext) test files of this folder with tifffile, from the layout
that Gwyddion's `lextfile` module, surfalize's `lext.py` and SurfaceTopography's `LEXT` reader
describe (see src/io/scan/lext.rs for the table), and prints what surfalize and SurfaceTopography
compute when they read each one back (recorded in README.md).

    python3 -m venv lext-venv
    lext-venv/bin/pip install tifffile==2026.3.3 surfalize==0.19.2 SurfaceTopography==1.27.1
    lext-venv/bin/python profilometry/make_lext.py profilometry

A LEXT file is a multi-page TIFF. tifffile writes the pages; the EXIF IFD that holds the device
settings (tifffile writes none, and refuses the ExifIFD tag 34665) is appended after them, and a
private placeholder tag that tifffile wrote last in the first page's IFD becomes the ExifIFD
tag pointing at it.

- `wave_pedestal.tifffile.lext` (little-endian, one strip a page):
  page 0, a 24-bit colour image whose ImageDescription is the `<TiffTagDescData>` XML
  (HeightInfo: 2.5 x 1.25 um a pixel, 50 pm a count), with Make, Model, Software, DateTime and
  the EXIF IFD whose DeviceSettingDescription (0xA40B) is the `<ExifTagDescData>` XML (objective,
  magnification, MakerCalibrationValueX/Y/Z = 1002000, 998000, 1010000, i.e. factors 1.002,
  0.998, 1.010); page 1 `INTENSITY` (16-bit); page 2 `HEIGHT` (16-bit counts; the points not
  measured hold 0); page 3 `INVALID`, a 1-bit mask (photometric 4) whose set bits are the points
  not measured.
- `wave_pedestal_be.tifffile.lext` (big-endian `MM`, signed 32-bit height counts in strips of 5 rows (Pillow, which surfalize reads
  with, reads no unsigned big-endian 32-bit image),
  no EXIF IFD: no calibration factors; the INVALID page first, the colour page last).

The surface (i = row from the top of the image; j = column) is wave_pedestal.py's,
micrometres, shifted up by 1 um so that the counts are positive.
"""
import io
import struct
import sys
from pathlib import Path

import numpy as np
import tifffile
from wave_pedestal import surface_um, surfalize_stats

ROWS, COLS = 23, 31
MISSING = [(3, 4), (12, 20), (22, 30), (0, 17), (7, 0)]
PX, PY, PZ = 2_500_000, 1_250_000, 50  # picometres a pixel, picometres a count
CAL = (1_002_000, 998_000, 1_010_000)  # MakerCalibrationValueX/Y/Z (x 1e-6: the factors)
SHIFT_UM = 1.0

TIFF_XML = """<?xml version="1.0" encoding="UTF-8"?>
<TiffTagDescData version="1.0">
  <FileInfo><FileVersion>2.1.3.1</FileVersion></FileInfo>
  <ImageInfo><ImageWidth>{cols}</ImageWidth><ImageHeight>{rows}</ImageHeight></ImageInfo>
  <HeightInfo>
    <HeightDataPerPixelX>{px}</HeightDataPerPixelX>
    <HeightDataPerPixelY>{py}</HeightDataPerPixelY>
    <HeightDataPerPixelZ>{pz}</HeightDataPerPixelZ>
    <HeightDataUnitX>2</HeightDataUnitX>
    <HeightDataUnitY>2</HeightDataUnitY>
    <HeightDataUnitZ>2</HeightDataUnitZ>
  </HeightInfo>
  <IntensityInfo>
    <IntensityDataPerPixelX>{px}</IntensityDataPerPixelX>
    <IntensityDataPerPixelY>{py}</IntensityDataPerPixelY>
    <IntensityDataPerPixelZ>1</IntensityDataPerPixelZ>
  </IntensityInfo>
</TiffTagDescData>
"""

EXIF_XML = """<?xml version="1.0" encoding="UTF-8"?>
<ExifTagDescData version="1.0">
  <ImageCommonSettingsInfo>
    <ObjectiveLenseType>MPLAPON50XLEXT</ObjectiveLenseType>
    <ObjectiveLenseMagnification>50.0</ObjectiveLenseMagnification>
    <ZoomMagnification>1.0</ZoomMagnification>
    <MakerCalibrationValueX>{cx}</MakerCalibrationValueX>
    <MakerCalibrationValueY>{cy}</MakerCalibrationValueY>
    <MakerCalibrationValueZ>{cz}</MakerCalibrationValueZ>
  </ImageCommonSettingsInfo>
</ExifTagDescData>
"""


def counts(cal_z):
    """The surface as counts of PZ * cal_z pm (0 where not measured), and the invalid mask."""
    z = surface_um(ROWS, COLS, MISSING)
    invalid = np.isnan(z)
    c = np.round((z + SHIFT_UM) * 1e6 / (PZ * cal_z))
    c[invalid] = 0
    return c, invalid


def colour(c):
    rgb = np.zeros((ROWS, COLS, 3), np.uint8)
    rgb[..., 0] = (c % 256).astype(np.uint8)
    rgb[..., 2] = 200
    return rgb


def ifd_entries(data, byteorder):
    """(tag, entry offset) of the first IFD's entries."""
    ifd = struct.unpack_from(byteorder + 'I', data, 4)[0]
    n = struct.unpack_from(byteorder + 'H', data, ifd)[0]
    return [(struct.unpack_from(byteorder + 'H', data, ifd + 2 + 12 * k)[0], ifd + 2 + 12 * k)
            for k in range(n)]


def add_exif(data, byteorder, xml):
    """Appends an EXIF IFD holding DeviceSettingDescription (0xA40B) = `xml` and points the first
    page's ExifIFD tag at it. The tag is ASCII, NUL-terminated, as Gwyddion's reader requires
    (the EXIF standard has it UNDEFINED; surfalize reads either)."""
    data = bytearray(data)
    if len(data) % 2:
        data += b'\0'
    at = len(data)
    payload = xml.encode('ascii') + b'\0'
    ifd = struct.pack(byteorder + 'H', 1)
    ifd += struct.pack(byteorder + 'HHII', 0xA40B, 2, len(payload), at + 2 + 12 + 4)
    ifd += struct.pack(byteorder + 'I', 0)
    data += ifd + payload
    entries = ifd_entries(data, byteorder)
    tag, entry = entries[-1]
    assert tag == PLACEHOLDER, 'the placeholder is the last entry (the entries stay sorted)'
    struct.pack_into(byteorder + 'HHII', data, entry, 34665, 4, 1, at)
    return bytes(data)


# Make, Model and DateTime of the first page (tifffile writes Software itself).
COMMON_TAGS = [
    (271, 's', 0, 'OLYMPUS', True),
    (272, 's', 0, 'OLS4100', True),
    (306, 's', 0, '2024:03:05 14:22:31', True),
]
SOFTWARE = 'LEXT 2.1.3.1'
# tifffile refuses to write the ExifIFD tag (34665) itself: a private tag written in its place,
# the last of the first page's entries, is renamed to 34665 once the EXIF IFD is appended.
PLACEHOLDER = 65000


def lext_le():
    c, invalid = counts(CAL[2] * 1e-6)
    assert c.max() < 65536
    xml = TIFF_XML.format(rows=ROWS, cols=COLS, px=PX, py=PY, pz=PZ)
    buf = io.BytesIO()
    with tifffile.TiffWriter(buf, byteorder='<', bigtiff=False) as tif:
        tif.write(colour(c), photometric='rgb', description=xml, metadata=None,
                  software=SOFTWARE, extratags=COMMON_TAGS + [(PLACEHOLDER, 'I', 1, 0, True)])
        tif.write(((c * 7) % 60000).astype('<u2'), photometric='minisblack',
                  description='INTENSITY', metadata=None, software=False)
        tif.write(c.astype('<u2'), photometric='minisblack', description='HEIGHT',
                  metadata=None, software=False)
        tif.write(invalid, photometric=4, description='INVALID', metadata=None, software=False)
    return add_exif(buf.getvalue(), '<', EXIF_XML.format(cx=CAL[0], cy=CAL[1], cz=CAL[2]))


def lext_be():
    c, invalid = counts(1.0)
    xml = TIFF_XML.format(rows=ROWS, cols=COLS, px=PX, py=PY, pz=PZ)
    buf = io.BytesIO()
    with tifffile.TiffWriter(buf, byteorder='>', bigtiff=False) as tif:
        tif.write(invalid, photometric=4, description=xml, metadata=None, software=SOFTWARE,
                  extratags=COMMON_TAGS)
        tif.write(((c * 7) % 60000).astype('>u2'), photometric='minisblack',
                  description='INTENSITY', metadata=None, software=False)
        tif.write(c.astype('>i4'), photometric='minisblack', description='HEIGHT',
                  metadata=None, software=False, rowsperstrip=5)
        tif.write(invalid, photometric=4, description='INVALID', metadata=None, software=False)
        tif.write(colour(c), photometric='rgb', description='COLOR', metadata=None,
                  software=False)
    return buf.getvalue()


# ---- Reading back ---------------------------------------------------------------------------

def topography_stats(path):
    """SurfaceTopography's heights, with the INVALID page (which it does not read) as the mask
    of points not measured, as surfalize and doefab apply it."""
    import SurfaceTopography
    r = SurfaceTopography.open_topography(str(path))
    t = r.topography()
    h = np.asarray(t.heights())  # (nx, ny) = (columns, rows)
    with tifffile.TiffFile(path) as tf:
        invalid = next(p for p in tf.pages[1:] if p.description == 'INVALID').asarray()
    v = h.T[~invalid.astype(bool)]
    nx, ny = t.nb_grid_pts
    sx, sy = t.physical_sizes
    sq = np.sqrt(np.mean((v - v.mean()) ** 2))
    sa = np.mean(np.abs(v - v.mean()))
    print(f'{path.name}: SurfaceTopography {SurfaceTopography.__version__}: {ny} rows x {nx} cols, '
          f'step {float(sx / nx)!r}, {float(sy / ny)!r} {t.unit}, masked {int(invalid.sum())}, '
          f'Sq {sq:.9g} Sa {sa:.9g} Sz {np.ptp(v):.9g} (numpy on its heights) {t.unit}')


def main(folder):
    folder = Path(folder)
    files = {
        'wave_pedestal.tifffile.lext': lext_le(),
        'wave_pedestal_be.tifffile.lext': lext_be(),
    }
    for name, data in files.items():
        (folder / name).write_bytes(data)
        print(f'wrote {name}: {len(data)} bytes')
    for name in files:
        for f in (surfalize_stats, topography_stats):
            try:
                f(folder / name)
            except Exception as e:  # a reader that refuses the file is reported, not fatal
                print(f'{name}: {f.__name__}: {type(e).__name__}: {e}')


if __name__ == '__main__':
    main(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).parent)
