"""Segment lengths and the knee's standing translation fused from the MRI and motion sources."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian
from personalize.parameter_fusion import (MOTION_KNEE_TRANSLATION_SD, MRI_POSTURE_SD, fuse_knee_standing_translation,
                                          fuse_segment_lengths, segment_length)


def test_segment_length_variance_is_the_projection_on_the_segment():
    p, q = np.array([0.0, 0.0, 0.4]), np.zeros(3)
    Cp = np.diag([1e-6, 1e-6, 4e-6])
    L, v = segment_length(p, q, Cp, np.zeros((3, 3)))
    assert L == pytest.approx(0.4) and v == pytest.approx(4e-6)
    # a shared (fully correlated) error moves both ends together: the length does not change
    _, v = segment_length(p, q, Cp, Cp, Cp)
    assert v == pytest.approx(0.0, abs=1e-18)
    with pytest.raises(InputError):
        segment_length(p, p, Cp, Cp)


def test_segment_length_variance_matches_monte_carlo():
    rng = np.random.default_rng(3)
    p, q = np.array([0.02, -0.03, 0.41]), np.array([0.0, 0.01, 0.0])
    A = rng.normal(size=(3, 3)) * 2e-3
    Cp, Cq = A @ A.T, np.diag([4e-6, 1e-6, 9e-6])
    L, v = segment_length(p, q, Cp, Cq)
    P = rng.multivariate_normal(p, Cp, 40000)
    Q = rng.multivariate_normal(q, Cq, 40000)
    Ls = np.linalg.norm(P - Q, axis=1)
    assert np.var(Ls) == pytest.approx(v, rel=0.05)
    assert np.mean(Ls) == pytest.approx(L, abs=3 * np.sqrt(v / 40000) + 1e-4)


def test_fused_lengths_weight_the_precise_source():
    I = np.eye(3)
    mri = {"hip_r": Gaussian([0, 0, 0.80], 1e-8 * I), "knee_r": Gaussian([0, 0, 0.40], 1e-8 * I),
           "ankle_r": Gaussian(np.zeros(3), 1e-8 * I)}
    motion = {"hip_r": Gaussian([0.1, 0.2, 0.81], 1e-4 * I), "knee_r": Gaussian([0.1, 0.2, 0.40], 1e-4 * I),
              "ankle_r": Gaussian([0.1, 0.2, 0.0], 4e-6 * I)}
    out = fuse_segment_lengths(mri, motion, sides=("r",))
    th = out["thigh_r"].summary()
    assert th["mri"] == pytest.approx(0.40) and th["motion"] == pytest.approx(0.41)
    assert th["mri_sd"] == pytest.approx(np.sqrt(2e-8)) and th["motion_sd"] == pytest.approx(np.sqrt(2e-4))
    w = 2e-4 / (2e-4 + 2e-8)                                  # information weight of the MRI
    assert th["fused"]["weights"]["mri"] == pytest.approx(w)
    assert th["fused"]["mean"][0] == pytest.approx(w * 0.40 + (1 - w) * 0.41)
    assert set(out) == {"thigh_r", "shank_r"}


def test_standing_translation_fusion():
    Ck = 1e-6 * np.eye(3)
    tm = np.array([0.003, -0.002, 0.001])
    f = fuse_knee_standing_translation(Ck, tm, 1e-8 * np.eye(3))
    vr = 1e-6 + MRI_POSTURE_SD**2
    vm = 1e-8 + MOTION_KNEE_TRANSLATION_SD**2
    np.testing.assert_allclose(f.mean, vr / (vr + vm) * tm)
    assert f.shares[0] == pytest.approx(vm / (vr + vm))
    np.testing.assert_allclose(np.diag(f.cov), vr * vm / (vr + vm))
