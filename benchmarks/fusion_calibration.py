"""Calibrate and check the hip-centre covariances of the MRI and motion sources; compare fusion schemes offline.

Reads the cache of `benchmarks/fusion_cache.py` (phantom subjects drawn like
``personalize validate`` from a TRAINING master seed) and splits it by subject:
the first ``--train`` subjects calibrate, the others are held out.

Calibration (written into `personalize.pipeline.hip`, `knee`, `foot`, `motion` as documented constants,
their numbers recorded in personalize/pipeline/calibration.json):

* which MRI scale is calibrated depends on the cache: phantoms whose label volume carries
  the body/skin label (tissue under the four pelvic markers measured, `personalize.skin`)
  calibrate `MRI_HIP_COV_SCALE_MEASURED`, bone-only ones `MRI_HIP_COV_SCALE`
  (``mri_cov_scale_constant`` in the output says which);

* MRI: the hip centre's error is the pelvis registration's (the femoral head is
  found to ~0.1 mm); its propagated covariance C_reg keeps its structure (and
  the cross-covariance of the two hips, one shared registration) and is scaled
  by k = mean(d²)/3 over the training legs, d² = eᵀ C_reg⁻¹ e (so E d² = 3);
* motion (SCoRE on the functional trial): its residual covariance ignores the
  soft-tissue artefact (STA), a systematic error; the STA term is the training
  legs' error second moment Σ_STA = mean(e eᵀ) in the pelvis axes (anterior,
  medial, up; left legs mirrored), added to the residual covariance.

* knee axis: the MRI axis sd is scaled (mean angle² = 2 (k sd)²) and SARA's
  artefact sd σ set from the training legs (2σ² = mean angle²).

Checks on the held-out legs: mean Mahalanobis d² (χ²₃: 3) and the fraction
below the χ²₃ 90 % quantile (6.25), claimed vs calibrated; then the fusion
schemes (claimed covariances per leg, calibrated per leg, calibrated joint
6-vector of both hips with the MRI cross-covariance): fraction of legs /
subjects (worst side) with the fused error below both sources, medians; and
the Monte-Carlo fraction for Gaussian fusion if the errors really were
N(0, calibrated covariances), independent between sources.

Usage::

    python benchmarks/fusion_calibration.py --cache /tmp/p1_cache --train 12 --json benchmarks/results/fusion_calibration.json
    python benchmarks/fusion_calibration.py --cache /tmp/p1_cache --train 12 --test-cache /tmp/p1_valcache \
        --json benchmarks/results/fusion_calibration_validation.json
"""
from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lowerlimb.geometry import skew  # noqa: E402  (after the sys.path line)

MIRROR = np.diag([1.0, -1.0, 1.0])


def load(cache: Path) -> list[dict]:
    """Per subject: axes A, sides {s: x_mri, C_mri, x_mot, C_score, C_floor, truth}, MRI 6x6 claimed covariance."""
    out = []
    for f in sorted(glob.glob(str(cache / "phantom_*.json"))):
        r = json.loads(Path(f).read_text())
        if set(r["sides"]) != {"r", "l"}:
            continue
        A = np.array(r["pelvis_axes"])
        R, cov, c = np.array(r["reg"]["R"]), np.array(r["reg"]["cov"]), np.array(r["reg"]["centre"])
        sub = {"subject": r["subject"], "A": A, "sides": {},
               # soft tissue under the pelvic markers measured in the MRI body label at all four sites?
               "skin_measured": bool(r.get("skin")) and all(v.get("source") == "MRI" for v in r["skin"].values())
               and len(r["skin"]) == 4}
        J, own = {}, {}
        for s, v in r["sides"].items():
            x = np.array(v["mri"][0])
            J[s] = np.hstack([-skew(x - c), np.eye(3)])
            own[s] = R @ np.array(v["hip_scanner_cov"]) @ R.T
            sub["sides"][s] = {"x_mri": x, "C_mri": np.array(v["mri"][1]), "x_mot": np.array(v["score"][0]),
                               "C_score": np.array(v["score"][1]), "C_mot_claimed": np.array(v["motion"][1]),
                               "truth": np.array(v["truth"])}
        C6 = np.zeros((6, 6))
        for i, a in enumerate("rl"):
            for j, b in enumerate("rl"):
                C6[3 * i:3 * i + 3, 3 * j:3 * j + 3] = J[a] @ cov @ J[b].T + (own[a] if a == b else 0)
        sub["C6_mri"] = C6
        out.append(sub)
    return out


