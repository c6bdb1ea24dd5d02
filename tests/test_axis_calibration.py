"""Axis uncertainties: the model-error angle of `benchmarks/axis_calibration.py` and the axis coverage of the
realistic validation (issue #17, [R1]: 95 % coverage of every estimate a user builds on)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def _rayleigh(rng, sd, n):
    """Angles (deg) of unit vectors with isotropic tangent errors of per-direction sd `sd` (deg)."""
    return np.hypot(rng.normal(scale=sd, size=n), rng.normal(scale=sd, size=n))


def test_model_angle_is_recovered_from_rayleigh_errors():
    from axis_calibration import coverage, fit_model_angle

    rng = np.random.default_rng(11)
    claimed = rng.uniform(0.2, 1.5, size=4000)                  # what the registrations state, deg
    theta = _rayleigh(rng, np.hypot(claimed, 4.0), claimed.size)  # true model error 4 deg
    m = fit_model_angle(theta, claimed)
    assert m == pytest.approx(4.0, abs=0.15)
    assert coverage(theta, claimed) < 0.3
    assert coverage(theta, np.hypot(claimed, m)) == pytest.approx(0.95, abs=0.015)
    # an honest claim needs none
    assert fit_model_angle(_rayleigh(rng, claimed, claimed.size), claimed) < 0.2


def test_axis_coverage_of_a_run_summary(tmp_path):
    from personalize.evaluation.realistic_set import coverage_metrics

    est = {"knee_r_axis": {"mri": {"sd_deg": 2.0}, "motion": {"sd_deg": 10.0}, "fused": {"sd_deg": 1.9}},
           "ankle_r_axis": {"mri": {"sd_deg": 3.0}, "motion": {"sd_deg": 10.0}, "fused": {"sd_deg": 2.9}}}
    errs = {"r": {"knee_axis_deg": {"mri": 4.8, "motion": 25.0, "fused": 4.0},
                  "ankle_axis_deg": {"mri": 7.4, "motion": 1.0, "fused": 7.2}}}
    out = coverage_metrics({"estimates": est, "errors_per_side": errs}, tmp_path)    # no truth files: axes only
    # inside the 95 % cone while θ/σ <= 2.448
    assert out["coverage.knee_axis_r.mri"] == 1.0 and out["coverage.knee_axis_r.motion"] == 0.0
    assert out["coverage.knee_axis_r.fused"] == 1.0 and out["coverage.ankle_axis_r.fused"] == 0.0
    assert out["mahalanobis2.ankle_axis_r.mri"] == pytest.approx((7.4 / 3.0) ** 2)
