# ruff: noqa  (scratch measuring stick of session 18; see README.md)
"""A floor for uimm-est's augmented cycle: the engine issue's reference step with [x; a].

``../shared/perf/reference_step.py`` is the fixed-size UIMM step written as whole-block
reductions (the measuring stick of the engine issue).  This script writes the same step
with each model's state augmented by the F = 3 fault magnitudes, as uimm-est does
(``[x; a]``, 6 states, the magnitudes a random walk, the dynamics expanded to first order
around ``a0`` with the derivative caches looked up by declared set like the reference's
banks, ``Fa[:, k] = use_k (dF_k x + dG_k u)``, ``H = [I, 0]``), with the reference's
features (log-space probabilities, missing channels, pivot repair, Joseph fallback under
``cond``, gate, non-finite guard, health, decision with hold, hand-over under ``cond``)
and, as a variant, the reset of the magnitudes a model does not use (uimm-est's
``reset_unused`` in its simplest form: unused entries to the prior, no correlation).
None of uimm-est's other rules (restarts, floors, walks, retraction hypotheses, settle
tests, re-centring) is here: this is what the augmented cycle costs when written as the
reference writes its step, a floor for the ``<= 2x`` line of the faults issue.

Timed interleaved in one process (process CPU time, medians) on the ``cost`` part's data
(sim 1, valve wear and leakage at the library size, 1 s tiled to ``5 x 1e4`` samples), with
the engine's fixed-size UIMM and uimm-est steps and the augmented ``imm_step`` alone::

    python benchmarks/results/faults_unknown_size/session18_floor/aug_floor.py [REPEATS]
    python benchmarks/results/faults_unknown_size/session18_floor/aug_floor.py 5 64

With a batch ``B > 1`` (second argument) only the reference-style steps run, on ``B`` runs
of ``1e4`` samples: the 5 x 1e4 samples cut into 5 runs and repeated (the runs' noise is
not independent, which does not matter for a timing).
"""
import importlib.util
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, "benchmarks")
import faults_unknown_size as fu  # noqa: E402  (sets x64)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from uimm_jax.engine.imm import IMMParams, imm_step  # noqa: E402
from uimm_jax.studies.run import setup_scenario, simulate_scenario  # noqa: E402

REP = int(sys.argv[1]) if len(sys.argv) > 1 else 5
BATCH = int(sys.argv[2]) if len(sys.argv) > 2 else 1  # > 1: the reference-style steps only
spec = importlib.util.spec_from_file_location(
    "reference_step", Path(__file__).resolve().parents[4].parent / "shared" / "perf" / "reference_step.py"
)
ref = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ref)
NF = len(ref.FAULTS)
M = NF + 1
n = 3
NA = n + NF


def params_at(a):
    """The plant's parameters with fault k at magnitude a[k] (air in oil on a log scale)."""
    p = dict(ref.NOMINAL)
    for k, f in enumerate(ref.FAULTS):
        for name, v in f.items():
            nom = ref.NOMINAL[name]
            p[name] = nom * (v / nom) ** a[k] if name == "Eh" else nom + a[k] * (v - nom)
    return p


