"""Where the wrinkle recovery of the wrinkled ICT kit is lost: a decomposition per feature.

Two splits of the kit's 26 wrinkled expressions and its 120-frame wrinkled take (markers: the
truth's handle vertices, head space):

* ``kit``: Bickel's protocol — train on the expressions and frames 0–79, test frames 80–119
  (which lead with expressions the training frames never show: eyeLookOut_R, jawLeft,
  mouthPucker, mouthSmile_R — new mixtures of expressions seen only as isolated meshes);
* ``interleaved``: train on the expressions and the frames outside every 8th frame (and its two
  neighbours), test those 15 frames: new mixtures like the training ones.

Rows, each scored by face RMS (cm, vertices 0:9409), wrinkle recovery k (the kit's README; per-frame
mean and pooled over frames) and the worst frame against the large scale alone:

* large scale alone; WPSD least squares P = 26 with the config's novelty gate and without;
* WPSD trained on the test frames too (in sample): what its features can represent at all;
* "oracle S": the plain truth as the large scale, details = the true wrinkle layer, fitted over
  WPSD's features or over the plain truth's own local strain (what each feature carries of the
  wrinkles when the large scale is perfect and the strain exact);
* local strain of the shell (the ``local_strain`` method) with the kernels of ``KERNELS``;
* hybrid: WPSD for the smooth error, then the local strain of the WPSD-corrected surface for
  the rest.

Usage: python -m bench.ict_wrinkled_decompose [--json bench/ict_wrinkled_decompose.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from bench.ict_wrinkled import DATA, ROOT, configured_rig
from facepipe.core.local_strain import StrainOperator, principal_strains, vertex_strain
from facepipe.core.psd import fit_details, greedy_basis, spread_subset
from facepipe.core.strain_details import fit_strain_details
from facepipe.core.tangent_frames import to_local, to_world
from facepipe.pipeline.fit import fit_rig
from facepipe.pipeline.rig import load_rig, load_sequence

FACE = slice(0, 9409)
KERNELS = [(0.08, 0.3)]  # the config's default (validated pairs: bench/ict_wrinkled_local_strain_validated.json)


def scores(P, T, S, large_rms=None) -> dict:
    d = (P - T)[:, FACE]
    rms = np.sqrt(np.einsum("tvc,tvc->tv", d, d).mean(1))
    a, b = (P - S)[:, FACE], (T - S)[:, FACE]
    k = np.einsum("tvc,tvc->t", a, b) / np.einsum("tvc,tvc->t", b, b)
    out = {"face_rms": float(rms.mean()), "recovery_mean": float(k.mean()),
           "recovery_pooled": float((a * b).sum() / (b * b).sum()), "per_frame_rms": rms}
    if large_rms is not None:
        out["worst_vs_large"] = float((rms - large_rms).max())
    return out


def poses_of_kit(config: str):
    """The rig (expressions only), and the 26 wrinkled / plain expressions + 120 frames, head space."""
    rig = configured_rig(config, {"examples.sequence": None, "psd.fit": "least-squares", "psd.max_poses": 26})
    plain = load_rig(ROOT / "configs" / "ict.toml")
    Sm = plain.example_positions[[plain.example_names.index(n) for n in rig.example_names]]
    Tt, _ = load_sequence(DATA / "ict_wrinkled" / "train_truth.npz", rig.mesh)
    St, _ = load_sequence(DATA / "ict" / "train_truth.npz", rig.mesh)
    return rig, np.concatenate([rig.example_positions, Tt]), np.concatenate([Sm, St])


def wpsd(geo, alpha, features, targets, train, max_poses=26, sample=2048):
    """WPSD least squares on the training poses (rest = pose 0 added), greedy basis on a vertex sample."""
    rows = np.r_[0, 1 + train]
    vs = spread_subset(targets.shape[1], sample)
    _, basis, _ = greedy_basis("wpsd", features[rows], targets[rows][:, vs], "least-squares", max_poses, 0.0,
                               alpha=alpha[vs])
    return fit_details("wpsd", features[rows], targets[rows], basis, "least-squares", alpha)


def run_split(name, train, test, ctx) -> dict:
    geo, alpha, op, T, S, feats, H = ctx["geo"], ctx["alpha"], ctx["op"], ctx["T"], ctx["S"], ctx["feats"], ctx["H"]
    out = {}
    Tt, St = T[test], S[test]
    L = ctx["L"][test]
    RL = geo.frames(L)
    base = scores(L, Tt, St)
    large_rms = base["per_frame_rms"]

    def row(label, P):
        r = scores(P, Tt, St, large_rms)
        r.pop("per_frame_rms")
        out[label] = r
        print(f"  {name:12s} {label:58s} RMS {r['face_rms']:.4f}  recovery {r['recovery_mean']:+.3f} (pooled "
              f"{r['recovery_pooled']:+.3f})  worst frame vs large {r['worst_vs_large']:+.4f}", flush=True)

    row("large scale alone", L)
    f_te = feats[1 + test]
    model = wpsd(geo, alpha, feats, ctx["D"], train)
    d_ng = model.evaluate(f_te)
    if ctx["gate"] is not None:  # (its cone: the 26 expressions)
        gated = dataclasses.replace(model, gate=ctx["gate"])
        row(f"WPSD LS P26, novelty gate (τ {ctx['gate'].tau:g})",
            L + to_world(RL, gated.evaluate(f_te, T[test][:, H] - geo.rest[H])))
    row("WPSD LS P26, gate off", L + to_world(RL, d_ng))
    both = np.union1d(train, test)
    row("WPSD LS P26 trained on the test frames too (in sample)",
        L + to_world(RL, wpsd(geo, alpha, feats, ctx["D"], both).evaluate(f_te)))
    RS = geo.frames(St)
    row("oracle S + WPSD features -> wrinkle layer",
        St + to_world(RS, wpsd(geo, alpha, feats, ctx["W"], train).evaluate(f_te)))
    sS, sL = ctx["sS"], ctx["sL"]
    for w, r in KERNELS:
        m = fit_strain_details(sS[np.r_[0, 1 + train]], ctx["W"][np.r_[0, 1 + train]], w, r)
        row(f"oracle S + its local strain -> wrinkle layer (σ {w}, λ {r})", St + to_world(RS, m.evaluate(sS[1 + test])))
        m = fit_strain_details(sL[np.r_[0, 1 + train]], ctx["D"][np.r_[0, 1 + train]], w, r)
        row(f"local strain of the shell (σ {w}, λ {r})", L + to_world(RL, m.evaluate(sL[1 + test])))
    # hybrid: WPSD's surface (its fit of the training poses, its prediction of the test ones)
    rows_tr = np.r_[0, 1 + train]
    d_tr = model.evaluate(feats[rows_tr])
    C_tr = ctx["Lall"][rows_tr] + to_world(geo.frames(ctx["Lall"][rows_tr]), d_tr)
    C_te = L + to_world(RL, d_ng)
    sC_tr = np.stack([vertex_strain(p, op) for p in C_tr])
    sC_te = np.stack([vertex_strain(p, op) for p in C_te])
    resid = to_local(geo.frames(C_tr), ctx["Pall"][rows_tr] - C_tr)
    RC = geo.frames(C_te)
    for w, r in KERNELS:
        m = fit_strain_details(sC_tr, resid, w, r)
        row(f"hybrid: WPSD, then local strain of its surface (σ {w}, λ {r})", C_te + to_world(RC, m.evaluate(sC_te)))
    p_true = principal_strains(sS[1 + test])[..., 0][:, FACE].ravel()
    out["strain_correlation"] = {
        "shell": float(np.corrcoef(principal_strains(sL[1 + test])[..., 0][:, FACE].ravel(), p_true)[0, 1]),
        "shell + WPSD": float(np.corrcoef(principal_strains(sC_te)[..., 0][:, FACE].ravel(), p_true)[0, 1])}
    print(f"  {name:12s} smallest principal strain vs the plain truth's, correlation: {out['strain_correlation']}")
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(ROOT / "configs" / "ict_wrinkled.toml"))
    ap.add_argument("--json", default=str(ROOT / "bench" / "ict_wrinkled_decompose.json"))
    args = ap.parse_args()
    t0 = time.perf_counter()
    rig, T, S = poses_of_kit(args.config)
    fit = fit_rig(rig)  # the geometry, WPSD weights and the novelty gate of the 26 expressions
    geo, H = fit.geometry, fit.geometry.handles
    rest = geo.rest
    P_all = np.concatenate([rest[None], T])  # pose 0: rest; 1..26 expressions; 27.. frames
    S_all = np.concatenate([rest[None], S])
    L_all = geo.large_scale(P_all)
    op = StrainOperator.of(rest, geo.faces, geo.neighbors)
    ctx = {"geo": geo, "alpha": fit.alpha, "op": op, "H": H, "T": T, "S": S, "L": L_all[1:], "Lall": L_all,
           "Pall": P_all, "feats": geo.features(P_all[:, H]), "D": geo.details(P_all),
           "W": to_local(geo.frames(S_all), P_all - S_all),
           "sS": np.stack([vertex_strain(p, op) for p in S_all]), "sL": np.stack([vertex_strain(p, op) for p in L_all]),
           "gate": fit.gate}
    frames = np.arange(120)
    held = frames[frames % 8 == 4]
    near = np.union1d(np.union1d(held - 1, held), held + 1)
    meshes = np.arange(26)
    result = {"prepare_s": time.perf_counter() - t0}
    result["interleaved"] = run_split("interleaved", np.r_[meshes, 26 + np.setdiff1d(frames, near)], 26 + held, ctx)
    Path(args.json).write_text(json.dumps(result, indent=1))  # (the kit split takes as long again)
    result["kit"] = run_split("kit 80-119", np.r_[meshes, 26 + np.arange(80)], 26 + np.arange(80, 120), ctx)
    result["seconds"] = time.perf_counter() - t0
    Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
