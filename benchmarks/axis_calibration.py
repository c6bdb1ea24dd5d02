"""Calibration of the knee and ankle axis uncertainties on the realistic validation phantoms ([V1]).

An axis estimate u with stated 1-sd angle σ (per tangent direction, `personalize.registration`'s
``sqrt(trace / 2)``) is honest when its angular error θ to the truth is Rayleigh with that σ:
p(θ) = θ/σ² exp(-θ²/2σ²), so that 95 % of the errors lie below 2.45 σ.

MRI axes (the femur or shank registration carrying the MRI axis into the lab): the registration's claim σ_reg,
scaled by ``MRI_<J>_AXIS_SD_SCALE`` (fitted on phantoms whose markers sit exactly on the joint axes), misses what
palpating real epicondyles and malleoli does to the segment's rotation about its long axis, so a model-error
angle m is added,

    σ² = (s σ_reg)² + m²,    m = argmax Σ_legs [ -ln σ² - θ²/(2σ²) ],

``MRI_<J>_AXIS_MODEL_SD_DEG`` on the legs with prior soft tissue (real anatomy) of one bone set
(``--choose-on``), checked on the others', and ``MRI_<J>_AXIS_MODEL_SD_DEG_MEASURED`` on those whose pelvic
tissue is measured (analytic anatomy).

Motion axes: one σ per kind of estimate, the Rayleigh maximum likelihood σ² = Σθ²/(2n) over the training legs
of that kind and anatomy, the largest over the anatomies (a source's error depends on the bones its markers sit
on: one pooled value left one set's legs under-covered): SARA on a walk (``MOTION_KNEE_AXIS_SD_DEG``) and the
transmalleolar line of the static trial (``MOTION_ANKLE_AXIS_SD_DEG``).  The Plug-in-Gait axes keep their own sds (reported).

Training legs: the summaries of `benchmarks/realistic_calibration.py run` folders (their ``results.json`` gives
the constants in force).  Usage::

    python benchmarks/axis_calibration.py --train /tmp/cal/train [/tmp/cal/train_an] [--write]
"""
from __future__ import annotations

