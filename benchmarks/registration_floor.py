"""Benchmark: the error floor of marker-to-bone registration under the realistic phantoms' noise (issue R1).

What the hip, knee and ankle centres of the MRI source can reach at best when the markers are palpated as
the realistic phantoms palpate them (`phantoms.marker_placement.PALPATION_SD_MM`, after Della Croce et al.
1999, 2005) over soft tissue drawn from the body build's table (`TISSUE_CLASSES`): the bones, their
landmarks and the joint centres in the bone are exact, the tissue is known only as the build's prior
(mean, sd along the normal), nothing else is in error.  Per draw the landmark markers of a real-anatomy
phantom (ICL-MRI or LHDL-CT, IOR marker set: the most bony landmarks of the presets) are placed as the
phantoms place them (`--swing`, the default): the landmark p_k moved tangentially by τ_k ~ N(0, (s_k²/2)
(I - n_k n_kᵀ)) and re-projected onto the bone (q_k), the marker along the bone's normal there averaged
over max(6 mm, t_k) (n'_k: a prominence's facets swing it by 20-50 deg),

    m_k = q_k + (t_k + r) n'_k,   t_k ~ build's log-normal;

with ``--no-swing``, m_k = p_k + τ_k + (t_k + r) n_k.  `personalize.registration.register_landmarks` fits
the pose from (p_k + (t̄_k + r) n_k, m_k) with the palpation and tissue covariances; the error is that
pose's displacement of the true joint centre:

* hip: pelvis from RASI, LASI, RPSI, LPSI;
* knee: femur from RKNE, RMFC, RTRO and the hip centre (exact, or with 3 mm per axis);
* ankle: tibia from RANK, RMMA, RTUB, RHFB and the knee centre (exact, or with 2.5 mm per axis).

The pipeline also estimates the tissue scale and fuses the motion source; neither removes palpation
error, so these medians bound what the realistic validation's median fused errors can reach.

Usage::

    python benchmarks/registration_floor.py [--draws 400] [--no-swing] [--json benchmarks/results/registration_floor.json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DATA = Path(os.environ.get("PERSONALIZE_SHARED_DATA", REPO.parent / "shared" / "data"))


def _truth(anat, anatomy: str, build: str, folder: Path) -> dict:
    from phantoms.real_subject import write_real_subject

    out = folder / f"{anatomy}_{build}"
    out.mkdir()
    return write_real_subject(out, anat, marker_set="ior", build=build, labels=False, meshes=False, sta=False,
                              noise_sd=0.0, static_frames=3, functional=False, gait_trials=0)


def _bone_of(anat, body: str, p: np.ndarray):
    """The mesh (body frame) of `body` nearest `p`."""
    meshes = [anat.local_meshes[b] for b, bb in anat.bone_body.items() if bb == body]
    return min(meshes, key=lambda m: float(np.min(np.linalg.norm(np.asarray(m.vertices) - p, axis=1))))


def _floor(anat, truth: dict, build: str, names, target, anchor=None, draws: int = 400, seed: int = 0,
           swing: bool = True) -> dict:
    from lowerlimb.geometry import DEFAULT_MARKER_RADIUS as r
    from phantoms.marker_placement import NORMAL_RADIUS_MIN, PALPATION_SD_MM, TISSUE_CLASSES, draw_tissue, skin_normal
    from personalize.registration import register_landmarks

    rng = np.random.default_rng(seed)
    M = truth["markers"]
    site = [M[k]["landmark"][1:] for k in names]
    table = TISSUE_CLASSES[build]
    key = [s if s in table else "KNE" for s in site]
    P = np.array([M[k]["landmark_body_m"] for k in names])
    mean = np.array([table[k][0] for k in key]) * 1e-3
    tsd = np.array([table[k][1] for k in key]) * 1e-3
    psd = np.array([PALPATION_SD_MM[s] for s in site]) * 1e-3
    meshes = [_bone_of(anat, M[k]["body"], p) for k, p in zip(names, P)]
    N = np.array([skin_normal(m, p, max(NORMAL_RADIUS_MIN, t)) for m, p, t in zip(meshes, P, mean)])
    Q = P + (mean + r)[:, None] * N
    nn = np.einsum("ki,kj->kij", N, N)
    C = (psd ** 2 / 2)[:, None, None] * (np.eye(3) - nn) + (tsd ** 2)[:, None, None] * nn
    err = []
    for _ in range(draws):
        tang = rng.normal(size=P.shape) * (psd / np.sqrt(2))[:, None]
        tang -= np.einsum("ki,ki->k", tang, N)[:, None] * N
        t = np.array([draw_tissue(rng, build, k) for k in key])
        if swing:
            m = []
            for mesh, p, d, tk in zip(meshes, P, tang, t):
                q = np.asarray(mesh.vertices)[mesh.kdtree.query(p + d)[1]]      # the phantoms' re-projection
                m.append(q + (tk + r) * skin_normal(mesh, q, max(NORMAL_RADIUS_MIN, tk)))
            m = np.array(m)
        else:
            m = P + tang + (t + r)[:, None] * N
        pts, covs = Q, C
        if anchor is not None:
            c, sd = anchor
            pts = np.vstack([Q, c])
            m = np.vstack([m, c + rng.normal(scale=max(sd, 1e-6), size=3)])
            covs = np.concatenate([C, [max(sd, 1e-4) ** 2 * np.eye(3)]])
        reg = register_landmarks(pts, m, covs, marker_sd=1e-3, k_outlier=50.0)
        err.append(float(np.linalg.norm(reg.R @ target + reg.t - target)))
    e = np.array(err) * 1e3
    return {"median_mm": float(np.median(e)), "p90_mm": float(np.percentile(e, 90))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=400)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--swing", action=argparse.BooleanOptionalAction, default=True,
                    help="markers placed as the phantoms place them (re-projected, normal at the palpated point)")
    a = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"shared data not found at {DATA}")
        return 0
    from phantoms.real_anatomy import load_real_anatomy

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for anatomy in ("ICL_MRI", "LHDL_CT"):
            anat = load_real_anatomy(DATA / "bones" / anatomy, DATA / "reference_models" / f"manual_{anatomy}.osim")
            for build in ("child", "adult", "obese"):
                tr = _truth(anat, anatomy, build, Path(tmp))
                J = {k: np.asarray(v["origin"]) for k, v in tr["joints"]["joints"].items()}
                tib = [k for k in ("RANK", "RMMA", "RTUB", "RHFB") if k in tr["markers"]]
                cases = {
                    "hip": (["RASI", "LASI", "RPSI", "LPSI"], J["hip_r"], None),
                    "knee | exact hip": (["RKNE", "RMFC", "RTRO"], J["knee_r"], (J["hip_r"], 0.0)),
                    "knee | hip 3 mm/axis": (["RKNE", "RMFC", "RTRO"], J["knee_r"], (J["hip_r"], 3e-3)),
                    "ankle | exact knee": (tib, J["ankle_r"], (J["knee_r"], 0.0)),
                    "ankle | knee 2.5 mm/axis": (tib, J["ankle_r"], (J["knee_r"], 2.5e-3)),
                }
                for what, (names, target, anchor) in cases.items():
                    res = _floor(anat, tr, build, names, target, anchor, a.draws, swing=a.swing)
                    rows.append({"anatomy": anatomy, "build": build, "centre": what, **res})
                    print(f"{anatomy:8s} {build:6s} {what:26s} median {res['median_mm']:5.1f} mm, "
                          f"90th percentile {res['p90_mm']:5.1f} mm")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps({"units": "mm", "draws": a.draws, "swing": a.swing, "rows": rows}, indent=1) + "\n")
        print(f"written {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
