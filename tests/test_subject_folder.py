"""The subject folder a lab hands over: the lab read from its trials, static found by name, TRC trials, subject.json.

Motion phantoms written by `phantoms.motion.write_trials` (the same seed: the same markers, rotated into each lab).
"""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from kinematics.gait.lab_frame import detect_lab
from kinematics.gait.subject import measure_from_bones, read_subject_values, subject_from_values
from kinematics.io.c3d import read_c3d
from lowerlimb.errors import InputError
from personalize.pipeline.inputs import find_inputs, find_trials
from personalize.pipeline.lab import plates_to_internal, rotate_points, to_internal
from phantoms import make_phantom
from phantoms.lab import Lab
from phantoms.motion import write_trials

#: a Y-up lab whose walkway runs 10 deg off +Z (towards +X)
_YAW = np.radians(10.0)
_Y_UP = Lab("y-up", np.array([0.0, 1.0, 0.0]), np.array([np.sin(_YAW), 0.0, np.cos(_YAW)]), np.zeros(3))


def _write(d, **kw):
    d.mkdir()
    write_trials(d, make_phantom(0), 0, rate=100, gait_trials=1, gait_cycles=1.0, crouch_angles=(),
                 functional_ranges=(45,), functional_time_scale=0.5, **kw)
    (d / "bones").mkdir()      # find_inputs needs bone images; these tests stop before reading them
    return d


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("labs")
    return {"z": _write(root / "z_up"), "y": _write(root / "y_up", lab=_Y_UP),
            "trc": _write(root / "trc", trial_format="trc", static_name="Static")}


def test_z_up_lab_facing_x_is_left_exactly_as_it_is(folders):
    """The phantom's lab (Z up, walking +X): rotation exactly the identity, trials the reader's values bit for bit."""
    d = folders["z"]
    inp = find_inputs(d)
    assert np.array_equal(inp.lab.internal_from_lab, np.eye(3))
    assert inp.lab.up_axis == "+Z" and inp.lab.facing_axis == "+X"
    for name, trial in {"static": inp.static, **inp.trials}.items():
        raw = read_c3d(d / f"{name}.c3d")
        assert np.array_equal(trial.positions, raw.positions, equal_nan=True), name
    assert inp.lab.to_json()["internal_from_lab"] == np.eye(3).tolist()


def _yaw(R):
    """phantom lab (X forward, Y left, Z up) -> `_Y_UP` -> internal (`R`): a 10 deg turn about the vertical."""
    from phantoms.motion import _lab_rotation

    M = R @ _lab_rotation(_Y_UP)
    np.testing.assert_allclose(M[2], [0, 0, 1], atol=1e-12)
    assert np.degrees(np.arccos(M[0, 0])) == pytest.approx(10.0)
    return M