def mirror(s):
    return MIRROR if s == "l" else np.eye(3)


def calibrate(train: list[dict]) -> dict:
    d2, M = [], []
    for sub in train:
        A = sub["A"]
        for s, v in sub["sides"].items():
            i = "rl".index(s)   # C6 blocks are in (r, l) order
            e = v["x_mri"] - v["truth"]
            # the UNSCALED registration covariance (the cached pipeline C_mri already holds the scale in force
            # when the cache was written), so the result is the absolute MRI_HIP_COV_SCALE
            b = slice(3 * i, 3 * i + 3)
            d2.append(e @ np.linalg.solve(sub["C6_mri"][b, b] + 1e-8 * np.eye(3), e))
            em = mirror(s) @ A.T @ (v["x_mot"] - v["truth"])
            M.append(np.outer(em, em))
    d2 = np.array(d2)
    return {"mri_cov_scale": float(np.mean(d2) / 3.0), "motion_sta_cov": np.mean(M, axis=0), "legs": len(d2),
            # robust check (heavy-tailed errors, e.g. log-normal soft tissue): median d² / χ²₃ median (2.366)
            "mri_cov_scale_by_median": float(np.median(d2) / 2.366)}


def covariances(sub: dict, cal: dict | None):
    """(C6_mri, {s: C_mot}) claimed (cal None: the pipeline's floored motion covariance) or calibrated."""
    A = sub["A"]
    if cal is None:
        return sub["C6_mri"], {s: v["C_mot_claimed"] for s, v in sub["sides"].items()}
    Cm = {s: v["C_score"] + A @ mirror(s) @ cal["motion_sta_cov"] @ mirror(s) @ A.T for s, v in sub["sides"].items()}
    return cal["mri_cov_scale"] * sub["C6_mri"], Cm


def evaluate(subs: list[dict], cal: dict | None, joint: bool) -> dict:
    from scipy import stats

    from personalize.fusion import fuse_gaussian, fuse_linear

    legs, worst, d2m, d2s, shares = [], [], [], [], []
    for sub in subs:
        C6, Cm = covariances(sub, cal)
        sd = sub["sides"]
        if joint:
            H = np.eye(6)
            f = fuse_linear([(np.concatenate([sd["r"]["x_mri"], sd["l"]["x_mri"]]), C6, H),
                             (sd["r"]["x_mot"], Cm["r"], H[:3]), (sd["l"]["x_mot"], Cm["l"], H[3:])],
                            ("mri", "motion_r", "motion_l"))
            fused = {"r": f.mean[:3], "l": f.mean[3:]}
            for i, s in enumerate("rl"):
                w = sum(np.trace(f.weights[k][3 * i:3 * i + 3, 3 * i:3 * i + 3]) / 3 for k in (1, 2))
                shares.append(w)
        else:
            fused = {}
            for i, s in enumerate("rl"):
                f = fuse_gaussian([(sd[s]["x_mri"], C6[3 * i:3 * i + 3, 3 * i:3 * i + 3]), (sd[s]["x_mot"], Cm[s])])
                fused[s] = f.mean
                shares.append(f.shares[1])
        row = {}
        for i, s in enumerate("rl"):
            v = sd[s]
            em, eo, ef = v["x_mri"] - v["truth"], v["x_mot"] - v["truth"], fused[s] - v["truth"]
            d2m.append(em @ np.linalg.solve(C6[3 * i:3 * i + 3, 3 * i:3 * i + 3], em))
            d2s.append(eo @ np.linalg.solve(Cm[s], eo))
            row[s] = [1e3 * np.linalg.norm(e) for e in (em, eo, ef)]
            legs.append(row[s])
        worst.append([max(row["r"][k], row["l"][k]) for k in range(3)])
    L, W = np.array(legs), np.array(worst)
    q90 = stats.chi2.ppf(0.9, 3)
    return {"legs": len(L), "subjects": len(W),
            "fused_below_both_legs": float(np.mean(L[:, 2] < L[:, :2].min(1))),
            "fused_below_mri_legs": float(np.mean(L[:, 2] < L[:, 0])),
            "fused_below_both_subjects_worst_side": float(np.mean(W[:, 2] < W[:, :2].min(1))),
            "median_mm_legs": dict(zip(("mri", "motion", "fused"), np.median(L, 0).tolist())),
            "median_mm_subjects_worst_side": dict(zip(("mri", "motion", "fused"), np.median(W, 0).tolist())),
            "mahalanobis_d2_mean": {"mri": float(np.mean(d2m)), "motion": float(np.mean(d2s))},
            "fraction_d2_below_chi2_3_q90": {"mri": float(np.mean(np.array(d2m) < q90)),
                                             "motion": float(np.mean(np.array(d2s) < q90))},
            "motion_share_mean": float(np.mean(shares))}


