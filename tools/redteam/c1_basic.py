# Class 1: correct single-film physics, varied conditions
import numpy as np, sys
sys.path.insert(0, __import__('os').path.dirname(__import__('os').path.abspath(__file__)))
from harness import run_case, show
import render
rng = np.random.default_rng(1)
grids = {'31b': np.arange(420, 561, 4.6667)[:31], '61b': np.arange(400, 701, 5.0), 'dense1': np.arange(400, 801, 1.0)}
grids['31b'] = np.linspace(420, 560, 31)
def batch(tag, wl, n2, n3, thetas, pol, ds, args, sigma=0.001, seed=0, **kw):
    R = np.array([render.R_coh(wl, 1.0, [(n2, d)], n3, th, pol) for d, th in zip(ds, thetas)])
    res, _ = run_case(tag, wl, R, ds, args, sigma=sigma, seed=seed, **kw); show(res); return res
which = sys.argv[1] if len(sys.argv) > 1 else 'all'
N = 30
for gname in ['31b', '61b', 'dense1']:
    wl = grids[gname]
    for th in [0, 30, 60, 80]:
        for pol in ['s', 'p', 'u']:
            if th == 0 and pol != 'u': continue
            ds = np.sort(rng.uniform(5, 3000, N))
            thetas = np.full(N, th)
            base = ['--n3', 1.6, '--pol', pol]
            # index and angle known
            batch(f'c1_{gname}_th{th}_{pol}_known', wl, 1.46, 1.6, thetas, pol, ds, base + ['--n2', 1.46, '--theta-deg', th], seed=th)
            # angle known, index unknown
            batch(f'c1_{gname}_th{th}_{pol}_n2unk', wl, 1.46, 1.6, thetas, pol, ds, base + ['--theta-deg', th], seed=th+1)
            # index known, angle unknown
            batch(f'c1_{gname}_th{th}_{pol}_thunk', wl, 1.46, 1.6, thetas, pol, ds, base + ['--n2', 1.46], seed=th+2)