def aug_banks():
    """Per declared set: F0 (3,3,M), G0 (3,M), dF (NF,3,3,M), dG (NF,3,M), use (NF,M)."""
    out = {k: [] for k in ("F0", "G0", "dF", "dG", "use")}
    for code in range(2**NF):
        D = {j for j in range(NF) if code >> j & 1}
        F0s, G0s, dFs, dGs, uses = [], [], [], [], []
        for extra in [None] + list(range(NF)):
            S = set(D)
            if extra is not None:
                S ^= {extra}  # D + f_j, or D - f_j when j is declared (retraction)
            a0 = np.array([1.0 if k in S else 0.0 for k in range(NF)])
            F0, G0 = ref.discretise(params_at(a0))
            dF, dG = [], []
            for k in range(NF):
                h = 1e-6
                e = np.eye(NF)[k] * h
                Fp, Gp = ref.discretise(params_at(a0 + e))
                Fm, Gm = ref.discretise(params_at(a0 - e))
                on = k in S
                dF.append((Fp - Fm) / (2 * h) * on)
                dG.append((Gp - Gm) / (2 * h) * on)
            F0s.append(F0), G0s.append(G0), dFs.append(np.stack(dF)), dGs.append(np.stack(dG))
            uses.append(a0 > 0)
        out["F0"].append(np.stack(F0s, -1))
        out["G0"].append(np.stack(G0s, -1))
        out["dF"].append(np.stack(dFs, -1))
        out["dG"].append(np.stack(dGs, -1))
        out["use"].append(np.stack(uses, -1))
    return {k: jnp.asarray(np.stack(v)) for k, v in out.items()}


_mm, _mmT, _mv = ref._mm, ref._mmT, ref._mv