def error_moments(subs):
    em, eo = [], []
    for sub in subs:
        for s, v in sub["sides"].items():
            em.append(1e3 * mirror(s) @ sub["A"].T @ (v["x_mri"] - v["truth"]))
            eo.append(1e3 * mirror(s) @ sub["A"].T @ (v["x_mot"] - v["truth"]))
    em, eo = np.array(em), np.array(eo)
    r = np.array([[1e3 * sub["A"].T @ (sub["sides"][s]["x_mri"] - sub["sides"][s]["truth"]) for s in "rl"] for sub in subs])
    return {"frame": "pelvis axes (x anterior, y medial (left legs mirrored), z up), mm",
            "mri_bias": em.mean(0).tolist(), "mri_sd": em.std(0, ddof=1).tolist(), "mri_rms": np.sqrt((em**2).mean(0)).tolist(),
            "motion_bias": eo.mean(0).tolist(), "motion_sd": eo.std(0, ddof=1).tolist(),
            "motion_rms": np.sqrt((eo**2).mean(0)).tolist(),
            "mri_right_left_correlation_xyz": [float(np.corrcoef(r[:, 0, i], r[:, 1, i])[0, 1]) for i in range(3)],
            "mri_motion_correlation_xyz": [float(np.corrcoef(em[:, i], eo[:, i])[0, 1]) for i in range(3)],
            "mri_second_moment": (em.T @ em / len(em)).tolist(), "motion_second_moment": (eo.T @ eo / len(eo)).tolist()}


def knee_axis_legs(cache: Path, subjects=None, key: str = "knee_axis") -> list[tuple]:
    """(u_mri, sd_mri deg, u_motion, sd_motion deg, truth) per leg (lab frame) of the cached subjects (`key`: knee_axis, ankle_axis).

    The sds are freed of the constants the cache was written with (`cache_constants`): sd_mri is the
    UNSCALED registration sd, sd_motion only the estimator's own part (SARA's; none for the ankle), the
    artefact floor hypot-ed into it removed.
    """
    c = cache_constants(cache)
    scale, floor = ((c["MRI_KNEE_AXIS_SD_SCALE"], c["MOTION_KNEE_AXIS_SD_DEG"]) if key == "knee_axis"
                    else (c["MRI_ANKLE_AXIS_SD_SCALE"], np.inf))
    out = []
    for f in sorted(glob.glob(str(cache / "phantom_*.json"))):
        r = json.loads(Path(f).read_text())
        if subjects is not None and r["subject"] not in subjects:
            continue
        for v in r["sides"].values():
            if key not in v:
                continue
            k = v[key]
            t = np.array(k["truth"]) / np.linalg.norm(k["truth"])
            smo = float(np.sqrt(max(float(k["motion"][1]) ** 2 - floor**2, 0.0)))
            out.append((np.array(k["mri"][0]), float(k["mri"][1]) / scale, np.array(k["motion"][0]), smo, t))
    return out


def cache_constants(cache: Path) -> dict:
    """Pipeline constants the cache was written with (its first record's ``constants``, else the current ones)."""
    from personalize.pipeline.calibration import constants

    keys = ("MRI_HIP_COV_SCALE", "MRI_KNEE_AXIS_SD_SCALE", "MOTION_KNEE_AXIS_SD_DEG", "MRI_ANKLE_AXIS_SD_SCALE",
            "MOTION_ANKLE_AXIS_SD_DEG")
    pl = constants()
    out = {k: float(pl.get(k, 1.0)) for k in keys}
    files = sorted(glob.glob(str(cache / "phantom_*.json")))
    if files:
        rec = json.loads(Path(files[0]).read_text()).get("constants")
        if rec is not None:   # a record's constants; a scale it does not name was not applied then (1)
            out = {k: float(rec.get(k, 1.0)) for k in keys}
    return out


def _angle(u, t):
    return float(np.degrees(np.arccos(min(1.0, abs(u @ t) / np.linalg.norm(u)))))


