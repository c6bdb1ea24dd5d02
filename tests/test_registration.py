"""Registration of MRI landmarks to static markers: known transforms, calibrated uncertainty, outliers, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.io.markers import MarkerTrial
from lowerlimb.errors import InputError
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS
from personalize.marker_registration import register_segments
from lowerlimb.geometry import kabsch
from personalize.registration import (SKIN_THICKNESS, _fit, _linearise, register_landmarks, skin_prior,
                                      static_marker_positions)

R_TRUE = Rotation.from_rotvec([0.3, -0.5, 1.2]).as_matrix()
T_TRUE = np.array([1.0, 0.5, 0.8])


def _pose_error(reg, R_true, t_true):
    """6-vector error (ω, δ) of the estimate in the registration's own parametrisation."""
    w = Rotation.from_matrix(R_true @ reg.R.T).as_rotvec()
    pre = reg.R.T @ (reg.centre - reg.t)
    return np.r_[w, R_true @ pre + t_true - reg.centre]


def _random_normals(rng, K):
    n = rng.normal(size=(K, 3))
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _tilt(rng, n, sd_rad):
    """Rotate unit vector n by a random tangent angle with per-axis sd `sd_rad`."""
    a = rng.normal(size=3) * sd_rad
    a -= (a @ n) * n
    return Rotation.from_rotvec(a).apply(n)


# Well-spread landmark set (pelvis-sized), scanner frame, metres.
P0 = np.array([[0.00, 0.95, 0.12], [0.00, 0.95, -0.12], [-0.15, 0.99, 0.05], [-0.15, 0.99, -0.05],
               [0.02, 0.84, 0.00], [-0.05, 0.88, 0.10]])


def test_transform_and_uncertainty_calibrated():
    """Over 200 noisy draws the recovered transform errors match the predicted covariance (± 30 %)."""
    rng = np.random.default_rng(1)
    K = len(P0)
    Cp = np.array([np.diag(rng.uniform(0.001, 0.003, 3)) ** 2 for _ in range(K)])
    N = _random_normals(rng, K)
    off, off_sd, nsd, msd = SKIN_THICKNESS + DEFAULT_MARKER_RADIUS, 0.003, np.radians(10.0), 0.003
    hip = np.array([0.0, 0.88, 0.08])  # a point away from the landmarks, like a hip centre
    hips = np.array([[0.0, 0.88, 0.08], [0.0, 0.88, -0.08]])  # both hip centres: one shared registration error
    errs, covs, hip_m2, dir_err, dir_sd, pair_m2, pair_e, pair_c = [], [], [], [], [], [], [], []
    for _ in range(200):
        Pn = P0 + np.array([rng.multivariate_normal(np.zeros(3), C) for C in Cp])
        true_centres = np.array([p + (off + off_sd * rng.normal()) * _tilt(rng, n, nsd) for p, n in zip(P0, N)])
        M = true_centres @ R_TRUE.T + T_TRUE + rng.normal(0, msd, (K, 3))
        reg = register_landmarks(Pn, M, Cp, msd, normals=N, offset=off, offset_sd=off_sd, normal_sd_deg=10.0,
                                 k_outlier=5.0)
        errs.append(_pose_error(reg, R_TRUE, T_TRUE))
        covs.append(reg.cov)
        y, cy = reg.transfer_point(hip)
        e = y - (R_TRUE @ hip + T_TRUE)
        hip_m2.append(e @ np.linalg.solve(cy, e))
        Y, C6 = reg.transfer_points(hips)
        e6 = (Y - (hips @ R_TRUE.T + T_TRUE)).ravel()
        # rank 5: a rotation about the line through both points moves neither
        pair_m2.append(e6 @ np.linalg.pinv(C6, rcond=1e-9, hermitian=True) @ e6)
        pair_e.append(e6)
        pair_c.append(C6)
        u, sd, _ = reg.transfer_direction([0.0, 0.0, 1.0], sd_deg=0.0)
        dir_err.append(np.degrees(np.arccos(np.clip(u @ R_TRUE[:, 2], -1, 1))))
        dir_sd.append(sd)
    errs, covs = np.array(errs), np.array(covs)
    ratio = errs.std(axis=0) / np.sqrt(np.mean(np.diagonal(covs, axis1=1, axis2=2), axis=0))
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio
    m2 = np.mean([e @ np.linalg.solve(C, e) for e, C in zip(errs, covs)])
    assert 6 * 0.7 < m2 < 6 * 1.3, m2
    assert 3 * 0.7 < np.mean(hip_m2) < 3 * 1.3
    # both points jointly: 5-dof Mahalanobis distances, and the predicted between-point covariance is the actual one
    assert np.linalg.matrix_rank(pair_c[0], tol=1e-9 * np.abs(pair_c[0]).max()) == 5
    assert 5 * 0.7 < np.mean(pair_m2) < 5 * 1.3
    emp = np.cov(np.array(pair_e).T)
    pred = np.mean(pair_c, axis=0)
    assert np.allclose(np.diag(emp[:3, 3:]), np.diag(pred[:3, 3:]), atol=0.3 * np.sqrt(np.diag(pred)[:3] * np.diag(pred)[3:]).max())
    Y1, C1 = reg.transfer_point(hips[1])
    np.testing.assert_allclose(C6[3:, 3:], C1, rtol=1e-9, atol=1e-20)
    np.testing.assert_allclose(Y[1], Y1)
    # Angle error of a direction: rms over draws vs predicted per-plane sd·√2 (2 tangent components).
    rms_angle = np.sqrt(np.mean(np.square(dir_err)))
    assert 0.7 < rms_angle / (np.sqrt(2) * np.sqrt(np.mean(np.square(dir_sd)))) < 1.3


