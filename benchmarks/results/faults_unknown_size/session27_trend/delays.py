# ruff: noqa  (scratch of session 27: see README.md)
import json,glob,sys,statistics as st
from collections import defaultdict
def collect(pat):
    out=defaultdict(list)
    for f in glob.glob(pat):
        d=json.load(open(f))
        for k,v in d.items():
            if not isinstance(v,list): continue
            for c in v:
                if not isinstance(c,dict) or c.get('method')!='uimm-est': continue
                for fa,md in c['median_delay_s'].items():
                    out[(c['case'],c['magnitude'],c.get('ramp'),fa)].append(md*1e3)
    return out
A=collect(sys.argv[1]); B=collect(sys.argv[2])
worst=0
for k in sorted(A):
    if k in B:
        a=st.mean(A[k]); b=st.mean(B[k]); worst=max(worst,b-a)
        print(k, f"{a:.1f} {b:.1f} {b-a:+.1f}")
print('worst', worst)
