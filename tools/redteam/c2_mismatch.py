# Class 2: model mismatch. Truth = film thickness (top film for stacks).
import numpy as np, sys
sys.path.insert(0, __import__('os').path.dirname(__import__('os').path.abspath(__file__)))
from harness import run_case, show
import render
wl61 = np.arange(400, 701, 5.0); wld = np.arange(400, 801, 2.0)
N = 30
def mk(wl, ds, fn):
    return np.array([fn(wl, d) for d in ds])
N2, N3 = 1.46, 2.0   # film on n=2 substrate (e.g. SiO2 on SiN-like)
def scen(name, th, pol):
    c = lambda wl, d, n2=N2, n3=N3, th=th, pol=pol, extra=(): render.R_coh(wl, 1.0, [(n2, d)] + list(extra), n3, th, pol)
    if name == 'interlayer10':   return lambda wl, d: render.R_coh(wl, 1.0, [(N2, d), (2.3, 10)], N3, th, pol)
    if name == 'interlayer3':    return lambda wl, d: render.R_coh(wl, 1.0, [(N2, d), (1.7, 3)], N3, th, pol)
    if name == 'twolayer':       return lambda wl, d: render.R_coh(wl, 1.0, [(N2, d), (1.7, 80)], N3, th, pol)
    if name == 'absorb005':      return lambda wl, d: render.R_coh(wl, 1.0, [(N2 - 0.005j, d)], N3, th, pol)
    if name == 'absorb02':       return lambda wl, d: render.R_coh(wl, 1.0, [(N2 - 0.02j, d)], N3, th, pol)
    if name == 'absorb05':       return lambda wl, d: render.R_coh(wl, 1.0, [(N2 - 0.05j, d)], N3, th, pol)
    if name == 'backside':       return lambda wl, d: render.R_backside(wl, 1.0, [(N2, d)], 1.52, th, pol)
    if name == 'roughness3':     return lambda wl, d: render.rough(lambda dd: render.R_coh(wl, 1.0, [(N2, dd)], N3, th, pol), d, 3.0)
    if name == 'roughness10':    return lambda wl, d: render.rough(lambda dd: render.R_coh(wl, 1.0, [(N2, dd)], N3, th, pol), d, 10.0)
    if name == 'bandwidth8':     return lambda wl, d: render.passband(lambda w: render.R_coh(w, 1.0, [(N2, d)], N3, th, pol), wl, 8.0)
    if name == 'wlshift1':       return lambda wl, d: render.R_coh(wl + 1.0, 1.0, [(N2, d)], N3, th, pol)
    if name == 'wlshift3':       return lambda wl, d: render.R_coh(wl + 3.0, 1.0, [(N2, d)], N3, th, pol)
    if name == 'gradient_n':     return lambda wl, d: render.R_coh(wl, 1.0, [(N2 - 0.02 + 0.04 * (i + 0.5) / 8, d / 8) for i in range(8)], N3, th, pol)
    if name == 'disp_film':      return lambda wl, d: render.R_coh(wl, 1.0, [(render.nk_from_yml(__import__('os').path.join(__import__('os').path.dirname(__import__('os').path.abspath(__file__)), '../../data/refractive-index/SiO2-Malitson.yml'), wl), d)], N3, th, pol)
    raise KeyError(name)
names = ['interlayer10', 'interlayer3', 'twolayer', 'absorb005', 'absorb02', 'absorb05', 'backside', 'roughness3', 'roughness10', 'bandwidth8', 'wlshift1', 'wlshift3', 'gradient_n', 'disp_film', 'wrong_n3_0.05', 'wrong_n3_0.15', 'wrong_n3_0.3', 'wrong_pol']
for gname, wl in [('61b', wl61), ('d2', wld)]:
  for th, pol in [(0, 'u'), (30, 's')]:
    for name in names:
      for seed in range(2):
        rng = np.random.default_rng(200 + seed)
        ds = np.sort(rng.uniform(100, 2500, N))
        n3_given = N3; pol_given = pol
        if name.startswith('wrong_n3'):
            fn = lambda wl, d: render.R_coh(wl, 1.0, [(N2, d)], N3, th, pol); n3_given = N3 + float(name.split('_')[-1])
        elif name == 'wrong_pol':
            if th == 0: continue
            fn = lambda wl, d: render.R_coh(wl, 1.0, [(N2, d)], N3, th, 'u'); pol_given = 's'
        else:
            fn = scen(name, th, pol)
        n3_arg = 1.52 if name == 'backside' else n3_given
        R = mk(wl, ds, fn)
        for kind, args in [('known', ['--n2', N2, '--theta-deg', th]), ('n2unk', ['--theta-deg', th]), ('thunk', ['--n2', N2])]:
          for var, vargs in [('def', []), ('eps0', ['--reflectance-accuracy', 0])]:
            tag = f'c2_{gname}_th{th}{pol}_{name}_{kind}_{var}_s{seed}'
            res, _ = run_case(tag, wl, R, ds, ['--n3', n3_arg, '--pol', pol_given] + args + vargs, sigma=0.001, seed=seed)
            if res['vw'] or res['rc'] != 0: show(res)
