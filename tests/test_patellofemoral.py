"""The patellofemoral joint (issue M1, `personalize.patellofemoral`): the patella's path on real bones, and the
joint in the model OpenSim reads."""
from __future__ import annotations

import numpy as np
import pytest

REAL = [("ICL_MRI", "r"), ("LHDL_CT", "r"), ("TLEM2_MRI", "r"), ("TLEM2_MRI", "l")]


def _bones(shared_data, name, side):
    from personalize.landmarks import detect_landmarks
    from personalize.surfaces import load_bones

    bones = load_bones(shared_data / "bones" / name)
    use = {k: v for k, v in bones.items() if k.startswith(("femur", "tibia", "patella", "fibula", "talus"))}
    return bones, detect_landmarks(use, trust_names=True)


def _track_on_a_hinge(bones, ls, side):
    """The path with the tibia turning about the femur's knee axis (no knee translation): geometry, knee frame,
    tuberosity function and the track."""
    from scipy.spatial.transform import Rotation

    from personalize.patellofemoral import PatellaGeometry, patellar_track

    f, p, t = (ls.bones[f"{b}_{side}"] for b in ("femur", "patella", "tibia"))
    fem, pat = bones[f"femur_{side}"].mesh, bones[f"patella_{side}"].mesh
    K = f.landmarks["intercondylar_midpoint"].position
    R = f.frames["anatomical"]["rotation"]
    Z = f.axes["knee_axis"].direction
    Z = Z if Z @ R[:, 2] > 0 else -Z
    Y = R[:, 1] - (R[:, 1] @ Z) * Z
    Y /= np.linalg.norm(Y)
    B = np.column_stack([np.cross(Y, Z), Y, Z])
    tt = t.landmarks[f"{side.upper()}TTB"].position
    g = PatellaGeometry(np.asarray(fem.vertices), np.asarray(fem.vertex_normals), np.asarray(pat.vertices),
                        np.asarray(pat.vertex_normals), p.landmarks["patella_centre"].position,
                        p.frames["articular"]["rotation"], tt)
    tt_f = (tt - K) @ B
    at = lambda q: Rotation.from_euler("z", -q).as_matrix() @ tt_f      # noqa: E731
    return g, (K, B), at, patellar_track(g, (K, B), at)


@pytest.mark.parametrize("name,side", REAL)
def test_patella_lags_knee_flexion_as_in_vivo_on_real_bones(shared_data, name, side):
    """On four real knees: the path converges over at least 0-45 deg, the patella flexes 0.6-0.75 deg per knee
    degree (in vivo it lags knee flexion by 30-40 %), and the tendon keeps its MRI length within 0.5 mm (checked
    on the moved apex, not on the solver's residual)."""
    bones, ls = _bones(shared_data, name, side)
    g, (K, B), at, tr = _track_on_a_hinge(bones, ls, side)
    assert tr is not None
    assert np.degrees(tr.flexion[0]) <= 0.0 and np.degrees(tr.flexion[-1]) >= 45.0
    assert 0.6 <= tr.patellar_flexion_ratio <= 0.75
    P = (np.asarray(bones[f"patella_{side}"].mesh.vertices) - K) @ B
    Rp = B.T @ g.patella_rotation
    apex = P[np.argmin((P - tr.centre) @ Rp[:, 1])]
    for q, a, t in zip(tr.flexion, tr.rotation, tr.translation):
        c, s = np.cos(a), np.sin(a)
        moved = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ apex + [t[0], t[1], 0.0]
        assert abs(np.linalg.norm(moved - at(q)) - tr.tendon_length) < 5e-4


def test_no_path_from_a_tibia_whose_tuberosity_is_not_there(shared_data):
    """VAKHUM-CT's tibia gives a tuberosity half a metre from the patella: no path (the patella stays on the femur)."""
    bones, ls = _bones(shared_data, "VAKHUM_CT", "r")
    assert _track_on_a_hinge(bones, ls, "r")[3] is None


@pytest.fixture(scope="module")
def icl_run(shared_data, tmp_path_factory):
    from personalize.evaluation.phantom_builder import PhantomOptions, build_phantom, write_phantom
    from personalize.pipeline import run_subject

    root = tmp_path_factory.mktemp("patella")
    opts = PhantomOptions(seed=2, anatomy=shared_data / "bones" / "ICL_MRI",
                          reference=shared_data / "reference_models" / "manual_ICL_MRI.osim", marker_set="pig",
                          static_frames=20, functional=False)
    write_phantom(build_phantom(opts), root / "subject")
    summary = run_subject(root / "subject", root / "out", report=False, muscles="none", generic=False, patella="joint")
    return root / "out", summary


