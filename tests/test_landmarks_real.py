"""Real bones (STAPLE data sets): joints against the hand-built ICL-MRI model, sides on TLEM2 (skips without shared data)."""
from __future__ import annotations

import numpy as np
import pytest

from personalize.frames import joints_from_landmarks
from personalize.landmarks import detect_landmarks
from personalize.evaluation.reference_models import compare_joints, read_reference_joints


@pytest.fixture(scope="module")
def icl(shared_data):
    from personalize.surfaces import load_bones

    ls = detect_landmarks(load_bones(shared_data / "bones" / "ICL_MRI"))
    return ls, joints_from_landmarks(ls)[0]


@pytest.fixture(scope="module")
def manual(shared_data):
    return read_reference_joints(shared_data / "reference_models" / "manual_ICL_MRI.osim", use_opensim=False)


def test_reference_readers_agree(shared_data, opensim):
    path = shared_data / "reference_models" / "manual_ICL_MRI.osim"
    a = read_reference_joints(path, use_opensim=True)
    b = read_reference_joints(path, use_opensim=False)
    for k in ("hip_r", "knee_r", "ankle_r", "subtalar_r"):
        assert np.allclose(a[k].origin, b[k].origin, atol=1e-9)
        assert np.allclose(a[k].rotation, b[k].rotation, atol=1e-5)   # v3 files store float32 angles


def test_staple_model_differences_match_the_published_ones(shared_data, manual):
    auto = read_reference_joints(shared_data / "reference_models" / "automatic_ICL_MRI.osim", use_opensim=False)
    d = compare_joints(auto, manual, ["hip_r", "knee_r", "ankle_r", "subtalar_r"])
    assert d["hip_r"]["distance_mm"] == pytest.approx(0.14, abs=0.01)
    assert d["knee_r"]["distance_mm"] == pytest.approx(2.5, abs=0.05)
    assert d["ankle_r"]["distance_mm"] == pytest.approx(0.9, abs=0.05)
    assert d["subtalar_r"]["distance_mm"] == pytest.approx(3.2, abs=0.1)


def test_icl_joints_close_to_the_hand_built_model(icl, manual):
    ls, J = icl
    d = compare_joints(J, manual, ["hip_r", "knee_r", "ankle_r", "subtalar_r"])
    assert d["hip_r"]["distance_mm"] < 0.5
    assert d["knee_r"]["distance_mm"] < 4.0 and d["knee_r"]["angle_deg"] < 3.0
    assert d["ankle_r"]["distance_mm"] < 4.0 and d["ankle_r"]["angle_deg"] < 4.0
    # the subtalar origin along its axis is a convention: compare the axis line
    assert d["subtalar_r"]["line_distance_mm"] < 3.0 and d["subtalar_r"]["angle_deg"] < 5.0
    for b, res in ls.bones.items():
        assert "side_mismatch" not in res.flags and "name_mismatch" not in res.flags, (b, res.flags)


def test_icl_knee_closer_to_the_hand_built_model_than_staple(icl, manual, shared_data):
    # the knee axis is the cylinder through the posterior condyles, the hand-built
    # model's convention: its centre must beat STAPLE's and its axis stay within 0.5 deg
    _, J = icl
    auto = read_reference_joints(shared_data / "reference_models" / "automatic_ICL_MRI.osim", use_opensim=False)
    ours = compare_joints(J, manual, ["knee_r"])["knee_r"]
    staple = compare_joints(auto, manual, ["knee_r"])["knee_r"]
    assert ours["distance_mm"] < staple["distance_mm"]
    assert ours["angle_deg"] < 0.5


def test_icl_markers_close_to_staple_markers(icl, shared_data):
    import defusedxml.ElementTree as ET

    root = ET.parse(str(shared_data / "reference_models" / "automatic_ICL_MRI.osim")).getroot()
    staple = {m.attrib["name"]: np.array([float(x) for x in m.findtext("location").split()])
              for m in root.iter("Marker")}
    ls, _ = icl
    for bone, name in (("pelvis", "RASI"), ("pelvis", "LASI"), ("pelvis", "SYMP")):
        assert np.linalg.norm(ls.bones[bone].landmarks[name].position - staple[name]) < 0.003, name


