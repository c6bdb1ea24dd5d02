"""Soft tissue estimated with the registration, its body-build prior, and the coverage calibration's statistics."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.gait.soft_tissue import (REFERENCE_AGE, REFERENCE_BMI, SCALE_LOG_SD, SITE_LOG_SD, TissueScalePrior,
                                         body_fat_fraction, tissue_prior, tissue_scale_prior)
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS
from personalize.pipeline.calibration import CHI2_3_95, coverage, fit_model_error, fit_scale_and_model_error
from personalize.registration import PALPATION_SD, register_landmarks

R_TRUE = Rotation.from_rotvec([0.2, -0.1, 1.4]).as_matrix()
T_TRUE = np.array([0.4, -0.2, 0.9])
NAMES = ("RASI", "LASI", "RPSI", "LPSI")
#: pelvis-sized bony landmarks (scanner, m): ASIS in front, PSIS behind, and their outward normals
BONE = np.array([[0.060, -0.115, 0.000], [0.060, 0.115, 0.000], [-0.100, -0.040, 0.020], [-0.100, 0.040, 0.020]])
NORMALS = np.array([[0.9, -0.3, 0.2], [0.9, 0.3, 0.2], [-0.9, -0.2, 0.3], [-0.9, 0.2, 0.3]])
NORMALS = NORMALS / np.linalg.norm(NORMALS, axis=1, keepdims=True)
HIP = np.array([0.0, -0.08, -0.07])          # a right hip centre in the same frame
MU = np.array([tissue_prior(n).mean for n in NAMES])


def _markers(thickness, rng=None, sd=0.0):
    q = BONE + (np.asarray(thickness) + DEFAULT_MARKER_RADIUS)[:, None] * NORMALS
    m = q @ R_TRUE.T + T_TRUE
    return m if rng is None else m + rng.normal(0.0, sd, m.shape)


def _register(M, prior, msd=2e-4):
    return register_landmarks(BONE, M, None, msd, normals=NORMALS, offset=MU + DEFAULT_MARKER_RADIUS,
                              offset_sd=np.array([tissue_prior(n).sd for n in NAMES]), normal_sd_deg=2.0,
                              names=NAMES, tissue=MU if prior is not None else None, tissue_prior=prior)


def test_prior_from_height_and_mass():
    """k₀ = fat-mass index over the reference's (Deurenberg 1991): hand-computed values."""
    assert body_fat_fraction(REFERENCE_BMI, REFERENCE_AGE) == pytest.approx(0.2665)
    ref = tissue_scale_prior(1.70, REFERENCE_BMI * 1.70 ** 2)
    assert ref.median == pytest.approx(1.0) and ref.log_sd < SCALE_LOG_SD
    # BMI 30, age unknown: BF = 1.2 * 30 + 0.23 * 35 - 5.4 - 5.4 = 33.25 %
    assert tissue_scale_prior(1.80, 30 * 1.80 ** 2).median == pytest.approx(0.3325 * 30 / (0.2665 * 24.5), rel=1e-9)
    # a 10-year-old of BMI 16 (children's formula): BF = 1.51 * 16 - 7.0 - 1.8 + 1.4 = 16.76 %
    assert tissue_scale_prior(1.40, 16 * 1.40 ** 2, age=10).median == pytest.approx(0.1676 * 16 / (0.2665 * 24.5))
    none = tissue_scale_prior(None, 70.0)
    assert none.median == 1.0 and none.log_sd == SCALE_LOG_SD and "no height" in none.basis


@pytest.mark.parametrize("k_true", [2.5, 4.0])
def test_known_tissue_scale_recovered(k_true):
    """Markers over k x the table's tissue (a thick subject, exact geometry).  Fixed at the table, the fit
    fails its chi-square (p 7e-4 at k = 2.5, 1.5e-13 at k = 4: the gate would refuse the subject) with 23-41 mm
    residuals; estimated, k comes back within 2 stated sd (2.19 +- 19 %, 3.31 +- 19 % with SITE_LOG_SD 0.4: the
    per-site sd shrinks it toward the prior), the residuals are 5-11 mm, p 0.3-0.8, and the hip is within 2.5 mm
    (1.2, 2.2) and inside its 95 % ellipsoid."""
    M = _markers(k_true * MU)
    prior = TissueScalePrior(1.0, SCALE_LOG_SD, SITE_LOG_SD, "test")
    reg, fixed = _register(M, prior), _register(M, None)
    assert abs(np.log(reg.tissue_scale / k_true)) < 2 * reg.tissue_scale_log_sd
    assert reg.tissue_scale > 0.8 * k_true and reg.tissue_scale_log_sd < 0.2 < SCALE_LOG_SD
    assert set(reg.tissue) == set(NAMES)
    t, sd = reg.tissue["RPSI"]
    assert t == pytest.approx(reg.tissue_scale * MU[2]) and 0 < sd < t
    assert fixed.p_value < 1e-3 and fixed.rms > 0.02
    assert reg.p_value > 0.1 and reg.rms < 0.4 * fixed.rms
    y, C = reg.transfer_point(HIP)
    e = y - (R_TRUE @ HIP + T_TRUE)
    assert np.linalg.norm(e) < 2.5e-3 and e @ np.linalg.solve(C, e) < 7.8


