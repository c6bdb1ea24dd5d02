"""The pipeline's calibrated uncertainty constants, and where their numbers come from (``calibration.json``).

Each constant is defined next to the estimator it parametrises
(`personalize.pipeline.hip`, `knee`, `foot`, `motion`); ``calibration.json``
beside this module records, per constant, its value, the benchmark and the
TRAINING phantom set it was calibrated on and the statistics measured there
(the benchmarks' own result files are not kept in the repository).
"""
from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

__all__ = ["constants", "calibration_record", "CALIBRATION_FILE", "coverage", "fit_scale_and_model_error", "fit_model_error",
           "record_realistic_fit", "record_measured_model_error",
           "record_realistic_check", "CHI2_3_95"]

CALIBRATION_FILE = Path(__file__).with_name("calibration.json")


#: chi-square 95 % quantile with 3 degrees of freedom (a 3-D ellipsoid)
CHI2_3_95 = 7.814727903251178
#: chi-square 95 % quantile with 2 degrees of freedom (an axis's angular error over its per-direction sd, squared)
CHI2_2_95 = 5.991464547107979


def constants() -> dict:
    """Name -> value of every calibrated constant in force (numbers, or lists for matrices)."""
    from . import foot, hip, knee, motion

    out = {}
    for mod in (hip, knee, foot, motion):
        for name in mod.__all__:
            v = getattr(mod, name)
            names = isinstance(v, tuple) and all(isinstance(x, str) for x in v)      # a marker list, not a number
            if name.isupper() and not name.endswith("_MARKERS") and not names and isinstance(v, (int, float, dict, tuple, np.ndarray)):
                out[name] = np.asarray(v).tolist() if isinstance(v, (np.ndarray, tuple)) else v
    return out


def calibration_record() -> dict:
    """``calibration.json``: constant name -> {value, benchmark, training_set, measured, note}."""
    return json.loads(CALIBRATION_FILE.read_text(encoding="utf-8"))["constants"]


def coverage(errors, covs) -> dict:
    """Mean squared Mahalanobis distance d² = eᵀ C⁻¹ e and the fraction of errors inside the 95 % ellipsoid.

    Parameters
    ----------
    errors : (N, 3) m, estimate minus truth; covs : (N, 3, 3) m², the stated covariances

    Returns
    -------
    {"n", "mean_d2", "median_d2", "coverage95"} (an honest 3-D covariance: mean d² 3, coverage 0.95)
    """
    E = np.asarray(errors, float).reshape(-1, 3)
    C = np.asarray(covs, float).reshape(-1, 3, 3)
    d2 = np.einsum("ka,kab,kb->k", E, np.linalg.inv(C), E)
    return {"n": int(len(E)), "mean_d2": float(np.mean(d2)), "median_d2": float(np.median(d2)),
            "coverage95": float(np.mean(d2 <= CHI2_3_95))}


def fit_scale_and_model_error(errors, covs, min_scale: float = 0.1) -> tuple[float, float]:
    """(s, σ) maximising the Gaussian likelihood of `errors` under N(0, s C_k + σ² I), s ≥ `min_scale`.

    Model: e_k ~ N(0, s C_k + σ² I) independently, C_k the propagated covariance of case k (m²), s a
    variance scale, σ a model-error sd (m) that the propagation does not see.  Minimised:

        L(s, σ) = Σ_k [ ln det(s C_k + σ² I) + e_kᵀ (s C_k + σ² I)⁻¹ e_k ]

    over ln s and ln σ (Nelder-Mead from the moment solution s = mean d² / 3, σ = 0.1 rms error;
    σ below 1 µm is reported as 0).  When the optimum has s below `min_scale` (the propagated covariance
    explains nothing of the errors), σ is refitted with s = `min_scale`: the pipeline divides by s to
    take a calibrated anchor back to the registration's scale, and the registration's own spread should
    still rank its subjects.

    Parameters
    ----------
    errors : (N, 3) m; covs : (N, 3, 3) m²

    Returns
    -------
    s (dimensionless), σ (m)
    """
    from scipy.optimize import minimize

    E = np.asarray(errors, float).reshape(-1, 3)
    C = np.asarray(covs, float).reshape(-1, 3, 3)
    eye = np.eye(3)

    def nll(x):
        S = np.exp(x[0]) * C + np.exp(2 * x[1]) * eye
        sign, logdet = np.linalg.slogdet(S)
        return float(np.sum(logdet) + np.einsum("ka,kab,kb->", E, np.linalg.inv(S), E))

    s0 = coverage(E, C)["mean_d2"] / 3.0
    sd0 = 0.1 * float(np.sqrt(np.mean(np.sum(E ** 2, axis=1)) / 3.0))
    best = None
    for x0 in ([np.log(s0), np.log(max(sd0, 1e-6))], [np.log(s0 * 0.1), np.log(max(10 * sd0, 1e-6))]):
        r = minimize(nll, x0, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 4000})
        if best is None or r.fun < best.fun:
            best = r
    s, sd = float(np.exp(best.x[0])), float(np.exp(best.x[1]))
    if s < min_scale:
        r = minimize(lambda y: nll([np.log(min_scale), y[0]]), [best.x[1]], method="Nelder-Mead",
                     options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 2000})
        s, sd = float(min_scale), float(np.exp(r.x[0]))
    return s, (sd if sd >= 1e-6 else 0.0)