def test_exact_data_recover_transform_exactly():
    reg = register_landmarks(P0, P0 @ R_TRUE.T + T_TRUE, None, 1e-6)
    assert np.allclose(reg.R, R_TRUE, atol=1e-9) and np.allclose(reg.t, T_TRUE, atol=1e-9)
    assert reg.rms < 1e-9 and not reg.rejected


def test_shifted_registration_moves_points_pivot_and_residuals():
    rng = np.random.default_rng(3)
    M = P0 @ R_TRUE.T + T_TRUE + rng.normal(0, 0.002, P0.shape)
    names = list("abcdef")
    reg = register_landmarks(P0, M, None, 0.002, names=names)
    used = [names.index(n) for n in reg.names]
    d = np.array([0.004, -0.010, 0.002])
    moved = reg.shifted(d)
    y, C = reg.transfer_point(P0[0])
    y2, C2 = moved.transfer_point(P0[0])
    np.testing.assert_allclose(y2, y + d, atol=1e-12)
    np.testing.assert_allclose(C2, C, atol=1e-15)  # the same map error, pivot moved with it
    np.testing.assert_allclose(moved.residuals, M[used] - (P0[used] @ moved.R.T + moved.t), atol=1e-9)
    np.testing.assert_allclose(moved.as_matrix()[:3, 3], reg.t + d)
    assert moved.chi2 == reg.chi2


def test_outlier_rejected_and_transform_unbiased():
    """A 25 mm misplaced marker is rejected (named) in ≥ 90 % of draws; clean draws rarely lose a point."""
    rng = np.random.default_rng(2)
    K, msd = len(P0), 0.002
    names = ["RASI", "LASI", "RPSI", "LPSI", "SYMP", "X"]
    hits, false_rej, ang = 0, 0, []
    for i in range(60):
        M = P0 @ R_TRUE.T + T_TRUE + rng.normal(0, msd, (K, 3))
        false_rej += bool(register_landmarks(P0, M, 0.001**2 * np.eye(3), msd, names=names).rejected)
        k = i % K
        M[k] += 0.025 * _random_normals(rng, 1)[0]
        reg = register_landmarks(P0, M, 0.001**2 * np.eye(3), msd, names=names)
        hits += list(reg.rejected) == [names[k]]
        e = _pose_error(reg, R_TRUE, T_TRUE)
        ang.append(e @ np.linalg.solve(reg.cov, e))
    assert hits >= 54, hits
    assert false_rej <= 6, false_rej
    # After rejection the transform is as good as its (clean-data) uncertainty says: χ²₆ 99 % = 16.8.
    assert np.mean(np.array(ang) < 16.8) >= 0.9


