# ruff: noqa  (scratch of session 26: see README.md)
"""summ.py TAG...: sim 1's abrupt cell at 3 per seed (files sizes_uimm-est_64<TAG>_seedK.json
under R/benchmarks/results/faults_unknown_size, R default the working directory): runs
with a false declaration, leakage detected, its p95 delay (ms), coverage, wrong retractions."""
import json,sys,glob,re
import os; R=os.environ.get('R','.')+'/benchmarks/results/faults_unknown_size/'
for tag in sys.argv[1:]:
    out=[]
    for f in sorted(glob.glob(R+f'sizes_uimm-est_64{tag}_seed*.json')):
        d=json.load(open(f)); c=[x for x in d['sim1'] if x['magnitude']==3.0][0]
        s=re.search(r'seed(\d+)',f).group(1)
        out.append(f"s{s}: F{c['runs_with_false_declaration']} det{c['detections']['leakage']} p95L{(c['p95_delay_s']['leakage'] or -1)*1e3:.0f} cov{c['magnitude_coverage']['valve_wear']:.2f}/{c['magnitude_coverage']['leakage']:.2f} wr{sum(c['wrong_retractions'].values())}")
    print(tag, ' | '.join(out))
