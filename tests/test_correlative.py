"""Correlative laws (Pronost et al. 2010, sections 3.2, 3.3, eq. 3 and 4.2)."""
from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation
from scipy.special import erf

from kinematics.mechanisms.correlative import CorrelativeLaw
from kinematics.mechanisms.correlative_fit import fit_law, fit_laws_by_group
from kinematics.mechanisms.law_transfer import knee_landmark_frame, scale_factor, transfer_law
from personalize.presentation.correlative_tables import coefficient_table, deviation_table, plot_deviation
from lowerlimb.errors import FitError, InputError

IND = ("knee_flexion_r", "knee_adduction_r", "knee_rotation_r")
DEP = ("knee_tx_r", "knee_ty_r", "knee_tz_r")
# Seed Table 1, subject 1 (crouch), rows T_x, T_y, T_z as [c1, c2, c3, c4]; read as m/rad and m.
SEED_C = np.array([[0.0573, 0.0361, 0.0582, 0.0748],
                   [0.0306, -0.0442, -0.1055, -0.5035],
                   [-0.0199, 0.0210, -0.2218, 0.0346]])


def crouch_angles(n, rng, foot_angle=0.0):
    """Knee rotations of a crouch: flexion 0..110 deg and back, small coupled ab/adduction and rotation (rad)."""
    t = np.linspace(0, 1, n)
    flex = np.radians(55) * (1 - np.cos(2 * np.pi * t))
    add = np.radians(4) * np.sin(2 * np.pi * t + 0.7) + np.radians(2) * np.sin(6 * np.pi * t) + 0.3 * foot_angle / 10
    rot = np.radians(8) * np.sin(4 * np.pi * t + 0.3) + 0.15 * foot_angle + np.radians(1) * rng.standard_normal(n)
    return np.column_stack([flex, add, rot])


def law_values(C, A):
    return A @ C[:, :3].T + C[:, 3]


def test_noise_free_recovery_within_2_percent():
    rng = np.random.default_rng(1)
    A = crouch_angles(200, rng)
    law = fit_law(A, law_values(SEED_C, A), IND, DEP, joint="knee_r")
    rel = np.abs(law.coefficients - SEED_C) / np.abs(SEED_C)
    assert rel.max() < 0.02
    np.testing.assert_allclose(law.coefficients, SEED_C, atol=1e-10)
    assert law.fit.valid and np.all(law.fit.r2 > 1 - 1e-12)
    assert law.fit.mean_deviation < 1e-12
    assert law.distance_to(CorrelativeLaw("truth", IND, DEP, SEED_C), A).max() < 1e-12
    # Exact law: predict reproduces the generating values at new angles.
    B = crouch_angles(11, rng)
    np.testing.assert_allclose(law.predict(B), law_values(SEED_C, B), atol=1e-12)
    np.testing.assert_allclose(law.predict(B[3]), law_values(SEED_C, B[3:4])[0], atol=1e-12)


def test_noise_statistics_and_covariance_calibration():
    rng = np.random.default_rng(2)
    sigma = 1e-3
    A = crouch_angles(3000, rng)
    Y = law_values(SEED_C, A) + sigma * rng.standard_normal((3000, 3))
    law = fit_law(A, Y, IND, DEP)
    # Residual RMS per axis ~ sigma; mean 3-D deviation ~ mean of a chi(3) = sigma sqrt(8/pi).
    np.testing.assert_allclose(law.fit.rms, sigma, rtol=0.05)
    assert law.fit.mean_deviation == pytest.approx(sigma * math.sqrt(8 / math.pi), rel=0.04)
    np.testing.assert_allclose(np.diag(law.residual_covariance), sigma ** 2, rtol=0.1)
    # Coefficient errors are consistent with the stated standard deviations.
    z = (law.coefficients - SEED_C) / law.coefficient_sd
    assert np.all(np.abs(z) < 4.5)
    assert np.all(law.coefficient_sd < 0.01 * np.abs(SEED_C).max())
    # Prediction standard error of the mean is much smaller than the noise.
    sd = law.predict_sd(A[:5])
    assert sd.shape == (5, 3) and np.all(sd < 0.2 * sigma)
    # Over the motion, the fitted law stays within a fraction of the noise of the true one.
    assert law.distance_to(CorrelativeLaw("truth", IND, DEP, SEED_C), A).max() < 0.25 * sigma


def _mean_norm_offset_gaussian(sigma, nu):
    """E|X| for X ~ N(mu, sigma^2 I_3), |mu| = nu (the 3-D Rice mean)."""
    if nu == 0:
        return sigma * math.sqrt(8 / math.pi)
    return (sigma * math.sqrt(2 / math.pi) * math.exp(-nu ** 2 / (2 * sigma ** 2))
            + (nu + sigma ** 2 / nu) * erf(nu / (sigma * math.sqrt(2))))


