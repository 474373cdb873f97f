# Variants on the worst class-1 thin-film cases: eps=0, modes, levels
import numpy as np, sys
sys.path.insert(0, __import__('os').path.dirname(__import__('os').path.abspath(__file__)))
from harness import run_case, show
import render
wl61 = np.arange(400, 701, 5.0); wl31 = np.linspace(420, 560, 31); wld = np.arange(400, 801, 2.0)
cases = [('61b', wl61, 1.46, 3.88, 45, 'u'), ('61b', wl61, 1.38, 1.6, 45, 's'), ('d2', wld, 1.38, 1.6, 65, 'p'), ('61b', wl61, 1.46, 3.88, 65, 'p'), ('61b', wl61, 2.0, 1.52, 45, 's'), ('31b', wl31, 1.46, 3.88, 45, 's')]
for gname, wl, n2, n3, th, pol in cases:
    for seed in range(2):
        rng = np.random.default_rng(100 + seed)
        ds = np.sort(rng.uniform(5, 300, 40)); thetas = np.full(40, th)
        R = np.array([render.R_coh(wl, 1.0, [(n2, d)], n3, t, pol) for d, t in zip(ds, thetas)])
        for kind, args in [('thunk', ['--n2', n2]), ('both', [])]:
            for var, vargs in [('eps0', ['--reflectance-accuracy', 0]), ('eps0.02', ['--reflectance-accuracy', 0.02]), ('accurate', ['--mode', 'accurate']), ('fast', ['--mode', 'fast']), ('abs', ['--level', 'absolute']), ('eps0_sig', ['--reflectance-accuracy', 0, '--noise-sigma', 0.001])]:
                tag = f'c1v_{gname}_n{n2}_{n3}_th{th}{pol}_{kind}_{var}_s{seed}'
                res, _ = run_case(tag, wl, R, ds, ['--n3', n3, '--pol', pol] + args + vargs, sigma=0.001, seed=seed)
