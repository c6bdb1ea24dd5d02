"""personalize.evaluation (phantom_set, metrics, validate) and its report: random phantom cohorts, metrics.csv, report.html."""
from __future__ import annotations

import json
from html.parser import HTMLParser

import numpy as np
import pytest

from lowerlimb.errors import InputError
from personalize.evaluation.metrics import flatten_metrics, fusion_statistics, metric_groups, metric_statistics, read_metrics
from personalize.evaluation.phantom_set import DEFAULT_RANGES, SURFACE_JOB, draw_subjects
from personalize.evaluation.validate import run_validation

SMALL = {"inplane_mm": (2.5, 3.0), "slice_mm": (3.0, 3.5)}  # coarse voxels keep the test fast


def test_draws_are_reproducible_and_in_range():
    a, b = draw_subjects(6, 11), draw_subjects(6, 11)
    assert a == b
    assert draw_subjects(3, 11) == a[:3]                  # subject i depends on (seed, i) only
    assert draw_subjects(6, 12) != a
    assert len({s.seed for s in a}) == 6
    for s in a:
        lo, hi = DEFAULT_RANGES["stature_m"]
        assert lo <= s.params["stature"] <= hi
        assert -10 <= s.params["femoral_anteversion_deg"] <= 40
        vox = sorted(s.voxel_mm)
        assert DEFAULT_RANGES["inplane_mm"][0] <= vox[0] == vox[1] <= DEFAULT_RANGES["inplane_mm"][1]
        assert DEFAULT_RANGES["slice_mm"][0] <= max(s.voxel_mm) <= DEFAULT_RANGES["slice_mm"][1] or vox[2] == vox[0]
        assert 0.2e-3 <= s.marker_noise_m <= 1.0e-3
    # the anisotropic axis varies between subjects
    assert len({int(np.argmax(s.voxel_mm)) for s in draw_subjects(12, 0)}) > 1
    with pytest.raises(InputError, match="--subjects"):
        draw_subjects(0, 1)


def test_metric_flattening_and_grouping():
    summary = {"seed": 3, "units": {"distance": "mm"},
               "errors": {"hip_centre_mm": {"fused": 2.0, "mri": 3.0, "motion": 9.0},
                          "knee_axis_deg": {"mri": 2.5, "motion": 4.0, "fused": 1.5}},
               "ik_rms_mm": 4.2, "angle_rmse_deg": {"knee_flexion": 2.0, "hip_flexion": 1.0},
               "surfaces": {"femur_r": {"mean_abs_distance_mm": 0.3, "volume_error_pct": -1.0},
                            "tibia_r": {"mean_abs_distance_mm": 0.4, "volume_error_pct": 2.0}},
               "ok": True, "note": "text"}
    m = flatten_metrics(summary)
    assert m["errors.hip_centre_mm.motion"] == 9.0 and m["ik_rms_mm"] == 4.2
    assert "seed" not in m and "ok" not in m and "note" not in m and not any(k.startswith("units") for k in m)
    g = metric_groups(list(m))
    assert [lbl for lbl, _ in g["errors.hip_centre_mm"]] == ["mri", "motion", "fused"]
    assert g["ik_rms_mm"] == [("ik_rms_mm", "ik_rms_mm")]
    assert dict(g["angle_rmse_deg"]) == {"knee_flexion": "angle_rmse_deg.knee_flexion",
                                         "hip_flexion": "angle_rmse_deg.hip_flexion"}
    assert dict(g["surfaces.mean_abs_distance_mm"]) == {"femur_r": "surfaces.femur_r.mean_abs_distance_mm",
                                                        "tibia_r": "surfaces.tibia_r.mean_abs_distance_mm"}
    rows = [{"x": 1.0}, {"x": 3.0}, {"x": float("nan")}, {"x": 5.0}]
    (st,) = metric_statistics(rows, ["x"])
    assert st["n"] == 3 and st["mean"] == 3.0 and st["sd"] == 2.0 and st["median"] == 3.0 and st["max"] == 5.0


class _Imgs(HTMLParser):
    def __init__(self):
        super().__init__()
        self.imgs = 0
        self.tables = 0

    def handle_starttag(self, tag, attrs):
        self.imgs += tag == "img"
        self.tables += tag == "table"


def test_validation_run_writes_metrics_and_report(tmp_path):
    """Two phantom subjects (femur only, 2.5-3.5 mm voxels, with motion trials) through the surface job."""
    out = tmp_path / "val"
    res = run_validation(2, 4, out, workers=2, bones=["femur_r"], ranges=SMALL, job=SURFACE_JOB, progress=False)
    assert res.batch.counts == {"ok": 2, "error": 0, "skipped": 0}
    rows = read_metrics(res.metrics_csv)
    specs = draw_subjects(2, 4, ranges=SMALL, bones=["femur_r"])
    assert [r["subject"] for r in rows] == [s.subject for s in specs]
    for r, s in zip(rows, specs):
        assert r["status"] == "ok"
        assert (r["voxel_x_mm"], r["voxel_y_mm"], r["voxel_z_mm"]) == pytest.approx(s.voxel_mm, abs=1e-4)
        assert r["marker_noise_mm"] == pytest.approx(s.marker_noise_m * 1e3, rel=1e-5)
        # surfaces from 2.5-3.5 mm label volumes against the exact phantom femur: sub-voxel mean distance
        assert 0.05 < r["surfaces.femur_r.mean_abs_distance_mm"] < 0.5 * max(s.voxel_mm)
        assert abs(r["surfaces.femur_r.volume_error_pct"]) < 5.0
        subj = out / "subjects" / s.subject
        truth = json.loads((subj / "truth.json").read_text())
        assert truth["motion"]["noise_sd_m"] == pytest.approx(s.marker_noise_m)   # motion phantom written
        assert truth["params"]["stature"] == pytest.approx(s.params["stature"])
        assert (subj / "static.c3d").is_file() and (subj / "gait_01.c3d").is_file()
        assert truth["image"]["voxel_m"] == pytest.approx([v * 1e-3 for v in s.voxel_mm])
    p = _Imgs()
    p.feed(res.report.read_text())
    assert p.imgs == 3          # one box plot per metric group (mean distance, max distance, volume error)
    assert p.tables == 2        # statistics + draws
    # same n and seed: resumes (nothing re-run), same metrics
    before = res.metrics_csv.read_text()
    res2 = run_validation(2, 4, out, workers=1, bones=["femur_r"], ranges=SMALL, job=SURFACE_JOB, progress=False)
    assert res2.batch.counts == {"ok": 0, "error": 0, "skipped": 2}
    assert res2.metrics_csv.read_text() == before
    with pytest.raises(InputError, match="other settings"):
        run_validation(2, 5, out, bones=["femur_r"], ranges=SMALL, job=SURFACE_JOB, progress=False)