# Seed Table 2: crouch (motion specific / sub-motion specific) and gait (motion specific), mm.
SEED_TABLE2 = {"Crouch": [(1.3, 1.1), (2.0, 1.4), (0.9, 0.7), (1.1, 0.9), (1.6, 1.0), (1.0, 0.8)],
               "Gait": [(1.1, None), (0.9, None), (1.5, None), (1.7, None), (3.1, None), (1.0, None)]}


def test_table2_deviation_statistics_reproduced():
    """Simulated subjects whose sub-motion laws differ (by the foot angle) reproduce the seed's Table 2.

    Noise level and the spread of the sub-motion laws are set from the seed's
    numbers; the regression, the per-sub-motion fits and the deviation
    statistic must then give those numbers back.
    """
    rng = np.random.default_rng(3)
    n_sub = 400
    feet = np.radians([0, 30, 60, 90, 120, 180])
    offsets = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    p = 4
    cells = {"Crouch": {}, "Gait": {}}
    for s, ((mot, sub), (gait, _)) in enumerate(zip(SEED_TABLE2["Crouch"], SEED_TABLE2["Gait"])):
        subj = f"Subject{s + 1}"
        # Residuals of a fit with p coefficients shrink by sqrt((n - p) / n): compensate.
        sigma = sub * 1e-3 / math.sqrt(8 / math.pi) * math.sqrt(n_sub / (n_sub - p))
        nu = brentq(lambda v: _mean_norm_offset_gaussian(sigma, v) - mot * 1e-3, 0.0, 0.05)
        base = crouch_angles(n_sub, rng)
        A, Y, g = [], [], []
        for j, foot in enumerate(feet):
            Aj = base.copy()
            Aj[:, 2] = base[:, 2] - base[:, 2].mean()  # same angle pattern in every sub-motion
            Cj = SEED_C.copy()
            Cj[:, 3] += nu * offsets[j]
            A.append(Aj)
            Y.append(law_values(Cj, Aj) + sigma * rng.standard_normal((n_sub, 3)))
            g += [f"{round(np.degrees(foot))} deg"] * n_sub
        A, Y = np.vstack(A), np.vstack(Y)
        motion_law = fit_law(A, Y, IND, DEP, groups=g)
        sub_laws = fit_laws_by_group(A, Y, g, IND, DEP)
        garr = np.asarray(g)
        sub_dev = np.mean(np.concatenate([sub_laws[k].deviation(A[garr == k], Y[garr == k]) for k in sub_laws]))
        # Gait: one law per motion only.
        sg = gait * 1e-3 / math.sqrt(8 / math.pi) * math.sqrt(3 * n_sub / (3 * n_sub - p))
        Ag = crouch_angles(3 * n_sub, rng) * 0.5
        gait_law = fit_law(Ag, law_values(SEED_C, Ag) + sg * rng.standard_normal((3 * n_sub, 3)), IND, DEP)
        cells["Crouch"][subj] = (motion_law.fit.mean_deviation, sub_dev)
        cells["Gait"][subj] = (gait_law.fit.mean_deviation, None)
        # Leave-one-sub-motion-out error exceeds the in-sample one (laws differ per foot angle).
        assert motion_law.fit.loto_mean_deviation > motion_law.fit.mean_deviation
    table = deviation_table(cells, unit="mm", digits=1)
    for row in table.rows:
        expected = [f"{a:.1f} / {'-' if b is None else f'{b:.1f}'}" for a, b in SEED_TABLE2[row[0]]]
        assert list(row[1:]) == expected
    md = table.to_markdown()
    assert "| Crouch | 1.3 / 1.1" in md.replace("  ", " ") or "1.3 / 1.1" in md
    parsed = list(csv.reader(io.StringIO(table.to_csv())))
    assert parsed[0] == ["motion"] + [f"Subject{i}" for i in range(1, 7)]
    assert parsed[2][5] == "3.1 / -"


def test_leave_one_trial_out_on_exact_law_matches_noise():
    rng = np.random.default_rng(4)
    sigma = 5e-4
    A = np.vstack([crouch_angles(150, rng) for _ in range(4)])
    Y = law_values(SEED_C, A) + sigma * rng.standard_normal((600, 3))
    law = fit_law(A, Y, IND, DEP, groups=np.repeat(np.arange(4), 150))
    assert law.fit.n_groups == 4
    np.testing.assert_allclose(law.fit.loto_rms, sigma, rtol=0.1)
    assert law.fit.loto_mean_deviation >= law.fit.mean_deviation


