# Class 3: calibration errors (gain / offset) with --level auto|absolute|scaled
import numpy as np, sys
sys.path.insert(0, __import__('os').path.dirname(__import__('os').path.abspath(__file__)))
from harness import run_case, show
import render
wl61 = np.arange(400, 701, 5.0)
N = 30; N2, N3 = 1.46, 2.0
def gain_fn(kind, wl, rng):
    if kind == 'g0.9': return 0.9 * np.ones_like(wl), 0
    if kind == 'g1.1': return 1.1 * np.ones_like(wl), 0
    if kind == 'g0.95': return 0.95 * np.ones_like(wl), 0
    if kind == 'gsmooth': return 1 + 0.08 * ((wl - 550) / 150) ** 2 - 0.04, 0
    if kind == 'gband': return 1 + rng.uniform(-0.06, 0.06, wl.size), 0
    if kind == 'o+0.01': return np.ones_like(wl), 0.01
    if kind == 'o-0.01': return np.ones_like(wl), -0.01
    if kind == 'o+0.004': return np.ones_like(wl), 0.004
    if kind == 'g1.05o+0.005': return 1.05 * np.ones_like(wl), 0.005
    if kind == 'g0.93o-0.005': return 0.93 * np.ones_like(wl), -0.005
    if kind == 'g0.97': return 0.97 * np.ones_like(wl), 0
for th, pol in [(0, 'u'), (30, 's')]:
  for kind in ['g0.9', 'g0.95', 'g0.97', 'g1.1', 'gsmooth', 'gband', 'o+0.01', 'o-0.01', 'o+0.004', 'g1.05o+0.005', 'g0.93o-0.005']:
    for seed in range(2):
        rng = np.random.default_rng(300 + seed)
        ds = np.sort(rng.uniform(50, 2500, N))
        g, o = gain_fn(kind, wl61, rng)
        R = np.array([render.R_coh(wl61, 1.0, [(N2, d)], N3, th, pol) for d in ds]) * g + o
        for who, args in [('known', ['--n2', N2, '--theta-deg', th]), ('n2unk', ['--theta-deg', th]), ('thunk', ['--n2', N2]), ('both', [])]:
            for lev in ['auto', 'absolute', 'scaled']:
                for var, vargs in [('def', []), ('eps0', ['--reflectance-accuracy', 0])]:
                    tag = f'c3_th{th}{pol}_{kind}_{who}_{lev}_{var}_s{seed}'
                    res, _ = run_case(tag, wl61, R, ds, ['--n3', N3, '--pol', pol, '--level', lev] + args + vargs, sigma=0.001, seed=seed)