def test_y_up_lab_gives_the_z_up_joint_estimates(folders):
    """The same subject in a Y-up lab whose walkway is 10 deg off +Z: the facing snaps to +Z (a signed permutation),
    the internal trials are the Z-up ones turned 10 deg about the vertical, and so are the Plug-in-Gait knee and
    ankle centres (0.024 mm apart at most: the chord solution's tolerance) and the SCoRE hip centres."""
    from personalize.pipeline.motion import motion_hip, pig_static

    z, y = find_inputs(folders["z"]), find_inputs(folders["y"])
    R = y.lab.internal_from_lab
    assert y.lab.up_axis == "+Y" and y.lab.facing_axis == "+Z"
    assert set(np.unique(R)) <= {-1.0, 0.0, 1.0}
    np.testing.assert_array_equal(R, [[0, 0, 1], [1, 0, 0], [0, 1, 0]])
    yaw = _yaw(R)
    np.testing.assert_allclose(y.static.positions, z.static.positions @ yaw.T, atol=1e-6)
    pz, py = pig_static(z), pig_static(y)
    for k in ("knee_r", "knee_l", "ankle_r", "ankle_l"):
        a, b = np.median(pz.centres[k], axis=0), np.median(py.centres[k], axis=0)
        np.testing.assert_allclose(b, yaw @ a, atol=1e-4, err_msg=k)
    for side in ("r", "l"):
        hz, _ = motion_hip(z.static, z.trials[z.functional], side)
        hy, _ = motion_hip(y.static, y.trials[y.functional], side)
        np.testing.assert_allclose(hy.mean, yaw @ hz.mean, atol=1e-4)
    # unsnapped (a walkway 30 deg off the lab axes): the internal X is the measured facing, not a lab axis
    turn = np.array([[np.cos(0.5), 0, np.sin(0.5)], [0, 1, 0], [-np.sin(0.5), 0, np.cos(0.5)]])
    st = replace(y.static, positions=y.static.positions @ np.linalg.inv(R).T @ turn.T)
    lab = detect_lab(st, [])
    assert "kept as measured" in " ".join(lab.evidence)
    X = lab.internal_from_lab[0]
    assert abs(X @ [0, 1, 0]) < 1e-12 and np.degrees(np.arccos(np.max(np.abs(X)))) > 20


def test_truth_is_mapped_by_the_trials_lab(folders):
    """The true static centres (written in the lab's axes) come back in the internal frame: Y-up = Z-up turned."""
    from personalize.evaluation.truth import true_static_centres

    z, y = find_inputs(folders["z"]), find_inputs(folders["y"])
    tz = true_static_centres(folders["z"], z.lab.internal_from_lab)
    ty = true_static_centres(folders["y"], y.lab.internal_from_lab)
    yaw = _yaw(y.lab.internal_from_lab)
    for k in tz:
        np.testing.assert_allclose(ty[k], yaw @ tz[k], atol=2e-6)
    raw = true_static_centres(folders["y"])
    assert raw["hip_r"][1] > 0.5 and ty["hip_r"][2] > 0.5     # lab Y up -> internal Z up


