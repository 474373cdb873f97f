"""README's table of the red team's runs: valid, and valid and wrong (off by
more than max(3σ, 2 nm)), by what the data are and what the scene gives."""
import collections, json, os

RESULTS = os.path.join(os.environ.get('REDTEAM_OUT', '/tmp/irid-redteam'), 'results.jsonl')
KIND = {'c1': 'one film, the model\'s physics', 'c1t': 'one film, the model\'s physics',
        'c1v': 'one film, the model\'s physics', 'c2': 'model mismatch', 'c2b': 'model mismatch',
        'c3': 'calibration error', 'c4': 'not reflectance'}


def given(tag):
    """What the run gave irid: both, the angle only, the index only, neither."""
    for key, what in [('_known', 'index and angle given'), ('_n2unk', 'index unknown'),
                      ('_thunk', 'angle unknown'), ('_both', 'both unknown')]:
        if key in tag:
            return what
    return 'index and angle given'


runs = {}
for line in open(RESULTS):
    r = json.loads(line)
    runs[r['tag']] = r  # the last run of a tag counts
table = collections.defaultdict(lambda: [0, 0, 0, 0])
for tag, r in runs.items():
    row = table[(KIND[tag.split('_')[0]], given(tag))]
    row[0] += 1
    row[1] += r.get('valid', 0)
    row[2] += r.get('vw', 0)
    row[3] += r['rc'] != 0
for (kind, what), (n, valid, wrong, failed) in sorted(table.items()):
    print(f'{kind:32} {what:24} runs {n:4}  valid {valid:6}  wrong {wrong:5} '
          f'({100 * wrong / max(valid, 1):4.1f} %)  refused {failed}')
