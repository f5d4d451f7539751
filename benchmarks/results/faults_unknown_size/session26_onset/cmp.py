# ruff: noqa  (scratch of session 26: see README.md)
"""cmp.py T0:T [T0:T ...]: session25_seeds/pool.py's pooled lines side by side (T0 the tag of
a setting's seed-0 files, T of its ``_seedK`` files; ``_x`` for none), only the cells where
the settings differ or a line fails.  Repository root; EXTRA as for pool.py."""
import sys, os
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'session25_seeds'))
import pool
sets = [a.split(':') for a in sys.argv[1:]]
for part in pool.PARTS:
    tabs = [pool.pooled(pool.find(t0, t, part)) for t0, t in sets]
    keys = sorted(set().union(*tabs), key=lambda k: (k[0], k[2], k[1]))
    for key in keys:
        rows = [tab.get(key) for tab in tabs]
        sig = [(r['false'], r['wrong'], round(r['det'] or 0, 3), round(r['cov'] or 0, 2)) if r else None for r in rows]
        bad = any(r and (r['false'] or r['wrong'] or (r['det'] or 1) < 0.99 or (r['cov'] or 1) < 0.9 or (r['retr_min'] is not None and r['retr_min'] < 0.99)) for r in rows)
        if bad or len(set(sig)) > 1:
            print(f"{part:12s} {key[0]} m{key[1]:g} r{key[2]:g}: " + ' || '.join(
                '-' if r is None else f"n{r['runs']} F{r['false']} W{r['wrong']} det{pool.fmt(r['det'])} cov{pool.fmt(r['cov'],2)} mare{pool.fmt(r['mare_max'],3)}" for r in rows))