def test_validate_command_refuses_bad_options(tmp_path, capsys):
    from personalize.cli import main

    assert main(["validate", "--subjects", "0", "--out", str(tmp_path / "v")]) == 2
    assert "--subjects: 0 is outside 1-10000" in capsys.readouterr().err
    assert main(["validate", "--subjects", "2", "--out", str(tmp_path / "v"), "--job", "no_such_module.job"]) == 2
    assert "cannot import no_such_module" in capsys.readouterr().err
    assert not (tmp_path / "v" / "metrics.csv").exists()


def test_report_of_pipeline_shaped_metrics(tmp_path):
    """Headline metrics (errors per source, IK RMS) are tabled and plotted; estimates only go to metrics.csv."""
    from personalize.presentation.validation_report import validation_report

    rng = np.random.default_rng(0)
    rows = []
    for i in range(5):
        summary = {"errors": {j: {s: float(rng.uniform(0, 10)) for s in ("fused", "mri", "motion")}
                              for j in ("hip_centre_mm", "knee_axis_deg", "ankle_axis_deg")},
                   "ik_rms_mm": float(rng.uniform(2, 9)),
                   "ik": {"gait_01": {"rms_mean_mm": 3.0 + i, "frames": 200}},
                   "estimates": {"hip_r": {"fused": {"x": 0.1, "y": 0.2, "z": 0.3}}},
                   "registration": {"femur_r": {"rms_mm": 1.0 + i}}}
        rows.append({"subject": f"p{i}", "status": "ok" if i < 4 else "error", "error": "" if i < 4 else "x: bad",
                     "stature": 1.7, **flatten_metrics(summary)})
    cols = [c for c in rows[0] if c not in ("subject", "status", "error", "stature")]
    assert "ik.gait_01.frames" not in cols
    path = validation_report(tmp_path / "r.html", rows, cols, ["stature"], seed=0, job="j")
    p = _Imgs()
    p.feed(path.read_text())
    assert p.imgs == 5        # hip, knee axis, ankle axis box plots; ik_rms_mm histogram; IK per trial
    assert p.tables == 5      # headline statistics, fusion vs sources, other quantities, failed subjects, draws
    assert "Fusion against each source" in path.read_text()
    text = path.read_text()
    assert "errors.hip_centre_mm.fused" in text and "registration.femur_r.rms_mm" in text
    assert "estimates.hip_r" not in text
    # statistics over the 4 completed subjects only
    hip = [r["errors.hip_centre_mm.mri"] for r in rows[:4]]
    (st,) = metric_statistics(rows[:4], ["errors.hip_centre_mm.mri"])
    assert st["mean"] == pytest.approx(np.mean(hip)) and f"{np.max(hip):.4g}" in text


def test_fusion_statistics_per_subject_and_leg():
    """Fractions of fused-below-both / -MRI / -motion and medians, from the summary's worst side and per-side errors."""
    legs = {"p0": {"r": (2.0, 10.0, 1.5), "l": (1.0, 8.0, 1.2)},     # right: fused best; left: MRI best
            "p1": {"r": (3.0, 2.0, 2.5), "l": (2.0, 9.0, 1.9)},      # right: motion best; left: fused best
            "p2": {"r": (1.0, 12.0, 0.9), "l": (1.5, 11.0, 1.4)}}    # fused best on both
    rows = []
    for name, sides in legs.items():
        per_side = {s: {"hip_centre_mm": dict(zip(("mri", "motion", "fused"), v))} for s, v in sides.items()}
        worst = {"hip_centre_mm": {src: max(per_side[s]["hip_centre_mm"][src] for s in sides) for src in ("mri", "motion", "fused")}}
        rows.append({"subject": name, **flatten_metrics({"errors": worst, "errors_per_side": per_side})})
    st = {r["unit"]: r for r in fusion_statistics(rows)}
    leg, subj = st["leg"], st["subject (worst side)"]
    assert leg["n"] == 6 and leg["fused_below_both"] == pytest.approx(4 / 6) and leg["fused_below_mri"] == pytest.approx(5 / 6)
    assert leg["fused_below_motion"] == pytest.approx(5 / 6)
    # worst sides: p0 (2, 10, 1.5) fused best; p1 (3, 9, 2.5) fused best; p2 (1.5, 12, 1.4) fused best
    assert subj["n"] == 3 and subj["fused_below_both"] == 1.0 and subj["median_mri"] == 2.0 and subj["median_fused"] == 1.5
    assert fusion_statistics([{"subject": "x"}]) == []