def test_bad_registration_input():
    with pytest.raises(InputError, match="at least 3"):
        register_landmarks(P0[:2], P0[:2], None, 0.002, names=["RASI", "LASI"])
    line = np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]], float)
    with pytest.raises(InputError, match="collinear"):
        register_landmarks(line, line, None, 0.002)
    bad = P0.copy()
    bad[1, 0] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        register_landmarks(bad, P0, None, 0.002, names=list("abcdef"))


# --------------------------------------------------------------------------- segments

def _skeleton():
    """Right-side landmarks (scanner frame: X anterior, Y superior, Z right), names, normals."""
    pel = {"RASI": [0.0, 0.95, 0.12], "LASI": [0.0, 0.95, -0.12], "RPSI": [-0.15, 0.99, 0.045],
           "LPSI": [-0.15, 0.99, -0.045], "SYMP": [0.02, 0.85, 0.0],
           "acetabulum_centre_r": [-0.02, 0.88, 0.085], "acetabulum_centre_l": [-0.02, 0.88, -0.085]}
    fem = {"RTRO": [-0.01, 0.87, 0.16], "RKNE": [0.0, 0.50, 0.135], "RMFC": [0.0, 0.50, 0.035],
           "femoral_head_centre": [-0.02, 0.88, 0.085], "lateral_condyle_centre": [0.0, 0.49, 0.11],
           "medial_condyle_centre": [0.0, 0.49, 0.06]}
    tib = {"RTTB": [0.045, 0.44, 0.09], "RMMA": [0.0, 0.08, 0.055], "plateau_centre": [0.0, 0.46, 0.09],
           "plafond_centre": [0.0, 0.07, 0.09]}
    fib = {"RHFB": [-0.01, 0.43, 0.135], "RANK": [-0.01, 0.06, 0.125]}
    cal = {"RHEE": [-0.07, 0.02, 0.09], "RD1M": [0.13, 0.01, 0.06], "RD5M": [0.10, 0.01, 0.14]}
    tal = {"talar_dome_centre": [0.0, 0.06, 0.09]}
    return {"pelvis": pel, "femur_r": fem, "tibia_r": tib, "fibula_r": fib, "calcn_r": cal, "talus_r": tal}


def _mirror(bones_r):
    from lowerlimb.bones import mirror_name
    out = {}
    for b, lms in bones_r.items():
        if b == "pelvis":
            continue
        out[mirror_name(b)] = {mirror_name(n) if n[:1] == "R" else n.replace("_r", "_l"): [x, y, -z]
                               for n, (x, y, z) in lms.items()}
    return out


def _landmark_set(bones):
    """The landmarks as a landmarks.json document would hold them, read by `LandmarkSet.from_json`."""
    from personalize.landmarks import LandmarkSet

    cov = (0.0015**2 * np.eye(3)).tolist()
    return LandmarkSet.from_json({"units": "m", "frame": "input", "bones": {
        b: {"landmarks": {n: {"position": list(p), "cov": cov} for n, p in lms.items()},
            "axes": {}, "scalars": {}, "frames": {}, "flags": []} for b, lms in bones.items()}})


MARKER_NAMES = ["RASI", "LASI", "RPSI", "LPSI", "SYMP"] + [s + m for s in "RL" for m in
                                                           ("TRO", "KNE", "MFC", "TTB", "HFB", "ANK", "MMA", "HEE", "D1M", "D5M")]


