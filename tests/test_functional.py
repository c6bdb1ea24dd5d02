"""Functional joint centre / axis estimators on seeded synthetic motion with known truth."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lowerlimb.errors import FitError
from kinematics.algorithms.functional import centre_transformation, pivot_sphere_fit, sara, score, sphere_fit
from kinematics.algorithms.segments import rigid_pose

HIP_IN_PELVIS = np.array([-0.07, -0.08, -0.09])  # m, right hip centre in the pelvis frame
PELVIS_MARKERS = np.array([[0.0, -0.12, 0.0], [0.0, 0.12, 0.0], [-0.16, -0.05, 0.03], [-0.16, 0.05, 0.03]])
# Thigh cluster in the femur frame (origin at the hip centre): lateral, 12-35 cm below.
THIGH_MARKERS = np.array([[0.03, -0.08, -0.15], [0.05, -0.09, -0.25], [-0.02, -0.08, -0.33], [0.06, -0.02, -0.30]])
NOISE = 0.0005  # m, per coordinate


def star_arc(n_per_arc: int = 25, amplitude_deg: float = 45.0) -> Rotation:
    """Femur-in-pelvis rotations of a star-arc: out-and-back arcs in 8 directions of the
    flexion/abduction plane followed by a circumduction at the full amplitude."""
    amp = np.radians(amplitude_deg)
    rotvecs = []
    s = np.sin(np.linspace(0, np.pi, n_per_arc))  # out and back
    for phi in np.radians(np.arange(0, 360, 45)):
        axis = np.array([np.sin(phi), np.cos(phi), 0.0])  # about pelvis y (flexion) / x (abduction)
        rotvecs += list(amp * s[:, None] * axis)
    for phi in np.linspace(0, 2 * np.pi, 2 * n_per_arc, endpoint=False):
        rotvecs.append(amp * np.array([np.sin(phi), np.cos(phi), 0.0]))
    return Rotation.from_rotvec(np.array(rotvecs))


def simulate(seed: int = 0, amplitude_deg: float = 45.0, n_per_arc: int = 25):
    """Lab marker trajectories of a moving pelvis and a thigh pivoting about HIP_IN_PELVIS."""
    rng = np.random.default_rng(seed)
    femur_rel = star_arc(n_per_arc, amplitude_deg)
    F = len(femur_rel)
    t = np.linspace(0, 1, F)
    # Pelvis wanders: 10 cm translation, +-10 deg rotation.
    pel_R = Rotation.from_rotvec(np.radians(10) * np.stack([np.sin(2 * np.pi * t), 0.5 * np.cos(3 * np.pi * t), np.sin(np.pi * t)], 1))
    pel_t = np.stack([0.1 * t, 0.05 * np.sin(2 * np.pi * t), 0.9 + 0.02 * t], 1)
    fem_R = pel_R * femur_rel
    fem_t = pel_t + pel_R.apply(HIP_IN_PELVIS)
    pel = pel_R.as_matrix() @ PELVIS_MARKERS.T
    pel = np.transpose(pel, (0, 2, 1)) + pel_t[:, None]
    thi = np.transpose(fem_R.as_matrix() @ THIGH_MARKERS.T, (0, 2, 1)) + fem_t[:, None]
    pel = pel + rng.normal(0, NOISE, pel.shape)
    thi = thi + rng.normal(0, NOISE, thi.shape)
    return pel, thi


@pytest.fixture(scope="module")
def star_poses():
    pel, thi = simulate(seed=1)
    P = rigid_pose(PELVIS_MARKERS, pel)
    T = rigid_pose(THIGH_MARKERS, thi)
    return P, T, pel, thi


def test_centre_transformation_recovers_hip(star_poses):
    P, T, _, _ = star_poses
    est = centre_transformation(P.R, P.t, T.R, T.t)
    err = np.linalg.norm(est.proximal - HIP_IN_PELVIS)
    assert err < 0.002
    assert np.linalg.norm(est.distal) < 0.002  # the femur frame origin is the hip centre
    # the reported sd is the right order of magnitude (within a factor 5 of the error, or above it)
    assert np.all(est.sd_proximal > 0) and np.max(est.sd_proximal) < 0.002
    assert est.rms < 0.005  # per-frame scatter of the centre path (pose noise x lever arm)


def test_score_recovers_hip(star_poses):
    P, T, _, _ = star_poses
    est = score(P.R, P.t, T.R, T.t)
    assert np.linalg.norm(est.proximal - HIP_IN_PELVIS) < 0.002
    assert np.linalg.norm(est.distal) < 0.002
    assert est.cov_proximal.shape == (3, 3) and np.all(np.linalg.eigvalsh(est.cov_proximal) > 0)


def test_sphere_fit_recovers_hip(star_poses):
    P, _, _, thi = star_poses
    local = P.to_local(thi)  # thigh markers in the pelvis frame
    fit = pivot_sphere_fit(local)
    assert np.linalg.norm(fit.centre - HIP_IN_PELVIS) < 0.002
    np.testing.assert_allclose(fit.radii, np.linalg.norm(THIGH_MARKERS, axis=1), atol=0.002)
    assert fit.rms < 3 * NOISE


def test_sphere_fit_exact_points():
    rng = np.random.default_rng(3)
    u = rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    c = np.array([0.1, -0.2, 0.3])
    fit = sphere_fit(c + 0.25 * u)
    np.testing.assert_allclose(fit.centre, c, atol=1e-10)
    np.testing.assert_allclose(fit.radii, [0.25], atol=1e-10)


def test_centre_estimates_are_reproducible_and_sd_is_calibrated():
    """Over seeds the spread of the CTT estimate matches its reported sd (within a factor 2.5)."""
    errs, sds = [], []
    for seed in range(8):
        pel, thi = simulate(seed=100 + seed, n_per_arc=12)
        P, T = rigid_pose(PELVIS_MARKERS, pel), rigid_pose(THIGH_MARKERS, thi)
        est = centre_transformation(P.R, P.t, T.R, T.t)
        errs.append(est.proximal - HIP_IN_PELVIS)
        sds.append(est.sd_proximal)
    rms_err = np.sqrt(np.mean(np.square(errs)))
    mean_sd = np.mean(sds)
    assert 0.4 < rms_err / mean_sd < 2.5


def test_plane_constrained_ctt_matches_seed_form(star_poses):
    """Eq. 30: the centre restricted to the plane z = 0 of the distal frame (here it lies there)."""
    P, T, _, _ = star_poses
    est = centre_transformation(P.R, P.t, T.R, T.t, basis=np.eye(3)[:, :2])
    assert abs(est.distal[2]) == 0.0
    assert np.linalg.norm(est.proximal - HIP_IN_PELVIS) < 0.002


KNEE_AXIS = np.array([0.1, 1.0, 0.05]) / np.linalg.norm([0.1, 1.0, 0.05])  # in the femur frame
KNEE_POINT = np.array([0.01, 0.0, -0.42])  # a point of the knee axis in the femur frame, m


def hinge_poses(seed: int, F: int = 120):
    """Femur and tibia cluster poses of a noisy hinge (0-70 deg flexion) about KNEE_AXIS."""
    rng = np.random.default_rng(seed)
    flex = np.radians(70) * 0.5 * (1 - np.cos(np.linspace(0, 4 * np.pi, F)))
    fem_R = Rotation.from_rotvec(np.radians(15) * np.stack([np.sin(np.linspace(0, 3, F)), 0.3 * np.ones(F), np.cos(np.linspace(0, 2, F))], 1))
    fem_t = np.stack([np.linspace(0, 1, F), 0.1 * np.ones(F), 0.9 * np.ones(F)], 1)
    tib_R = fem_R * Rotation.from_rotvec(flex[:, None] * KNEE_AXIS)
    tib_t = fem_t + fem_R.apply(KNEE_POINT)  # tibia frame origin on the axis
    fem_markers = np.array([[0.05, -0.08, -0.2], [0.0, -0.09, -0.3], [0.07, -0.05, -0.35]])
    tib_markers = np.array([[0.05, -0.07, -0.1], [0.0, -0.08, -0.2], [0.06, -0.03, -0.3]])
    mf = np.transpose(fem_R.as_matrix() @ fem_markers.T, (0, 2, 1)) + fem_t[:, None] + rng.normal(0, NOISE, (F, 3, 3))
    mt = np.transpose(tib_R.as_matrix() @ tib_markers.T, (0, 2, 1)) + tib_t[:, None] + rng.normal(0, NOISE, (F, 3, 3))
    return rigid_pose(fem_markers, mf), rigid_pose(tib_markers, mt)


def _axis_errors(ax):
    ang = np.arccos(min(1.0, abs(ax.direction_proximal @ KNEE_AXIS)))
    d = KNEE_POINT - ax.point_proximal
    return ang, np.linalg.norm(d - (d @ ax.direction_proximal) * ax.direction_proximal)


def test_sara_recovers_knee_axis():
    Pf, Pt = hinge_poses(7)
    ax = sara(Pf.R, Pf.t, Pt.R, Pt.t)
    ang, dist = _axis_errors(ax)
    assert np.degrees(ang) < 1.0
    assert dist < 0.002  # true axis point to the estimated axis line
    np.testing.assert_allclose(np.linalg.norm(ax.direction_distal), 1.0)
    # a hinge leaves SCoRE without a unique centre: its covariance says so along the axis
    c = score(Pf.R, Pf.t, Pt.R, Pt.t).cov_proximal
    sd_along = np.sqrt(KNEE_AXIS @ c @ KNEE_AXIS)
    assert sd_along > 10 * np.sqrt(np.min(np.linalg.eigvalsh(c)))
    assert sd_along > 0.005


def test_sara_uncertainty_is_calibrated():
    """Over seeds, the axis direction and point errors match the reported sd (within a factor 2.5)."""
    angs, sds, dists, psd = [], [], [], []
    for seed in range(10):
        Pf, Pt = hinge_poses(200 + seed, F=60)
        ax = sara(Pf.R, Pf.t, Pt.R, Pt.t)
        ang, dist = _axis_errors(ax)
        angs.append(ang)
        dists.append(dist)
        sds.append(ax.direction_sd)
        psd.append(np.sqrt(np.trace(ax.cov_point_proximal)))
    assert 0.4 < np.sqrt(np.mean(np.square(angs))) / np.mean(sds) < 2.5
    assert 0.4 < np.sqrt(np.mean(np.square(dists))) / np.mean(psd) < 2.5


def test_no_motion_is_a_fit_error():
    F = 20
    R = np.repeat(np.eye(3)[None], F, 0)
    t = np.zeros((F, 3))
    with pytest.raises(FitError):
        centre_transformation(R, t, R, t + 0.1)
    with pytest.raises(FitError):
        score(R, t, R, t + 0.1)


@pytest.mark.parametrize("method", ["score", "ctt", "sphere"])
def test_joint_centre_from_marker_trial(method):
    """From raw marker trajectories (cluster shapes unknown, gaps in one marker) to the lab hip path."""
    from kinematics.algorithms.functional import joint_centre_from_clusters
    from kinematics.io.markers import MarkerTrial

    pel, thi = simulate(seed=5, n_per_arc=15)
    pos = np.concatenate([pel, thi], axis=1)
    pos[40:45, 5] = np.nan
    names = ("P1", "P2", "P3", "P4", "T1", "T2", "T3", "T4")
    trial = MarkerTrial(names, pos, 100.0, np.arange(len(pos)) / 100.0, "star.c3d")
    est, lab = joint_centre_from_clusters(trial, names[:4], names[4:], method)
    # truth in the lab: the pelvis pose from noise-free reconstruction of the same simulation
    P_true = rigid_pose(PELVIS_MARKERS, pel)
    truth = P_true.to_lab(HIP_IN_PELVIS)
    assert np.nanmean(np.linalg.norm(lab - truth, axis=1)) < 0.002
    assert est.cov_proximal.shape == (3, 3) and est.cov_distal.shape == (3, 3)
    with pytest.raises(Exception, match="missing markers: T9"):
        joint_centre_from_clusters(trial, names[:4], ("T1", "T2", "T9"), method)
