"""agg.py LOG...: over the changed frames of ab.py logs, per robot and variant: count, axis RMS/max, centroid RMS, tips max RMS."""
import sys, re, math, collections
pat = re.compile(r"\[(\w+)\] (\w+) (\d+) r(\d) p(\d+): amb (\w+)->(\w+) axis ([\d.None]+)->([\d.None]+) c ([\d.None]+)->([\d.None]+) tipmax ([\d.None]+)->([\d.None]+)")
g = collections.defaultdict(list)
for f in sys.argv[1:]:
    for line in open(f):
        m = pat.search(line)
        if m:
            v, mode, seed, r = m.group(1), m.group(2), m.group(3), m.group(4)
            vals = [None if x == 'None' else float(x) for x in m.groups()[7:]]
            g[(v, mode, r)].append((seed, m.group(5), m.group(6), m.group(7), vals))
rms = lambda xs: math.sqrt(sum(x * x for x in xs) / len(xs)) if xs else float('nan')
for k, rows in sorted(g.items()):
    a0 = [r[4][0] for r in rows if r[4][0] is not None]; a1 = [r[4][1] for r in rows if r[4][1] is not None]
    c0 = [r[4][2] for r in rows]; c1 = [r[4][3] for r in rows]
    t0 = [r[4][4] for r in rows if r[4][4] is not None]; t1 = [r[4][5] for r in rows if r[4][5] is not None]
    clean = sum(1 for r in rows if r[2] == 'False' or r[3] == 'False')
    better = sum(1 for r in rows if r[4][0] is not None and r[4][1] is not None and r[4][1] < r[4][0])
    print(f"{k[0]} {k[1]} r{k[2]}: {len(rows)} changed ({clean} clean before or after), axis better {better}; axis RMS {rms(a0):.2f} -> {rms(a1):.2f} max {max(a0):.2f} -> {max(a1):.2f}; "
          f"centroid RMS {rms(c0):.3f} -> {rms(c1):.3f}; tip-max RMS {rms(t0):.3f} -> {rms(t1):.3f}")
