"""Virtual medial knee marker and knee-axis pairs (`personalize.pipeline.virtual_markers`) against exact geometry."""
import numpy as np
from scipy.spatial.transform import Rotation

from lowerlimb.estimates import Gaussian
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS
from personalize.landmarks.common import BoneLandmarks, Landmark
from personalize.pipeline import virtual_markers as vm
from personalize.registration import Registration, skin_prior


def _femur(side: str, width: float = 0.09):
    """Epicondyles at z = 0.5 m, 0.09 m apart along the lab's y (the knee axis), centred on x = y = 0."""
    S = side.upper()
    lat = -1.0 if side == "r" else 1.0                       # lateral is -y (right) / +y (left), y left
    kne = np.array([0.0, lat * width / 2, 0.5])
    mfc = np.array([0.0, -lat * width / 2, 0.5])
    lm = {f"{S}KNE": Landmark(kne, np.zeros((3, 3))), f"{S}MFC": Landmark(mfc, np.zeros((3, 3)))}
    return {f"femur_{side}": BoneLandmarks(f"femur_{side}", side, lm)}, kne, mfc, lat


def test_virtual_medial_knee_lands_on_the_medial_marker_when_the_axis_is_the_pelvis_axis():
    for side in ("r", "l"):
        S = side.upper()
        bones, kne, mfc, lat = _femur(side)
        t_l, t_m = skin_prior(f"{S}KNE")[0], skin_prior(f"{S}MFC")[0]
        r = DEFAULT_MARKER_RADIUS
        m_kne = kne + (t_l + r) * np.array([0.0, lat, 0.0])
        true_mfc_marker = mfc - (t_m + r) * np.array([0.0, lat, 0.0])
        static = {f"{S}KNE": Gaussian(m_kne, np.eye(3) * 1e-6)}
        v = vm.virtual_medial_knee(static, bones, side, hip=np.array([0.0, lat * 0.05, 0.9]), pelvis_axes=np.eye(3),
                                   knee_axis_mri=np.array([0.0, 1.0, 0.0]))
        # the thigh leans 0.045 m medially over 0.4 m: the medial direction is made orthogonal to it
        thigh = np.array([0.0, lat * 0.05, 0.9]) - m_kne
        thigh /= np.linalg.norm(thigh)
        n = np.array([0.0, -lat, 0.0]) - np.dot([0.0, -lat, 0.0], thigh) * thigh
        n /= np.linalg.norm(n)
        L = 0.09 + t_l + t_m + 2 * r
        np.testing.assert_allclose(v.mean, m_kne + L * n, atol=1e-12)
        assert np.linalg.norm(v.mean - true_mfc_marker) < 0.006      # the lean moves it a few mm, within the sds
        # anterior sd: L sin(10 deg) plus the knee marker's 1 mm
        sd_x = np.sqrt(v.cov[0, 0])
        assert abs(sd_x - np.hypot(L * np.sin(np.radians(vm.STANDING_HIP_ROTATION_SD_DEG)), 1e-3)) < 1e-4


def test_virtual_medial_knee_needs_its_marker_and_landmarks():
    bones, kne, *_ = _femur("r")
    assert vm.virtual_medial_knee({}, bones, "r", np.zeros(3), np.eye(3)) is None
    assert vm.virtual_medial_knee({"RKNE": Gaussian(kne, np.eye(3) * 1e-6)}, {}, "r", np.array([0, 0, 1.0]), np.eye(3)) is None


def test_knee_axis_pairs_carry_the_axis_direction_through_the_femur_registration():
    R = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    t = np.array([0.3, 1.2, 0.05])
    Om = np.diag([1e-4, 4e-4, 9e-4])
    cov = np.zeros((6, 6))
    cov[:3, :3] = Om
    reg = Registration(R=R, t=t, cov=cov, centre=t, names=(), rejected={}, residuals=np.zeros((0, 3)),
                       mahalanobis=np.zeros(0), chi2=0.0, dof=0, p_value=1.0)
    c, u = np.array([0.01, 0.02, 0.5]), np.array([0.0, 0.6, 0.8])
    k = np.array([0.2, 0.1, 0.45])                      # the (fused) lab knee centre the shank is registered to
    pairs = vm.knee_axis_pairs(reg, c, u, k, "r")
    assert [p[0] for p in pairs] == ["knee_axis_r_a", "knee_axis_r_b"]
    ell = vm.KNEE_AXIS_HALF_LENGTH
    w = R @ u
    for (name, mri, lab), sign in zip(pairs, (1, -1)):
        np.testing.assert_allclose(mri.mean, c + sign * ell * u, atol=1e-15)
        np.testing.assert_allclose(lab.mean, k + sign * ell * w, atol=1e-15)
        # no variance along the axis from the rotation; (ell sin 5 deg)^2 in every direction
        assert abs(w @ lab.cov @ w - (ell * np.sin(np.radians(vm.KNEE_STANDING_ROTATION_SD_DEG)))**2) < 1e-15
        e = np.cross(w, [1.0, 0.0, 0.0])
        e /= np.linalg.norm(e)
        expected = ell**2 * (np.cross(e, w) @ Om @ np.cross(e, w)) + (ell * np.sin(np.radians(5.0)))**2
        assert abs(e @ lab.cov @ e - expected) < 1e-15