def knee_axes(train: list[tuple], test: list[tuple], claimed_scale: float, claimed_floor_deg: float) -> dict:
    """Knee- (or ankle-) axis calibration: MRI sd scale k (mean angle² / (2 (k sd)²) = 1) and the artefact sd σ (2σ² = mean angle²).

    Legs from `knee_axis_legs` (unscaled MRI sd, motion sd without floor).  "claimed": the pipeline's
    constants in force (`claimed_scale`, `claimed_floor_deg`); "calibrated": (k, σ).  Returns the constants
    and, per set, both.
    """
    from personalize.fusion import fuse_axis

    am = np.array([_angle(m, t) for m, _, _, _, t in train])
    ao = np.array([_angle(o, t) for _, _, o, _, t in train])
    k = float(np.sqrt(np.mean(am**2 / (2 * np.array([x[1] for x in train]) ** 2))))
    sta = float(np.sqrt(np.mean(ao**2) / 2))
    res = {"mri_sd_scale": k, "motion_sta_sd_deg": sta, "units": "deg"}
    for name, legs in (("train", train), ("test", test)):
        if not legs:
            continue
        for label, km, so in (("claimed", claimed_scale, claimed_floor_deg), ("calibrated", k, sta)):
            ef, em, eo, d2m, d2o = [], [], [], [], []
            for m, sm, o, smo, t in legs:
                sdm = km * sm
                sdo = float(np.hypot(smo, so))
                f = fuse_axis([m, o], [sdm, sdo])
                ef.append(_angle(f.direction, t))
                em.append(_angle(m, t))
                eo.append(_angle(o, t))
                d2m.append(em[-1] ** 2 / sdm**2)
                d2o.append(eo[-1] ** 2 / sdo**2)
            ef, em, eo = map(np.array, (ef, em, eo))
            res[f"{name}_{label}"] = {"legs": len(ef), "median_deg": {"mri": float(np.median(em)), "motion": float(np.median(eo)),
                                                                     "fused": float(np.median(ef))},
                                      "fused_below_motion": float(np.mean(ef < eo)),
                                      "fused_below_both": float(np.mean(ef < np.minimum(em, eo))),
                                      "mahalanobis_d2_mean_expect_2": {"mri": float(np.mean(d2m)), "motion": float(np.mean(d2o))}}
    return res


