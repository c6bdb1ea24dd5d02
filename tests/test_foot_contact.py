"""Foot-ground contact element (Tändl et al. 2010, sec. 3.2): equilibrium physics and eq. 25 identification."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import FitError
from kinematics.gait.foot_contact import (
    FootElement,
    FootParameters,
    fit_foot_parameters,
    foot_geometry,
    sagittal_stance,
    spring_moment,
    static_equilibrium,
)

ELEMENT = FootElement()
TRUE = FootParameters(stiffness=300.0, heel_offset=0.05, joint_offset=0.09, fore_offset=0.07, sole_depth=0.07)


def loads(m=40, seed=1):
    """Ankle wrenches of a foot loaded at random: 100-1000 N, CoP from the heel rim to the fore foot."""
    rng = np.random.default_rng(seed)
    fv = -rng.uniform(100, 1000, m)
    fu = fv * rng.uniform(-0.2, 0.2, m)
    cop = rng.uniform(-0.065, 0.15, m)  # m in front of the ankle
    moment = cop * fv + 0.07 * fu  # m_a = -(CoP - A) x GRF with the ankle 7 cm above the ground
    return np.stack([fu, fv], -1), moment, np.zeros(m), np.zeros(m)


@pytest.fixture(scope="module")
def measured():
    force, moment, au, ground = loads()
    eq = static_equilibrium(ELEMENT, TRUE, au, force, moment, ground)
    assert eq.converged.all()
    return force, moment, au, ground, eq


def test_equilibrium_balances_the_ankle_wrench(measured):
    force, moment, au, _, eq = measured
    # the contacts carry the whole vertical load ...
    np.testing.assert_allclose(eq.normal.sum(1), -force[:, 1], rtol=1e-9)
    # ... and their moment about the ankle cancels m_a (forces parallel to the ground reaction)
    A = np.stack([au, eq.height], -1)
    t = force[:, 0] / force[:, 1]
    arm = eq.contact_points - A[:, None]
    m_contacts = np.sum(eq.normal * (arm[..., 0] - arm[..., 1] * t[:, None]), axis=1)
    np.testing.assert_allclose(m_contacts + moment, 0.0, atol=1e-6 * np.abs(moment).max())
    # the fore foot bends by the spring law under its contact's moment about the midfoot joint
    g = foot_geometry(ELEMENT, TRUE.as_vector(), A, eq.angle, eq.midfoot)
    P1 = eq.contact_points[:, 0]
    m_fore = eq.normal[:, 0] * ((P1 - g["joint"])[:, 0] - (P1 - g["joint"])[:, 1] * t)
    np.testing.assert_allclose(spring_moment(ELEMENT, TRUE.stiffness, eq.midfoot), m_fore, atol=1e-6)
    # loads on the fore foot bend the midfoot (toes up) more than any heel load does
    cop = (moment - 0.07 * force[:, 0]) / force[:, 1]
    assert eq.midfoot[cop > 0.1].min() > max(eq.midfoot[cop < -0.03].max(), np.radians(1.0))


def test_five_parameters_recovered_within_5_percent(measured):
    force, moment, au, ground, eq = measured
    x0 = FootParameters(*(TRUE.as_vector() * np.array([1.4, 0.7, 1.3, 0.75, 1.2])))
    fit = fit_foot_parameters(ELEMENT, np.stack([au, eq.height], -1), eq.angle, force, moment, ground, x0, n_starts=1)
    err = fit.parameters.as_vector() / TRUE.as_vector() - 1
    assert np.all(np.abs(err) < 0.05), dict(zip(FootParameters.NAMES, err))
    assert fit.rms_angle < np.radians(0.01) and fit.rms_height < 1e-5


def test_noisy_poses_uncertainty_covers_truth(measured):
    force, moment, au, ground, eq = measured
    rng = np.random.default_rng(7)
    ankle = np.stack([au, eq.height + rng.normal(0, 1e-4, len(au))], -1)
    angle = eq.angle + rng.normal(0, np.radians(0.1), len(au))
    x0 = FootParameters(*(TRUE.as_vector() * np.array([0.8, 1.2, 0.9, 1.2, 0.9])))
    fit = fit_foot_parameters(ELEMENT, ankle, angle, force, moment, ground, x0)
    err = fit.parameters.as_vector() - TRUE.as_vector()
    assert np.all(np.abs(err) < 3 * fit.sd), (err, fit.sd)
    assert np.radians(0.05) < fit.rms_angle < np.radians(0.15)  # residual at the noise level


def test_unloaded_frames_are_refused(measured):
    force, moment, au, ground, eq = measured
    force = force.copy()
    force[3, 1] = 10.0  # a frame pulling the foot off the ground
    with pytest.raises(FitError, match="loaded frames"):
        fit_foot_parameters(ELEMENT, np.stack([au, eq.height], -1), eq.angle, force, moment, ground, TRUE)


def test_sagittal_projection_of_a_lab_stance():
    """A foot walking along -x (as mocap_pig's stair descent): u = -x, the angle toes-up positive."""
    m = 3
    ankle = np.array([[1.0, 0.3, 0.08]] * m)
    pitch = np.radians([10.0, 0.0, -20.0])
    axis = np.stack([-np.cos(pitch), np.zeros(m), np.sin(pitch)], -1)
    grf = np.array([[0.0, 0.0, 700.0]] * m)
    cop = ankle + np.array([-0.1, 0.0, -0.08])  # 10 cm in front of the ankle
    s = sagittal_stance(ankle, axis, grf, cop)
    np.testing.assert_allclose(s["progression"], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(s["angle"], pitch, atol=1e-12)
    np.testing.assert_allclose(s["force"], [[0.0, -700.0]] * m, atol=1e-9)
    # the leg must hold the foot against a ground reaction 10 cm in front of the ankle: m_a = -0.1 * 700
    np.testing.assert_allclose(s["moment"], -70.0, atol=1e-9)


@pytest.mark.slow
def test_mocap_pig_stance_fit(shared_data):
    """The element identified on the right foot's stance on plate 4 of Movement_trial.c3d (stair descent):
    RMS hind-foot angle error under 5 deg (the seed's acceptable variation; measured 3.4 deg) and well under
    a constant angle's (8.1 deg)."""
    from kinematics.io.c3d import read_c3d
    from kinematics.gait.plate_contacts import assign_feet
    from kinematics.io.forceplates import read_force_plates
    from kinematics.gait.pig import plug_in_gait, static_foot_offsets
    from kinematics.gait.subject import read_vsk

    d = shared_data / "mocap_pig"
    static = read_c3d(d / "Static_trial.c3d")
    sub = static_foot_offsets(static, read_vsk(d / "Test.vsk"))
    trial = read_c3d(d / "Movement_trial.c3d")
    pig, spig = plug_in_gait(trial, sub), plug_in_gait(static, sub)
    plates = read_force_plates(d / "Movement_trial.c3d")
    c = next(c for c in assign_feet(plates, trial) if c.plate == 3)
    assert c.foot == "R" and c.usable
    up = np.array([0.0, 0.0, 1.0])
    p = plates[c.plate]
    fr = np.arange(c.start, c.stop)
    fr = fr[p.force[fr] @ up > 0.2 * sub.mass * 9.81]
    axis_static = -np.nanmean(spig.segments["foot_r"].axes[:, :, 2], axis=0)  # heel-to-toe, standing = neutral
    neutral = np.arctan2(axis_static @ up, np.linalg.norm(axis_static - (axis_static @ up) * up))
    st = sagittal_stance(pig.centres["ankle_r"][fr], -pig.segments["foot_r"].axes[fr, :, 2], p.force[fr], p.cop[fr], up)
    angle = st["angle"] - neutral
    x0 = FootParameters(300.0, 0.05, 0.08, 0.06, float(np.median(st["ankle"][:, 1] - st["ground"])))
    fit = fit_foot_parameters(ELEMENT, st["ankle"], angle, st["force"], st["moment"], st["ground"], x0, n_starts=1)
    assert fit.equilibrium.converged.mean() > 0.9
    assert fit.rms_angle < np.radians(5.0) and fit.rms_angle < 0.6 * np.std(angle)
