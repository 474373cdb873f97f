#!/usr/bin/env python3
"""Regenerate tests/fixtures/envi: small ENVI files, valid, invalid and
damaged, and the manifest `expected.txt` that tests/io_envi.rs checks.

Every data file holds a 4 x 3 x 5 cube (samples x lines x bands) whose
stored value at (sample s, line l, band b) is 1 + s + 4*l + 12*b, so a
valid fixture reads back as that value divided by its scale factor.
Only the standard library is used.
"""
import os
import struct

S, L, B = 4, 3, 5
HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..", "tests", "fixtures", "envi")


def value(s, l, b):
    return 1 + s + 4 * l + 12 * b


def order(interleave):
    if interleave == "bsq":
        return [(s, l, b) for b in range(B) for l in range(L) for s in range(S)]
    if interleave == "bil":
        return [(s, l, b) for l in range(L) for b in range(B) for s in range(S)]
    return [(s, l, b) for l in range(L) for s in range(S) for b in range(B)]


FMT = {1: "B", 2: "h", 4: "f", 5: "d", 12: "H"}


def data(dtype, interleave, big, offset=0):
    e = ">" if big else "<"
    out = b"\x00" * offset
    for s, l, b in order(interleave):
        out += struct.pack(e + FMT[dtype], value(s, l, b))
    return out


def header(dtype, interleave, big, offset=0, extra="", wl=None):
    wl = wl or "wavelength units = Nanometers\nwavelength = {400, 450, 500, 550, 600}\n"
    return (
        f"ENVI\nsamples = {S}\nlines = {L}\nbands = {B}\nheader offset = {offset}\n"
        f"file type = ENVI Standard\ndata type = {dtype}\ninterleave = {interleave}\n"
        f"byte order = {1 if big else 0}\n{wl}{extra}"
    )


def put(sub, name, hdr_text, payload, data_ext="img"):
    d = os.path.join(ROOT, sub)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name + ".hdr"), "w", encoding="utf-8") as f:
        f.write(hdr_text)
    if payload is not None:
        data_name = name if data_ext == "" else f"{name}.{data_ext}"
        with open(os.path.join(d, data_name), "wb") as f:
            f.write(payload)


manifest = []


def ok(sub, name, scale, **kw):
    manifest.append(f"{sub}/{name}.hdr\tok {scale}")


def err(sub, name, fragment):
    manifest.append(f"{sub}/{name}.hdr\terror {fragment}")


# --- valid -----------------------------------------------------------------
# Spectral Python style: multi-line description, micrometres, big-endian u16 BIP.
spy = (
    "ENVI\ndescription = {\n  Spectral Python fixture,\n  two lines}\n"
    f"samples = {S}\nlines = {L}\nbands = {B}\nheader offset = 0\nfile type = ENVI Standard\n"
    "data type = 12\ninterleave = bip\nbyte order = 1\n"
    "wavelength units = Micrometers\nwavelength = {\n 0.400, 0.450,\n 0.500, 0.550, 0.600}\n"
    "fwhm = {0.01, 0.01, 0.01, 0.01, 0.01}\nreflectance scale factor = 1000\n"
)
put("valid", "spy_u16_bip_be", spy, data(12, "bip", True))
ok("valid", "spy_u16_bip_be", 1000)
# ENVI style: upper-case keys, comments, header offset, i16 BIL, data file `.bil`.
envi = (
    "ENVI\n; written by hand in the style of ENVI 5\nDescription = {i16 bil fixture}\n"
    f"Samples = {S}\nLines   = {L}\nBands = {B}\nHeader Offset = 16\nFile Type = ENVI Standard\n"
    "Data Type = 2\nInterleave = BIL\nByte Order = 0\nWavelength Units = nm\n"
    "Wavelength = { 400.0 , 450.0 , 500.0 , 550.0 , 600.0 }\nReflectance Scale Factor = 100\n"
)
put("valid", "envi_i16_bil_offset", envi, data(2, "bil", False, 16), "bil")
ok("valid", "envi_i16_bil_offset", 100)
# Plain f32 BSQ, data file without extension.
put("valid", "f32_bsq_noext", header(4, "bsq", False), data(4, "bsq", False), "")
ok("valid", "f32_bsq_noext", 1)
# u8 and f64, either byte order.
put("valid", "u8_bip", header(1, "bip", False, extra="reflectance scale factor = 255\n"), data(1, "bip", False))
ok("valid", "u8_bip", 255)
put("valid", "f64_bil_be", header(5, "bil", True), data(5, "bil", True), "raw")
ok("valid", "f64_bil_be", 1)

