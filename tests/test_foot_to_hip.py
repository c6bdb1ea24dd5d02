"""Foot-to-hip reconstruction (seed eqs. 26-37) and the seed's two validation claims on motion phantoms."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lowerlimb.errors import InputError
from kinematics.gait.foot_to_hip import calibrate, hip_centre_in_pelvis, knee_ankle_axes, rotate_about, seed_femur_frame
from kinematics.io.markers import MarkerTrial
from kinematics.gait.pig import SegmentPose
from kinematics.gait.reconstruction import reconstruct, tibia_fluctuation
from kinematics.gait.subject import SubjectMeasurements
from phantoms import make_phantom
from phantoms.motion import make_trials

D_KNEE, D_ANKLE, L_SHANK = 0.056, 0.034, 0.40


def _leg(side, n=30, theta=0.0, beta=0.0, phi=0.0, seed=0):
    """Markers of a shank whose knee axis u, centres K, A are known; foot at `theta` from perpendicular
    to the shank, heel-toe line turned by -beta about the shank line, ankle axis = Rot(shank, phi) u."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(rng.normal(scale=0.4, size=(n, 3))).as_matrix()
    lat = np.array([0.0, -1.0, 0.0]) if side == "R" else np.array([0.0, 1.0, 0.0])
    u = R @ lat
    w = R @ np.array([0.0, 0.0, 1.0])
    v = np.cross(w, u) if side == "R" else np.cross(u, w)        # anterior
    K = rng.normal(scale=0.3, size=(n, 3))
    A = K - L_SHANK * w
    u_a = rotate_about(u, w, phi)
    kne, ank = K + D_KNEE * u, A + D_ANKLE * u_a
    # with phi != 0 the ankle marker is off the knee-axis plane; the shank line is then KNE - ANK
    u_t = (kne - ank) / np.linalg.norm(kne - ank, axis=1, keepdims=True)
    u_f = np.cos(theta) * v + np.sin(theta) * w
    u_f = rotate_about(u_f, u_t, -beta)
    hee = A - 0.05 * u_f - 0.04 * w
    toe = hee + 0.2 * u_f
    return dict(u=u, u_a=u_a, K=K, A=A, KNE=kne, ANK=ank, HEE=hee, TOE=toe, KNEM=K - D_KNEE * u, ANKM=A - D_ANKLE * u_a)


@pytest.mark.parametrize("side", ["R", "L"])
def test_seed_equations_recover_axis_and_centres_exactly(side):
    g = _leg(side)
    est = knee_ankle_axes(g["KNE"], g["ANK"], g["HEE"], g["TOE"], D_KNEE, D_ANKLE, side)
    np.testing.assert_allclose(est.knee_axis, g["u"], atol=1e-12)
    np.testing.assert_allclose(est.knee, g["K"], atol=1e-12)
    np.testing.assert_allclose(est.ankle, g["A"], atol=1e-12)
    np.testing.assert_allclose(np.sin(est.alpha), (D_KNEE - D_ANKLE) / np.linalg.norm(g["KNE"] - g["ANK"], axis=1))
    # eq. (29): e3 = u, e1 ⟂ (THI - knee); the Plug-in-Gait-axes frame has y pointing left
    thi = g["K"] + 0.15 * np.cross(g["u"], g["TOE"] - g["HEE"]) * (1 if side == "R" else -1) + 0.05 * g["u"]
    fem = seed_femur_frame(est.knee, est.knee_axis, thi, side)
    assert np.allclose(np.einsum("fij,fik->fjk", fem.axes, fem.axes), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(fem.axes[..., 1] * g["u"], axis=1)), 1.0, atol=1e-12)


def test_dorsiflexed_foot_error_is_second_order():
    g = _leg("R", theta=np.radians(20))
    est = knee_ankle_axes(g["KNE"], g["ANK"], g["HEE"], g["TOE"], D_KNEE, D_ANKLE, "R")
    err = np.degrees(np.arccos(np.clip(np.sum(est.knee_axis * g["u"], axis=1), -1, 1)))
    # the seed's eq. (27) is exact only with the foot perpendicular to the shank: sin(alpha) sin(theta) ~ 1 deg
    assert 0.2 < err.max() < 1.5


def test_static_calibration_recovers_foot_offset_and_torsion():
    beta, phi = np.radians(12.0), np.radians(-22.0)
    legs = {s: _leg(s, n=40, beta=beta, phi=phi if s == "R" else -phi, seed=3) for s in "RL"}
    names, cols = [], []
    for s, g in legs.items():
        for m in ("KNE", "ANK", "HEE", "TOE", "KNEM", "ANKM"):
            names.append(f"{s}{m}")
            cols.append(g[m])
    static = MarkerTrial(tuple(names), np.stack(cols, axis=1), 100.0, np.arange(40) / 100.0, "static")
    r = 0.007
    subj = SubjectMeasurements(0.9, 0.9, 2 * (D_KNEE - r), 2 * (D_KNEE - r), 2 * (D_ANKLE - r), 2 * (D_ANKLE - r))
    cal = calibrate(subj, static)
    assert "static" in cal.source
    for s, g in legs.items():
        est = knee_ankle_axes(g["KNE"], g["ANK"], g["HEE"], g["TOE"], cal.d_knee[s], cal.d_ankle[s], s,
                              cal.foot_offset[s], cal.axis_rotation[s])
        np.testing.assert_allclose(est.knee_axis, g["u"], atol=2e-3)
        # with torsion the shank line is not exactly perpendicular to u: sub-millimetre, not exact
        np.testing.assert_allclose(est.ankle, g["A"], atol=1e-3)
        np.testing.assert_allclose(est.knee, g["K"], atol=1e-3)
    # without a static trial: the seed's assumption (beta = 0) and the measured torsion
    cal0 = calibrate(subj, None)
    assert cal0.foot_offset == {"R": 0.0, "L": 0.0} and cal0.source.startswith("R: seed")


