"""Plug-in-Gait kinetics: statics of a still leg (analytic), and agreement with Vicon Nexus' stored moments."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.io.markers import MarkerTrial
from kinematics.gait.pig import PiGResult, SegmentPose
from kinematics.gait.pig_kinetics import (
    GRAVITY,
    PIG_SEGMENTS,
    GroundReaction,
    angular_velocity,
    pig_components,
    plug_in_gait_kinetics,
)


def test_angular_velocity_of_a_steady_spin():
    t = np.arange(50) / 100.0
    w = np.array([0.3, -1.2, 2.0])
    R = Rotation.from_rotvec(np.outer(t, w)).as_matrix() @ Rotation.from_euler("xyz", [0.3, 0.2, 0.1]).as_matrix()
    np.testing.assert_allclose(angular_velocity(R, 100.0)[1:-1], np.tile(w, (48, 1)), atol=1e-3)


def _still_leg(F=20):
    """A motionless right and left leg (knee bent, foot flat) in PiG frames, and a ground reaction under each foot."""
    segs, centres, names, pos = {}, {}, [], []
    for s, sfx, lat in (("R", "_r", -1.0), ("L", "_l", 1.0)):
        hip = np.array([0.0, lat * 0.1, 0.9])
        knee = np.array([0.05, lat * 0.1, 0.5])
        ankle = np.array([0.0, lat * 0.1, 0.08])
        toe = np.array([0.15, lat * 0.1, 0.03])
        def frame(z, x_hint):
            z = z / np.linalg.norm(z)
            y = np.cross(z, x_hint)
            y /= np.linalg.norm(y)
            return np.stack([np.cross(y, z), y, z], -1)
        fem = frame(hip - knee, np.array([1.0, 0, 0]))
        tib = frame(knee - ankle, np.array([1.0, 0, 0]))
        foot = frame(ankle - toe, np.array([0, 0, 1.0]))
        for n, o, ax in (("femur", knee, fem), ("tibia", ankle, tib), ("tibia_untorsioned", ankle, tib), ("foot", toe, foot)):
            segs[n + sfx] = SegmentPose(np.tile(o, (F, 1)), np.tile(ax, (F, 1, 1)))
        centres.update({"hip" + sfx: np.tile(hip, (F, 1)), "knee" + sfx: np.tile(knee, (F, 1)),
                        "ankle" + sfx: np.tile(ankle, (F, 1))})
        for mk, p in (("TOE", toe), ("HEE", np.array([-0.05, lat * 0.1, 0.03]))):
            names.append(s + mk)
            pos.append(np.tile(p, (F, 1)))
    segs["pelvis"] = SegmentPose(np.tile([0.0, 0, 0.95], (F, 1)), np.tile(np.eye(3), (F, 1, 1)))
    trial = MarkerTrial(tuple(names), np.stack(pos, 1), 100.0, np.arange(F) / 100.0, "still")
    pig = PiGResult(segs, centres, {}, {}, trial.time)
    return trial, pig, centres


def test_still_leg_moments_are_the_statics_of_the_loads_below():
    trial, pig, C = _still_leg()
    F = trial.n_frames
    mass = 70.0
    force = np.tile([30.0, -20.0, 400.0], (F, 1))
    cop = np.tile([0.07, -0.1, 0.0], (F, 1))
    free = np.tile([0.0, 0.0, 1.5], (F, 1))
    mirror = np.array([1.0, -1.0, 1.0])  # the left leg is the right one mirrored in the x-z plane
    grf = {"R": GroundReaction(force, cop, free, np.ones(F, bool)),
           "L": GroundReaction(force * mirror, cop * mirror, -free, np.ones(F, bool))}
    kin = plug_in_gait_kinetics(trial, pig, mass, grf)
    s, sfx = "R", "_r"
    toe = trial.marker("RTOE")
    coms = {"foot": 0.5 * (C["ankle_r"] + toe),
            "tibia": C["ankle_r"] + 0.567 * (C["knee_r"] - C["ankle_r"]),
            "femur": C["knee_r"] + 0.567 * (C["hip_r"] - C["knee_r"])}
    below = []
    for joint, seg in (("ankle", "foot"), ("knee", "tibia"), ("hip", "femur")):
        below.append(seg)
        j = C[joint + sfx]
        # moment of the proximal segment on the distal one balances every load below the joint
        ext = np.cross(grf[s].cop - j, force) + free
        for b in below:
            ext = ext + np.cross(coms[b] - j, PIG_SEGMENTS[b].mass_fraction * mass * np.tile(GRAVITY, (F, 1)))
        local = np.einsum("fji,fj->fi", pig.segments[seg + sfx].axes, -ext)
        np.testing.assert_allclose(kin.moments[joint + sfx], pig_components(local, joint, s), atol=1e-9)
        np.testing.assert_allclose(kin.powers[joint + sfx], 0.0, atol=1e-9)  # nothing moves
    # a foot flat under a ground reaction in front of the ankle: plantarflexor (X > 0) moment
    assert np.all(kin.moments["ankle_r"][:, 0] > 0) and np.all(kin.moments["ankle_l"][:, 0] > 0)
    # the mirrored leg under the mirrored load reports the same moments (Plug-in-Gait's left-side signs)
    for joint in ("ankle", "knee", "hip"):
        np.testing.assert_allclose(kin.moments[joint + "_l"], kin.moments[joint + "_r"], atol=1e-9)


def test_unloaded_standing_foot_gives_nan_not_a_swing_moment():
    trial, pig, _ = _still_leg()
    F = trial.n_frames
    zero = GroundReaction(np.zeros((F, 3)), np.full((F, 3), np.nan), np.zeros((F, 3)), np.zeros(F, bool))
    kin = plug_in_gait_kinetics(trial, pig, 70.0, {"R": zero, "L": zero})
    assert np.all(np.isnan(kin.moments["hip_r"])) and not kin.valid["R"].any()
    assert any("off the plates" in n for n in kin.notes)


# --------------------------------------------------------------------------- Vicon Nexus


@pytest.fixture(scope="module")
def nexus(shared_data):
    from kinematics.io.c3d import read_c3d, read_c3d_outputs
    from kinematics.gait.plate_contacts import assign_feet
    from kinematics.io.forceplates import read_force_plates
    from kinematics.gait.pig import plug_in_gait, static_foot_offsets
    from kinematics.gait.pig_kinetics import ground_reactions
    from kinematics.gait.subject import read_vsk

    d = shared_data / "mocap_pig"
    sub = static_foot_offsets(read_c3d(d / "Static_trial.c3d"), read_vsk(d / "Test.vsk"))
    trial = read_c3d(d / "Movement_trial.c3d")
    plates = read_force_plates(d / "Movement_trial.c3d")
    contacts = assign_feet(plates, trial)
    grf, _ = ground_reactions(plates, contacts, trial.n_frames)
    kin = plug_in_gait_kinetics(trial, plug_in_gait(trial, sub), sub.mass, grf)
    return {"plates": plates, "contacts": contacts, "grf": grf, "kin": kin,
            "out": read_c3d_outputs(d / "Movement_trial.c3d")}


def test_nexus_trial_plates_and_feet(nexus):
    plates, contacts = nexus["plates"], nexus["contacts"]
    assert len(plates) == 4
    for p in plates:
        assert p.loaded.any() and not p.cop_outside[p.loaded].any()
    assert [(c.plate, c.foot) for c in contacts] == [(3, "R"), (2, "L"), (1, "R"), (0, "L")]


@pytest.mark.parametrize("side", ["R", "L"])
def test_moments_and_powers_match_nexus_over_stance(nexus, side):
    """Mean |ours - Nexus| over the stance Nexus computed with a plate, per component, <= 5 % of Nexus' range
    (measured: 0.1-2.3 %)."""
    kin, out, sfx = nexus["kin"], nexus["out"], "_" + side.lower()
    ng = out[side + "GroundReactionForce"]
    stance = nexus["grf"][side].loaded & np.all(np.isfinite(ng), 1) & (np.abs(ng[:, 2]) > 0)
    assert stance.sum() > 60
    for joint, name in (("hip", "Hip"), ("knee", "Knee"), ("ankle", "Ankle")):
        ours = kin.moment_per_kg(joint + sfx, "N mm/kg")[stance]
        ref = out[f"{side}{name}Moment"][stance] * 1e3  # read_c3d_outputs gives N m (per kg)
        err = np.nanmean(np.abs(ours - ref), 0) / (np.nanmax(ref, 0) - np.nanmin(ref, 0))
        assert np.all(err < 0.05), (joint, err)
        p = kin.power_per_kg(joint + sfx)[stance]
        q = out[f"{side}{name}Power"][stance, 2]
        assert np.nanmean(np.abs(p - q)) / (np.nanmax(q) - np.nanmin(q)) < 0.05, joint


def test_bad_inputs_are_refused():
    from types import SimpleNamespace

    from lowerlimb.errors import InputError
    from kinematics.gait.pig_kinetics import ground_reactions

    trial, pig, _ = _still_leg()
    F = trial.n_frames
    zero = GroundReaction(np.zeros((F, 3)), np.full((F, 3), np.nan), np.zeros((F, 3)), np.zeros(F, bool))
    with pytest.raises(InputError, match="still: body mass must be a positive number"):
        plug_in_gait_kinetics(trial, pig, None, {"R": zero, "L": zero})
    plates = SimpleNamespace(n_frames=F * 9, source="trial.c3d")  # plates left at the analog rate
    with pytest.raises(InputError, match="trial.c3d: force plates have 180 frames, the markers 20"):
        ground_reactions(plates, [], F)


def test_foot_on_two_plates_keeps_the_summed_wrench():
    """Two plates under one foot: force, and moment about any point, are the sums of the plates' wrenches."""
    from types import SimpleNamespace

    from kinematics.gait.pig_kinetics import ground_reactions

    n = 5
    rng = np.random.default_rng(3)
    plates = []
    for k in range(2):
        force = np.column_stack([rng.normal(0, 20, n), rng.normal(0, 20, n), 300 + 100 * k + rng.normal(0, 5, n)])
        cop = np.column_stack([0.5 * k + rng.normal(0, 0.02, n), rng.normal(0, 0.02, n), np.zeros(n)])
        free = np.column_stack([np.zeros(n), np.zeros(n), rng.normal(0, 2, n)])
        plates.append(SimpleNamespace(loaded=np.ones(n, bool), force=force, cop=cop, free_moment=free,
                                      normal=np.array([0.0, 0.0, 1.0])))
    fp = type("Plates", (), {"n_frames": n, "source": "two.c3d", "__getitem__": lambda self, i: plates[i]})()
    contacts = [SimpleNamespace(foot="R", usable=True, plate=k, start=0, stop=n, describe=lambda: "") for k in range(2)]
    grf, notes = ground_reactions(fp, contacts, n)
    g = grf["R"]
    np.testing.assert_allclose(g.force, plates[0].force + plates[1].force, atol=1e-12)
    q = np.array([0.2, -0.3, 0.9])   # moment about an arbitrary point (a joint centre)
    want = sum(np.cross(p.cop - q, p.force) + p.free_moment for p in plates)
    np.testing.assert_allclose(np.cross(g.cop - q, g.force) + g.free_moment, want, atol=1e-9)
    # the combined centre of pressure lies between the plates' (normal-force weighted)
    assert np.all((g.cop[:, 0] > plates[0].cop[:, 0]) & (g.cop[:, 0] < plates[1].cop[:, 0]))
    assert any("two plates" in m for m in notes)
    assert np.all(grf["L"].force == 0) and not grf["L"].loaded.any()