# --- invalid: a well-formed data file, a bad header -------------------------
good = data(4, "bsq", False)
cases = [
    ("bad_interleave", header(4, "bsx", False), "field `interleave`: unknown value \"bsx\""),
    ("no_magic", header(4, "bsq", False)[5:], "not an ENVI header"),
    ("missing_samples", header(4, "bsq", False).replace(f"samples = {S}\n", ""), "field `samples`: missing"),
    ("zero_lines", header(4, "bsq", False).replace(f"lines = {L}", "lines = 0"), "field `lines`: not a positive integer"),
    ("complex_type", header(6, "bsq", False), "field `data type`: type 6 is not supported"),
    ("byte_order_2", header(4, "bsq", False).replace("byte order = 0", "byte order = 2"), "field `byte order`: must be 0 or 1"),
    ("wavelength_count", header(4, "bsq", False, wl="wavelength = {400, 450, 500}\n"), "field `wavelength`: has 3 values but `bands` = 5"),
    ("wavelength_text", header(4, "bsq", False, wl="wavelength = {400, 450, abc, 550, 600}\n"), "field `wavelength`: value 3 is not a number"),
    ("unclosed_brace", header(4, "bsq", False, wl="wavelength = {400, 450,\n500, 550, 600\n"), "field `wavelength`: `{` is never closed"),
    ("bad_units", header(4, "bsq", False, wl="wavelength units = furlongs\nwavelength = {1,2,3,4,5}\n"), "field `wavelength units`: unknown value"),
    ("zero_scale", header(4, "bsq", False, extra="reflectance scale factor = 0\n"), "field `reflectance scale factor`: must be positive"),
    ("no_wavelength", header(4, "bsq", False, wl="\n"), "field `wavelength`: missing"),
    ("no_equals", header(4, "bsq", False, extra="just some words\n"), "expected `key = value`"),
    ("huge_dims", header(4, "bsq", False).replace(f"samples = {S}", "samples = 18446744073709551615"), "too large"),
]
for name, text, frag in cases:
    put("invalid", name, text, good)
    err("invalid", name, frag)

# --- damaged: a good header, a bad data file ---------------------------------
put("damaged", "short_data", header(4, "bsq", False), good[:-7])
err("damaged", "short_data", "data file too short")
put("damaged", "offset_past_end", header(4, "bsq", False, offset=len(good)), good)
err("damaged", "offset_past_end", "data file too short")
put("damaged", "empty_data", header(4, "bsq", False), b"")
err("damaged", "empty_data", "data file too short")
put("damaged", "no_data_file", header(4, "bsq", False), None)
err("damaged", "no_data_file", "no data file beside the header")
d = os.path.join(ROOT, "damaged")
with open(os.path.join(d, "binary_header.hdr"), "wb") as f:
    f.write(bytes(range(256)) * 4)
with open(os.path.join(d, "binary_header.img"), "wb") as f:
    f.write(good)
err("damaged", "binary_header", "not an ENVI header")

with open(os.path.join(ROOT, "expected.txt"), "w", encoding="utf-8") as f:
    f.write("# fixture\texpected outcome (`ok SCALE`, or `error` and a fragment of the message)\n")
    f.write("# regenerate with tools/make_envi_fixtures.py\n")
    f.write("\n".join(manifest) + "\n")