def test_bad_input_errors():
    rng = np.random.default_rng(5)
    A = crouch_angles(50, rng)
    Y = law_values(SEED_C, A)
    with pytest.raises(InputError, match="3 frames for 4 coefficients"):
        fit_law(A[:3], Y[:3], IND, DEP)
    with pytest.raises(InputError, match="no residual degree of freedom"):
        fit_law(A[:4], Y[:4], IND, DEP)
    flat = A.copy()
    flat[:, 1] = 0.02
    with pytest.raises(FitError, match="knee_adduction_r do not vary"):
        fit_law(flat, Y, IND, DEP)
    coll = A.copy()
    coll[:, 2] = 2 * A[:, 0] - 0.1
    with pytest.raises(FitError, match=r"rank 3 < 4.*collinear") as ei:
        fit_law(coll, Y, IND, DEP)
    assert "knee_rotation_r" in str(ei.value) and "knee_flexion_r" in str(ei.value)
    with pytest.raises(InputError, match="knee_tx_r listed both"):
        fit_law(A, Y, ("knee_flexion_r", "knee_tx_r", "knee_rotation_r"), DEP)
    with pytest.raises(InputError, match="share the frame count"):
        fit_law(A, Y[:-1], IND, DEP)
    # Missing values: frames dropped and counted, not silently used.
    An = A.copy()
    An[[3, 7], 0] = np.nan
    law = fit_law(An, Y, IND, DEP)
    assert law.fit.n_dropped == 2 and law.fit.n_frames == 48
    np.testing.assert_allclose(law.coefficients, SEED_C, atol=1e-9)


def test_nearly_collinear_flagged_not_hidden():
    rng = np.random.default_rng(6)
    A = crouch_angles(200, rng)
    A[:, 2] = 0.5 * A[:, 0] + 1e-4 * rng.standard_normal(200)  # rotation almost a copy of flexion
    law = fit_law(A, law_values(SEED_C, A) + 1e-4 * rng.standard_normal((200, 3)), IND, DEP)
    assert law.fit.condition > 1e3 and not law.fit.well_conditioned and not law.fit.valid
    # The uncertainty of the confounded coefficients is correspondingly large.
    assert law.coefficient_sd[:, 2].min() > 10 * law.coefficient_sd[:, 1].max()


def test_json_round_trip_and_schema(tmp_path):
    rng = np.random.default_rng(7)
    A = crouch_angles(100, rng)
    law = fit_law(A, law_values(SEED_C, A) + 1e-4 * rng.standard_normal((100, 3)), IND, DEP, joint="knee_r")
    d = law.to_json()
    assert d["joint"] == "knee_r" and d["dependent"] == list(DEP) and d["independent"] == list(IND)
    assert np.shape(d["coefficients"]) == (3, 4)
    assert d["units"]["coefficients"] == ["m/rad", "m/rad", "m/rad", "m"]
    assert set(d["fit"]) >= {"r2", "rms", "max_abs", "valid"}
    p = law.write(tmp_path / "law.json")
    back = CorrelativeLaw.from_json(p)
    assert back.same_as(law)
    np.testing.assert_allclose(back.covariance, law.covariance)
    np.testing.assert_allclose(back.fit.r2, law.fit.r2)
    # A minimal truth-style law (no covariance, no fit) is accepted.
    mini = CorrelativeLaw.from_json({"joint": "knee_l", "dependent": list(DEP), "independent": list(IND),
                                     "coefficients": SEED_C.tolist(), "units": {"independent": "rad", "dependent": "m"}})
    assert mini.covariance is None and mini.same_as(CorrelativeLaw("knee_l", IND, DEP, SEED_C))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"dependent": ["a"], "independent": ["b"], "coefficients": [[1, 2, 3]]}))
    with pytest.raises(InputError, match="coefficients of shape"):
        CorrelativeLaw.from_json(bad)
    bad.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        CorrelativeLaw.from_json(bad)


