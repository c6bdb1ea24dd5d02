"""Benchmark (issue M1): the personalised muscles against gait2392 scaled to the same subject by OpenSim's ScaleTool.

Builds a phantom on the real ICL-MRI anatomy (OpenSim's marker names), runs the pipeline on it with
``--muscles gait2392``, scales gait2392 to the phantom's virtual (bony) markers with OpenSim's ScaleTool, and
compares muscle by muscle the MTU lengths and the hip, knee and ankle flexion moment arms over sweeps of hip
flexion -20..60 deg, knee flexion 0..90 deg and ankle -20..20 deg, each pose carried to the personalised model as
the same anatomical posture (`personalize.muscles.compare`).  Prints the table and the fractions of muscles within
15 %; target: >= 90 % for each.

Usage::

    python benchmarks/muscles.py [--out DIR] [--subject PHANTOM_DIR --model PIPELINE_OUT] [--n 17] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DATA = Path(os.environ.get("PERSONALIZE_SHARED_DATA", REPO.parent / "shared" / "data"))


def build(out: Path, seed: int = 0) -> tuple[Path, Path]:
    """The ICL-MRI phantom (opensim markers) and its pipeline output with muscles: (subject dir, model dir)."""
    from personalize.evaluation.phantom_builder import PhantomOptions, build_phantom, write_phantom
    from personalize.pipeline import run_subject

    subject, model = out / "subject", out / "model"
    opts = PhantomOptions(seed=seed, anatomy=DATA / "bones" / "ICL_MRI",
                          reference=DATA / "reference_models" / "manual_ICL_MRI.osim", marker_set="opensim",
                          static_frames=20, functional=False)
    write_phantom(build_phantom(opts), subject)
    run_subject(subject, model, report=False, overwrite=True, muscles="gait2392", model_check=False)
    return subject, model


def main() -> None:
    from personalize.muscles.compare import compare_run, table, worst

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="work folder (default: a temporary one)")
    ap.add_argument("--subject", type=Path, help="an existing phantom subject folder (with truth.json)")
    ap.add_argument("--model", type=Path, help="its pipeline output with muscles (model.osim, muscles.json)")
    ap.add_argument("--n", type=int, default=17, help="poses per sweep")
    ap.add_argument("--json", type=Path, help="write the result here")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = a.out or Path(tmp)
        subject, model = (a.subject, a.model) if a.subject and a.model else build(out)
        res = compare_run(model, subject, out / "scale", n=a.n)
        print(table(res))
        print("\nwithin 15 % (target >= 90 %): " + ", ".join(
            f"{k} {100 * v:.0f} % of {res['counts'][k]}" for k, v in res["fractions"].items()))
        for k, rows in worst(res).items():
            print(f"worst {k:12s} " + ", ".join(f"{m} {100 * e:.0f} %" for m, e in rows))
        rep = json.loads((model / "muscles.json").read_text(encoding="utf-8"))
        print("knee axial rotation held to match gait2392's posture (deg): " + ", ".join(
            f"{k} {v * 57.29577951308232:.1f}" for k, v in rep["coordinates"]["held"].items() if "rotation" in k))
        if a.json:
            a.json.write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