def main(argv=None) -> dict:
    from personalize.fusion import fusion_monte_carlo

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/p1_cache"))
    ap.add_argument("--train", type=int, default=12, help="number of subjects (in name order) used to calibrate")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--test-cache", type=Path, default=None,
                    help="held-out subjects from another cache (e.g. a validation run's); default: the rest of --cache")
    a = ap.parse_args(argv)
    subs = load(a.cache)
    train, test = subs[:a.train], subs[a.train:]
    if a.test_cache is not None:
        test = load(a.test_cache)
    cal = calibrate(train)
    measured = [s["skin_measured"] for s in train]
    if all(measured):
        constant = "MRI_HIP_COV_SCALE_MEASURED"
    elif not any(measured):
        constant = "MRI_HIP_COV_SCALE"
    else:
        constant = "mixed training set (measured and prior soft tissue): calibrate each case on its own cache"
    res = {"mri_cov_scale_constant": constant, "train_subjects_with_measured_skin": int(sum(measured)),"units": "mm, mm^2", "cache": str(a.cache), "test_cache": str(a.test_cache or a.cache), "train_subjects": [s["subject"] for s in train],
           "test_subjects": [s["subject"] for s in test],
           "calibration": {"mri_cov_scale": cal["mri_cov_scale"], "mri_cov_scale_by_median": cal["mri_cov_scale_by_median"],
                           "motion_sta_sd_mm": (1e3 * np.sqrt(np.diag(cal["motion_sta_cov"]))).tolist(),
                           "motion_sta_cov_mm2": (1e6 * cal["motion_sta_cov"]).tolist(), "legs": cal["legs"]},
           "errors_train": error_moments(train), "errors_test": error_moments(test) if test else None}
    for name, c, joint in (("claimed_per_leg", None, False), ("calibrated_per_leg", cal, False),
                           ("calibrated_joint_hips", cal, True)):
        res[name] = {"train": evaluate(train, c, joint), "test": evaluate(test, c, joint) if test else None}
    # Monte-Carlo bound: errors truly N(0, calibrated covariance), independent sources (per leg)
    Cm = np.mean([cal["mri_cov_scale"] * sub["C6_mri"][:3, :3] for sub in subs], axis=0)
    mc = fusion_monte_carlo(Cm * 1e6, cal["motion_sta_cov"] * 1e6, n=20000, seed=1)
    em = np.array(res["errors_train"]["mri_bias"])
    mc_b = fusion_monte_carlo(Cm * 1e6, cal["motion_sta_cov"] * 1e6, n=20000, seed=1, bias_a=em)
    # the same with the held-out legs' own error second moments (what the errors really were)
    mc_t = None
    if test:
        et = res["errors_test"]
        mc_t = fusion_monte_carlo(np.array(et["mri_second_moment"]), np.array(et["motion_second_moment"]), n=20000, seed=1)
    # diagnostic only (never used to choose weights): the held-out fraction if the motion information were
    # multiplied by f, for a range of f; shows whether any weighting of these two sources reaches 90 %
    scan = []
    for f in (0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0):
        c2 = {**cal, "motion_sta_cov": cal["motion_sta_cov"] / max(f, 1e-9)}
        ev = evaluate(test or train, c2, True)
        scan.append({"motion_information_factor": f, "fused_below_both_legs": ev["fused_below_both_legs"],
                     "fused_below_both_subjects_worst_side": ev["fused_below_both_subjects_worst_side"],
                     "median_fused_legs_mm": ev["median_mm_legs"]["fused"],
                     "median_fused_worst_side_mm": ev["median_mm_subjects_worst_side"]["fused"]})
    res["weight_scan"] = {"on": "held-out legs" if test else "training legs", "rows": scan}
    # reference cases: with independent Gaussian errors fusion beats both sources in ~55 % of draws whatever the
    # ratio of two isotropic covariances; only sources precise in complementary directions do much better
    ref = {"isotropic_equal": (np.eye(3), np.eye(3)), "isotropic_sd_ratio_6": (np.eye(3), 36 * np.eye(3)),
           "complementary_sd_ratio_3": (np.diag([1.0, 1.0, 9.0]), np.diag([9.0, 9.0, 1.0])),
           "complementary_sd_ratio_10": (np.diag([1.0, 1.0, 100.0]), np.diag([100.0, 100.0, 1.0]))}
    res["monte_carlo_reference_cases"] = {k: fusion_monte_carlo(a, b, n=20000, seed=2)["fraction_below_both"]
                                          for k, (a, b) in ref.items()}
    res["monte_carlo"] = {"independent_zero_mean": mc, "with_training_mri_bias": mc_b, "held_out_second_moments": mc_t,
                          "note": "fused = information-weighted mean with the calibrated covariances; "
                                  "fraction of draws where the fused error is below both sources' errors"}
    names = [s["subject"] for s in train]
    test_knee = (knee_axis_legs(a.test_cache) if a.test_cache is not None
                 else knee_axis_legs(a.cache, [s["subject"] for s in test]))
    from personalize.pipeline.calibration import constants

    pl = constants()
    res["cache_constants"] = cache_constants(a.cache)
    res["pipeline_constants_claimed"] = {k: float(pl[k]) for k in (
        "MRI_HIP_COV_SCALE", "MRI_HIP_COV_SCALE_MEASURED", "MRI_KNEE_AXIS_SD_SCALE", "MOTION_KNEE_AXIS_SD_DEG",
        "MRI_ANKLE_AXIS_SD_SCALE", "MOTION_ANKLE_AXIS_SD_DEG")}
    pc = res["pipeline_constants_claimed"]
    res["knee_axis"] = knee_axes(knee_axis_legs(a.cache, names), test_knee, pc["MRI_KNEE_AXIS_SD_SCALE"],
                                 pc["MOTION_KNEE_AXIS_SD_DEG"])
    # ankle: the same model; the motion (transmalleolar) axis has no estimator sd of its own, the constant is all
    test_ankle = (knee_axis_legs(a.test_cache, key="ankle_axis") if a.test_cache is not None
                  else knee_axis_legs(a.cache, [s["subject"] for s in test], key="ankle_axis"))
    train_ankle = knee_axis_legs(a.cache, names, key="ankle_axis")
    if train_ankle:
        res["ankle_axis"] = knee_axes(train_ankle, test_ankle, pc["MRI_ANKLE_AXIS_SD_SCALE"], pc["MOTION_ANKLE_AXIS_SD_DEG"])
    print(json.dumps(res, indent=1, default=float))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(res, indent=1, default=float) + "\n")
    return res


if __name__ == "__main__":
    main()