def test_tissue_scale_uncertainty_covers_truth():
    """40 subjects: k, each site and the palpation drawn as the model says, 2 mm marker noise; the stated sd of ln k covers the
    true scale (|z| < 1.96 in 85-100 %) and the hip error is covered by its stated covariance (mean d² near 3)."""
    rng = np.random.default_rng(7)
    prior = TissueScalePrior(1.0, SCALE_LOG_SD, SITE_LOG_SD, "test")
    z, d2 = [], []
    for _ in range(40):
        k = np.exp(rng.normal(0.0, SCALE_LOG_SD))
        t = k * MU * np.exp(rng.normal(0.0, SITE_LOG_SD, 4))
        palp = rng.normal(0.0, PALPATION_SD, (4, 3))
        palp -= np.einsum("ki,ki->k", palp, NORMALS)[:, None] * NORMALS       # palpation slides along the skin
        reg = _register(_markers(t, rng, 0.002) + palp @ R_TRUE.T, prior, msd=0.002)
        z.append((np.log(reg.tissue_scale) - np.log(k)) / reg.tissue_scale_log_sd)
        y, C = reg.transfer_point(HIP)
        e = y - (R_TRUE @ HIP + T_TRUE)
        d2.append(e @ np.linalg.solve(C, e))
    z = np.abs(np.array(z))
    assert 0.85 <= np.mean(z < 1.96) <= 1.0, np.mean(z < 1.96)
    assert 2.0 < np.mean(d2) < 4.5, np.mean(d2)


def test_measured_tissue_is_not_scaled():
    """Points whose tissue is known (tissue 0) keep their offset: all known -> no scale estimated, the same fit."""
    M = _markers(MU)
    prior = TissueScalePrior(1.0, SCALE_LOG_SD, SITE_LOG_SD, "test")
    known = register_landmarks(BONE, M, None, 2e-4, normals=NORMALS, offset=MU + DEFAULT_MARKER_RADIUS, offset_sd=1e-3,
                               names=NAMES, tissue=np.zeros(4), tissue_prior=prior)
    plain = register_landmarks(BONE, M, None, 2e-4, normals=NORMALS, offset=MU + DEFAULT_MARKER_RADIUS, offset_sd=1e-3,
                               names=NAMES)
    assert known.tissue_scale is None and not known.tissue
    np.testing.assert_array_equal(known.R, plain.R)
    np.testing.assert_array_equal(known.cov, plain.cov)


def test_coverage_and_model_error_fit():
    """Errors drawn from N(0, s C_k + σ² I): coverage() of the true covariances is 95 %, the likelihood fit
    recovers s and σ, and the fitted covariances cover 95 % too."""
    rng = np.random.default_rng(3)
    n, s_true, sd_true = 600, 2.5, 0.004
    A = rng.normal(0.0, 0.002, (n, 3, 3))
    C = np.einsum("kij,klj->kil", A, A) + 1e-7 * np.eye(3)
    truth = s_true * C + sd_true ** 2 * np.eye(3)
    E = np.array([rng.multivariate_normal(np.zeros(3), c) for c in truth])
    c_true = coverage(E, truth)
    assert abs(c_true["coverage95"] - 0.95) < 0.03 and abs(c_true["mean_d2"] - 3.0) < 0.4
    assert coverage(E, C)["coverage95"] < 0.8          # the unscaled covariances are over-confident
    s, sd = fit_scale_and_model_error(E, C)
    assert s == pytest.approx(s_true, rel=0.25) and sd == pytest.approx(sd_true, rel=0.25)
    fitted = coverage(E, s * C + sd ** 2 * np.eye(3))
    assert abs(fitted["coverage95"] - 0.95) < 0.03
    # scale held at 1: the model-error sd of errors N(0, C_k + σ² I) comes back; none for honest covariances
    E1 = np.array([rng.multivariate_normal(np.zeros(3), c + sd_true ** 2 * np.eye(3)) for c in C])
    assert fit_model_error(E1, C) == pytest.approx(sd_true, rel=0.15)
    assert fit_model_error(E1, C + sd_true ** 2 * np.eye(3)) < 0.3 * sd_true
    assert CHI2_3_95 == pytest.approx(7.8147, abs=1e-4)
