# README claim check: 15 nm n=2.3 interlayer, films 120-2500 nm on n=2.0, 400-800 @2 nm, sigma 0.001, normal incidence
import numpy as np, sys
sys.path.insert(0, __import__('os').path.dirname(__import__('os').path.abspath(__file__)))
from harness import run_case, show
import render
wl = np.arange(400, 801, 2.0)
for seed in range(2):
    rng = np.random.default_rng(500 + seed)
    ds = np.sort(rng.uniform(120, 2500, 30))
    for il in [5, 10, 15]:
        R = np.array([render.R_coh(wl, 1.0, [(1.46, d), (2.3, il)], 2.0, 0, 'u') for d in ds])
        for var, vargs in [('def', []), ('eps0', ['--reflectance-accuracy', 0]), ('eps0_abs', ['--reflectance-accuracy', 0, '--level', 'absolute']), ('eps0_abs_sig', ['--reflectance-accuracy', 0, '--level', 'absolute', '--noise-sigma', 0.001])]:
            res, _ = run_case(f'c2b_il{il}_{var}_s{seed}', wl, R, ds, ['--n3', 2.0, '--n2', 1.46, '--theta-deg', 0, '--pol', 'u'] + vargs, sigma=0.001, seed=seed)
            show(res)