def test_scaling_eq3():
    src = {"RGT": np.array([0.0, 0.0, 0.08]), "RLFE": np.array([0.0, -0.40, 0.05]), "RMFE": np.array([0.0, -0.40, -0.05])}
    tgt = {"RGT": np.array([0.0, 0.0, 0.088]), "RLFE": np.array([0.0, -0.44, 0.055]), "RMFE": np.array([0.0, -0.44, -0.045])}
    s1 = np.linalg.norm(tgt["RGT"] - tgt["RLFE"]) / np.linalg.norm(src["RGT"] - src["RLFE"])
    s2 = 0.1 / 0.1
    s = scale_factor(tgt, src)
    assert s == pytest.approx(0.5 * (s1 + s2))
    law = CorrelativeLaw("knee_r", IND, DEP, SEED_C, residual_covariance=np.eye(3) * 1e-6, normal_inverse=np.eye(4))
    sc = law.scaled(s)
    np.testing.assert_allclose(sc.coefficients, SEED_C * s)
    np.testing.assert_allclose(sc.coefficient_sd, law.coefficient_sd * s)
    # A transmission (angle on angle) is scale free.
    gear = CorrelativeLaw("gear", ("ra",), ("rb",), [[-0.5, 0.0]], dependent_units=("rad",))
    np.testing.assert_allclose(gear.scaled(2.0).coefficients, gear.coefficients)
    with pytest.raises(InputError, match="landmarks missing: RMFE"):
        scale_factor({"RGT": 0, "RLFE": 0}, src)


def test_knee_landmark_frame_axes():
    R = knee_landmark_frame([0.01, 0.4, 0.08], [0, 0, 0.05], [0, 0, -0.05], side="r")
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], [0, 0, 1], atol=1e-12)  # to the right
    assert R[1, 1] > 0.99  # cranial
    assert R[0, 0] > 0.99  # anterior


def test_transfer_five_steps_to_other_frames():
    rng = np.random.default_rng(8)
    src = {"RGT": np.array([0.02, -0.08, 0.09]), "RLFE": np.array([0.0, -0.48, 0.05]),
           "RMFE": np.array([0.005, -0.47, -0.045])}
    s_true = 1.07
    R_true = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    hip_target = np.array([0.1, -0.02, 0.3])
    tgt = {k: hip_target + s_true * R_true @ v for k, v in src.items()}
    law = fit_law(crouch_angles(60, rng), law_values(SEED_C, crouch_angles(60, np.random.default_rng(8))), IND, DEP)
    tr = transfer_law(law, src, tgt, target_origin=hip_target)
    assert tr.scale == pytest.approx(s_true, rel=1e-12)
    np.testing.assert_allclose(tr.rotation, R_true, atol=1e-12)
    A = crouch_angles(20, rng)
    expected = hip_target + s_true * law.predict(A) @ R_true.T
    np.testing.assert_allclose(tr.law.predict(A), expected, atol=1e-12)
    # Uncertainty is carried along: sd of the translation prediction scales by s (rotation-invariant norm).
    tot_src = np.trace(law.residual_covariance)
    assert np.trace(tr.law.residual_covariance) == pytest.approx(s_true ** 2 * tot_src, rel=1e-10)


def test_coefficient_table_and_plot(tmp_path):
    rng = np.random.default_rng(9)
    A = crouch_angles(120, rng)
    Y = law_values(SEED_C, A) + 1e-3 * rng.standard_normal((120, 3))
    laws = {"all": fit_law(A, Y, IND, DEP), "first half": fit_law(A[:60], Y[:60], IND, DEP)}
    t = coefficient_table(laws)
    assert t.header == ("dependent", "coefficient", "unit", "all", "first half")
    assert len(t.rows) == 12
    assert t.rows[3][:3] == ("knee_tx_r", "c4 (constant)", "m")
    assert t.rows[4][2] == "m/rad"
    val = float(t.rows[7][3].split(" ± ")[0])
    assert val == pytest.approx(laws["all"].coefficients[1, 3], abs=1e-4)
    png = plot_deviation(tmp_path / "dev.png", A, laws["all"].deviation(A, Y), IND)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_fluoroscopy_knee_law(shared_data):
    from kinematics.io.storage import read_sto

    tab = read_sto(shared_data / "knee_fluoroscopy" / "DM_fluoroscopic_gait_knee6dof.sto")
    # Rotation labels look swapped in this file: knee_rot_r (~48 deg range) behaves as flexion.
    ind = ["knee_rot_r", "knee_add_r", "knee_flex_r"]
    dep = ["knee_ant_r", "knee_sup_r", "knee_lat_r"]
    A, Y = tab.select(ind), tab.select(dep)
    law = fit_law(A, Y, ind, dep, joint="knee_r")
    # Independent check of the regression against numpy's least squares.
    M = np.column_stack([A, np.ones(len(A))])
    ref, *_ = np.linalg.lstsq(M, Y, rcond=None)
    np.testing.assert_allclose(law.coefficients, ref.T, atol=1e-12)
    res = Y - M @ ref
    np.testing.assert_allclose(law.fit.rms, np.sqrt(np.mean(res ** 2, axis=0)), rtol=1e-10)
    np.testing.assert_allclose(law.fit.r2, 1 - (res ** 2).sum(0) / ((Y - Y.mean(0)) ** 2).sum(0), rtol=1e-10)
    assert law.fit.n_frames == 101 and law.fit.well_conditioned
    # A TKR knee during gait: the law explains the superior translation well, sub-mm to mm deviations.
    assert law.fit.r2[1] > 0.9
    assert law.fit.mean_deviation < 2e-3