@pytest.fixture(scope="module")
def world():
    """Landmarks JSON, the static trial made from it with per-segment poses, and the true poses."""
    rng = np.random.default_rng(3)
    bones = _skeleton()
    bones.update(_mirror(bones))
    lm = _landmark_set(bones)
    # Lab: Z up, X forward; each segment gets its own small extra rotation (a static pose is not the MRI pose).
    base = Rotation.from_euler("x", 90, degrees=True)
    seg_of = {}
    for b, lms in bones.items():
        for n in lms:
            seg_of[n] = b if b not in ("fibula_r", "fibula_l", "talus_r", "talus_l") else b.replace("fibula", "tibia").replace("talus", "calcn")
    poses = {}
    for seg in ("pelvis", "femur_r", "tibia_r", "calcn_r", "femur_l", "tibia_l", "calcn_l"):
        Rs = (Rotation.from_rotvec(rng.normal(0, 0.05, 3)) * base).as_matrix()
        poses[seg] = (Rs, np.array([0.5, 1.2, 0.0]) + rng.normal(0, 0.01, 3))
    normals = {}
    pos = np.zeros((40, len(MARKER_NAMES), 3))
    from personalize.marker_registration import _internal_reference, SEGMENT_BONES
    flat = {n: np.array(p, float) for lms in bones.values() for n, p in lms.items()}
    for j, n in enumerate(MARKER_NAMES):
        seg = seg_of[n]
        side = None if seg == "pelvis" else seg[-1]
        base_seg = seg if seg == "pelvis" else seg[:-2]
        bnames = [b if b == "pelvis" else f"{b}_{side}" for b in SEGMENT_BONES[base_seg]]
        ref = _internal_reference(lm.bones, bnames, flat[n])
        nrm = flat[n] - ref
        nrm /= np.linalg.norm(nrm)
        normals[n] = nrm
        centre = flat[n] + (skin_prior(n)[0] + DEFAULT_MARKER_RADIUS) * nrm   # per-site tissue (the default prior)
        Rs, ts = poses[seg]
        pos[:, j] = Rs @ centre + ts + rng.normal(0, 0.002, 3) + rng.normal(0, 0.0005, (40, 3))
    pos[5:8, 3] = np.nan  # gaps are ignored by the robust static positions
    trial = MarkerTrial(tuple(MARKER_NAMES), pos, 100.0, np.arange(40) / 100.0, "static.c3d")
    return lm, trial, poses, normals, flat


def test_static_positions_are_robust():
    pos = np.zeros((21, 1, 3))
    pos[:, 0, 0] = np.linspace(-0.001, 0.001, 21)
    pos[3, 0] = [5.0, 5.0, 5.0]  # a ghost marker in one frame
    pos[4, 0] = np.nan
    st = static_marker_positions(MarkerTrial(("RASI",), pos, 100.0, np.arange(21) / 100.0, "s.c3d"), placement_sd=0.0)
    p, c = st["RASI"].mean, st["RASI"].cov
    assert np.allclose(p, 0.0, atol=2e-4)  # the mean would be 0.26 m off
    assert 0.0003 < np.sqrt(c[0, 0]) < 0.001 and c[1, 1] < 1e-10


def test_register_segments_recovers_every_segment(world):
    lm, trial, poses, normals, flat = world
    regs = register_segments(lm, trial, normals=normals)
    assert set(regs) == {"pelvis", "femur_r", "tibia_r", "calcn_r", "femur_l", "tibia_l", "calcn_l"}
    for seg, reg in regs.items():
        Rt, tt = poses[seg]
        ang = np.degrees(np.linalg.norm(Rotation.from_matrix(Rt @ reg.R.T).as_rotvec()))
        assert ang < 3.0 * np.linalg.norm(reg.rotation_sd_deg) + 0.5, (seg, ang)
        assert not reg.rejected
    # The femoral head centre carried into the lab lies within its propagated uncertainty of the truth.
    hc = flat["femoral_head_centre"]
    y, cy = regs["femur_r"].transfer_point(hc, 0.0015**2 * np.eye(3))
    e = y - (poses["femur_r"][0] @ hc + poses["femur_r"][1])
    assert e @ np.linalg.solve(cy, e) < 16.3  # χ²₃ 99.9 %
    assert np.linalg.norm(e) < 0.02


def test_guessed_normals_are_less_certain_but_agree(world):
    lm, trial, poses, normals, flat = world
    with_n = register_segments(lm, trial, normals=normals)
    guessed = register_segments(lm, trial)
    for seg in with_n:
        # Same normals here (the guess uses the same internal references), but the guess is declared less certain.
        assert np.trace(guessed[seg].cov) >= np.trace(with_n[seg].cov)
        ang = np.degrees(np.linalg.norm(Rotation.from_matrix(poses[seg][0] @ guessed[seg].R.T).as_rotvec()))
        assert ang < 5.0


def _rename(trial, mapping, drop=()):
    keep = [i for i, n in enumerate(trial.names) if n not in drop]
    names = tuple(mapping.get(trial.names[i], trial.names[i]) for i in keep)
    return MarkerTrial(names, trial.positions[:, keep], trial.rate, trial.time, trial.source)