def make_aug_step(reset, lean=False, stay=0.9999, threshold=0.99, hold=100, gate=100.0, walk=1e-4,
                  prior_mean=1.0, prior_var=0.25):
    B_ = aug_banks()
    Pi = np.full((M, M), (1 - stay) / (M - 1))
    np.fill_diagonal(Pi, stay)
    Pib = jnp.asarray(Pi)[:, :, None]
    Qa = np.zeros((NA, NA))
    Qa[:n, :n] = ref.Q
    Qa[n:, n:] = np.eye(NF) * walk**2
    Qab = jnp.asarray(Qa)[:, :, None, None]
    Rb = jnp.asarray(ref.R)[:, :, None, None]
    I3 = jnp.eye(3)[:, :, None, None]
    Ia = jnp.eye(NA)[:, :, None, None]
    c = 3 * math.log(2 * math.pi)
    floor = float(jnp.finfo(jnp.float64).tiny) ** 0.5
    bits = (1 << jnp.arange(NF, dtype=jnp.int32))[:, None]
    pc = np.zeros((NA, NA))
    pc[n:, n:] = np.eye(NF) * prior_var
    prior_const = jnp.asarray(pc)[:, :, None, None]

    def step(carry, inp):
        x, P, lmu, declared, run_model, run_len = carry
        u, z = inp
        code = jnp.sum(jnp.where(declared, bits, 0), 0)
        if lean:  # no lookup: the bank of nothing declared, a constant
            code = jnp.zeros_like(code)
        F0 = jnp.moveaxis(B_["F0"][code], 0, -1)   # (3,3,M,B)
        G0 = jnp.moveaxis(B_["G0"][code], 0, -1)   # (3,M,B)
        dF = jnp.moveaxis(B_["dF"][code], 0, -1)   # (NF,3,3,M,B)
        dG = jnp.moveaxis(B_["dG"][code], 0, -1)   # (NF,3,M,B)
        use = jnp.moveaxis(B_["use"][code], 0, -1)  # (NF,M,B)
        active = jnp.concatenate([jnp.ones((1,) + code.shape, bool), ~declared], 0)
        if reset:  # unused magnitudes to the prior, uncorrelated
            a = jnp.where(use, x[n:], prior_mean)
            x = jnp.concatenate([x[:n], a], 0)
            keep = jnp.concatenate([jnp.ones((n,) + use.shape[1:], bool), use], 0)
            both = keep[:, None] & keep[None, :]
            prior = prior_const
            P = jnp.where(both, P, prior)
        # mixing, eqs. (15)-(17)
        top = jnp.max(lmu, axis=0, keepdims=True)
        top = jnp.where(jnp.isfinite(top), top, 0.0)
        mu = jnp.exp(lmu - top)
        cbar = jnp.sum(mu[:, None, :] * Pib, axis=0)
        om = Pib * mu[:, None, :] / cbar[None, :, :]
        xm = jnp.sum(om[None] * x[:, :, None, :], axis=1)
        d = x[:, :, None, :] - xm[:, None, :, :]
        Pm = jnp.sum(om[None, None] * (P[:, :, :, None, :] + d[:, None] * d[None, :]), axis=2)
        # predict through the first-order expansion in a
        da = jnp.where(use, xm[n:] - 1.0 * use, 0.0)  # a0 = 1 for used faults
        Fx = F0 + jnp.sum(dF * da[:, None, None], axis=0)
        Gx = G0 + jnp.sum(dG * da[:, None], axis=0)
        xs = xm[:n]
        Fa = jnp.moveaxis(jnp.sum(dF * xs[None, None], axis=2) + dG * u, 0, 1)  # (3,NF,M,B)
        G = jnp.concatenate([Fx, Fa], 1)  # (3,6,M,B)
        xp = jnp.concatenate([_mv(Fx, xs) + Gx * u, xm[n:]], 0)
        GP = _mm(G, Pm)  # (3,6)
        TL = _mmT(GP, G)
        TR = GP[:, n:]
        Pp = jnp.concatenate([jnp.concatenate([TL, TR], 1),
                              jnp.concatenate([jnp.swapaxes(TR, 0, 1), Pm[n:, n:]], 1)], 0) + Qab
        # update, H = [I, 0]
        valid = jnp.isfinite(z)
        y = jnp.where(valid[:, None, :], z[:, None, :] - xp[:n], 0.0)
        Pxx = Pp[:n, :n]
        S = jnp.where(valid[:, None, None, :] & valid[None, :, None, :], Pxx + Rb, I3)
        PH = jnp.where(valid[None, :, None, :], Pp[:, :n], 0.0)  # (6,3)
        s00, s01, s02, s11, s12, s22 = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
        c00, c01, c02 = s11 * s22 - s12 * s12, s02 * s12 - s01 * s22, s01 * s12 - s02 * s11
        c11, c12, c22 = s00 * s22 - s02 * s02, s01 * s02 - s00 * s12, s00 * s11 - s01 * s01
        det = s00 * c00 + s01 * c01 + s02 * c02
        repaired = (s00 <= floor) | (c22 <= floor * s00) | (det <= floor * c22)
        det = jnp.where(repaired, jnp.maximum(det, floor), det)
        Si = jnp.stack([jnp.stack([c00, c01, c02]), jnp.stack([c01, c11, c12]),
                        jnp.stack([c02, c12, c22])]) / det
        K = _mm(PH, Si)  # (6,3)
        maha = jnp.sum(y * _mv(Si, y), axis=0)
        xn = xp + _mv(K, y)
        KPH = _mmT(K, PH)  # (6,6)
        margin = 0.99 * jnp.stack([Pp[i, i] for i in range(NA)]) - jnp.stack([KPH[i, i] for i in range(NA)])

        def joseph(_):
            Hf = jnp.concatenate([jnp.where(valid[:, None, None, :], I3, 0.0),
                                  jnp.zeros((n, NF) + I3.shape[2:3] + valid.shape[1:])], 1)
            IK = Ia - _mm(K, Hf)
            return _mmT(_mm(IK, Pp), IK) + _mmT(_mm(K, Rb), K)

        def standard(_):
            Pn = Pp - KPH
            return 0.5 * (Pn + jnp.swapaxes(Pn, 0, 1))

        if lean:  # no Joseph fallback
            Pn = standard(None)
        else:
            Pn = lax.cond(jnp.any(repaired) | ~jnp.all(margin >= 0.0), joseph, standard, None)
        ll = -0.5 * (maha + jnp.log(det) + c)
        health = jnp.where(jnp.any(repaired & active, 0), 1, 0) | jnp.where(jnp.any(~valid, 0), 8, 0)
        rj = jnp.min(jnp.where(active, maha, jnp.inf), axis=0) > gate
        xn, Pn, ll = jnp.where(rj, xp, xn), jnp.where(rj, Pp, Pn), jnp.where(rj, 0.0, ll)
        health |= jnp.where(rj, 4, 0)
        fin = jnp.isfinite(ll) & jnp.all(jnp.isfinite(xn), 0) & jnp.all(jnp.isfinite(Pn), (0, 1))
        xn, Pn = jnp.where(fin, xn, x), jnp.where(fin, Pn, P)
        ll = jnp.where(fin, ll, jnp.finfo(jnp.float64).min / 4)
        health |= jnp.where(jnp.any(~fin & active, 0), 2, 0)
        a_ = jnp.where(active, jnp.log(cbar) + top + ll, -jnp.inf)
        amax = jnp.max(a_, axis=0, keepdims=True)
        lmun = a_ - amax - jnp.log(jnp.sum(jnp.exp(a_ - amax), axis=0, keepdims=True))
        mun = jnp.exp(lmun)
        xc = jnp.sum(mun[None] * xn, axis=1)
        cand = jnp.argmax(mun, axis=0).astype(jnp.int32)
        cand_set = (cand[None, :] == jnp.arange(1, M)[:, None]) | declared
        qual = jnp.any(cand_set & ~declared, axis=0) & (jnp.max(mun, axis=0) >= threshold)
        run_len = jnp.where(qual, jnp.where(cand == run_model, run_len + 1, 1), 0)
        dnow = qual & (run_len >= hold)
        new_decl = jnp.where(dnow[None], cand_set, declared)
        run_len = jnp.where(dnow, 0, run_len).astype(jnp.int32)
        recognised = jnp.sum(jnp.where(cand_set, bits, 0), 0)

        def handover(op):
            xn_, Pn_, lm_ = op
            oh = (cand[None, :] == jnp.arange(M)[:, None]).astype(xn_.dtype)
            dn = dnow[None]
            xn_ = jnp.where(dn, jnp.sum(xn_ * oh[None], axis=1, keepdims=True), xn_)
            Pn_ = jnp.where(dn, jnp.sum(Pn_ * oh[None, None], axis=2, keepdims=True), Pn_)
            tp = jnp.max(lm_, axis=0, keepdims=True)
            mv = jnp.where((jnp.arange(M) == 0)[:, None], tp, jnp.where(oh > 0, -jnp.inf, lm_))
            mx = jnp.max(mv, axis=0, keepdims=True)
            mv = mv - mx - jnp.log(jnp.sum(jnp.exp(mv - mx), axis=0, keepdims=True))
            return xn_, Pn_, jnp.where(dn, mv, lm_)

        xn, Pn, lmun = lax.cond(jnp.any(dnow), handover, lambda o: o, (xn, Pn, lmun))
        jos = jnp.any(repaired) | ~jnp.all(margin >= 0.0)
        return (xn, Pn, lmun, new_decl, cand, run_len), (mun, xc, recognised, health, jos)

    return step