def test_rotations_are_exact_for_signed_permutations():
    """A signed permutation moves and negates coordinates (bit for bit); a general rotation multiplies."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, 4, 3))
    x[0, 1] = np.nan
    P = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    out = rotate_points(P, x)
    assert np.array_equal(out[..., 0], -x[..., 2], equal_nan=True) and np.array_equal(out[..., 2], x[..., 1],
                                                                                        equal_nan=True)
    assert rotate_points(np.eye(3), x) is x
    c, s = np.cos(0.3), np.sin(0.3)
    G = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(rotate_points(G, x[1:]), x[1:] @ G.T)


def test_static_is_found_whatever_its_case(tmp_path):
    """Static.c3d, STATIC.C3D, static_trial.trc are the static; two of them are refused, naming both."""
    for name in ("Static.c3d", "STATIC.C3D", "Static_trial.trc"):
        d = tmp_path / name.replace(".", "_")
        d.mkdir()
        (d / name).write_bytes(b"")
        (d / "gait_01.c3d").write_bytes(b"")
        static, motion = find_trials(d)
        assert static.name == name and [p.name for p in motion] == ["gait_01.c3d"]
    d = tmp_path / "two"
    d.mkdir()
    for name in ("Static.c3d", "static_2.trc", "gait_01.trc"):
        (d / name).write_bytes(b"")
    with pytest.raises(InputError, match=r"several static trials \(Static.c3d, static_2.trc\)"):
        find_trials(d)
    # the same trial as C3D and TRC (personalize phantom --format both) is read once, from the C3D
    d = tmp_path / "both"
    d.mkdir()
    for name in ("static.c3d", "static.trc", "gait_01.c3d", "gait_01.trc", "crouch.TRC"):
        (d / name).write_bytes(b"")
    static, motion = find_trials(d)
    assert static.name == "static.c3d" and [p.name for p in motion] == ["crouch.TRC", "gait_01.c3d"]
    with pytest.raises(InputError, match="missing: the static"):
        find_trials(_only(tmp_path / "nostatic", "gait_01.c3d"))


def _only(d, name):
    d.mkdir()
    (d / name).write_bytes(b"")
    return d


def test_trc_trials_are_read(folders):
    """A folder of TRC trials with ``Static.trc``: found, read (mm -> m) and the same markers as the C3D folder."""
    t, z = find_inputs(folders["trc"]), find_inputs(folders["z"])
    assert t.static.source.endswith("Static.trc") and sorted(t.trials) == sorted(z.trials)
    assert t.functional == "functional_hip"
    np.testing.assert_allclose(t.static.positions, z.static.positions, atol=1e-5, equal_nan=True)
    g = t.trials["gait_01"]
    np.testing.assert_allclose(g.positions, z.trials["gait_01"].positions, atol=1e-5, equal_nan=True)


def test_subject_json_with_mass_and_height_only(folders, tmp_path):
    """Without leg length, knee and ankle widths, find_inputs defers them to the bones; measured on the phantom's
    bone landmarks they match its calliper widths (knee 0.0 mm: the phantom's knee markers sit on the epicondyles
    over 5 mm tissue; ankle +3 mm: its malleolar markers are projected onto the ankle axis) and its tape leg length
    (bony ASIS-knee-malleolus +20 to +23 mm: the phantom's tape ends on the ankle axis above the malleolus)."""
    import shutil

    d = tmp_path / "s"
    shutil.copytree(folders["z"], d)
    full = json.loads((d / "subject.json").read_text())
    (d / "subject.json").write_text(json.dumps({"mass": full["mass"], "height": full["height"]}))
    inp = find_inputs(d)
    assert inp.subject is None and inp.subject_given == {"mass": full["mass"], "height": full["height"]}
    (d / "subject.json").write_text(json.dumps({"mass": 70.0, "left_knee_width": 0.1}))
    with pytest.raises(InputError, match="missing subject measurements"):
        subject_from_values(read_subject_values(d / "subject.json"), d / "subject.json")

    truth = make_phantom(0).truth()
    pts = {n: np.asarray(v["position"]) for b in truth["landmarks"]["bones"].values()
           for n, v in b["landmarks"].items()}
    for s in "rl":
        pts[f"{s.upper()}KJC"] = np.asarray(truth["joints"]["joints"][f"knee_{s}"]["origin"])
    given = {"mass": 70.0, "height": 1.75}
    m, src = measure_from_bones(given, pts, source="subject.json")
    for side in ("left", "right"):
        assert getattr(m, f"{side}_knee_width") - full[f"{side}_knee_width"] == pytest.approx(0.0, abs=2e-4)
        assert getattr(m, f"{side}_ankle_width") - full[f"{side}_ankle_width"] == pytest.approx(0.003, abs=1e-3)
        assert 0.015 < getattr(m, f"{side}_leg_length") - full[f"{side}_leg_length"] < 0.03
        assert "bones" in src[f"{side}_leg_length"]
    # explicit values win; a side without bones takes the other side's
    m2, src2 = measure_from_bones({**given, "left_knee_width": 0.111}, {k: v for k, v in pts.items() if k[0] != "L"
                                                                       or k.startswith("LASI")})
    assert m2.left_knee_width == 0.111 and src2["left_knee_width"] == "subject file"
    assert m2.left_ankle_width == m2.right_ankle_width and "no left bones" in src2["left_ankle_width"]
    with pytest.raises(InputError, match="left_knee_width is neither given nor measurable: the bones lack LMFC / RMFC"):
        measure_from_bones(given, {k: v for k, v in pts.items() if not k.endswith("MFC")}, source="subject.json")


def test_ambiguous_lab_is_one_line(folders, tmp_path):
    """A lab tilted 35 deg (no axis is vertical) is refused naming the trial and the angle."""
    import shutil

    from kinematics.io.c3d import write_c3d

    d = tmp_path / "tilted"
    shutil.copytree(folders["z"], d)
    c, s = np.cos(np.radians(35)), np.sin(np.radians(35))
    tilt = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    for p in sorted(d.glob("*.c3d")):
        tr = read_c3d(p)
        write_c3d(p, replace(tr, positions=tr.positions @ tilt.T))
    with pytest.raises(InputError, match=r"ambiguous lab: the pelvis-to-feet direction is 3\d\.\d deg") as e:
        find_inputs(d)
    assert "\n" not in str(e.value)


def test_plates_to_internal_rotates_every_vector(folders):
    """`plates_to_internal` turns corners, centre, axes, normal, force, moment, CoP and free moment by the lab."""
    from kinematics.io.forceplates import ForcePlate, ForcePlates

    y = find_inputs(folders["y"])
    R = y.lab.internal_from_lab
    F = np.array([[1.0, 700.0, 2.0]])          # lab Y up: the vertical load along +Y
    p = ForcePlate(0, 2, np.array([[0, 0, 0], [0.6, 0, 0], [0.6, 0, 0.4], [0, 0, 0.4]], float),
                   np.array([0.3, 0.0, 0.2]), np.eye(3)[:, [0, 2, 1]] * [1, 1, -1], np.array([0.0, 1.0, 0.0]),
                   F, np.array([[3.0, 4.0, 5.0]]), np.array([[0.3, 0.0, 0.2]]), np.array([[0.0, 1.0, 0.0]]),
                   np.array([True]), np.array([False]))
    plates = ForcePlates((p,), 100.0, np.zeros(1), 20.0, 1000.0, 100.0)
    q = plates_to_internal(plates, y.lab)[0]
    np.testing.assert_array_equal(q.normal, [0, 0, 1])
    np.testing.assert_array_equal(q.force[0], R @ F[0])
    assert q.force[0, 2] == 700.0
    np.testing.assert_array_equal(q.rotation, R @ p.rotation)
    np.testing.assert_array_equal(q.corners, p.corners @ R.T)
    assert plates_to_internal(plates, find_inputs(folders["z"]).lab) is plates
    assert to_internal(y.static, find_inputs(folders["z"]).lab) is y.static


def test_ground_reactions_of_a_y_up_lab(shared_data):
    """mocap_pig's plates turned into a Y-up lab give the Z-up lab's ground reactions in OpenSim's ground
    (force, centre of pressure, free moment: the vertical no longer assumed Z), and `lab_to_ground` maps each
    lab's vertical to the model's."""
    from types import SimpleNamespace

    from kinematics.gait.inverse_dynamics import lab_to_ground
    from kinematics.gait.plate_contacts import assign_feet
    from kinematics.io.external_loads import LAB_TO_OPENSIM, axis_permutation, loads_from_plates
    from kinematics.io.forceplates import read_force_plates

    path = shared_data / "mocap_pig" / "Movement_trial.c3d"
    plates, markers = read_force_plates(path), read_c3d(path)
    contacts = assign_feet(plates, markers)
    ref, _ = loads_from_plates(plates, contacts, rotation=LAB_TO_OPENSIM)
    Q = axis_permutation(np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]))     # Z-up lab -> Y-up lab
    np.testing.assert_array_equal(Q, [[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    yup = plates.rotated(Q)
    assert np.allclose(yup[0].normal, [0, 1, 0])
    got, _ = loads_from_plates(yup, contacts, rotation=LAB_TO_OPENSIM @ Q.T, up=(0.0, 1.0, 0.0))
    assert len(ref) == len(got) >= 1
    for a, b in zip(ref, got):
        for f in ("force", "point", "torque"):
            np.testing.assert_allclose(getattr(b, f), getattr(a, f), atol=1e-9, err_msg=f)
        assert np.nanmax(a.force[:, 1]) > 400.0          # a stance's vertical reaction, along OpenSim's Y
    opensim = SimpleNamespace(gravity=np.array([0.0, -9.80665, 0.0]), name="gait2392")
    internal = SimpleNamespace(gravity=np.array([0.0, 0.0, -9.80665]), name="personalize")
    np.testing.assert_array_equal(lab_to_ground(opensim), LAB_TO_OPENSIM)
    np.testing.assert_array_equal(lab_to_ground(opensim, (0.0, 1.0, 0.0)), np.eye(3))
    np.testing.assert_array_equal(lab_to_ground(internal), np.eye(3))
    np.testing.assert_array_equal(lab_to_ground(internal, (0.0, 1.0, 0.0)), LAB_TO_OPENSIM.T)


def test_internal_frame_of_the_shared_labs(shared_data):
    """opensim_gait2392 (Y up, facing +X): internal = lab turned Z up, exactly; mocap_pig (Z up, the static facing +X,
    the movement trial walking -X): the identity; the pig's progression agrees with `walking_direction` (0.4 deg)."""
    from kinematics.gait.gait_cycles import walking_direction
    from kinematics.io.trials import read_trial

    g = shared_data / "opensim_gait2392"
    lab = detect_lab(read_trial(g / "subject01_static.trc"), [read_trial(g / "subject01_walk1.trc")])
    np.testing.assert_array_equal(lab.internal_from_lab, [[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    assert lab.describe().endswith("static facing +X")
    p = shared_data / "mocap_pig"
    walk = read_trial(p / "Movement_trial.c3d")
    lab = detect_lab(read_trial(p / "Static_trial.c3d"), [walk])
    assert np.array_equal(lab.internal_from_lab, np.eye(3)) and lab.describe().startswith("Z up, walking -X")
    wd = walking_direction(walk, up=lab.up)
    assert np.degrees(np.arccos(wd @ lab.forward)) < 1.0


def test_loads_from_a_y_up_c3d(shared_data, tmp_path):
    """mocap_pig's movement trial rewritten in a Y-up lab (markers and plate corners turned; the channels are in the
    plate's frame): `loads_from_c3d` reads the vertical from the markers, the plates with it, and gives gait2392's
    ground (Y up) the same ground reactions as from the Z-up file."""
    from types import SimpleNamespace

    import ezc3d

    from kinematics.gait.inverse_dynamics import loads_from_c3d
    from kinematics.io.external_loads import LAB_TO_OPENSIM

    src = shared_data / "mocap_pig" / "Movement_trial.c3d"
    c = ezc3d.c3d(str(src))
    pts = np.array(c["data"]["points"])
    pts[:3] = np.einsum("ij,jmf->imf", LAB_TO_OPENSIM, pts[:3])
    c["data"]["points"] = pts
    corners = np.array(c["parameters"]["FORCE_PLATFORM"]["CORNERS"]["value"])
    c["parameters"]["FORCE_PLATFORM"]["CORNERS"]["value"] = np.einsum("ij,jcp->icp", LAB_TO_OPENSIM, corners)
    c.write(str(tmp_path / "yup.c3d"))
    model = SimpleNamespace(gravity=np.array([0.0, -9.80665, 0.0]), name="gait2392", body_names=("calcn_r", "calcn_l"))
    ref, got = loads_from_c3d(src, model), loads_from_c3d(tmp_path / "yup.c3d", model)
    assert any(n.startswith("lab: Y up") for n in got.notes) and any(n.startswith("lab: Z up") for n in ref.notes)
    assert len(ref.loads) == len(got.loads) >= 1 and ref.exclude == got.exclude
    for a, b in zip(ref.loads, got.loads):
        assert a.body == b.body
        for f in ("force", "point", "torque"):
            np.testing.assert_allclose(getattr(b, f), getattr(a, f), atol=1e-6, err_msg=f)
