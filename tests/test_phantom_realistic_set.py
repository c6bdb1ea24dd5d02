"""The realistic validation set's design and its coverage metric."""
from __future__ import annotations

import numpy as np

from kinematics.io.markers import MarkerTrial


def test_realistic_set_covers_every_level(shared_data):
    from personalize.evaluation.realistic_set import draw_realistic_subjects

    specs = draw_realistic_subjects(20, 0, shared_data)
    assert len(specs) == 20
    assert {s.anatomy for s in specs} == {"analytic", "ICL_MRI", "LHDL_CT"}
    assert {s.marker_set for s in specs} == {"pig", "ior", "cast", "opensim"}
    assert {s.lab for s in specs} == {"z-up", "y-up"} and {s.tissue for s in specs} == {"child", "adult", "obese"}
    assert sum(not s.functional for s in specs) == 10
    assert {s.imaging for s in specs} == {"labels", "meshes"}
    assert {s.static_name for s in specs} == {"static", "Static"} and {s.trial_format for s in specs} == {"c3d", "trc"}
    assert min(s.static_frames for s in specs) == 7
    for ms in ("ior", "cast", "opensim"):                       # every non-PiG set in both labs
        assert {s.lab for s in specs if s.marker_set == ms} == {"z-up", "y-up"}
    assert draw_realistic_subjects(20, 0, shared_data) == specs  # reproducible


def test_coverage_metric_counts_truth_inside_the_95_ellipsoid(tmp_path):
    from kinematics.io.storage import write_trc
    from personalize.evaluation.realistic_set import coverage_metrics

    (tmp_path / "truth").mkdir()
    t = np.array([[[0.1, 0.2, 0.9]]])
    write_trc(tmp_path / "truth" / "static_centres.trc", MarkerTrial(("RHJC",), np.repeat(t, 3, 0), 100.0, np.arange(3) / 100))
    sd = 0.004
    cov = (sd**2 * np.eye(3)).tolist()
    summary = {"estimates": {"hip_r_centre": {
        "mri": (t[0, 0] + [0.003, 0, 0]).tolist(), "mri_cov": cov,          # 0.75 sd: inside
        "motion": (t[0, 0] + [0.012, 0, 0]).tolist(), "motion_cov": cov,    # 3 sd: outside (chi2 9 > 7.81)
        "fused": {"mean": (t[0, 0] + [0.0, 0.01, 0]).tolist(), "cov": cov}}}}
    m = coverage_metrics(summary, tmp_path)
    assert m["coverage.hip_r.mri"] == 1.0 and m["coverage.hip_r.motion"] == 0.0 and m["coverage.hip_r.fused"] == 1.0
    assert abs(m["mahalanobis2.hip_r.motion"] - 9.0) < 1e-3


def test_no_palpation_ablation_reaches_the_real_anatomy_phantoms(shared_data, tmp_path, monkeypatch):
    """``--no-palpation``: the same draws with the bony markers placed exactly; the flag survives realistic.json and
    reaches `phantoms.real_subject.write_real_subject`."""
    import json
    from dataclasses import replace

    import phantoms.real_subject as rs
    from personalize.evaluation import realistic_set as R

    a = R.draw_realistic_subjects(6, 0, shared_data)
    b = R.draw_realistic_subjects(6, 0, shared_data, palpation=False)
    assert all(s.palpation for s in a) and [replace(s, palpation=False) for s in a] == b
    spec = next(s for s in b if s.anatomy != "analytic")
    assert R.RealisticSpec.from_json(json.loads(json.dumps(spec.to_json()))) == spec
    d = tmp_path / "subject"
    d.mkdir()
    (d / R.REALISTIC_SPEC).write_text(json.dumps(spec.to_json()), encoding="utf-8")
    seen = {}
    monkeypatch.setattr(rs, "write_real_subject", lambda stage, anat, **kw: seen.update(kw))
    monkeypatch.setattr(R, "_real_anatomy", lambda root, name: None)
    R.ensure_realistic_subject(d)
    assert seen["palpation"] is False
