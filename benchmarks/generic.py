"""Benchmark (issue M1): what MRI personalisation buys over gait2392 scaled to the same markers.

Runs the [V1] realistic validation subjects (`personalize.evaluation.realistic_set.draw_realistic_subjects`: real
ICL-MRI and LHDL-CT anatomy with four marker sets and both lab orientations, and analytic phantoms) through
`personalize run` with the comparison on (`personalize.generic_comparison`), and tabulates per marker set and lab
the median joint-centre errors against the truth (static pose, mm; both sides pooled) and the median gait-angle
RMSE (deg) of the personalised model and of the scaled gait2392.

Usage::

    python benchmarks/generic.py [--subjects 24] [--seed 0] [--workers 2] [--out DIR] [--json FILE] [--rows FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DATA = Path(os.environ.get("PERSONALIZE_SHARED_DATA", REPO.parent / "shared" / "data"))
ANGLES = ("hip_flexion", "hip_adduction", "hip_rotation", "knee_flexion", "ankle_angle")


def one(spec_json: dict, work: str) -> dict:
    """Materialise one realistic subject and run it with the comparison: a row of errors (or the refusal)."""
    from lowerlimb.atomic import write_text
    from lowerlimb.errors import FitError, InputError
    from personalize.evaluation.realistic_set import REALISTIC_SPEC, ensure_realistic_subject
    from personalize.pipeline import run_subject

    d = Path(work) / spec_json["subject"]
    d.mkdir(parents=True, exist_ok=True)
    write_text(d / REALISTIC_SPEC, json.dumps(spec_json) + "\n")
    ensure_realistic_subject(d)
    row = {k: spec_json[k] for k in ("subject", "anatomy", "marker_set", "lab", "tissue", "functional")}
    try:
        s = run_subject(d, Path(work) / "out" / spec_json["subject"], report=False, overwrite=True, muscles="none",
                        generic=True)
    except (InputError, FitError) as exc:
        return {**row, "refused": str(exc)}
    g = s.get("generic") or {}
    t = g.get("truth") or {}
    for j, e in (t.get("centre_error_mm") or {}).items():
        row[f"{j}_mm"] = (e["personalised"], e["generic"])
    for c, e in (t.get("angle_rmse_deg") or {}).items():
        row[f"{c}_deg"] = (e["personalised"], e["generic"])
    row["scale_factors"] = g.get("scale_factors")
    row["marker_rms_mm"] = {k: v["marker_rms_mm"] for k, v in (g.get("trials") or {}).items()}
    return row


def _medians(rows: list, keys, suffix: str) -> dict:
    """key -> (personalised median, generic median, n) over the rows' ``<key><side>_<suffix>`` entries (both sides
    pooled)."""
    out = {}
    for k in keys:
        v = np.array([r[f"{k}{s}{suffix}"] for r in rows for s in "rl" if f"{k}{s}{suffix}" in r], float)
        if len(v):
            out[k] = (float(np.median(v[:, 0])), float(np.median(v[:, 1])), len(v))
    return out


def table(rows: list) -> str:
    groups: dict = {}
    for r in rows:
        if "refused" not in r:
            groups.setdefault((r["marker_set"], r["lab"]), []).append(r)
    groups[("all", "all")] = [r for r in rows if "refused" not in r]
    keys = ("hip_", "knee_", "ankle_")
    lines = ["| marker set | lab | n | " + " | ".join(f"{k[:-1]} centre mm (pers. / generic)" for k in keys)
             + " | " + " | ".join(f"{a} RMSE deg" for a in ("hip_flexion", "knee_flexion", "ankle_angle")) + " |",
             "|---|---|---|" + "---|" * 6]
    for (ms, lab), rs in sorted(groups.items(), key=lambda kv: (kv[0][0] == "all", kv[0])):
        cm = _medians(rs, keys, "_mm")
        angles = ("hip_flexion_", "knee_flexion_", "ankle_angle_")
        am = _medians(rs, angles, "_deg")
        cells = [f"{cm[k][0]:.1f} / {cm[k][1]:.1f}" if k in cm else "-" for k in keys]
        cells += [f"{am[k][0]:.1f} / {am[k][1]:.1f}" if k in am else "-" for k in angles]
        lines.append(f"| {ms} | {lab} | {len(rs)} | " + " | ".join(cells) + " |")
    refused = [r for r in rows if "refused" in r]
    if refused:
        lines.append(f"\nrefused: {', '.join(r['subject'] for r in refused)}")
    return "\n".join(lines)


def main() -> None:
    from personalize.evaluation.realistic_set import draw_realistic_subjects

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subjects", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, help="work folder (default: a temporary one)")
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--rows", type=Path, help="tabulate the rows of an earlier --json instead of running")
    a = ap.parse_args()
    if a.rows:
        print(table(json.loads(a.rows.read_text(encoding="utf-8"))))
        return
    specs = [s.to_json() for s in draw_realistic_subjects(a.subjects, a.seed, DATA)]
    with tempfile.TemporaryDirectory() as tmp:
        work = os.fspath(a.out or tmp)
        with ProcessPoolExecutor(a.workers) as pool:
            rows = list(pool.map(one, specs, [work] * len(specs)))
    print(table(rows))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(rows, indent=1, default=float) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
