import numpy as np, subprocess, csv, json, os, time, sys
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import render
# The binary under test and where the tables and results go.
IRID = os.environ.get('IRID', 'target/release/irid')
OUT = os.environ.get('REDTEAM_OUT', '/tmp/irid-redteam')
CASES = os.path.join(OUT, 'cases')
RESULTS = os.path.join(OUT, 'results.jsonl')
os.makedirs(CASES, exist_ok=True)

def run_case(tag, wl, R, truth_d, args, sigma=0.001, seed=0, transform=None, extra_note='', timeout=120, write_fmt='%.7g', no_noise=False):
    """R: array (nspec, nbands) of clean reflectance. truth_d: per spectrum thickness.
    args: list of extra irid args. transform: fn(noisy R)-> data written."""
    rng = np.random.default_rng(seed)
    Y = R + (0 if no_noise else rng.normal(0, sigma, R.shape))
    if transform is not None:
        Y = transform(Y)
    names = ['s%03d_d%.1f' % (i, d) for i, d in enumerate(truth_d)]
    inp = os.path.join(CASES, tag + '.csv'); out = os.path.join(CASES, tag + '.out.csv')
    render.write_table(inp, wl, list(Y), names, write_fmt)
    if os.path.exists(out): os.remove(out)
    cmd = ['/usr/bin/time', '-f', 'MAXRSS_KB=%M', IRID, 'fit', inp, '--out', out, '--threads', '1', '--json'] + [str(a) for a in args]
    t0 = time.time()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        rc = p.returncode; so, se = p.stdout, p.stderr
    except subprocess.TimeoutExpired:
        rc = 'TIMEOUT'; so = se = ''
    el = time.time() - t0
    rss = None
    for l in se.splitlines():
        if l.startswith('MAXRSS_KB='): rss = int(l.split('=')[1])
    res = dict(tag=tag, n=len(truth_d), rc=rc, elapsed=round(el, 2), rss_kb=rss, cmd=' '.join(cmd[3:]), note=extra_note)
    if 'panick' in se or 'panic' in se: res['panic'] = True
    js = None
    for l in so.splitlines():
        if l.startswith('{'):
            try: js = json.loads(l)
            except Exception: pass
    res['json'] = js
    if rc != 0 or not os.path.exists(out):
        res['stderr_tail'] = se[-800:]
        res.update(valid=0, vw=0, flagged=0)
        with open(RESULTS, 'a') as f: f.write(json.dumps(res) + '\n')
        return res, None
    rows = list(csv.DictReader(open(out)))
    valid = vw = flagged = 0; reasons = {}; bad = []
    for row, d in zip(rows, truth_d):
        rsn = int(row['reason']); reasons[rsn] = reasons.get(rsn, 0) + 1
        if rsn in (0, 8) and row['valid'] == '1':
            valid += 1
            t = float(row['thickness_nm']); s = float(row['sigma_thickness_nm'])
            if not np.isfinite(t) or abs(t - d) > max(3 * s, 2.0):
                vw += 1; bad.append((row['name'], d, t, s, rsn, row['n_film'], row['theta_deg']))
        else:
            flagged += 1
    res.update(valid=valid, vw=vw, flagged=flagged, reasons=reasons, bad=bad[:6])
    with open(RESULTS, 'a') as f: f.write(json.dumps(res) + '\n')
    return res, rows

def show(res):
    js = res.get('json') or {}
    extra = ' n_film=%s level=%s noise=%s' % (js.get('n_film'), js.get('level'), js.get('noise_sigma'))
    s = '%-40s n=%d valid=%d VW=%d flagged=%d reasons=%s rc=%s t=%.1fs rss=%sMB%s' % (res['tag'], res['n'], res['valid'], res['vw'], res['flagged'], res.get('reasons'), res['rc'], res['elapsed'], (res['rss_kb'] or 0)//1024, extra)
    print(s)
    for b in res.get('bad', [])[:4]:
        print('     VW: %s truth=%.1f irid=%.2f sigma=%.2f reason=%d n=%s th=%s' % b)
    if res['rc'] != 0: print('   stderr:', res.get('stderr_tail', '')[-400:])
    sys.stdout.flush()