def aug_init(B, mu0=(0.97, 0.01, 0.01, 0.01)):
    x0 = jnp.concatenate([jnp.zeros((n, M, B)), jnp.ones((NF, M, B))], 0)
    P0 = np.zeros((NA, NA))
    P0[:n, :n] = 0.1 * np.eye(n)
    P0[n:, n:] = 0.25 * np.eye(NF)
    P0 = jnp.broadcast_to(jnp.asarray(P0)[:, :, None, None], (NA, NA, M, B))
    lm = jnp.broadcast_to(jnp.log(jnp.asarray(mu0))[:, None], (M, B))
    return (x0, P0, lm, jnp.zeros((NF, B), bool), jnp.zeros((B,), jnp.int32),
            jnp.zeros((B,), jnp.int32))


# ---- data and the engine's steps (as session17_cost/prof.py)
sc = fu._scenario(1, 1.0)
setups = {m: setup_scenario(sc, m) for m in ("uimm", "uimm-est")}
truth = simulate_scenario(setups["uimm"], 0)
y = jnp.asarray(np.tile(truth["y"], (5, 1)))[..., None]
u = jnp.asarray(np.tile(truth["u"], (5, 1)))[..., None]
if BATCH > 1:
    y = jnp.tile(jnp.moveaxis(y[..., 0].reshape(5, -1, 3), 0, -1), (1, 1, -(-BATCH // 5)))[..., :BATCH]
    u = u[: y.shape[0]]
N = y.shape[0] * BATCH
us = u[:, 0, 0]


def one(st_):
    return jax.tree.map(lambda a: a[..., None], st_)


def scan_engine(step):
    @jax.jit
    def run(s, u, y):
        return lax.scan(lambda c, uy: (step(c, *uy)[0], None), s, (u, y))[0]
    return lambda s: run(s, u, y)


def scan_ref(step):
    @jax.jit
    def run(c, u, z):
        def body(cc, uz):
            c2, o = step(cc, uz)
            return c2, (o[0], o[-1] if len(o) > 4 else jnp.zeros((), bool))
        return lax.scan(body, c, (u, z))
    return lambda s: run(s, us, y)


V = {}
for m, st in setups.items() if BATCH == 1 else ():
    d, p = st.diagnoser, st.params
    V[f"engine {m}"] = (scan_engine(lambda s, u, y, d=d, p=p: d.step(s, p, u, y, with_cov=False)), one(st.init_state))
est = setups["uimm-est"]
d, p = est.diagnoser, est.params
F_ = d.num_faults
q_aug = jnp.zeros((n + F_, n + F_)).at[:n, :n].set(p.imm.Q).at[n:, n:].set(jnp.eye(F_) * d.per_sample.walk**2)
ip = IMMParams(p.imm.log_transition, q_aug, p.imm.R)
s0 = one(est.init_state)
if BATCH == 1:
  V["engine augmented imm_step alone"] = (
    scan_engine(lambda s, u, y: imm_step(d.aug, s, s0.cache, ip, u, y, gate=d.gate, with_cov=False)), s0.imm)
V["reference (3 states)"] = (scan_ref(ref.make_step()), ref.init(BATCH))
V["augmented reference (6 states)"] = (scan_ref(make_aug_step(False)), aug_init(BATCH))
V["augmented reference + reset"] = (scan_ref(make_aug_step(True)), aug_init(BATCH))
V["augmented reference, lean (no lookup, no Joseph)"] = (scan_ref(make_aug_step(False, lean=True)), aug_init(BATCH))

res = {k: [] for k in V}
outs = {}
for k, (f, s_) in V.items():
    outs[k] = jax.block_until_ready(f(s_))
for r in range(REP):
    for k, (f, s_) in V.items():
        t0 = time.process_time()
        jax.block_until_ready(f(s_))
        res[k].append(1e6 * (time.process_time() - t0) / N)
base_e = np.median(res["engine uimm"]) if BATCH == 1 else np.nan
base_r = np.median(res["reference (3 states)"])
print(f"{BATCH} run(s), {N // BATCH} steps, {REP} repeats, process CPU time, medians")
print("| variant | us per run-step | to the engine's fixed-size UIMM | to the reference |")
print("|---|---:|---:|---:|")
for k, v in res.items():
    med = np.median(v)
    print(f"| {k} | {med:.3f} | {med / base_e:.2f} | {med / base_r:.2f} |")
for k in ("augmented reference (6 states)", "augmented reference + reset"):
    c, (mu, jos) = outs[k]
    print(f"{k}: Joseph branch on {int(np.sum(np.asarray(jos)))} of {N // BATCH} steps; declared at the end {np.asarray(c[3])[:, 0].astype(int).tolist()}, "
          f"magnitudes of model 0 {np.round(np.asarray(c[0])[n:, 0, 0], 3).tolist()}, "
          f"finite {bool(np.all(np.isfinite(np.asarray(mu))))}")
