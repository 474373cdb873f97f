#!/usr/bin/env python3
"""Cramér–Rao bound of the paper's cylinder under each level model.

An independent formulation (numpy, its own Airy reflectance, numerical
derivatives; nothing from irid) of what the data can tell when the image
shares an unknown level: every pixel has its own thickness and angle, the
image one film index and the level's parameters. The Fisher information
is assembled per pixel and the pixels' own parameters eliminated (Schur
complement), which gives the covariance of the image-wide parameters; a
pixel's thickness error is then its own noise plus the shared error those
parameters leave (the same for every pixel of one image, so it does not
average out). The printed "expected MAE" is the mean |Δd| over pixels
that an efficient estimator reaches, averaged over noise realisations;
its median and 90th percentile over images show how much one image's
value scatters.

    python3 tools/level_crb.py            # the scene of tests/estimate_trust.rs

The cylinder: MgF2-like film n = 1.37 on n = 1.60, 420 → 560 nm across
140 columns, 10° → 42.5° down 14 rows, s-polarised, 31 bands 400–700 nm,
σ = 0.001; data y_k = g_k·R_k + o_k.
"""
import math

import numpy as np

LAM = np.arange(400.0, 701.0, 10.0)
NB = len(LAM)
N1, N2, N3 = 1.0, 1.37, 1.60
W, H, SIGMA = 140, 14, 0.001


def airy_s(d, theta_deg, n2):
    """s-polarised reflectance of one film (ambient / film / substrate)."""
    s = math.sin(math.radians(theta_deg))
    c1 = math.cos(math.radians(theta_deg))
    c2 = math.sqrt(1 - (N1 * s / n2) ** 2)
    c3 = math.sqrt(1 - (N1 * s / N3) ** 2)
    r12 = (N1 * c1 - n2 * c2) / (N1 * c1 + n2 * c2)
    r23 = (n2 * c2 - N3 * c3) / (n2 * c2 + N3 * c3)
    cd = np.cos(4 * math.pi * n2 * d * c2 / LAM)
    return (r12**2 + r23**2 + 2 * r12 * r23 * cd) / (1 + (r12 * r23) ** 2 + 2 * r12 * r23 * cd)


def per_band_gain(amp):
    """The per-band gain errors of tests/estimate_trust.rs."""
    return np.array([1 + amp * (((k * 37 + 11) % 13) / 6 - 1) for k in range(NB)])


def level_columns(model, r):
    """∂y/∂(level parameters) at the level's value (gain g multiplies r)."""
    one = np.ones(NB)
    eye = np.eye(NB)
    kk = (1 / LAM - 1 / 550) * 550
    cols = {
        "none": [],
        "gain": [r],
        "offset": [one],
        "gain+offset": [r, one],
        "smooth (quadratic gain, offset)": [r, r * kk, r * kk * kk, one],
        "gain per band": [eye[k] * r for k in range(NB)],
        "gain and offset per band": [eye[k] * r for k in range(NB)] + [eye[k] for k in range(NB)],
    }[model]
    return cols


def bound(model, gain, rng):
    """(expected, median, p90) MAE of an efficient estimator, nm."""
    nglob = 1 + len(level_columns(model, np.zeros(NB)))
    c = np.zeros((nglob, nglob))
    blocks = []
    for row in range(H):
        th = 10 + 2.5 * row
        for col in range(W):
            d = 420 + 140 * col / (W - 1)
            f = lambda d=d, th=th, n=N2: gain * airy_s(d, th, n)
            jd = (f(d=d + 1e-3) - f(d=d - 1e-3)) / 2e-3
            jt = (f(th=th + 1e-4) - f(th=th - 1e-4)) / 2e-4
            jn = (f(n=N2 + 1e-6) - f(n=N2 - 1e-6)) / 2e-6
            j = np.stack([jd, jt], 1)
            k = np.stack([jn] + level_columns(model, f()), 1)
            a, b = j.T @ j, j.T @ k
            blocks.append((a, b))
            c += k.T @ k
    s = c.copy()
    for a, b in blocks:
        s -= b.T @ np.linalg.solve(a, b)
    cov = SIGMA**2 * np.linalg.inv(s)
    sens = np.array([-np.linalg.solve(a, b)[0] for a, b in blocks])
    local = np.array([SIGMA * math.sqrt(np.linalg.inv(a)[0, 0]) for a, _ in blocks])
    chol = np.linalg.cholesky(cov)

    erf = np.frompyfunc(math.erf, 1, 1)

    def mean_abs(bias, sd):
        # E|x| for x ~ N(bias, sd²).
        z = bias / (sd * math.sqrt(2))
        return sd * math.sqrt(2 / math.pi) * np.exp(-z * z) + bias * erf(z).astype(float)

    draws = chol @ rng.standard_normal((nglob, 2000))
    maes = np.array([np.mean(mean_abs(sens @ g, local)) for g in draws.T])
    return maes.mean(), np.median(maes), np.percentile(maes, 90)


def main():
    rng = np.random.default_rng(1)
    cases = [
        ("clean", np.ones(NB), ["none", "gain"]),
        ("white reference 5 % high", np.full(NB, 1 / 1.05), ["gain", "gain+offset", "smooth (quadratic gain, offset)"]),
        ("white reference 8 % low", np.full(NB, 1 / 0.92), ["gain", "gain+offset"]),
        ("white reference 5 % low", np.full(NB, 1 / 0.95), ["gain", "gain+offset", "smooth (quadratic gain, offset)"]),
        ("stray light +0.004", np.ones(NB), ["offset", "gain+offset", "smooth (quadratic gain, offset)"]),
        ("per-band gain ±6 %", per_band_gain(0.06), ["gain per band", "gain and offset per band"]),
    ]
    print("| data | level model (film index unknown too) | expected MAE | median | p90 |")
    print("|---|---|---|---|---|")
    for label, gain, models in cases:
        for model in models:
            mean, med, p90 = bound(model, gain, rng)
            print(f"| {label} | {model} | {mean:.3f} nm | {med:.3f} nm | {p90:.3f} nm |")


if __name__ == "__main__":
    main()