@pytest.mark.parametrize("side", ["r", "l"])
def test_tlem2_both_sides_detected_with_their_side(shared_data, side):
    from personalize.surfaces import load_bones

    bones = [f"{b}_{side}" for b in ("femur", "tibia", "talus", "calcn")]
    ls = detect_landmarks(load_bones(shared_data / "bones" / "TLEM2_MRI", bones=bones))
    for b in bones:
        assert ls.bones[b].side == side, (b, ls.bones[b].flags, ls.bones[b].notes)
    J, _ = joints_from_landmarks(ls)
    assert {f"knee_{side}", f"ankle_{side}"} <= set(J)
    # knee axis points to the subject's right on both sides: in the TLEM2 scan the right is -x
    assert J[f"knee_{side}"].rotation[0, 2] < -0.9
    # a shallow tibial plafond (found among the concave distal patches) and a talus
    # scanned plantarflexed (head confirmed by its sphere) are not low-confidence
    for b in (f"tibia_{side}", f"talus_{side}"):
        assert "low_confidence" not in ls.bones[b].flags, (b, ls.bones[b].notes)
    assert "plafond_centre" in ls.bones[f"tibia_{side}"].landmarks


def _ankle_in_talus_frame(bones, side, turn_deg, about):
    """Ankle axis with the foot bones turned by `turn_deg` about `about` = (point, direction),
    expressed back in the talus' own (unturned) frame."""
    from scipy.spatial.transform import Rotation

    p0, u0 = about
    rot = Rotation.from_rotvec(np.radians(turn_deg) * u0)
    turned = {}
    for k, s in bones.items():
        m = s.mesh
        if k in (f"talus_{side}", f"calcn_{side}", f"toes_{side}"):
            m = m.copy()
            m.vertices = rot.apply(m.vertices - p0) + p0
        turned[k] = m
    ax = detect_landmarks(turned).bones[f"talus_{side}"].axes["ankle_axis"]
    return rot.inv().apply(np.asarray(ax.point) - p0) + p0, rot.inv().apply(np.asarray(ax.direction))


def test_icl_talar_dome_does_not_depend_on_the_scan_ankle_angle(shared_data, monkeypatch):
    # the same talus scanned with the foot 15 deg more plantar- or dorsiflexed must give
    # the same ankle axis in the talus: the dome is taken in the talus' neutral pose
    from personalize.landmarks import talus as talus_mod
    from personalize.surfaces import load_bones

    bones = load_bones(shared_data / "bones" / "ICL_MRI", bones=["tibia_r", "fibula_r", "talus_r", "calcn_r", "toes_r"])
    ax = detect_landmarks(bones).bones["talus_r"].axes["ankle_axis"]
    about = (np.asarray(ax.point), np.asarray(ax.direction))

    def spread(turns):
        res = [_ankle_in_talus_frame(bones, "r", t, about) for t in turns]
        move = max(np.linalg.norm(p - res[0][0]) for p, _ in res)
        ang = max(np.degrees(np.arccos(min(1.0, abs(u @ res[0][1])))) for _, u in res)
        return move * 1e3, ang

    move, ang = spread((-15, 0, 15))
    assert move < 0.2 and ang < 0.2, (move, ang)
    # the scan-pose contact (the previous default) is what this guards against: its dome centre moves 3.2 mm
    # (its axis 0.4 deg: the seeds of `DOME_SEED_ANGLES` steady the axis, not the contact's extent)
    monkeypatch.setattr(talus_mod, "DOME_NEUTRAL_POSE", False)
    move_scan, ang_scan = spread((-15, 0, 15))
    assert move_scan > 1.0 and move_scan > 10 * move, (move_scan, ang_scan)