def test_centre_transformation_in_the_thigh_shank_plane():
    rng = np.random.default_rng(5)
    n = 60
    H = np.array([-0.02, -0.09, -0.08])                 # pelvis frame
    h_f = np.array([0.012, 0.0, 0.41])                  # femur frame: (x1, 0, x2), eq. (30)
    R = Rotation.from_rotvec(rng.normal(scale=0.3, size=(n, 3))).as_matrix()
    femur = SegmentPose(H - R @ h_f, R)
    pelvis = SegmentPose(np.zeros((n, 3)), np.repeat(np.eye(3)[None], n, axis=0))
    est = hip_centre_in_pelvis(pelvis, femur)
    np.testing.assert_allclose(est.proximal, H, atol=1e-10)
    np.testing.assert_allclose(est.distal, h_f, atol=1e-10)
    assert est.rms < 1e-10


# ----------------------------------------------------------------------------- phantom validation
@pytest.fixture(scope="module")
def gait_world():
    ph = make_phantom(0)
    sk, trials, _ = make_trials(ph, 0, rate=100, gait_trials=1, gait_cycles=2.0, crouch_angles=(), functional_ranges=(45,),
                                functional_time_scale=0.5)
    return sk, {t.name: t for t in trials}


@pytest.fixture(scope="module")
def recs(gait_world):
    sk, T = gait_world
    g, st = T["gait_01"].markers, T["static"].markers
    return {m: reconstruct(g, m, static=st, subject=sk.subject) for m in ("pig", "foot-to-hip")}


def test_seed_claim_tibia_frame_fluctuation(gait_world, recs):
    """Seed Fig. 20: RTIBM1, RTIBM2 (tibia-fixed) and RANKM fluctuate less in the foot-to-hip tibia frame."""
    sk, T = gait_world
    g = T["gait_01"].markers
    fl = {}
    for m, rec in recs.items():
        fl[m] = np.mean([tibia_fluctuation(rec.segments[f"tibia_{s.lower()}"],
                                           np.stack([g.marker(f"{s}{n}") for n in ("TIBM1", "TIBM2", "ANKM")], axis=1))
                         for s in "RL"], axis=0)
    assert np.all(fl["foot-to-hip"] < fl["pig"]), fl
    # the true tibia frame sees only the 0.5 mm noise on the bone-fixed markers
    true_tib = sk.segment_poses(sk.state(T["gait_01"].q))["tibia_r"]
    bone = np.stack([g.marker(n) for n in ("RTIBM1", "RTIBM2")], axis=1)
    assert np.all(tibia_fluctuation(true_tib, bone) < 1.2e-3)


def test_seed_claim_knee_adduction_and_rotation(gait_world, recs):
    sk, T = gait_world
    truth = sk.angles(sk.state(T["gait_01"].q))
    rmse = {}
    for m, rec in recs.items():
        d = np.concatenate([rec.angles[f"knee_{s}"] - truth[f"knee_{s}"] for s in "rl"])
        rmse[m] = np.degrees(np.sqrt(np.nanmean(d**2, axis=0)))
    assert rmse["foot-to-hip"][1] < rmse["pig"][1] and rmse["foot-to-hip"][2] < rmse["pig"][2], rmse
    # knee flexion stays comparable (within a few degrees of the truth for both)
    assert rmse["pig"][0] < 6 and rmse["foot-to-hip"][0] < 6


def test_functional_trial_hip_centres(gait_world):
    sk, T = gait_world
    g, st, fu = T["gait_01"].markers, T["static"].markers, T["functional_hip"].markers
    truth = sk.centres_lab(sk.state(T["gait_01"].q))
    for m in ("pig", "foot-to-hip"):
        rec = reconstruct(g, m, static=st, subject=sk.subject, functional=fu)
        err = np.linalg.norm(rec.centres["hip_r"] - truth["hip_r"], axis=1).mean()
        assert err < 0.03, (m, err)
        assert np.all(np.isfinite(rec.centre_cov["hip_r"])) and np.all(np.isfinite(rec.centre_cov["knee_r"]))
        assert rec.hip_in_pelvis["R"].n_frames > 100


def test_bad_inputs(gait_world):
    sk, T = gait_world
    g = T["gait_01"].markers
    keep = [n for n in g.names if n not in ("RTOE", "LHEE")]
    with pytest.raises(InputError, match="RTOE, LHEE"):
        reconstruct(g.subset(keep), "foot-to-hip", subject=sk.subject)
    with pytest.raises(InputError, match="method"):
        reconstruct(g, "davis", subject=sk.subject)
    other = make_trials(make_phantom(1, stature=1.45), 1, rate=20, gait_trials=0, crouch_angles=(),
                        functional_ranges=(), static_duration=0.5)[1][0].markers
    with pytest.raises(InputError, match="leg length"):
        reconstruct(g, "pig", static=other, subject=sk.subject)


def test_swapped_sides_and_wrong_units_are_refused(gait_world):
    sk, T = gait_world
    g = T["gait_01"].markers
    swapped = MarkerTrial(tuple({"R": "L", "L": "R"}[n[0]] + n[1:] for n in g.names), g.positions, g.rate, g.time, "swapped.c3d")
    for m in ("pig", "foot-to-hip"):
        with pytest.raises(InputError, match="swapped"):
            reconstruct(swapped, m, subject=sk.subject)
    mm = MarkerTrial(g.names, g.positions * 1000, g.rate, g.time, "mm.c3d")
    with pytest.raises(InputError, match="units"):
        reconstruct(mm, "foot-to-hip", subject=sk.subject)