def test_the_patella_follows_knee_flexion_in_opensim(icl_run, opensim):
    """OpenSim reads the joint as written: with knee flexion set, the coupler moves the patella coordinate with
    it and the patella lands where the repository's own kinematics put it; the patella mesh rides on it."""
    from kinematics.algorithms.fk import body_pose
    from kinematics.io.opensim_io import load_osim

    out, _ = icl_run
    ours = load_osim(out / "model.osim")
    m = opensim.Model(str(out / "model.osim"))
    state = m.initSystem()
    assert "patella_r_geometry" in [m.getBodySet().get("patella_r").get_attached_geometry(i).getName()
                                    for i in range(m.getBodySet().get("patella_r").getPropertyByName(
                                        "attached_geometry").size())]
    for q in (0.2, 0.7, 1.2):
        m.getCoordinateSet().get("knee_flexion_r").setValue(state, q)      # the coupler assembles beta
        assert m.getCoordinateSet().get("knee_flexion_r_beta").getValue(state) == pytest.approx(q, abs=1e-6)
        p_os = m.getBodySet().get("patella_r").getPositionInGround(state)
        qv = np.array([m.getCoordinateSet().get(n).getValue(state) for n in ours.coordinate_names])
        _, p = body_pose(ours, qv, "patella_r")
        assert np.linalg.norm(np.array([p_os.get(i) for i in range(3)]) - p) < 1e-6


def test_opensims_ik_reproduces_ours_with_the_patella(icl_run):
    from opensim_checks import opensim_ik_difference_deg

    out, summary = icl_run
    trial = next(t for t in summary["ik"] if t != "static")
    worst, names = opensim_ik_difference_deg(out / "kinematics" / f"{trial}_ik_setup.xml",
                                             out / "kinematics" / f"{trial}.mot", out / "opensim_check",
                                             out / "model.osim")
    assert "knee_flexion_r_beta" in names
    assert worst < 0.5


def test_the_patella_rides_on_the_femur_through_flexion(icl_run):
    """The written model end to end: the patella mesh on its body, moved by the joint over 0-100 deg of knee
    flexion, keeps its gap to the femur mesh (bone to bone, the MRI's cartilage) within 1 mm and never enters it."""
    import trimesh

    from kinematics.algorithms.fk import body_pose
    from kinematics.io.opensim_io import load_osim

    out, _ = icl_run
    m = load_osim(out / "model.osim")
    fem, pat = (trimesh.load(out / "meshes" / f"{b}_r.stl") for b in ("femur", "patella"))
    q0 = np.array(m.default_q, float)
    gaps = []
    for deg in range(0, 101, 20):
        q = q0.copy()
        q[[m.coordinate_index("knee_flexion_r"), m.coordinate_index("knee_flexion_r_beta")]] = np.radians(deg)
        (Rf, pf), (Rp, pp) = body_pose(m, q, "femur_r"), body_pose(m, q, "patella_r")
        P = ((np.asarray(pat.vertices) @ Rp.T + pp) - pf) @ Rf
        gaps.append(float(trimesh.proximity.closest_point(fem, P)[1].min()))
        assert trimesh.proximity.signed_distance(fem, P).max() <= 0.0
    assert 0.001 < gaps[0] < 0.008 and np.ptp(gaps) < 0.001


def test_a_bad_patella_choice_is_refused_before_any_work(tmp_path):
    from lowerlimb.errors import InputError
    from personalize.pipeline import run_subject

    with pytest.raises(InputError, match="--patella"):
        run_subject(tmp_path / "nowhere", tmp_path / "out", patella="hinge")
    assert not (tmp_path / "out").exists()


def test_opensims_inverse_dynamics_equals_ours_with_the_patella(icl_run, opensim, tmp_path):
    """The patella's coordinate is "Coupled" to OpenSim, which reads it in radians whatever the header says: the
    IK files hold it so, and OpenSim's ID on them equals personalize's (every coordinate within 1e-6 of its peak)."""
    from opensim_checks import generalised_force, synthetic_load_id_against_opensim

    out, _ = icl_run
    opensim.Logger.setLevelString("warn")
    _, os_id, _ = synthetic_load_id_against_opensim(out, tmp_path)
    assert np.abs(generalised_force(os_id, "knee_flexion_r_beta")).max() < 1.0      # a 0.1 kg patella
