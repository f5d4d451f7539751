# ruff: noqa  (scratch of session 22: see README.md)
"""compare.py A.json B.json: per cell of two sweep files, false runs, wrong retractions, lowest
detection and coverage (A then B; "<--" where they differ) and the median delays."""
import json,sys,glob
def rows(path):
    d=json.load(open(path)); out=[]
    for k,v in d.items():
        if isinstance(v,list):
            for c in v:
                if isinstance(c,dict) and 'runs' in c:
                    cov=[x for x in c.get('magnitude_coverage',{}).values() if x is not None]
                    out.append((c.get('case'),c.get('magnitude'),c.get('ramp'), c['runs_with_false_declaration'], sum(c.get('wrong_retractions',{}).values()), min(c.get('detection_probability',{}).values(),default=None), round(min(cov),3) if cov else None, {f:round(1e3*x,1) for f,x in c.get('median_delay_s',{}).items() if x}))
    return out
a,b=sys.argv[1],sys.argv[2]
for ra,rb in zip(rows(a),rows(b)):
    flag = '' if ra[3:7]==rb[3:7] else '  <--'
    print(ra[:3], 'false',ra[3],rb[3],'wrong',ra[4],rb[4],'det',ra[5],rb[5],'cov',ra[6],rb[6], flag)
    if ra[7]!=rb[7]: print('     delays', ra[7], rb[7])
