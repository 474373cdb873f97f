"""Independent thin-film renderer (characteristic matrix, Macleod convention N = n - ik).
Supports multilayers, absorbing layers, oblique incidence, s/p/unpolarised,
incoherent substrate backside, thickness spread, passband, wavelength shift."""
import numpy as np, yaml, os

def nk_from_yml(path, wl_nm):
    d = yaml.safe_load(open(path))
    wl_um = np.asarray(wl_nm, float) / 1000.0
    n = np.zeros_like(wl_um); k = np.zeros_like(wl_um); got_n = False
    for ent in d['DATA']:
        t = ent['type']
        if t.startswith('formula'):
            c = [float(x) for x in str(ent['coefficients']).split()]
            f = int(t.split()[1])
            if f == 1:
                s = 1 + c[0]
                for i in range(1, len(c), 2):
                    s = s + c[i] * wl_um**2 / (wl_um**2 - c[i+1]**2)
                n = np.sqrt(s)
            elif f == 2:
                s = 1 + c[0]
                for i in range(1, len(c), 2):
                    s = s + c[i] * wl_um**2 / (wl_um**2 - c[i+1])
                n = np.sqrt(s)
            elif f == 4:
                s = c[0]
                rest = c[1:]
                # formula 4: c0 + c1 λ^c2/(λ^2 - c3^c4) + c5 λ^c6/(λ^2-c7^c8) + c9 λ^c10 + ...
                i = 0
                for _ in range(2):
                    if i + 3 < len(rest):
                        s = s + rest[i] * wl_um**rest[i+1] / (wl_um**2 - rest[i+2]**rest[i+3]); i += 4
                while i + 1 < len(rest):
                    s = s + rest[i] * wl_um**rest[i+1]; i += 2
                n = np.sqrt(s)
            elif f == 5:
                s = c[0]
                for i in range(1, len(c), 2):
                    s = s + c[i] * wl_um**c[i+1]
                n = s
            else:
                raise ValueError('formula %d' % f)
            got_n = True
        elif t == 'tabulated nk':
            a = np.array([[float(x) for x in l.split()] for l in ent['data'].strip().splitlines()])
            n = np.interp(wl_um, a[:, 0], a[:, 1]); k = np.interp(wl_um, a[:, 0], a[:, 2]); got_n = True
        elif t == 'tabulated n':
            a = np.array([[float(x) for x in l.split()] for l in ent['data'].strip().splitlines()])
            n = np.interp(wl_um, a[:, 0], a[:, 1]); got_n = True
        elif t == 'tabulated k':
            a = np.array([[float(x) for x in l.split()] for l in ent['data'].strip().splitlines()])
            k = np.interp(wl_um, a[:, 0], a[:, 1])
    return n - 1j * k

def _ncos(N, n0sin):
    q = np.sqrt(N * N - n0sin * n0sin + 0j)
    # choose branch: Re>0, or decaying (Im<0 in Macleod convention)
    q = np.where((q.real < 0) | ((np.abs(q.real) < 1e-12) & (q.imag > 0)), -q, q)
    return q

def stack_r(wl, n0, layers, nsub, theta_deg, pol):
    """layers: list of (N(wl) array or scalar, d_nm) from ambient side. returns complex r (amplitude)"""
    wl = np.asarray(wl, float)
    n0 = np.asarray(n0 + 0j) * np.ones_like(wl)
    n0sin = n0 * np.sin(np.radians(theta_deg))
    def eta(N):
        N = np.asarray(N + 0j) * np.ones_like(wl)
        q = _ncos(N, n0sin)  # N cos theta
        if pol == 's':
            return q, q
        else:
            return q, N * N / q  # N/cos = N^2/(N cos)
    q0, e0 = eta(n0)
    qs, es = eta(nsub)
    B = np.ones_like(wl, complex); C = es.copy()
    for N, d in reversed(layers):
        q, e = eta(N)
        delta = 2 * np.pi * q * d / wl
        c, s = np.cos(delta), np.sin(delta)
        B, C = c * B + 1j * s / e * C, 1j * e * s * B + c * C
    return (e0 * B - C) / (e0 * B + C)

def R_coh(wl, n0, layers, nsub, theta_deg, pol):
    if pol in ('s', 'p'):
        return np.abs(stack_r(wl, n0, layers, nsub, theta_deg, pol))**2
    w = 0.5 if pol == 'u' else float(pol)
    return w * R_coh(wl, n0, layers, nsub, theta_deg, 's') + (1 - w) * R_coh(wl, n0, layers, nsub, theta_deg, 'p')

def R_backside(wl, n0, layers, nsub, theta_deg, pol, n_back=1.0):
    """Coherent film stack on a thick transparent substrate, incoherent backside reflection into n_back."""
    if pol not in ('s', 'p'):
        w = 0.5 if pol == 'u' else float(pol)
        return w * R_backside(wl, n0, layers, nsub, theta_deg, 's', n_back) + (1 - w) * R_backside(wl, n0, layers, nsub, theta_deg, 'p', n_back)
    Rf = R_coh(wl, n0, layers, nsub, theta_deg, pol)
    Tf = 1 - Rf  # lossless films assumed
    nsub_r = np.real(np.asarray(nsub) * np.ones_like(np.asarray(wl, float)))
    th_s = np.degrees(np.arcsin(n0 * np.sin(np.radians(theta_deg)) / nsub_r))
    Rb = np.array([R_coh(np.array([w_]), ns_, [], n_back, t_, pol)[0] for w_, ns_, t_ in zip(wl, nsub_r, th_s)])
    Rf_back = Rf  # lossless stack: same reflectance from both sides
    return Rf + Tf * Tf * Rb / (1 - Rf_back * Rb)

def rough(fn, d, sd, npts=21):
    """average fn(d') over Gaussian spread of thickness"""
    x, w = np.polynomial.hermite_e.hermegauss(npts)
    w = w / w.sum()
    return sum(wi * fn(d + sd * xi) for xi, wi in zip(x, w))

def passband(fn, wl, fwhm, npts=15):
    x, w = np.polynomial.hermite_e.hermegauss(npts)
    w = w / w.sum(); sd = fwhm / 2.3548
    return sum(wi * fn(wl + sd * xi) for xi, wi in zip(x, w))

def write_table(path, wl, cols, names, fmt='%.7g'):
    with open(path, 'w') as f:
        f.write('wavelength_nm,' + ','.join(names) + '\n')
        for i, w in enumerate(wl):
            f.write(('%.4f' % w) + ',' + ','.join(('nan' if not np.isfinite(c[i]) else fmt % c[i]) for c in cols) + '\n')
