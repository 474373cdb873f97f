# Class 1b: thin films (5-300 nm), angle/index unknown, several seeds
import numpy as np, sys
sys.path.insert(0, __import__('os').path.dirname(__import__('os').path.abspath(__file__)))
from harness import run_case, show
import render
wl61 = np.arange(400, 701, 5.0); wl31 = np.linspace(420, 560, 31); wld = np.arange(400, 801, 2.0)
tot = {}
for gname, wl in [('61b', wl61), ('31b', wl31), ('d2', wld)]:
  for n2, n3 in [(1.46, 3.88), (2.0, 1.52), (1.38, 1.6)]:
    for th, pol in [(0, 'u'), (45, 's'), (45, 'p'), (45, 'u'), (65, 'p')]:
      for seed in range(2):
        rng = np.random.default_rng(100 + seed)
        ds = np.sort(rng.uniform(5, 300, 40)); thetas = np.full(40, th)
        R = np.array([render.R_coh(wl, 1.0, [(n2, d)], n3, t, pol) for d, t in zip(ds, thetas)])
        for kind, args in [('known', ['--n2', n2, '--theta-deg', th]), ('thunk', ['--n2', n2]), ('n2unk', ['--theta-deg', th]), ('both', [])]:
            tag = f'c1t_{gname}_n{n2}_{n3}_th{th}{pol}_{kind}_s{seed}'
            res, _ = run_case(tag, wl, R, ds, ['--n3', n3, '--pol', pol] + args, sigma=0.001, seed=seed)
            show(res)