def test_swapped_sides_are_refused(world):
    from lowerlimb.bones import mirror_name
    lm, trial, *_ = world
    swapped = _rename(trial, {n: mirror_name(n) for n in trial.names})
    with pytest.raises(InputError, match="mirrored"):
        register_segments(lm, swapped)
    # Left-leg markers labelled as the right leg (the right leg's own markers absent).
    legs = [n for n in trial.names if n[:1] in "RL" and n[1:] not in ("ASI", "PSI")]
    only_left_as_right = _rename(trial, {n: "R" + n[1:] for n in legs if n[0] == "L"},
                                 drop=[n for n in legs if n[0] == "R"])
    with pytest.raises(InputError, match="sides mixed"):
        register_segments(lm, only_left_as_right, sides=("r",))


def test_too_few_correspondences_named(world):
    lm, trial, *_ = world
    short = _rename(trial, {}, drop=("RHEE", "RD5M"))
    with pytest.raises(InputError, match=r"calcn_r has 1 usable.*RD1M.*missing in static trial: RHEE, RD5M"):
        register_segments(lm, short)


def test_millimetre_markers_refused(world):
    lm, trial, *_ = world
    mm = MarkerTrial(trial.names, trial.positions * 1000.0, trial.rate, trial.time, trial.source)
    with pytest.raises(InputError, match="units"):
        register_segments(lm, mm)


def test_express_in_frame_is_calibrated():
    """A lab point expressed in an uncertain segment frame: predicted covariance matches 300 draws."""
    from personalize.registration import express_in_frame
    rng = np.random.default_rng(7)
    R0 = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    o0, y0 = np.array([0.5, 1.2, 0.9]), np.array([0.45, 1.15, 0.82])
    Co, Cw, Cy = np.diag([4e-6, 1e-6, 2e-6]), np.diag([1e-4, 4e-4, 1e-4]), 1e-6 * np.eye(3)
    truth = R0.T @ (y0 - o0)
    m2 = []
    for _ in range(300):
        R = Rotation.from_rotvec(rng.multivariate_normal(np.zeros(3), Cw)).as_matrix() @ R0
        o = o0 + rng.multivariate_normal(np.zeros(3), Co)
        y = y0 + rng.multivariate_normal(np.zeros(3), Cy)
        loc, C = express_in_frame(y, Cy, o, R, Co, Cw)
        e = loc - truth
        m2.append(e @ np.linalg.solve(C, e))
    assert 3 * 0.8 < np.mean(m2) < 3 * 1.2


def test_segment_selection_and_skipping(world):
    lm, trial, poses, normals, flat = world
    # A Plug-in-Gait-like static trial: no trochanter, medial or metatarsal markers.
    pig_like = _rename(trial, {}, drop=[s + m for s in "RL" for m in ("TRO", "MFC", "D1M", "D5M", "TTB", "HFB")])
    with pytest.raises(InputError, match="femur_r has 1 usable"):
        register_segments(lm, pig_like)
    regs = register_segments(lm, pig_like, on_missing="skip")
    assert set(regs) == {"pelvis"}
    assert set(regs.skipped) == {"femur_r", "tibia_r", "calcn_r", "femur_l", "tibia_l", "calcn_l"}
    assert "RKNE" in regs.skipped["femur_r"] and "RTRO" in regs.skipped["femur_r"]
    only = register_segments(lm, trial, segments=("pelvis", "femur_l"))
    assert set(only) == {"pelvis", "femur_l"}
    with pytest.raises(InputError, match="unknown segment"):
        register_segments(lm, trial, segments=("thigh_r",))


