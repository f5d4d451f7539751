"""Print a saved single run (``SAVE=file.npz ramp_false.py one ...``) around its changes of leader.

Usage: ``python window.py FILE.npz K0 K1 [EVERY]``: every sample from ``K0`` to ``K1`` where the
most probable model changes, and every ``EVERY``-th sample (default 10): the sample, the
leader (0: model 0, ``j + 1``: the slot of fault ``j``), the declared set's code, the mode
probabilities, and each fault's estimate and sd (model 0's for a declared fault, its own
hypothesis' otherwise).
"""

import sys

import numpy as np

path, k0, k1 = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
every = int(sys.argv[4]) if len(sys.argv) > 4 else 10
d = np.load(path)
mp, dec, m, sd = d["mode_probs"], d["declared"], d["magnitude"], d["magnitude_sd"]
lead = mp.argmax(1)
for k in range(k0, k1):
    if k == k0 or lead[k] != lead[k - 1] or (k - k0) % every == 0:
        print(k, lead[k], dec[k], np.round(mp[k], 4), np.round(m[k], 4), np.round(sd[k], 4))
