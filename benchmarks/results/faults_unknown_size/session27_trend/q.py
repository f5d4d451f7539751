# ruff: noqa  (scratch of session 27: see README.md)
import json,sys,glob
for f in sorted(sum([glob.glob(a) for a in sys.argv[1:]],[])):
    d=json.load(open(f))
    for k,v in d.items():
        if not isinstance(v,list): continue
        for c in v:
            if not isinstance(c,dict) or c.get('method')!='uimm-est': continue
            w=sum((c.get('wrong_retractions') or {}).values())
            cov={kk:round(vv,3) for kk,vv in (c.get('magnitude_coverage') or {}).items()}
            print(f.split('/')[-1][:60], c['case'], c['magnitude'], c.get('ramp'), 'F',c['runs_with_false_declaration'],'W',w,'det',min(c['detection_probability'].values()) if c['detection_probability'] else None,'med',{kk:(None if vv is None else round(vv*1e3,1)) for kk,vv in c['median_delay_s'].items()},'cov',cov)
