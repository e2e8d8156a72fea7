#!/usr/bin/env python3
"""Writes small seed files (a 6 x 5 map with one non-measured point) for the fuzz targets.

Standard library only, independent of doefab's own writers: each file follows the format
description quoted in the reader's module docs (src/io/scan/*.rs, src/io/npy.rs) or, for
OpenEXR, the OpenEXR file layout document.
Usage: make_seeds.py CORPUS_DIR (writes CORPUS_DIR/TARGET/NAME).
"""
import os
import struct
import sys

ROWS, COLS = 5, 6
Z = [[1e-9 * (10 * i + j) + (4e-7 if 1 <= i <= 3 and 2 <= j <= 4 else 0.0) for j in range(COLS)] for i in range(ROWS)]
MISSING = (4, 5)


def flat():
    return [Z[i][j] for i in range(ROWS) for j in range(COLS)]


def put(out, target, name, data):
    d = os.path.join(out, target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


def gsf():
    head = ("Gwyddion Simple Field 1.0\nXRes = %d\nYRes = %d\nXReal = 6e-06\nYReal = 5e-06\n"
            "XYUnits = m\nZUnits = m\n" % (COLS, ROWS)).encode()
    head += b"\0" * (4 - len(head) % 4)
    vals = flat()
    vals[MISSING[0] * COLS + MISSING[1]] = float("nan")
    return head + struct.pack("<%df" % len(vals), *vals)


def sdf_binary(wide):
    h = b"bISO-1.0" if wide else b"bBCR-1.0"
    h += b"fuzzseed  " + b"010120250000" + b"010120250000"
    h += struct.pack("<II" if wide else "<HH", COLS, ROWS)
    h += struct.pack("<4d", 1e-6, 1e-6, 1.0 if wide else 1e-9, 1e-9)  # f64 data in metres
    h += bytes([0, 5 if not wide else 7, 0])  # Compression, DataType (i16 / f64), CheckType
    if wide:
        vals = flat()
        vals[MISSING[0] * COLS + MISSING[1]] = float("nan")
        return h + struct.pack("<%dd" % len(vals), *vals)
    return h + struct.pack("<%dh" % (ROWS * COLS), *[round(v * 1e9) for v in flat()])


def sdf_ascii():
    lines = ["aISO-1.0", "ManufacID = fuzzseed", "CreateDate = 010120250000", "ModDate = 010120250000",
             "NumPoints = %d" % COLS, "NumProfiles = %d" % ROWS, "Xscale = 1e-06", "Yscale = 1e-06",
             "Zscale = 1", "Zresolution = -1", "Compression = 0", "DataType = 7", "CheckType = 0", "*"]
    for i in range(ROWS):
        lines.append(" ".join("BAD" if (i, j) == MISSING else "%g" % Z[i][j] for j in range(COLS)))
    lines += ["*", "*"]
    return ("\n".join(lines) + "\n").encode()


def sur(bits):
    h = bytearray(512)
    h[0:12] = b"DIGITAL SURF"
    struct.pack_into("<HHHH", h, 12, 0, 1, 1, 2)
    struct.pack_into("<H", h, 86, 1)
    struct.pack_into("<H", h, 98, bits)
    counts = [round(v * 1e10) for v in flat()]  # 0.1 nm per count
    lo, hi = min(counts), max(counts)
    struct.pack_into("<iiiii", h, 100, lo, hi, COLS, ROWS, COLS * ROWS)
    struct.pack_into("<fff", h, 120, 1.0, 1.0, 0.1)
    for k, name in enumerate([b"X", b"Y", b"Z"]):
        h[132 + 16 * k:132 + 16 * k + len(name)] = name
    for k, unit in enumerate([b"\xb5m", b"\xb5m", b"nm"]):
        h[180 + 16 * k:180 + 16 * k + len(unit)] = unit
        h[228 + 16 * k:228 + 16 * k + len(unit)] = unit
    struct.pack_into("<fff", h, 466, 0.0, 0.0, -5.0)
    counts[MISSING[0] * COLS + MISSING[1]] = lo - 1
    return bytes(h) + struct.pack("<%d%s" % (len(counts), "h" if bits == 16 else "i"), *counts)


def metropro():
    hsize = 834
    h = bytearray(hsize)
    struct.pack_into(">Ihi", h, 0, 0x881B0370, 2, hsize)
    struct.pack_into(">HHhxxi", h, 52, 0, 0, 0, 0)
    struct.pack_into(">hhHHi", h, 64, 3, 4, COLS, ROWS, 4 * COLS * ROWS)
    struct.pack_into(">ff", h, 164, 0.5, 632.8e-9)
    struct.pack_into(">f", h, 176, 1.0)
    struct.pack_into(">f", h, 184, 1e-6)
    struct.pack_into(">h", h, 218, 1)
    r, k = 32768.0, 0.5 * 632.8e-9
    phase = [round(v * r / k) for v in flat()]
    phase[MISSING[0] * COLS + MISSING[1]] = 2147483647
    return bytes(h) + struct.pack(">%di" % len(phase), *phase)


def opd(elem):
    """Wyko OPD: 01 00, a directory of 24-byte entries (name, type, size, flags), the data in
    order; the array column by column, each from the last row up (src/io/scan/opd.rs)."""
    wavelength, mult = 632.8, 4096
    unit = wavelength * 1e-9 / mult
    if elem == 4:
        cols = [[(3.0e38 if (i, j) == MISSING else Z[i][j] / unit) for i in reversed(range(ROWS))] for j in range(COLS)]
        data = b"".join(struct.pack("<%df" % ROWS, *c) for c in cols)
    else:
        cols = [[(32767 if (i, j) == MISSING else round(Z[i][j] / unit)) for i in reversed(range(ROWS))] for j in range(COLS)]
        data = b"".join(struct.pack("<%dh" % ROWS, *c) for c in cols)
    entries = [
        (b"RAW_DATA", 3, struct.pack("<3H", COLS, ROWS, elem) + data),
        (b"Wavelength", 7, struct.pack("<f", wavelength)),
        (b"Mult", 6, struct.pack("<h", mult)),
        (b"Pixel_size", 7, struct.pack("<f", 1e-3)),
        (b"Aspect", 7, struct.pack("<f", 1.0)),
        (b"Title", 5, b"seed\0\0\0\0"),
    ]
    head = b"\x01\x00" + struct.pack("<16sHIH", b"Directory", 1, 24 * (len(entries) + 1), 0xFFFF)
    head += b"".join(struct.pack("<16sHIH", n, t, len(d), 0) for n, t, d in entries)
    return head + b"".join(d for _, _, d in entries)


def plu():
    """Sensofar PLu: a 500-byte header (date text, pitch in um at 404 and 408, type 3 at 428),
    rows and columns, f32 heights in um row by row, 1000001 = not measured (src/io/scan/plu.rs)."""
    h = bytearray(500)
    h[:24] = b"Mon Apr 19 11:40:13 2021"
    struct.pack_into("<II", h, 388, ROWS, COLS)
    struct.pack_into("<ff", h, 404, 1.0, 1.0)
    struct.pack_into("<I", h, 428, 3)
    v = [1000001.0 if (k // COLS, k % COLS) == MISSING else x * 1e6 for k, x in enumerate(flat())]
    return bytes(h) + struct.pack("<II", ROWS, COLS) + struct.pack("<%df" % len(v), *v)


def al3d():
    """Alicona AL3D: the 17-byte magic, 52-byte tags (20-byte key, 30-byte value, CR LF; Version
    and TagCount first), a 256-byte comment ending in CR LF, then f32 depths in metres, each row
    padded to 8 bytes; 3e15 as f32 = not measured (src/io/scan/al3d.rs)."""
    stride = (COLS * 4 + 7) // 8 * 8
    tags = [("Rows", ROWS), ("Cols", COLS), ("PixelSizeXMeter", "1e-06"), ("PixelSizeYMeter", "2e-06"),
            ("InvalidPixelValue", "3000000028082176.0"), ("NumberOfPlanes", 0), ("TextureImageOffset", 0)]
    offset = 17 + 52 * (3 + len(tags)) + 256
    tags.append(("DepthImageOffset", offset))
    out = b"AliconaImaging\0\r\n"
    for k, v in [("Version", 1), ("TagCount", len(tags))] + tags:
        out += struct.pack("20s30s2s", k.encode(), str(v).encode(), b"\r\n")
    out += b"seed".ljust(254, b"\0") + b"\r\n"
    for i in range(ROWS):
        row = [3e15 if (i, j) == MISSING else Z[i][j] for j in range(COLS)]
        out += struct.pack("<%df" % COLS, *row).ljust(stride, b"\0")
    return out


def tmd():
    """TrueMap TMD v2.0: the 32-byte magic, a NUL-terminated comment, columns and rows (u32), x and
    y length, x and y offset (f32 mm), f32 heights in mm row by row; NaN = not measured
    (src/io/scan/tmd.rs)."""
    v = [float("nan") if (k // COLS, k % COLS) == MISSING else x * 1e3 for k, x in enumerate(flat())]
    return (b"Binary TrueMap Data File v2.0\r\n\0" + b"seed\0" + struct.pack("<II", COLS, ROWS)
            + struct.pack("<ffff", COLS * 1e-3, ROWS * 2e-3, 0.0, 0.0) + struct.pack("<%df" % len(v), *v))


def npy(descr, shape, fmt, vals):
    head = "{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, shape)
    head += " " * (63 - (len(head) + 10) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(head)) + head.encode() + struct.pack(fmt, *vals)


def exr():
    """Uncompressed scanline OpenEXR, one FLOAT channel "Z" (OpenEXR file layout document)."""
    def attr(name, typ, data):
        return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(data)) + data
    chlist = b"Z\0" + struct.pack("<iB3xii", 2, 0, 1, 1) + b"\0"
    box = struct.pack("<4i", 0, 0, COLS - 1, ROWS - 1)
    head = b"\x76\x2f\x31\x01" + struct.pack("<i", 2)
    head += attr("channels", "chlist", chlist) + attr("compression", "compression", b"\0")
    head += attr("dataWindow", "box2i", box) + attr("displayWindow", "box2i", box)
    head += attr("lineOrder", "lineOrder", b"\0") + attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
    head += attr("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0))
    head += attr("screenWindowWidth", "float", struct.pack("<f", 1.0)) + b"\0"
    start = len(head) + 8 * ROWS
    lines = [struct.pack("<ii", i, 4 * COLS) + struct.pack("<%df" % COLS, *Z[i]) for i in range(ROWS)]
    offsets = []
    for line in lines:
        offsets.append(start)
        start += len(line)
    return head + struct.pack("<%dQ" % ROWS, *offsets) + b"".join(lines)


def gwy():
    """Gwyddion native: GWYP, a GwyContainer holding /0/data and /0/mask GwyDataFields
    (src/io/scan/gwy.rs); the non-measured point is under the mask."""
    def obj(name, comps):
        body = b"".join(comps)
        return name.encode() + b"\0" + struct.pack("<I", len(body)) + body

    def comp(name, kind, value):
        return name.encode() + b"\0" + kind + value

    def unit(u):
        return obj("GwySIUnit", [comp("unitstr", b"s", u.encode() + b"\0")])

    def field(vals, z):
        return obj("GwyDataField", [
            comp("xres", b"i", struct.pack("<i", COLS)), comp("yres", b"i", struct.pack("<i", ROWS)),
            comp("xreal", b"d", struct.pack("<d", 6e-6)), comp("yreal", b"d", struct.pack("<d", 5e-6)),
            comp("si_unit_xy", b"o", unit("m")), comp("si_unit_z", b"o", unit(z)),
            comp("data", b"D", struct.pack("<I", len(vals)) + struct.pack("<%dd" % len(vals), *vals))])
    mask = [1.0 if (i, j) == MISSING else 0.0 for i in range(ROWS) for j in range(COLS)]
    return b"GWYP" + obj("GwyContainer", [
        comp("/0/data", b"o", field(flat(), "m")), comp("/0/data/title", b"s", b"seed\0"),
        comp("/0/mask", b"o", field(mask, ""))])


def main():
    out = sys.argv[1]
    put(out, "gsf", "seed.gsf", gsf())
    put(out, "sdf_binary", "u16_header_i16.sdf", sdf_binary(False))
    put(out, "sdf_binary", "u32_header_f64_nan.sdf", sdf_binary(True))
    put(out, "sdf_ascii", "seed_bad.sdf", sdf_ascii())
    put(out, "sur", "int16.sur", sur(16))
    put(out, "sur", "int32.sur", sur(32))
    put(out, "metropro", "format2.dat", metropro())
    put(out, "opd", "f32.opd", opd(4))
    put(out, "opd", "i16.opd", opd(2))
    put(out, "plu", "topography.plu", plu())
    put(out, "gwy", "masked.gwy", gwy())
    put(out, "al3d", "seed.al3d", al3d())
    put(out, "tmd", "seed.tmd", tmd())
    put(out, "exr", "float_z.exr", exr())
    v = flat()
    put(out, "npy", "f8_2d.npy", npy("<f8", "(%d, %d)" % (ROWS, COLS), "<%dd" % len(v), v))
    put(out, "npy", "f4_3d.npy", npy("<f4", "(%d, %d, 1)" % (ROWS, COLS), "<%df" % len(v), v))
    put(out, "npy", "u2_2d.npy", npy("<u2", "(%d, %d)" % (ROWS, COLS), "<%dH" % len(v), [round(x * 1e9) for x in v]))


if __name__ == "__main__":
    main()
