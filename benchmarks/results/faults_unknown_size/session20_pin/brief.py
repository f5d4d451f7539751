# ruff: noqa  (scratch of session 20: see README.md)
import json, sys
sys.path.insert(0, "session19_fast")
exec(open(__file__.replace("session20_pin/brief.py", "session19_fast/cmp.py")).read().split("files = sys.argv")[0])
files = sys.argv[1:]
R = [rows(f) for f in files]
print("file order:", [f.split("/")[-1] for f in files])
for key in R[0]:
    vals = []
    for r in R:
        c = r.get(key)
        vals.append("-" if c is None else f"F{c['false']} d{c['det']:.2f} wr{c['wr']} m{c['mare']} c{c['cov']} {list(c['delay'].values())}")
    print(key[0], key[2], key[3], " | ".join(vals))