def test_law_as_coordinate_coupling():
    law = CorrelativeLaw("knee_r", IND, DEP, SEED_C)
    coords = ("hip_flexion_r",) + DEP + IND
    cpl = law.to_coupling(coords)
    assert cpl.n_rows == 3 and cpl.labels == DEP
    rng = np.random.default_rng(10)
    a = crouch_angles(5, rng)
    q = np.column_stack([np.zeros(5), law.predict(a), a])
    np.testing.assert_allclose(cpl.residual(q), 0.0, atol=1e-14)  # the law's own values satisfy the rows
    q[:, 1] += 1e-3
    np.testing.assert_allclose(cpl.residual(q)[:, 0], 1e-3, atol=1e-14)
    with pytest.raises(InputError, match="not in the model"):
        law.to_coupling(("hip_flexion_r",))


def test_law_as_coupling_in_ik_tracks_translations_better_than_a_free_joint():
    """Seed 4.1: the correlative knee (3 rotations + 3 coupled translations) inside IK.

    Markers of a shank moved by a knee that obeys a known law, with 1 mm noise:
    IK with the law as coupling rows recovers the joint translations more
    accurately than IK with an unconstrained six-DOF (free) knee.
    """
    from kinematics.algorithms.fk import marker_positions
    from kinematics.algorithms.ik import solve_ik
    from kinematics.multibody.joints import Transform, free, weld
    from kinematics.io.markers import MarkerTrial
    from kinematics.multibody.model import Body, Coordinate, Marker, Model

    names = IND + DEP
    coords = [Coordinate(n, "rotational", 0.0) for n in IND] + [Coordinate(n, "translational", 0.0) for n in DEP]
    joints = [weld("hip", "ground", "thigh", parent_offset=Transform(np.eye(3), (0.0, 0.9, 0.0))),
              free("knee_r", "thigh", "shank", names, sequence="ZXY",
                   parent_offset=Transform(np.eye(3), (0.0, -0.4, 0.0)))]
    bodies = [Body("thigh", 8.0, (0.0, -0.2, 0.0), np.diag([0.1, 0.03, 0.1])),
              Body("shank", 3.5, (0.0, -0.2, 0.0), np.diag([0.05, 0.005, 0.05]))]
    markers = [Marker(f"shank_{i}", "shank", p) for i, p in enumerate(
        [(0.05, -0.1, 0.03), (0.0, -0.25, 0.06), (-0.04, -0.2, -0.03), (0.0, -0.38, 0.05), (0.03, -0.3, -0.05)])]
    free_model = Model(tuple(bodies), tuple(joints), tuple(coords), tuple(markers), name="free knee")
    C = np.array([[0.010, 0.004, 0.006, 0.004], [0.006, -0.004, -0.010, -0.003], [-0.002, 0.002, -0.015, 0.002]])
    law = CorrelativeLaw("knee_r", IND, DEP, C)
    coupled = free_model.with_couplings(law.to_coupling([c.name for c in coords]))

    rng = np.random.default_rng(13)
    A = -crouch_angles(30, rng)
    q_true = np.column_stack([A, law.predict(A)])
    X = marker_positions(free_model, q_true) + rng.normal(0, 1e-3, (30, 5, 3))
    trial = MarkerTrial(tuple(m.name for m in markers), X, 60.0, np.arange(30) / 60.0, "synthetic")
    q0 = q_true[0]
    res_c = solve_ik(coupled, trial, q0=q0)
    res_f = solve_ik(free_model, trial, q0=q0)
    assert res_c.converged.all() and res_f.converged.all()
    # The coupled solution obeys the law exactly.
    np.testing.assert_allclose(res_c.q[:, 3:], law.predict(res_c.q[:, :3]), atol=1e-9)
    err_c = np.sqrt(np.mean((res_c.q[:, 3:] - q_true[:, 3:]) ** 2))
    err_f = np.sqrt(np.mean((res_f.q[:, 3:] - q_true[:, 3:]) ** 2))
    assert err_c < 0.5 * err_f
    assert np.degrees(np.abs(res_c.q[:, 0] - q_true[:, 0])).max() < 2.0
