"""Marker inverse kinematics (kinematics.algorithms.ik) with couplings, limits, gaps; agreement with OpenSim."""
from __future__ import annotations

import numpy as np
import pytest

from kin_helpers import leg_model
from kinematics.multibody.coupling import CoordinateCoupler, LinearCoupling, LinearInequalities
from lowerlimb.errors import InputError
from kinematics.algorithms.fk import marker_positions
from kinematics.multibody.functions import SimmSpline
from kinematics.algorithms.coordinate_map import coordinate_map
from kinematics.algorithms.ik import solve_ik, solve_pose
from kinematics.algorithms.tasks import com_task, marker_task, orientation_task
from kinematics.io.ik_setup import CoordinateTask, read_ik_setup
from kinematics.io.markers import MarkerTrial
from kinematics.multibody.model import Coordinate

GAIT = "opensim_gait2392"


@pytest.fixture(scope="module")
def model():
    return leg_model(exportable=False)


def _trajectory(model, n=40, amp=0.35, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 60.0
    lo, hi = model.lower, model.upper
    mid = np.clip(model.default_q, lo + 0.05, hi - 0.05)
    half = np.minimum(amp, 0.45 * (hi - lo))
    phase = rng.uniform(0, 2 * np.pi, model.n_q)
    q = mid + half * np.sin(2 * np.pi * 0.8 * t[:, None] + phase) * np.sin(phase)
    return t, q


def _trial(model, q, t, noise=0.0, seed=1):
    x = marker_positions(model, q)
    if noise:
        x = x + np.random.default_rng(seed).normal(0, noise, x.shape)
    return MarkerTrial(model.marker_names, x, 60.0, t, "synthetic.trc")


def test_recovers_exact_poses(model):
    t, q = _trajectory(model)
    res = solve_ik(model, _trial(model, q, t), q0=q[0] + 0.05, tolerance=1e-9)
    assert res.solved.all() and res.converged.all()
    np.testing.assert_allclose(res.q, q, atol=1e-6)
    assert res.rms.max() < 1e-8
    assert res.marker_errors.shape == (len(t), len(model.markers))
    qs, rms = solve_pose(model, marker_positions(model, q[5]), q0=q[5] + 0.03, tolerance=1e-10)
    np.testing.assert_allclose(qs, q[5], atol=1e-7)
    assert rms < 1e-9


def test_first_frame_found_whatever_the_heading(model):
    """No q0: a subject facing backwards (pelvis rotated ~170 deg, far from the default) is still found."""
    t, q = _trajectory(model, n=8, seed=12)
    q[:, model.coordinate_index("pelvis_rotation")] += 2.95
    q[:, model.coordinate_index("pelvis_tx")] += 1.5
    res = solve_ik(model, _trial(model, q, t), tolerance=1e-9)
    assert res.rms.max() < 1e-7
    d = res.q - q
    d[:, model.rotational] = np.angle(np.exp(1j * d[:, model.rotational]))     # the same pose modulo 2 pi
    np.testing.assert_allclose(d, 0.0, atol=1e-5)


def test_expmap_joint_tracks_a_full_turn(model):
    """The exp-map shoulder turns 1.5 revolutions about a fixed axis: no singularity, |r| stays <= pi."""
    t, q = _trajectory(model, n=60, seed=13)
    ix = [model.coordinate_index(c) for c in ("arm_x", "arm_y", "arm_z")]
    axis = np.array([0.3, 0.8, 0.52]) / np.linalg.norm([0.3, 0.8, 0.52])
    ang = np.linspace(0.2, 3 * np.pi, len(t))
    q[:, ix] = ang[:, None] * axis
    res = solve_ik(model, _trial(model, q, t), q0=q[0], tolerance=1e-9)
    assert res.rms.max() < 1e-7
    assert np.linalg.norm(res.q[:, ix], axis=1).max() <= np.pi + 0.1
    np.testing.assert_allclose(marker_positions(model, res.q), marker_positions(model, q), atol=1e-7)


def test_marker_task_jacobian(model):
    q = model.random_q(2, np.random.default_rng(4))
    y = marker_positions(model, q) + 0.01
    w = np.linspace(0.5, 2.0, len(model.markers))
    r, J = marker_task(model, q, y, w)
    e = 1e-6
    fd = np.stack([(marker_task(model, q + e * np.eye(model.n_q)[i], y, w)[0]
                    - marker_task(model, q - e * np.eye(model.n_q)[i], y, w)[0]) / (2 * e) for i in range(model.n_q)], -1)
    np.testing.assert_allclose(J, fd, atol=2e-9)
    np.testing.assert_allclose(r.reshape(2, -1, 3), -0.01 * np.sqrt(w)[None, :, None] * np.ones((2, 1, 3)), atol=1e-15)


def test_orientation_and_com_task_jacobians(model):
    rng = np.random.default_rng(8)
    q = model.random_q(3, rng)
    from scipy.spatial.transform import Rotation

    target = Rotation.from_rotvec([0.3, -1.2, 0.8]).as_matrix()
    e, J = orientation_task(model, q, "foot", target, weight=4.0)
    h = 1e-6
    fd = np.stack([(orientation_task(model, q + h * np.eye(model.n_q)[i], "foot", target, 4.0)[0]
                    - orientation_task(model, q - h * np.eye(model.n_q)[i], "foot", target, 4.0)[0]) / (2 * h)
                   for i in range(model.n_q)], -1)
    np.testing.assert_allclose(J, fd, atol=1e-8)
    # e is the rotation vector taking the target to the current orientation.
    from kinematics.algorithms.fk import body_pose

    R = body_pose(model, q, "foot")[0]
    np.testing.assert_allclose(Rotation.from_rotvec(e / 2.0).as_matrix() @ target, R, atol=1e-12)
    c, Jc = com_task(model, q, np.zeros(3))
    fdc = np.stack([(com_task(model, q + h * np.eye(model.n_q)[i], np.zeros(3))[0]
                     - com_task(model, q - h * np.eye(model.n_q)[i], np.zeros(3))[0]) / (2 * h) for i in range(model.n_q)], -1)
    np.testing.assert_allclose(Jc, fdc, atol=2e-9)


def test_linear_equality_coupling_holds_to_1e10(model):
    names = model.coordinate_names
    row = LinearCoupling.correlative(names, "hip_rotation", {"hip_flexion": 0.2, "knee_angle": -0.1}, 0.02)
    row = row.stack(LinearCoupling.correlative(names, "subtalar_angle", {"ankle_angle": 0.5}, 0.0))
    mc = model.with_couplings(row)
    t, q = _trajectory(model, n=20)
    res = solve_ik(mc, _trial(model, q, t, noise=0.004), q0=q[0])   # markers of an uncoupled motion
    assert np.abs(row.residual(res.q)).max() < 1e-10
    # The coupled solution fits worse than the free one but stays close (the coupling is violated by the data).
    free = solve_ik(model, _trial(model, q, t, noise=0.004), q0=q[0])
    assert (res.cost >= free.cost - 1e-12).all()
    cmap = coordinate_map(mc)
    np.testing.assert_allclose(cmap.projector @ cmap.projector, cmap.projector, atol=1e-12)


def test_coordinate_limit_is_never_exceeded(model):
    i = model.coordinate_index("knee_angle")
    coords = list(model.coordinates)
    c = coords[i]
    coords[i] = Coordinate(c.name, c.kind, c.default, (-1.0, -0.2), clamped=True)
    mc = model.replace(coordinates=tuple(coords))
    t, q = _trajectory(model, n=30)
    q[:, i] = np.linspace(-0.5, 0.15, len(t))               # the data flexes beyond the limit
    res = solve_ik(mc, _trial(model, q, t), q0=q[0])
    assert res.q[:, i].max() <= -0.2 + 1e-12
    beyond = q[:, i] > -0.2 + 0.02
    np.testing.assert_allclose(res.q[beyond, i], -0.2, atol=1e-12)     # active
    inside = q[:, i] < -0.2 - 0.02
    np.testing.assert_allclose(res.q[inside], q[inside], atol=1e-5)   # inactive: exact fit
    # Unclamped coordinates are free (OpenSim semantics) unless limits='all'.
    free = solve_ik(model, _trial(model, q, t), q0=q[0])
    assert free.q[:, i].max() > 0.1


def test_locked_coordinate_stays_at_its_default(model):
    i = model.coordinate_index("mtp_angle")
    coords = list(model.coordinates)
    c = coords[i]
    coords[i] = Coordinate(c.name, c.kind, 0.1, c.range, locked=True)
    ml = model.replace(coordinates=tuple(coords))
    t, q = _trajectory(model, n=10, seed=6)
    res = solve_ik(ml, _trial(model, q, t), q0=q[0])
    np.testing.assert_array_equal(res.q[:, i], 0.1)
    assert coordinate_map(ml).n_z == model.n_q - 1


def test_linear_inequality(model):
    names = model.coordinate_names
    G = np.zeros((1, len(names)))
    G[0, names.index("hip_flexion")] = 1.0
    G[0, names.index("hip_adduction")] = 1.0
    mi = model.replace(inequalities=LinearInequalities(names, G, [0.1], ("flex+add",)))
    t, q = _trajectory(model, n=20, seed=3)
    q[:, names.index("hip_flexion")] = np.linspace(-0.1, 0.4, len(t))
    res = solve_ik(mi, _trial(model, q, t), q0=q[0])
    s = res.q @ G[0]
    assert s.max() <= 0.1 + 1e-12
    assert np.isclose(s, 0.1, atol=1e-10).any()


def test_nonlinear_coupler_chain_rule(model):
    sp = SimmSpline([-1.0, -0.5, 0.0, 0.5], [0.1, -0.05, 0.0, 0.08])
    mc = model.replace(couplers=(CoordinateCoupler("subtalar_angle", ("ankle_angle",), sp, "st"),))
    t, q = _trajectory(model, n=15, seed=5)
    ia, isub = model.coordinate_index("ankle_angle"), model.coordinate_index("subtalar_angle")
    q[:, isub] = sp(q[:, ia])
    res = solve_ik(mc, _trial(model, q, t), q0=q[0] + 0.02, tolerance=1e-9)
    np.testing.assert_allclose(res.q, q, atol=1e-6)
    np.testing.assert_allclose(res.q[:, isub], sp(res.q[:, ia]), atol=1e-14)


def test_gaps_weights_and_empty_frames(model):
    t, q = _trajectory(model, n=24, seed=2)
    tr = _trial(model, q, t)
    pos = tr.positions.copy()
    rng = np.random.default_rng(9)
    # Gaps that keep every segment determined: up to one of the 4 markers of each big segment per frame.
    for seg in ("pelvis", "thigh", "shank", "foot"):
        idx = [k for k, n in enumerate(model.marker_names) if n.startswith(seg + "_")]
        drop = rng.random(len(t)) < 0.5
        pos[np.flatnonzero(drop), rng.choice(idx, drop.sum())] = np.nan
    pos[7] = np.nan                                      # a frame with every marker missing
    gappy = MarkerTrial(tr.names, pos, 60.0, t, "gappy.trc")
    w = {n: (5.0 if n.startswith("pelvis") else 1.0) for n in model.marker_names}
    res = solve_ik(model, gappy, marker_weights=w, q0=q[0])
    assert not res.solved[7] and np.isnan(res.q[7]).all() and np.isnan(res.rms[7])
    ok = res.solved
    assert ok.sum() == len(t) - 1 and res.determined[ok].all()
    np.testing.assert_allclose(res.q[ok], q[ok], atol=1e-5)
    assert np.isnan(res.marker_errors[np.isnan(pos[..., 0])]).all()
    np.testing.assert_allclose(np.linalg.norm(res.residuals, axis=-1), res.marker_errors, equal_nan=True)
    np.testing.assert_allclose(res.rms[ok], np.sqrt(np.nanmean(res.marker_errors[ok] ** 2, axis=1)))
    with pytest.raises(InputError, match="every frame"):
        solve_ik(model, MarkerTrial(tr.names, np.full_like(pos, np.nan), 60.0, t, "empty.trc"))
    with pytest.raises(InputError, match="look like millimetres"):
        solve_ik(model, MarkerTrial(tr.names, 1000.0 * tr.positions, 60.0, t, "mm.trc"))
    other = MarkerTrial(tuple(f"X{i}" for i in range(3)), np.zeros((2, 3, 3)), 60.0, t[:2], "other.trc")
    with pytest.raises(InputError, match="none of the model's markers"):
        solve_ik(model, other)


def test_coordinate_tasks_pull_towards_targets(model):
    t, q = _trajectory(model, n=10, seed=4)
    tr = _trial(model, q, t, noise=0.003)
    i = model.coordinate_index("mtp_angle")
    res0 = solve_ik(model, tr, q0=q[0])
    res1 = solve_ik(model, tr, coordinate_tasks=[CoordinateTask("mtp_angle", 1e6, 0.3)], q0=q[0])
    assert np.abs(res1.q[:, i] - 0.3).max() < 1e-3 < np.abs(res0.q[:, i] - 0.3).max()


def test_read_ik_setup(shared_data):
    su = read_ik_setup(shared_data / GAIT / "subject01_Setup_IK.xml")
    assert su.marker_weights["R.ASIS"] == 10 and su.marker_weights["Top.Head"] == 0.1
    assert len(su.marker_weights) == 31 and len(su.coordinate_tasks) == 4
    assert su.coordinate_tasks[0] == CoordinateTask("subtalar_angle_r", 1000.0, None)
    assert su.time_range == (0.5, 2.5) and su.accuracy == 1e-5


def test_ik_agrees_with_opensim_on_gait2392(shared_data, opensim):
    """Per-frame RMS <= OpenSim's + 0.1 mm; coordinates within 0.5 deg / 0.5 mm of OpenSim's solution."""
    from kinematics.io.opensim_io import load_osim, opensim_inverse_kinematics
    from kinematics.io.storage import read_trc

    d = shared_data / GAIT
    su = read_ik_setup(d / "subject01_Setup_IK.xml")
    model_path, trc = d / "subject01_simbody_adjusted.osim", d / "subject01_walk1.trc"
    ref = opensim_inverse_kinematics(model_path, trc, su.marker_weights, su.coordinate_tasks, su.time_range, su.accuracy)
    m = load_osim(model_path)
    trial = read_trc(trc).window(*su.time_range)
    res = solve_ik(m, trial, su.marker_weights, su.coordinate_tasks)
    np.testing.assert_allclose(res.time, ref["time"], atol=1e-9)
    assert res.solved.all()
    assert (res.rms <= ref["rms"] + 1e-4).all()
    order = [ref["coordinates"].index(c) for c in m.coordinate_names]
    dq = np.abs(res.q - ref["q"][:, order])
    rot = m.rotational
    assert np.degrees(dq[:, rot]).max() < 0.5
    assert dq[:, ~rot].max() < 5e-4


@pytest.mark.parametrize("with_coupler", [False, True])
def test_ik_residual_jacobian_in_z_matches_finite_differences(model, with_coupler):
    """The reduced Jacobian dr/dz used by the solver (constant-dq/dz fast path and coupler chain rule)."""
    from kinematics.algorithms.ik import _Problem

    m = model.with_couplings(LinearCoupling.correlative(model.coordinate_names, "hip_rotation", {"hip_flexion": 0.3}, 0.1))
    if with_coupler:
        sp = SimmSpline([-1.0, -0.5, 0.0, 0.5], [0.1, -0.05, 0.0, 0.08])
        m = m.replace(couplers=(CoordinateCoupler("subtalar_angle", ("ankle_angle",), sp, "st"),))
    cmap = coordinate_map(m)
    rng = np.random.default_rng(21)
    midx = np.arange(len(m.markers))
    cidx = np.array([m.coordinate_index("mtp_angle")])
    prob = _Problem(m, cmap, midx, rng.uniform(0.5, 2, len(midx)), cidx, np.array([0.1]), np.array([3.0]))
    z = rng.uniform(-0.4, 0.4, (3, cmap.n_z))
    y = marker_positions(m, cmap.expand(z)) + rng.normal(0, 0.01, (3, len(midx), 3))
    ok = rng.random((3, len(midx))) > 0.2
    r, J, _, _ = prob.evaluate(z, y, ok)
    h = 1e-6
    fd = np.stack([(prob.evaluate(z + h * np.eye(cmap.n_z)[i], y, ok, jac=False)[0]
                    - prob.evaluate(z - h * np.eye(cmap.n_z)[i], y, ok, jac=False)[0]) / (2 * h)
                   for i in range(cmap.n_z)], -1)
    np.testing.assert_allclose(J, fd, atol=5e-9)


def test_pipelined_window_reaches_the_sequential_minimum_with_sparse_markers():
    """Plug-in-Gait markers only (hip and knee rotation nearly redundant), fast functional hip star-arcs.

    The default pipelined window (block=16) once warm-started frames from iterates
    still far from their optimum and carried a wrong local minimum over hundreds of
    frames (19.6 mm mean RMS against 2.05 mm frame by frame); it must reach the same
    minima as sequential warm starting (block=1).
    """
    from phantoms import make_phantom
    from phantoms.motion import make_trials

    sk, trials, _ = make_trials(make_phantom(1), 1, gait_trials=0, crouch_angles=(), functional_ranges=(45,),
                                functional_time_scale=0.5, static_duration=0.3, extra_markers=False,
                                device_markers=False)
    trial = next(t for t in trials if t.name == "functional_hip").markers
    assert set(n[1:] for n in trial.names) == {"ASI", "PSI", "THI", "KNE", "TIB", "ANK", "HEE", "TOE"}
    seq = solve_ik(sk.model, trial, block=1)
    win = solve_ik(sk.model, trial)                                  # default block
    assert seq.converged.all() and win.converged.all()
    assert np.nanmean(seq.rms) < 3e-3                                # STA + noise only
    assert np.nanmean(win.rms) == pytest.approx(np.nanmean(seq.rms), abs=2e-5)
    assert np.nanmax(win.rms - seq.rms) < 2e-4                       # no frame left in another minimum
