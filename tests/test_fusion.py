"""Gaussian fusion: analytic products, Monte-Carlo gain over each source, axes on the sphere, pose blending."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.gait.pig import SegmentPose
from lowerlimb.errors import InputError
from kinematics.gait.chain_blend import blend_poses
from personalize.fusion import fuse_axis, fuse_gaussian, fuse_linear, fusion_monte_carlo

# Hip centre in the pelvis frame (m): an MRI-like estimate (precise, anisotropic) and a motion-like one.
C_MRI = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.5], [0.0, 0.5, 9.0]]) * 1e-6
C_MOT = np.array([[25.0, -5.0, 0.0], [-5.0, 16.0, 0.0], [0.0, 0.0, 4.0]]) * 1e-6
HIP = np.array([-0.02, -0.07, 0.085])


def test_product_matches_the_closed_form():
    x1, x2 = HIP + [0.001, -0.002, 0.0], HIP + [-0.003, 0.001, 0.002]
    f = fuse_gaussian([(x1, C_MRI), (x2, C_MOT)], names=("mri", "motion"))
    # Independent two-source form: C = C1 (C1 + C2)⁻¹ C2, x = C2 (C1 + C2)⁻¹ x1 + C1 (C1 + C2)⁻¹ x2.
    S = np.linalg.inv(C_MRI + C_MOT)
    assert np.allclose(f.cov, C_MRI @ S @ C_MOT, rtol=1e-10, atol=1e-20)
    assert np.allclose(f.mean, C_MOT @ S @ x1 + C_MRI @ S @ x2, atol=1e-14)
    assert np.allclose(f.weights.sum(axis=0), np.eye(3)) and np.isclose(f.shares.sum(), 1.0)
    assert np.allclose(f.weights[0] @ x1 + f.weights[1] @ x2, f.mean)
    assert f.shares[0] > f.shares[1]  # the more precise source gets more weight
    d = x1 - x2
    assert np.isclose(f.chi2, d @ S @ d) and f.dof == 3


def test_scalar_fusion_and_disagreement_flag():
    f = fuse_gaussian([(1.0, 0.04), (2.0, 0.01)])
    assert np.isclose(f.mean[0], 1.8) and np.isclose(f.cov[0, 0], 0.008)
    assert np.allclose(f.shares, [0.2, 0.8])
    assert np.isclose(f.chi2, 1.0 / 0.05) and not f.consistent
    assert fuse_gaussian([(1.0, 0.04), (1.1, 0.01)]).consistent
    # Three sources: information adds up.
    g = fuse_gaussian([(0.5, 1.0), (0.7, 1.0), (0.9, 2.0)])
    assert np.isclose(g.cov[0, 0], 1 / 2.5) and np.isclose(g.mean[0], (0.5 + 0.7 + 0.45) / 2.5)


def test_fused_estimate_beats_each_source_monte_carlo():
    rng = np.random.default_rng(4)
    n = 2000
    e1 = rng.multivariate_normal(np.zeros(3), C_MRI, n)
    e2 = rng.multivariate_normal(np.zeros(3), C_MOT, n)
    fused = np.array([fuse_gaussian([(HIP + a, C_MRI), (HIP + b, C_MOT)]) for a, b in zip(e1, e2)])
    ef = np.array([f.mean for f in fused]) - HIP
    mse = [np.mean(np.sum(e**2, axis=1)) for e in (e1, e2, ef)]
    assert mse[2] < mse[0] and mse[2] < mse[1]
    # Per-draw: the fused error is smaller than both source errors far more often than not.
    better = (np.linalg.norm(ef, axis=1) < np.linalg.norm(e1, axis=1)) & (np.linalg.norm(ef, axis=1) < np.linalg.norm(e2, axis=1))
    assert better.mean() > 0.5
    # The reported covariance is the actual spread of the fused estimate.
    emp = np.cov(ef.T)
    assert np.allclose(np.sqrt(np.diag(emp)), fused[0].sd, rtol=0.1)
    m2 = np.mean([e @ np.linalg.solve(fused[0].cov, e) for e in ef])
    assert 2.7 < m2 < 3.3
    # Consistent sources pass the χ² test about 99 % of the time.
    assert 0.97 < np.mean([f.consistent for f in fused]) <= 1.0


def test_bad_fusion_input():
    with pytest.raises(InputError, match="positive definite"):
        fuse_gaussian([(HIP, np.zeros((3, 3))), (HIP, C_MOT)])
    with pytest.raises(InputError, match="3x3"):
        fuse_gaussian([(HIP, np.eye(2)), (HIP, C_MOT)])
    with pytest.raises(InputError, match="nothing"):
        fuse_gaussian([])


# --------------------------------------------------------------------------- correlated sources (both hips)

def _two_hip_mri_cov():
    """6x6 covariance of two MRI hips sharing one registration error (m²): shared 2 mm, own 0.5 mm per axis."""
    shared = np.diag([2.0, 1.0, 1.5]) ** 2 * 1e-6
    own = 0.5**2 * 1e-6 * np.eye(3)
    return np.block([[shared + own, shared], [shared, shared + own]])


def test_linear_fusion_without_correlation_is_the_product_of_gaussians():
    x1, x2 = HIP + [0.001, -0.002, 0.0], HIP + [-0.003, 0.001, 0.002]
    f, g = fuse_linear([(x1, C_MRI), (x2, C_MOT)]), fuse_gaussian([(x1, C_MRI), (x2, C_MOT)])
    assert np.allclose(f.mean, g.mean, atol=1e-15) and np.allclose(f.cov, g.cov, rtol=1e-10, atol=1e-20)
    assert np.allclose(f.weights, g.weights) and np.isclose(f.chi2, g.chi2) and f.dof == g.dof == 3


def test_joint_hip_fusion_uses_the_shared_registration_error():
    """Motion on the right hip only also corrects the left MRI hip, through the MRI cross-covariance."""
    rng = np.random.default_rng(7)
    C6 = _two_hip_mri_cov()
    Cm = np.diag([3.0, 3.0, 3.0]) ** 2 * 1e-6
    truth = np.concatenate([HIP, HIP * [1, -1, 1]])
    H = np.eye(6)
    n = 1500
    e_mri = rng.multivariate_normal(np.zeros(6), C6, n)
    e_mot = rng.multivariate_normal(np.zeros(3), Cm, n)
    joint, naive = [], []
    for a, b in zip(e_mri, e_mot):
        f = fuse_linear([(truth + a, C6, H), (truth[:3] + b, Cm, H[:3])], ("mri", "motion_r"))
        joint.append(f.mean - truth)
        g = fuse_linear([(truth + a, C6 * np.kron(np.eye(2), np.ones((3, 3))), H), (truth[:3] + b, Cm, H[:3])])
        naive.append(g.mean - truth)
    joint, naive = np.array(joint), np.array(naive)
    mse = lambda e: np.mean(np.sum(e**2, axis=1))  # noqa: E731
    # the left hip (no motion data) improves over its MRI estimate only when the cross-covariance is used
    assert mse(joint[:, 3:]) < 0.8 * mse(e_mri[:, 3:])
    assert np.isclose(mse(naive[:, 3:]), mse(e_mri[:, 3:]))
    assert mse(joint[:, :3]) < mse(e_mri[:, :3]) and mse(joint[:, :3]) < mse(e_mot)
    # reported covariance = actual spread (Mahalanobis distances ~ chi2 with 6 dof)
    m2 = np.mean([e @ np.linalg.solve(f.cov, e) for e in joint])
    assert 5.6 < m2 < 6.4
    # matrix weights: the MRI block weights sum with the motion's to I; the motion weight on the left hip
    # is carried by its cross block only
    assert np.allclose(f.weights.sum(axis=0), np.eye(6))
    assert np.allclose(f.weights[1][3:, 3:], 0) and np.abs(f.weights[1][3:, :3]).max() > 0.1
    assert f.dof == 3 and 0 < f.shares[1] < 0.5


def test_cross_covariance_equals_stacked_gls():
    """The 'cross' argument gives the same result as one stacked observation with the full covariance."""
    C6 = _two_hip_mri_cov()
    z = np.concatenate([HIP + 0.001, HIP * [1, -1, 1] - 0.002])
    zm = HIP + [0.004, 0.0, -0.003]
    Cm = 9e-6 * np.eye(3)
    H = np.eye(6)
    a = fuse_linear([(z, C6, H), (zm, Cm, H[:3])])
    b = fuse_linear([(z[:3], C6[:3, :3], H[:3]), (z[3:], C6[3:, 3:], H[3:]), (zm, Cm, H[:3])], cross={(0, 1): C6[:3, 3:]})
    assert np.allclose(a.mean, b.mean, atol=1e-14) and np.allclose(a.cov, b.cov, atol=1e-20)
    assert np.isclose(a.chi2, b.chi2)


def test_linear_fusion_bad_input():
    H = np.eye(6)
    with pytest.raises(InputError, match="do not determine"):
        fuse_linear([(HIP, C_MRI, H[:3]), (HIP, C_MOT, H[:3])])          # nothing observes the left hip
    with pytest.raises(InputError, match="not positive definite"):
        fuse_linear([(HIP, C_MRI), (HIP, C_MRI)], cross={(0, 1): 2 * C_MRI})
    with pytest.raises(InputError, match="cross-covariance"):
        fuse_linear([(HIP, C_MRI), (HIP, C_MOT)], cross={(0, 1): np.eye(2)})


def test_monte_carlo_bound_of_gaussian_fusion():
    # equal isotropic sources: the fused error is N(0, C/2), its median 1/sqrt(2) of a source's
    r = fusion_monte_carlo(np.eye(3), np.eye(3), n=20000, seed=3)
    assert r["median_fused"] == pytest.approx(r["median_a"] / np.sqrt(2), rel=0.03)
    # a source 6x worse: fusion rarely beats both (the better source's error dominates)
    r = fusion_monte_carlo(np.eye(3), 36 * np.eye(3), n=20000, seed=3)
    assert 0.45 < r["fraction_below_both"] < 0.7 and r["median_fused"] < r["median_a"]


# --------------------------------------------------------------------------- axes

def _perturb(rng, u, sd_deg):
    a = rng.normal(size=3) * np.radians(sd_deg)
    a -= (a @ u) * u
    return Rotation.from_rotvec(a).apply(u)


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(abs(a @ b), -1, 1)))


def test_axis_fusion_on_the_sphere():
    rng = np.random.default_rng(5)
    u = np.array([0.1, -0.05, 1.0])
    u /= np.linalg.norm(u)
    sd_mri, sd_mot = 2.0, 6.0
    err = {"mri": [], "mot": [], "fused": []}
    sds = []
    for i in range(400):
        a, b = _perturb(rng, u, sd_mri), _perturb(rng, u, sd_mot)
        if i % 2:
            b = -b  # the motion axis may point the other way
        f = fuse_axis([a, b], [sd_mri, sd_mot], names=("mri", "motion"))
        assert f.flipped[1] == bool(i % 2) and not f.flipped[0]
        err["mri"].append(_angle(a, u))
        err["mot"].append(_angle(b, u))
        err["fused"].append(_angle(f.direction, u))
        sds.append(f.sd_deg)
    rms = {k: np.sqrt(np.mean(np.square(v))) for k, v in err.items()}
    assert rms["fused"] < rms["mri"] < rms["mot"]
    expected = 1 / np.sqrt(1 / sd_mri**2 + 1 / sd_mot**2)
    assert np.allclose(sds, expected, rtol=1e-3)
    # Angle error has two tangent components: rms angle = √2 · per-component sd.
    assert 0.85 < rms["fused"] / (np.sqrt(2) * expected) < 1.15
    assert np.isclose(f.shares[0], sd_mot**2 / (sd_mri**2 + sd_mot**2), rtol=1e-3)


def test_axis_fusion_is_the_weighted_geodesic_mean():
    a = np.array([0.0, 0.0, 1.0])
    b = Rotation.from_rotvec([0.3, 0.0, 0.0]).apply(a)  # 0.3 rad away
    f = fuse_axis([a, b], [1.0, 2.0])
    # Weights 4/5 and 1/5 along the geodesic: the fused axis is 0.06 rad from a towards b.
    assert np.isclose(np.arccos(f.direction @ a), 0.06, atol=1e-9)
    assert np.isclose(np.arccos(f.direction @ b), 0.24, atol=1e-9)


def test_axis_points_fused_across_the_axis():
    u = np.array([0.0, 0.0, 1.0])
    p1, p2 = np.array([0.01, 0.0, 0.05]), np.array([0.0, 0.02, -0.03])  # differ along the axis too
    C1, C2 = np.diag([1e-6, 1e-6, 1.0]), np.diag([4e-6, 4e-6, 1.0])
    f = fuse_axis([u, u], [1.0, 1.0], points=[p1, p2], point_covs=[C1, C2])
    assert np.allclose(f.point[:2], [0.008, 0.004], atol=1e-12)
    assert np.allclose(f.point_cov[:2, :2], 0.8e-6 * np.eye(2), rtol=1e-9)
    assert np.allclose(f.point_cov[:, 2], 0.0, atol=1e-15)


# --------------------------------------------------------------------------- poses

def test_equal_weights_give_the_geodesic_midpoint():
    R0 = Rotation.from_rotvec([0.2, -0.1, 0.4])
    R1 = R0 * Rotation.from_rotvec([0.0, 0.5, 0.0])
    b = blend_poses((R0.as_matrix(), np.zeros(3)), (R1.as_matrix(), np.ones(3)), 0.01, 0.01)
    mid = (R0 * Rotation.from_rotvec([0.0, 0.25, 0.0])).as_matrix()
    assert np.allclose(b.R[0], mid, atol=1e-12) and np.allclose(b.t[0], 0.5)
    assert np.allclose(b.weight_a, 0.5)


def test_blending_reduces_error_when_one_chain_is_noisier():
    rng = np.random.default_rng(6)
    F = 300
    t_true = np.c_[np.linspace(0, 1.2, F), 0.1 * np.sin(np.linspace(0, 6, F)), np.full(F, 0.9)]
    R_true = Rotation.from_rotvec(np.c_[np.zeros(F), np.linspace(0, 1, F), 0.2 * np.sin(np.linspace(0, 6, F))])
    # Chain a (top-down PiG): noisy in the middle of the trial; chain b (foot-to-hip): uniform noise.
    sa = np.where((np.arange(F) > 100) & (np.arange(F) < 200), 0.012, 0.002)
    sb = np.full(F, 0.005)

    def noisy(s):
        R = Rotation.from_rotvec(rng.normal(size=(F, 3)) * (s / 0.2)[:, None]) * R_true  # 0.2 m lever arm
        return SegmentPose(t_true + rng.normal(size=(F, 3)) * s[:, None], R.as_matrix())

    a, b = noisy(sa), noisy(sb)
    # Residuals: per-frame marker rms, proportional to each chain's error scale.
    b_res = sb * (1 + 0.1 * rng.normal(size=F))
    a_res = sa * (1 + 0.1 * rng.normal(size=F))
    out = blend_poses(a, b, a_res, b_res)

    def errs(R, t):
        ang = np.linalg.norm((Rotation.from_matrix(R) * R_true.inv()).as_rotvec(), axis=1)
        return np.sqrt(np.mean(ang**2)), np.sqrt(np.mean(np.sum((t - t_true) ** 2, axis=1)))

    ea, eb, ef = errs(a.axes, a.origin), errs(b.axes, b.origin), errs(out.R, out.t)
    assert ef[0] < min(ea[0], eb[0]) and ef[1] < min(ea[1], eb[1])
    assert out.weight_a[150] < 0.3 and out.weight_a[20] > 0.7
    assert np.allclose(out.weight_a + out.weight_b, 1.0)
    assert isinstance(out.as_segment_pose(), SegmentPose)


def test_blending_fills_gaps_from_the_other_chain():
    F = 4
    Ra = np.repeat(np.eye(3)[None], F, axis=0)
    Rb = np.repeat(Rotation.from_rotvec([0, 0, 0.1]).as_matrix()[None], F, axis=0)
    ta, tb = np.zeros((F, 3)), np.ones((F, 3))
    Ra[1] = np.nan
    tb[2] = np.nan
    ra = np.array([0.01, 0.01, 0.01, np.nan])
    out = blend_poses((Ra, ta), (Rb, tb), ra, 0.01)
    assert np.allclose(out.R[1], Rb[1]) and np.allclose(out.t[1], 1.0) and out.weight_b[1] == 1.0
    assert np.allclose(out.R[2], np.eye(3)) and out.weight_a[2] == 1.0
    assert np.allclose(out.t[3], 1.0)  # chain a has no residual in frame 3: unusable
    both_nan = blend_poses((Ra[1:2], ta[1:2]), (Rb[2:3], tb[2:3]), 0.01, 0.01)
    assert np.all(np.isnan(both_nan.R)) and np.isnan(both_nan.weight_a[0])
    with pytest.raises(InputError, match="frames"):
        blend_poses((Ra, ta), (Rb[:2], tb[:2]), 0.01, 0.01)


def test_project_estimate_types_are_read():
    from kinematics.algorithms.functional import AxisEstimate, CentreEstimate
    ce = CentreEstimate(HIP + 0.004, np.zeros(3), C_MOT, np.eye(3), 0.001, 100)
    mri = {"position": list(HIP), "cov": C_MRI.tolist()}
    f = fuse_gaussian([mri, ce], names=("mri", "score"))
    ref = fuse_gaussian([(HIP, C_MRI), (HIP + 0.004, C_MOT)])
    assert np.allclose(f.mean, ref.mean) and np.allclose(f.cov, ref.cov)
    from personalize.fusion import fuse_axes
    u = np.array([0.0, 0.0, 1.0])
    ax = AxisEstimate(np.array([0.0, 0.01, 0.0]), u, np.zeros(3), u, 1e-6 * np.eye(3), np.radians(4.0), 0.001, 0.01, 100)
    joint = {"origin": [0.0, 0.0, 0.0], "origin_cov": (4e-6 * np.eye(3)).tolist(), "rotation": np.eye(3).tolist(),
             "axis_sd_deg": 2.0}
    fa = fuse_axes([ax, joint], names=("sara", "mri"))
    assert np.isclose(fa.sd_deg, 1 / np.sqrt(1 / 16 + 1 / 4)) and np.isclose(fa.shares[1], 0.8)
    assert np.allclose(fa.point[:2], [0.0, 0.008])
    with pytest.raises(InputError, match="cannot read"):
        fuse_gaussian([object()])