import argparse
import json
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: motion source of a leg (summary ``sources``' first word) -> the constant its sd is
MOTION_SOURCES = {("knee", "SARA"): "MOTION_KNEE_AXIS_SD_DEG", ("ankle", "transmalleolar"): "MOTION_ANKLE_AXIS_SD_DEG"}


def axis_legs(folders) -> list[dict]:
    """Per leg and axis: MRI and motion stated sds and errors (deg), the motion source and the tissue path."""
    rows = []
    for folder in map(Path, folders):
        const = json.loads((folder / "results.json").read_text())["constants"]
        for f in sorted((folder / "results").glob("*/summary.json")):
            s = json.loads(f.read_text())
            spec = folder / "subjects" / f.parent.name / "realistic.json"
            anatomy = json.loads(spec.read_text())["anatomy"] if spec.is_file() else "?"
            measured = any(v.get("source") == "MRI" for v in (s.get("skin_thickness") or {}).values())
            for side in s["sides"]:
                for j in ("knee", "ankle"):
                    e = (s.get("estimates") or {}).get(f"{j}_{side}_axis")
                    err = (s.get("errors_per_side") or {}).get(side, {}).get(f"{j}_axis_deg")
                    if not e or not err:
                        continue
                    key = f"MRI_{j.upper()}_AXIS_MODEL_SD_DEG" + ("_MEASURED" if measured else "")
                    m_then = float(const.get(key, 0.0))
                    rows.append({"subject": f.parent.name, "anatomy": anatomy, "joint": j, "measured": measured,
                                 "mri_sd": float(np.sqrt(max(e["mri"]["sd_deg"] ** 2 - m_then ** 2, 0.0))),
                                 "mri_err": float(err["mri"]), "motion_sd": float(e["motion"]["sd_deg"]),
                                 "motion_err": float(err["motion"]),
                                 "motion_source": s["sources"].get(f"{j}_axis_{side}_motion", "").split(" ")[0]})
    return rows


def coverage(theta, sd) -> float:
    """Fraction of the angular errors inside the stated 95 % cone."""
    from personalize.pipeline.calibration import CHI2_2_95

    return float(np.mean((np.asarray(theta) / np.asarray(sd)) ** 2 <= CHI2_2_95))


def fit_model_angle(theta, sd) -> float:
    """m (deg) maximising the Rayleigh likelihood of `theta` under σ² = sd² + m²."""
    th, s2 = np.maximum(np.asarray(theta, float), 1e-6), np.asarray(sd, float) ** 2

    def nll(m):
        v = s2 + m * m
        return float(np.sum(np.log(v) + th ** 2 / (2.0 * v)))

    return float(minimize_scalar(nll, bounds=(0.0, 45.0), method="bounded").x)


def fit(folders, choose_on: str = "LHDL_CT") -> dict:
    """The constants of the module docstring; the MRI model-error angles of the prior-tissue path are chosen on the
    legs of anatomy `choose_on` and checked on every other anatomy (``coverage95_by_anatomy``)."""
    rows = axis_legs(folders)
    out = {}

    def by_anatomy(rs, sd_of):
        return {a: coverage([r[k] for r in rs if r["anatomy"] == a], [sd_of(r) for r in rs if r["anatomy"] == a])
                for a in sorted({r["anatomy"] for r in rs}) for k in ("mri_err" if "mri" in sd_of.__name__ else "motion_err",)}

    for j in ("knee", "ankle"):
        for measured in (False, True):
            rs = [r for r in rows if r["joint"] == j and r["measured"] == measured]
            chosen = [r for r in rs if measured or r["anatomy"] == choose_on]
            if len(chosen) < 4:
                continue
            m = fit_model_angle([r["mri_err"] for r in chosen], [r["mri_sd"] for r in chosen])

            def mri_sd(r, m=m):
                return float(np.hypot(r["mri_sd"], m))

            name = f"MRI_{j.upper()}_AXIS_MODEL_SD_DEG" + ("_MEASURED" if measured else "")
            out[name] = {"value": round(m, 2), "chosen_on": "analytic anatomy" if measured else choose_on,
                         "legs": len(chosen), "median_error_deg": float(np.median([r["mri_err"] for r in rs])),
                         "coverage95_before": coverage([r["mri_err"] for r in rs], [r["mri_sd"] for r in rs]),
                         "coverage95_by_anatomy": by_anatomy(rs, mri_sd)}
    for (j, src), name in MOTION_SOURCES.items():
        rs = [r for r in rows if r["joint"] == j and r["motion_source"] == src]
        if len(rs) < 4:
            continue
        per_set = {a: float(np.sqrt(np.mean(np.square([r["motion_err"] for r in rs if r["anatomy"] == a])) / 2.0))
                   for a in sorted({r["anatomy"] for r in rs})}
        sd = max(per_set.values())

        def motion_sd(r, sd=sd):
            return sd

        out[name] = {"value": round(sd, 2), "chosen_on": "the largest of the per-anatomy values", "per_anatomy": per_set,
                     "legs": len(rs),
                     "median_error_deg": float(np.median([r["motion_err"] for r in rs])),
                     "coverage95_before": coverage([r["motion_err"] for r in rs], [r["motion_sd"] for r in rs]),
                     "coverage95_by_anatomy": by_anatomy(rs, motion_sd)}
    return out


def write(fits: dict, folders) -> None:
    from personalize.pipeline.calibration import CALIBRATION_FILE, _write_record

    doc = json.loads(CALIBRATION_FILE.read_text(encoding="utf-8"))
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    for name, f in fits.items():
        doc["constants"][name] = {"value": f["value"], "units": "deg", "benchmark": "benchmarks/axis_calibration.py",
                                  "training_set": ", ".join(map(str, folders)), "fitted": when,
                                  "method": "Rayleigh maximum likelihood of the angular errors",
                                  "measured": {k: v for k, v in f.items() if k != "value"}}
    _write_record(doc)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--train", type=Path, nargs="+", required=True)
    ap.add_argument("--choose-on", default="LHDL_CT", help="anatomy whose legs choose the MRI model-error angles")
    ap.add_argument("--write", action="store_true", help="record the fits in personalize/pipeline/calibration.json")
    a = ap.parse_args(argv)
    fits = fit(a.train, a.choose_on)
    print(json.dumps(fits, indent=1))
    if a.write:
        write(fits, a.train)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
