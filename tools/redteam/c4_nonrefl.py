# Class 4: non-reflectance inputs
import numpy as np, sys
sys.path.insert(0, __import__('os').path.dirname(__import__('os').path.abspath(__file__)))
from harness import run_case, show
import render
wl61 = np.arange(400, 701, 5.0); wld = np.arange(400, 801, 2.0)
N = 30; N2, N3 = 1.46, 2.0
lamp = lambda wl: np.exp(-((wl - 600) / 180) ** 2)
for gname, wl in [('61b', wl61), ('d2', wld)]:
  for seed in range(2):
    rng = np.random.default_rng(400 + seed)
    ds = np.sort(rng.uniform(50, 2500, N))
    R = np.array([render.R_coh(wl, 1.0, [(N2, d)], N3, 0, 'u') for d in ds])
    tfs = {
      'percent_noflag': (lambda Y: Y * 100, []),
      'percent_flag': (lambda Y: Y * 100, ['--percent']),
      'counts': (lambda Y: np.round(Y * 40000 * lamp(wl) + 1000), []),
      'counts_free': (lambda Y: np.round(Y * 40000 * lamp(wl) + 1000), ['--level', 'free']),
      'norm_max1': (lambda Y: (Y * lamp(wl)) / (Y * lamp(wl)).max(axis=1, keepdims=True), []),
      'norm_max1_free': (lambda Y: (Y * lamp(wl)) / (Y * lamp(wl)).max(axis=1, keepdims=True), ['--level', 'free']),
      'norm_flat_max1': (lambda Y: Y / Y.max(axis=1, keepdims=True), []),
      'neg_offset': (lambda Y: Y - 0.03, []),
      'nan_cols': (lambda Y: np.where(np.arange(Y.shape[0])[:, None] % 5 == 0, np.nan, Y), []),
      'nan_half': (lambda Y: np.where((np.arange(Y.shape[1])[None, :] % 2 == 0) & (np.arange(Y.shape[0])[:, None] % 3 == 0), np.nan, Y), []),
      'nan_blue': (lambda Y: np.where((np.arange(Y.shape[1])[None, :] < Y.shape[1] * 0.55) & (np.arange(Y.shape[0])[:, None] % 3 == 0), np.nan, Y), []),
      'zeros_cols': (lambda Y: np.where(np.arange(Y.shape[0])[:, None] % 5 == 0, 0.0, Y), []),
      'x2': (lambda Y: Y * 2, []),
      'x0.5': (lambda Y: Y * 0.5, []),
      'sqrtR': (lambda Y: np.sqrt(np.clip(Y, 0, None)), []),
      'transmission': (lambda Y: 1 - Y, []),
    }
    for name, (tf, extra) in tfs.items():
        for who, args in [('known', ['--n2', N2, '--theta-deg', 0]), ('n2unk', ['--theta-deg', 0]), ('both', [])]:
            tag = f'c4_{gname}_{name}_{who}_s{seed}'
            res, _ = run_case(tag, wl, R, ds, ['--n3', N3, '--pol', 'u'] + args + extra, sigma=0.001, seed=seed, transform=tf)
            if res['rc'] != 0: print(tag, 'rc', res['rc'], res.get('stderr_tail', '')[-300:].replace('\n', ' | '))