def test_default_soft_tissue_prior_is_per_site(world):
    """Markers over site-specific tissue (PSIS 19.6 mm, ASIS 9.7 mm): the per-site default prior recovers the pelvis;
    one uniform 5 mm thickness shifts it (the systematic bias a single default caused)."""
    lm, trial, poses, normals, flat = world
    names = ("RASI", "LASI", "RPSI", "LPSI", "SYMP")
    assert skin_prior("RPSI")[0] > skin_prior("RASI")[0] > 0.005
    c = np.mean([flat[n] for n in names], axis=0)
    Rt, tt = poses["pelvis"]
    per_site = register_segments(lm, trial, normals=normals, segments=("pelvis",))["pelvis"]
    uniform = register_segments(lm, trial, normals=normals, segments=("pelvis",), skin_thickness=SKIN_THICKNESS,
                                skin_sd=0.003)["pelvis"]
    err = lambda r: float(np.linalg.norm(r.R @ c + r.t - (Rt @ c + tt)))  # noqa: E731
    assert err(per_site) < 0.003
    assert err(uniform) > 2 * err(per_site) and err(uniform) > 0.003


def test_correspondences_take_each_landmark_from_its_own_bone():
    """A shank's fibula landmark (RANK) takes its outward normal from the fibula surface, not the tibia's; with a
    joint axis the landmark is moved onto the axis and the normal is the axis direction, away from its point."""
    import trimesh

    from lowerlimb.estimates import Gaussian
    from personalize.landmarks import BoneLandmarks, Landmark
    from personalize.marker_registration import SURFACE_NORMAL_SD_DEG, marker_correspondences

    tib = trimesh.creation.icosphere(subdivisions=4, radius=0.02)
    fib = trimesh.creation.icosphere(subdivisions=4, radius=0.01)
    fib.apply_translation([0.05, 0.0, 0.0])
    ank = np.array([0.05, 0.01, 0.0])                 # on the fibula sphere, normal +y
    bones = {"tibia_r": BoneLandmarks("tibia_r", "r", {"RMMA": Landmark(np.array([-0.02, 0.0, 0.0]), 1e-6 * np.eye(3))}),
             "fibula_r": BoneLandmarks("fibula_r", "r", {"RANK": Landmark(ank, 1e-6 * np.eye(3))})}
    static = {n: Gaussian.isotropic(np.zeros(3), 0.003) for n in ("RANK", "RMMA")}
    c = marker_correspondences(bones, ["tibia_r", "fibula_r"], ("RANK", "RMMA"), static,
                               surfaces={"tibia_r": tib, "fibula_r": fib})
    assert c.names == ["RANK", "RMMA"]
    np.testing.assert_allclose(c.normals[0], [0.0, 1.0, 0.0], atol=0.05)      # the tibia's nearest normal is +x
    np.testing.assert_allclose(c.normals[1], [-1.0, 0.0, 0.0], atol=0.05)
    assert c.normal_sd_deg == [SURFACE_NORMAL_SD_DEG] * 2
    assert c.offset[0] == pytest.approx(skin_prior("RANK")[0] + DEFAULT_MARKER_RADIUS)
    # on the transmalleolar axis through (0.01, 0, 0) along x: projected, normal along the axis away from the point
    a = marker_correspondences(bones, ["tibia_r", "fibula_r"], ("RANK", "RMMA"), static,
                               surfaces={"tibia_r": tib, "fibula_r": fib}, axis=([0.01, 0.0, 0.0], [2.0, 0.0, 0.0]))
    np.testing.assert_allclose(a.mri[0], [0.05, 0.0, 0.0])
    np.testing.assert_allclose(a.normals[0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(a.normals[1], [-1.0, 0.0, 0.0])


def _gauss_newton(Q, M, Cq, Cm, R, t, iters=50):
    """The former undamped Gauss-Newton of `_fit` (no step control), kept here as the reference that diverges."""
    w0 = 1.0 / np.trace(Cq + Cm, axis1=1, axis2=2)
    c = (w0 @ M) / w0.sum()
    for _ in range(iters):
        _, _, _, H, g, _ = _linearise(Q, M, Cq, Cm, R, t, c)
        dx = np.linalg.lstsq(H, g, rcond=None)[0]
        dR = Rotation.from_rotvec(dx[:3]).as_matrix()
        R, t = dR @ R, c + dR @ (t - c) + dx[3:]
    return R, t, c, _linearise(Q, M, Cq, Cm, R, t, c)


def _outlier_problem(seed=2):
    """Six landmarks (5 cm spread), 20 mm sd along each bone normal, 3 mm markers, one marker moved 0.5 m."""
    rng = np.random.default_rng(seed)
    K = int(rng.integers(3, 7))
    Q = rng.normal(scale=0.05, size=(K, 3))
    R_true = Rotation.random(random_state=seed).as_matrix()
    t_true = rng.normal(size=3)
    M = Q @ R_true.T + t_true + rng.normal(scale=0.003, size=(K, 3))
    M[0] += rng.normal(size=3) * 0.5 / np.sqrt(3)
    N = rng.normal(size=(K, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    Cq = 0.02**2 * np.einsum("ki,kj->kij", N, N) + 1e-8 * np.eye(3)
    Cm = np.repeat((0.003**2 * np.eye(3))[None], K, axis=0)
    return Q, M, Cq, Cm


def test_damped_fit_cannot_diverge():
    """A mislabelled marker with anisotropic landmark noise: Gauss-Newton diverges, Levenberg-Marquardt does not.

    Measured (seed 2, 6 landmarks, marker 0 moved 0.5 m): from the weighted Kabsch start (χ² = 25 439)
    undamped Gauss-Newton oscillates (χ² 1.7e7, 1.6e9, 4.2e4, ... every 5 iterations) and ends after 50
    at χ² = 4.2e11 with a residual of 867 m, as `registration._fit` did on a real subject.  The damped
    fit only accepts decreasing steps: χ² = 8223, largest residual 0.52 m (the moved marker).  With the
    outlier rejected by `register_landmarks` (d = 115 sd) the problem is well posed and the fit reaches the
    same optimum as Gauss-Newton on the five inliers (χ² = 5.1597 on 9 dof; R within 1e-9, t within 1e-10 m).
    """
    Q, M, Cq, Cm = _outlier_problem()
    w0 = 1.0 / np.trace(Cq + Cm, axis1=1, axis2=2)
    R0, t0 = kabsch(Q, M, w0)
    c0 = (w0 @ M) / w0.sum()
    chi2_start = _linearise(Q, M, Cq, Cm, R0, t0, c0)[5]
    *_, (r_gn, _, _, _, _, chi2_gn) = _gauss_newton(Q, M, Cq, Cm, R0, t0)
    assert chi2_gn > 1e3 * chi2_start and np.max(np.linalg.norm(r_gn, axis=1)) > 10.0

    R, t, c, H, r, S, J = _fit(Q, M, Cq, Cm)
    chi2 = _linearise(Q, M, Cq, Cm, R, t, c)[5]
    assert chi2 <= chi2_start
    assert np.max(np.linalg.norm(r, axis=1)) < 0.6
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)

    reg = register_landmarks(Q, M, mri_cov=Cq, marker_sd=0.003)
    assert list(reg.rejected) == ["0"] and reg.rejected["0"] > 50
    Cf = Cq[1:] + 1e-12 * np.eye(3)  # register_landmarks' covariance floor
    R_gn, t_gn, _, lin = _gauss_newton(Q[1:], M[1:], Cf, Cm[1:], *kabsch(Q[1:], M[1:], w0[1:]))
    assert np.max(np.abs(reg.R - R_gn)) < 1e-8 and np.max(np.abs(reg.t - t_gn)) < 1e-8
    assert reg.chi2 == pytest.approx(lin[5], rel=1e-8)


def test_damped_fit_from_far_reaches_the_optimum():
    """Started 1 and 3 rad away from the optimum (isotropic noise), the fit reaches the Kabsch-started optimum."""
    rng = np.random.default_rng(4)
    K = len(P0)
    M = P0 @ R_TRUE.T + T_TRUE + rng.normal(scale=0.003, size=(K, 3))
    Cq = np.repeat((1e-6 * np.eye(3))[None], K, axis=0)
    Cm = np.repeat((0.003**2 * np.eye(3))[None], K, axis=0)
    R_ref, t_ref, *_ = _fit(P0, M, Cq, Cm)
    for angle in (1.0, 3.0):
        R0 = Rotation.from_rotvec([angle, 0.0, 0.0]).as_matrix() @ R_TRUE
        R, t, *_ = _fit(P0, M, Cq, Cm, R0=R0, t0=T_TRUE + 0.3)
        assert np.max(np.abs(R - R_ref)) < 1e-9 and np.max(np.abs(t - t_ref)) < 1e-9