def fit_model_error(errors, covs) -> float:
    """σ (m) maximising the Gaussian likelihood of `errors` under N(0, C_k + σ² I): the model-error sd a
    source's stated covariances C_k lack (the scale kept at 1; 0 when they already cover the errors).

    Minimised over ln σ: L(σ) = Σ_k [ ln det(C_k + σ² I) + e_kᵀ (C_k + σ² I)⁻¹ e_k ].
    """
    from scipy.optimize import minimize_scalar

    E = np.asarray(errors, float).reshape(-1, 3)
    C = np.asarray(covs, float).reshape(-1, 3, 3)

    def nll(y):
        S = C + np.exp(2 * y) * np.eye(3)
        return float(np.sum(np.linalg.slogdet(S)[1]) + np.einsum("ka,kab,kb->", E, np.linalg.inv(S), E))

    r = minimize_scalar(nll, bounds=(np.log(1e-6), np.log(0.2)), method="bounded", options={"xatol": 1e-6})
    sd = float(np.exp(r.x))
    return sd if nll(r.x) < nll(np.log(1e-6)) and sd > 2e-6 else 0.0


def _write_record(doc: dict) -> None:
    from lowerlimb.atomic import write_text

    write_text(CALIBRATION_FILE, json.dumps(doc, indent=1, ensure_ascii=False) + "\n")


_FIT_STATS = ("mri_before", "mri_after", "fused_before", "fused_after_offline", "mri_median_error_mm")


def _training_set(f: dict, tissue: str) -> str:
    return (f"{f['subjects']} realistic phantom subjects ({f['legs']} legs, {tissue}), "
            f"draw_realistic_subjects(seed={f['training_seed']}), runnable={f['runnable']}")


def _sd_entry(value: float, benchmark: str, train: str, when: str, training_dir: str, method: str,
              measured: dict) -> dict:
    """One model-error sd's record in ``calibration.json``."""
    return {"value": round(value, 5), "units": "m per axis", "benchmark": benchmark, "training_set": train,
            "fitted": when, "results": training_dir, "method": method, "measured": measured}


def record_realistic_fit(fits: dict, names: dict, benchmark: str, training_dir: str) -> None:
    """Write (s_j, σ_j) of `benchmarks/realistic_calibration.py` fit into ``calibration.json`` with their provenance.

    fits : joint -> {"scale", "model_sd_m", "legs", "subjects", "training_seed", "runnable", statistics ...}
    names : joint -> (scale constant name, model-error constant name[, motion model-error constant name])
    """
    doc = json.loads(CALIBRATION_FILE.read_text(encoding="utf-8"))
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    for jn, f in fits.items():
        sname, mname = names[jn][:2]
        train = _training_set(f, "prior soft tissue")
        stats = {k: f[k] for k in _FIT_STATS if k in f}
        doc["constants"][sname] = {**doc["constants"].get(sname, {}), "value": round(f["scale"], 4),
                                   "benchmark": benchmark, "training_set": train, "measured": stats,
                                   "method": "maximum likelihood of the MRI errors under N(0, s C_reg + sd^2 I)",
                                   "fitted": when, "results": training_dir}
        doc["constants"][mname] = _sd_entry(f["model_sd_m"], benchmark, train, when, training_dir,
                                            "with the scale, maximum likelihood of the MRI errors under "
                                            "N(0, s C_reg + sd^2 I) (prior soft tissue)", stats)
        if len(names[jn]) > 2 and "motion_model_sd_m" in f:
            doc["constants"][names[jn][2]] = _sd_entry(
                f["motion_model_sd_m"], benchmark, train, when, training_dir,
                "maximum likelihood of the motion centre errors under N(0, C_stated + sd^2 I)",
                {k: f[k] for k in ("motion_before", "motion_after", "motion_median_error_mm") if k in f})
    _write_record(doc)


def record_measured_model_error(fits: dict, names: dict, benchmark: str, training_dir: str) -> None:
    """Write σ_j of the measured-tissue path (`benchmarks/realistic_calibration.py` fit) into ``calibration.json``.

    fits : joint -> {"model_sd_m", "legs", "subjects", "training_seed", "runnable", statistics ...}
    names : joint -> (scale constant name, model-error constant name)
    """
    doc = json.loads(CALIBRATION_FILE.read_text(encoding="utf-8"))
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    for jn, f in fits.items():
        doc["constants"][names[jn][1]] = _sd_entry(
            f["model_sd_m"], benchmark, _training_set(f, "pelvic tissue measured in the skin label"), when,
            training_dir, "maximum likelihood of the MRI errors under N(0, C_stated + sd^2 I), the measured scale kept",
            {k: f[k] for k in _FIT_STATS if k in f})
    _write_record(doc)


def record_realistic_check(report: dict, names: dict, seed: int, runnable: str, folder: str) -> None:
    """Add the CHECK seed's coverage (`benchmarks/realistic_calibration.py` check) to the constants' records."""
    doc = json.loads(CALIBRATION_FILE.read_text(encoding="utf-8"))
    for jn, rep in report.items():
        sname = names[jn][0]
        rec = doc["constants"].setdefault(sname, {})
        rec["check"] = {"seed": seed, "runnable": runnable, "legs": rep["legs"], "results": folder,
                        **{src: rep[src] for src in ("mri", "motion", "fused") if src in rep}}
    _write_record(doc)
