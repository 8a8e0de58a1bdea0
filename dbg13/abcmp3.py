"""abcmp.py: per-frame changes and target misses, base accuracy JSONs (/tmp/ax13/base) against ab.py's v1 and v2."""
import sys, json, glob, os
sys.path.insert(0, '.')
from benchmarks import accuracy as A
def misses(summ, tag):
    m = []
    w = summ
    if w['centroid_rms_mm'] and w['centroid_rms_mm'] > 0.1: m.append(f"{tag} centroid {w['centroid_rms_mm']:.3f}")
    if w['axis_median_deg'] and w['axis_median_deg'] > 0.5: m.append(f"{tag} axis med {w['axis_median_deg']:.3f}")
    if w['tips_rms_mm'] and w['tips_rms_mm'] > 0.3: m.append(f"{tag} tips {w['tips_rms_mm']:.3f}")
    if w['silent_failures']: m.append(f"{tag} silent {w['silent_failures']}")
    return m
tot = {'base': 0, 'v3': 0}
for f in sorted(glob.glob('/tmp/ax13/ab3/*.json')):
    mode, seed = os.path.basename(f)[:-5].split('_')
    bf = f"/tmp/ax13/base/{'acc' if mode == 'cold' else 'acct'}_{seed}.json"
    if not os.path.exists(bf): print('no base for', f); continue
    B = json.load(open(bf)); N = json.load(open(f))
    for r, var in N.items():
        base = B['frames'][r]['weighted']
        ms = {'base': misses(A.summarise(base), f'r{r}')}
        for v in ('v3',):
            ms[v] = misses(A.summarise(var[v]), f'r{r}')
            for i, (x, y) in enumerate(zip(base, var[v])):
                dc = abs((x.get('centroid_mm') or 0) - (y.get('centroid_mm') or 0))
                da = abs((x.get('axis_deg') or 0) - (y.get('axis_deg') or 0))
                tx = max(x.get('tips_mm') or [0]); ty = max(y.get('tips_mm') or [0])
                if x['ok'] != y['ok'] or x['ambiguous'] != y['ambiguous'] or dc > 1e-3 or da > 1e-3:
                    clean = x['ok'] and not x['ambiguous']
                    print(f"{mode} {seed} r{r} pose {i} {v}: {'CLEAN' if clean else 'flagged'} amb {x['ambiguous']}->{y['ambiguous']} "
                          f"c {x.get('centroid_mm') or -1:.3f}->{y.get('centroid_mm') or -1:.3f} ax {x.get('axis_deg') or -1:.2f}->{y.get('axis_deg') or -1:.2f} "
                          f"tipmax {tx:.2f}->{ty:.2f} | {(y.get('reason') or '')[:90]}")
        for k in ms:
            tot[k] += len(ms[k])
        if any(ms.values()): print(f'  MISSES {mode} {seed} r{r}:', {k: v for k, v in ms.items()})
print('total misses', tot)
