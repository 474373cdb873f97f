#!/usr/bin/env python3
"""Cross-check irid's ENVI files with Spectral Python (not used by tests).

    pip install spectral numpy
    tools/envi_crosscheck.py cube.hdr [more.hdr ...]
    tools/envi_crosscheck.py --write spy.hdr   # a cube written by SPy, for `irid fit`

For each header, reads the cube with `spectral.envi.open`, prints its shape,
interleave, data type and band centres, and the value at the first pixel of
every band after SPy applies the `reflectance scale factor` — what
`irid fit` should read (for the fixtures: (1 + 12 b) / scale). With `--write`, writes a small u16 BIL cube through SPy's own
writer so irid's reader can be checked against it.
"""
import sys

import numpy as np
import spectral.io.envi as envi


def show(path):
    img = envi.open(path)
    meta = img.metadata
    # SPy applies the `reflectance scale factor` itself when loading.
    arr = img.load()
    first = np.asarray(arr[0, 0, :], dtype=np.float64).ravel()
    print(f"{path}: {img.ncols} x {img.nrows} x {img.nbands} bands, "
          f"interleave {meta.get('interleave')}, data type {meta.get('data type')}, "
          f"byte order {meta.get('byte order')}")
    print("  wavelengths:", meta.get("wavelength"), meta.get("wavelength units"))
    print("  pixel (0, 0):", " ".join(repr(float(v)) for v in first))


def write(path):
    rows, cols, bands = 3, 4, 5
    data = np.fromfunction(lambda r, c, b: 1 + c + 4 * r + 12 * b, (rows, cols, bands))
    meta = {
        "wavelength": [400, 450, 500, 550, 600],
        "wavelength units": "Nanometers",
        "fwhm": [10] * 5,
        "reflectance scale factor": 1000,
    }
    envi.save_image(path, data.astype(np.uint16), interleave="bil", metadata=meta,
                    force=True, ext=".img")
    print("wrote", path)


if __name__ == "__main__":
    args = sys.argv[1:]
    if args[:1] == ["--write"]:
        write(args[1])
    else:
        for p in args:
            show(p)