def test_icl_decimated_mesh_gives_the_same_joints(shared_data, monkeypatch):
    # a "low-quality" mesh: ICL-MRI decimated to a quarter of its faces (median edge
    # ~5 mm, dense where curved, sparse where flat); its long edges are split before
    # detection, so the joints stay those of the full mesh
    from types import SimpleNamespace

    from personalize.landmarks import surface
    from personalize.surfaces import decimate, load_bones

    names = ["femur_r", "tibia_r", "fibula_r", "talus_r", "calcn_r", "toes_r"]
    bones = load_bones(shared_data / "bones" / "ICL_MRI", bones=names)
    full = joints_from_landmarks(detect_landmarks(bones))[0]
    ref = {k: SimpleNamespace(origin=np.asarray(v.origin), rotation=np.asarray(v.rotation)) for k, v in full.items()}
    coarse = {k: decimate(b.mesh, len(b.mesh.faces) // 4) for k, b in bones.items()}

    def differences():
        ls = detect_landmarks(coarse)
        return ls, compare_joints(joints_from_landmarks(ls)[0], ref, ["knee_r", "ankle_r", "subtalar_r"])

    ls, d = differences()
    assert any("coarse mesh" in n for n in ls.bones["femur_r"].notes)
    assert d["knee_r"]["distance_mm"] < 1.0 and d["knee_r"]["angle_deg"] < 0.5, d
    assert d["ankle_r"]["distance_mm"] < 1.0 and d["ankle_r"]["angle_deg"] < 1.0, d
    assert d["subtalar_r"]["distance_mm"] < 2.0 and d["subtalar_r"]["angle_deg"] < 2.0, d
    # detected on the decimated vertices as they are, the knee moves by millimetres
    monkeypatch.setattr(surface, "SUBDIVIDED_EDGE", 1.0)
    _, d_raw = differences()
    assert d_raw["knee_r"]["distance_mm"] > 1.5, d_raw


def test_tlem2_talar_dome_follows_the_joint_space(shared_data):
    # a segmentation that keeps (part of) the cartilage narrows the joint space: with
    # the talus 2 mm closer to the tibia the dome contact is taken within the new joint
    # space plus the same margin, so the ankle stays put (a fixed 6 mm gap moved it 5.6 mm).
    # Measured 0.13 mm / 0.28 deg; the bound is TLEM2's dome reproducibility (~1 mm / 1 deg
    # for 1-2 mm joint-space or refit-count changes), not this one value
    from personalize.surfaces import load_bones

    bones = load_bones(shared_data / "bones" / "TLEM2_MRI", bones=["tibia_r", "talus_r", "calcn_r", "toes_r"])
    ls = detect_landmarks(bones)
    up = ls.bones["tibia_r"].frames["anatomical"]["rotation"][:, 1]
    base = ls.bones["talus_r"].axes["ankle_axis"]
    moved = {}
    for k, b in bones.items():
        m = b.mesh
        if k != "tibia_r":
            m = m.copy()
            m.vertices = m.vertices + 0.002 * up
        moved[k] = m
    a = detect_landmarks(moved).bones["talus_r"].axes["ankle_axis"]
    shift = np.linalg.norm(np.asarray(a.point) - 0.002 * up - np.asarray(base.point)) * 1e3
    turn = np.degrees(np.arccos(min(1.0, abs(float(np.dot(a.direction, base.direction))))))
    assert shift < 1.0 and turn < 1.0, (shift, turn)


def test_icl_bones_at_a_childs_size_give_the_scaled_joints(icl, shared_data, tmp_path):
    """ICL_MRI's bones shrunk to 0.6 of their size (a 7-9-year-old's pelvis, 157 mm wide): the joints are the
    adult ones shrunk, as for any similarity of the input.  Pelvis, talus and foot search their lengths in units
    of their own size below an adult's (`ADULT_PELVIS_WIDTH`, ...).  Measured: hip, knee 0.03 mm, 0.0 deg; ankle
    0.4 mm, 0.4 deg; subtalar 2.5 mm, 2.8 deg; mtp 0.5 mm, 1.2 deg.  With the adult constants the pelvic frame
    was 155 deg off (its sockets' search radii start at 16 mm) and the mtp 31 mm (no metatarsal head sphere)."""
    import trimesh

    from personalize.surfaces import load_bones

    s, c = 0.6, np.array([0.1, -0.05, -0.8])                  # m, about a point near the bones
    for f in sorted((shared_data / "bones" / "ICL_MRI").glob("*.ply")):
        if f.stem not in ("pelvis", "pelvis_r", "pelvis_l"):
            m = trimesh.load(str(f), process=False)
            m.vertices = (np.asarray(m.vertices) - 1e3 * c) * s + 1e3 * c
            m.export(str(tmp_path / f.name))
    joints = joints_from_landmarks(detect_landmarks(load_bones(tmp_path)))[0]
    limits = {"hip": (0.5, 1.0), "knee": (0.5, 1.0), "ankle": (1.0, 1.0), "subtalar": (4.0, 4.0), "mtp": (1.5, 2.0)}
    for name, j in icl[1].items():
        mm, deg = limits[name[:-2]]
        child = joints[name]
        dist = np.linalg.norm(child.origin - ((j.origin - c) * s + c)) * 1e3
        for a, b in ((j.rotation, child.rotation), (j.parent.rotation, child.parent.rotation)):
            ang = np.degrees(np.arccos(np.clip(np.sum(a * b, axis=0), -1, 1))).max()
            assert dist < mm and ang < deg, (name, dist, ang)


@pytest.mark.parametrize("name", ["LHDL_CT", "TLEM2_MRI"])
def test_a_childs_size_pelvis_keeps_its_frame(shared_data, tmp_path, name):
    """Pelvis and femurs of LHDL_CT and TLEM2_MRI shrunk to 0.6: the hip joints' pelvic frames are the adult
    ones (0.0 deg measured).  Before: LHDL_CT's was turned 177 deg (its femur, flagged for disagreeing knee
    estimates, gave no anterior, and the pelvis' own symphysis cue flipped), TLEM2_MRI's 159 deg (a 38 mm
    spurious socket passed the adult radius limit)."""
    import trimesh

    from personalize.surfaces import load_bones

    src = shared_data / "bones" / name
    files = [f for f in sorted(src.glob("*.ply")) if f.stem == "pelvis_no_sacrum" or f.stem.startswith("femur_")]
    (tmp_path / "adult").mkdir()
    (tmp_path / "child").mkdir()
    s = 0.6
    for f in files:
        m = trimesh.load(str(f), process=False)
        m.export(str(tmp_path / "adult" / f.name))
        m.vertices = np.asarray(m.vertices) * s
        m.export(str(tmp_path / "child" / f.name))
    adult = joints_from_landmarks(detect_landmarks(load_bones(tmp_path / "adult")))[0]
    child = joints_from_landmarks(detect_landmarks(load_bones(tmp_path / "child")))[0]
    hips = [j for j in adult if j.startswith("hip_")]
    assert hips
    for j in hips:
        assert np.linalg.norm(child[j].origin - s * adult[j].origin) < 0.5e-3
        ang = np.degrees(np.arccos(np.clip(np.sum(adult[j].parent.rotation * child[j].parent.rotation, axis=0), -1, 1)))
        assert ang.max() < 1.0, (j, ang)


def test_mc22_left_talar_dome_is_the_same_at_90_percent(shared_data, tmp_path):
    """MC22's left foot, at its size and shrunk to 0.9: the talar dome axis is one cylinder (0.38 mm rms).
    The neutral-pose re-selection turned it 84 deg onto a 1.05 mm rms one at full size only, so the ankle axis
    depended on a 10 % change of size; it may now turn the axis at most `DOME_NEUTRAL_MAX_TURN_DEG`."""
    import trimesh

    from personalize.surfaces import load_bones

    src = shared_data / "bones" / "MC22"
    axes = []
    for s in (1.0, 0.9):
        d = tmp_path / f"s{s}"
        d.mkdir()
        for f in sorted(src.glob("*_l.ply")):
            m = trimesh.load(str(f), process=False)
            m.vertices = np.asarray(m.vertices) * s
            m.export(str(d / f.name))
        t = detect_landmarks(load_bones(d), trust_names=True).bones["talus_l"]
        axes.append(t.axes["ankle_axis"].direction)
        assert t.fits["talar_dome"]["rms"] < 0.6e-3
    assert np.degrees(np.arccos(abs(axes[0] @ axes[1]))) < 5.0
