"""Phantoms on real anatomy (ICL-MRI / LHDL-CT bones with their expert models): truth skeleton, OpenSim IK,
label volumes, marker sets, labs and soft-tissue classes written as truth says."""
from __future__ import annotations

import json

import numpy as np
import pytest

from kinematics.io.marker_sets import preset, read_marker_set
from kinematics.io.trials import read_trial


@pytest.fixture(scope="module")
def icl(shared_data):
    from phantoms.real_anatomy import load_real_anatomy

    return load_real_anatomy(shared_data / "bones" / "ICL_MRI", shared_data / "reference_models" / "manual_ICL_MRI.osim")


def _write(tmp_path, anat, name, **kw):
    from phantoms.real_subject import write_real_subject

    out = tmp_path / name
    out.mkdir()
    kw = {"labels": False, "meshes": False, "sta": False, "noise_sd": 0.0, "static_frames": 7, "functional": False,
          **kw}
    truth = write_real_subject(out, anat, **kw)
    return out, truth


def test_mirrored_side_is_the_mirror_image(icl):
    """Same coordinates on both sides give the mirror-image leg (pelvis fixed); the scan pose puts every bone on its mesh."""
    from kinematics.algorithms.fk import forward_kinematics

    M, c = icl.symmetry
    assert np.linalg.det(M) == pytest.approx(-1.0)
    m = icl.model
    rng = np.random.default_rng(3)
    q = icl.scan_q.copy()
    for i, n in enumerate(m.coordinate_names):
        if n.endswith("_r"):
            q[i] = rng.normal(scale=0.4)
            q[m.coordinate_index(n[:-1] + "l")] = q[i]
    st = forward_kinematics(m, q)
    pel = m.body_index("pelvis")
    Rp, pp = st.rotations[0, pel], st.positions[0, pel]

    def in_pelvis(bone):
        k = m.body_index(icl.bone_body[bone])
        return (np.asarray(icl.local_meshes[bone].vertices) @ st.rotations[0, k].T + st.positions[0, k] - pp) @ Rp

    for b in ("femur", "tibia", "calcn"):
        assert np.abs(in_pelvis(f"{b}_r") @ M.T + c - in_pelvis(f"{b}_l")).max() < 1e-9
    # the left hip centre sits in the left acetabulum: the mirror of the right hip centre
    o_r, o_l = icl.joints_scanner["hip_r"][0], icl.joints_scanner["hip_l"][0]
    assert np.linalg.norm(M @ o_r + c - o_l) < 1e-9
    assert 0.15 < np.linalg.norm(o_r - o_l) < 0.22


def test_opensim_ik_reproduces_truth_icl_ior_yup(icl, tmp_path, opensim):
    """Noise-free, artefact-free ior markers of a Y-up lab through OpenSim's own IK on truth_model.osim: < 0.5 mm."""
    from kinematics.io.opensim_io import opensim_inverse_kinematics
    from kinematics.io.storage import read_mot

    out, truth = _write(tmp_path, icl, "icl", marker_set="ior", lab="y-up", static_name="Static", gait_trials=1)
    assert (out / "Static.c3d").is_file() and not (out / "functional_hip.c3d").exists()
    assert truth["lab"]["up"] == [0.0, 1.0, 0.0]
    osim_model = opensim.Model(str(out / "truth_model.osim"))
    g = osim_model.getGravity()
    assert [g.get(i) for i in range(3)] == pytest.approx([0.0, -9.80665, 0.0])
    # mass properties: the subject's mass shared by the bodies (the expert's ICL masses are mm^3 volumes)
    subject = json.loads((out / "subject.json").read_text())
    bs = osim_model.getBodySet()
    masses = [bs.get(i).getMass() for i in range(bs.getSize())]
    assert sum(masses) == pytest.approx(subject["mass"], rel=1e-9) and min(masses) > 0.05
    assert 1.5 < subject["height"] < 2.0 and 0.7 < subject["right_leg_length"] < 1.1
    for trial in ("static", "gait_01"):
        r = opensim_inverse_kinematics(out / "truth_model.osim", out / "truth" / f"{trial}_markers.trc")
        assert r["rms"].max() < 5e-4, (trial, r["rms"].max())
        tab = read_mot(out / "truth" / f"{trial}.mot")
        for k, name in enumerate(r["coordinates"]):
            want = tab.values[:, list(tab.columns).index(name)]
            got = r["q"][:, k]
            if name in ("pelvis_tx", "pelvis_ty", "pelvis_tz"):
                assert np.abs(got - want).max() < 5e-4, name
            else:
                assert np.degrees(np.abs(got - np.radians(want))).max() < 0.5, name
    # the trial as written (C3D, mm) is the same marker data
    st = read_trial(out / "Static.c3d")
    assert st.n_frames == 7 and set(st.names) == set(read_marker_set(out / "markers.json").labels)


@pytest.fixture(scope="module")
def icl_labels(icl, tmp_path_factory):
    from phantoms.imaging import write_label_nifti
    from phantoms.real_anatomy import mesh_label_volume

    d = tmp_path_factory.mktemp("icl_labels")
    bones = ("femur_r", "tibia_r")
    lab, aff, lmap = mesh_label_volume({b: icl.meshes[b] for b in bones}, voxel=(1e-3,) * 3)
    write_label_nifti(d / "labels.nii.gz", lab, aff)
    (d / "label_map.json").write_text(json.dumps(lmap))
    return d, bones


def test_label_volume_1mm_surfaces_within_quarter_mm(icl, icl_labels):
    """Surfaces from the 1 mm label volume of the ICL bones lie within 0.25 mm (mean) of the meshes."""
    from personalize.surfaces import load_bones, surface_distance

    d, bones = icl_labels
    surf = load_bones(d / "labels.nii.gz", d / "label_map.json", bones=list(bones), workers=1, eager_points=False)
    for b in bones:
        dist = surface_distance(surf[b].mesh, icl.meshes[b], n=20000, seed=0)
        assert dist["mean"] < 2.5e-4, (b, dist["mean"])
        assert abs(surf[b].volume - icl.meshes[b].volume) / icl.meshes[b].volume < 0.02


def _check_written(out, truth, anat, ms_name):
    """Markers in the static trial = the truth model's markers at the true static pose; markers.json = placed set."""
    from kinematics.algorithms.fk import forward_kinematics, point_positions
    from kinematics.io.opensim_io import load_osim
    from kinematics.io.storage import read_mot

    model = load_osim(out / "truth_model.osim")
    ms = read_marker_set(out / "markers.json")
    full = preset(ms_name)
    assert ms.name == ms_name
    for k in ms.labels:
        assert ms.markers[k].segment == full.markers[k].segment
        assert ms.markers[k].landmark == full.markers[k].landmark
        assert truth["markers"][k]["body"] == ms.markers[k].segment
    skipped = [k for k in full.labels if k not in ms.labels]
    assert all(full.markers[k].segment == "torso" for k in skipped)
    tab = read_mot(out / "truth" / "static.mot")
    rot = {c.name for c in model.coordinates if c.kind == "rotational"}
    q = np.column_stack([np.radians(tab.values[:, list(tab.columns).index(c)]) if c in rot
                         else tab.values[:, list(tab.columns).index(c)] for c in model.coordinate_names])
    st = forward_kinematics(model, q[:1])
    static = read_trial(next(p for p in out.iterdir() if p.stem.lower() == "static" and p.suffix in (".c3d", ".trc")))
    for k in static.names:
        mk = model.markers[model.marker_index(k)]
        want = point_positions(model, st, np.array([model.body_index(mk.body)]), mk.offset[None])[0, 0]
        assert np.linalg.norm(static.marker(k)[0] - want) < 2e-5, k      # file precision (float32, mm)
        # marker positions in bone frames: truth.json's offset is the model's
        assert np.allclose(truth["markers"][k]["offset_m"], mk.offset, atol=1e-9)
    return model, static, ms


def _bone_distance(anat, label, tm):
    """Distance from a marker (body frame) to the nearest vertex of its landmark's bone."""
    p = np.asarray(tm["offset_m"])
    surf = np.asarray(tm["surface_point_body_m"])
    bones = [b for b, body in anat.bone_body.items() if body == tm["body"]]
    V = np.concatenate([np.asarray(anat.local_meshes[b].vertices) for b in bones])
    return float(np.min(np.linalg.norm(V - surf, axis=1))), float(np.linalg.norm(p - surf))


def _clearance(anat, tm):
    """Distance from a marker centre (body frame) to the nearest vertex of any bone of its body."""
    p = np.asarray(tm["offset_m"])
    V = np.concatenate([np.asarray(anat.local_meshes[b].vertices) for b, body in anat.bone_body.items()
                        if body == tm["body"]])
    return float(np.min(np.linalg.norm(V - p, axis=1)))


@pytest.mark.parametrize("ms_name,lab,walk,build,fmt", [
    ("pig", "z-up", "+x", "adult", "c3d"),
    ("ior", "y-up", "-z", "child", "trc"),
    ("cast", "z-up", "+y", "obese", "c3d"),
    ("opensim", "y-up", "+x", "adult", "both"),
])
def test_marker_set_lab_and_tissue_written_as_truth(icl, tmp_path, ms_name, lab, walk, build, fmt):
    from lowerlimb.geometry import DEFAULT_MARKER_RADIUS

    out, truth = _write(tmp_path, icl, ms_name, marker_set=ms_name, lab=lab, walk=walk, build=build,
                        trial_format=fmt, gait_trials=1)
    model, static, ms = _check_written(out, truth, icl, ms_name)
    # lab axes: vertical and walking direction as asked, gravity along -up
    up = np.zeros(3)
    up[2 if lab == "z-up" else 1] = 1.0
    fwd = np.zeros(3)
    fwd["xyz".index(walk[1])] = 1.0 if walk[0] == "+" else -1.0
    assert np.allclose(truth["lab"]["up"], up) and np.allclose(truth["lab"]["forward"], fwd)
    assert np.allclose(model.gravity, -9.80665 * up)
    pel = [k for k in static.names if ms.markers[k].segment == "pelvis"]
    foot = [k for k in static.names if ms.markers[k].segment.startswith("calcn")]
    h_pel = np.mean([static.marker(k)[0] @ up for k in pel])
    h_foot = np.mean([static.marker(k)[0] @ up for k in foot])
    assert 0.75 < h_pel - h_foot < 1.1 and -0.01 < h_foot < 0.12
    gait = read_trial(out / f"gait_01.{'trc' if fmt == 'trc' else 'c3d'}")
    d = np.nanmean(gait.positions[-1], axis=0) - np.nanmean(gait.positions[0], axis=0)
    assert d @ fwd > 2.0 and abs(d @ up) < 0.05                  # 2.2 s at 1.25 m/s
    if fmt == "both":
        assert (out / "static.trc").is_file() and (out / "static.c3d").is_file()
    # CAST: anatomical markers in the static only
    static_only = [k for k, v in ms.markers.items() if v.static_only]
    assert bool(static_only) == (ms_name == "cast")
    assert set(static_only) <= set(static.names) and not set(static_only) & set(gait.names)
    # soft tissue: each bony marker sits (thickness + radius) off its bone along the normal, on the surface point
    for k, tm in truth["markers"].items():
        if tm["kind"] != "landmark":
            continue
        on_bone, off = _bone_distance(icl, k, tm)
        assert on_bone < 1e-9
        assert off == pytest.approx(tm["thickness_m"] + DEFAULT_MARKER_RADIUS, abs=1e-9)
        # ... on the outside: no bone of its body nearer than most of that offset (a normal flipped inward put
        # the lateral malleolus marker 15 mm into the ankle, 1-2 mm from the fibula)
        assert _clearance(icl, tm) > 0.6 * off, k
        assert tm["palpation_error_m"] < 0.06
    assert truth["tissue"]["build"] == build


def test_tissue_classes_order_and_obese_pelvis():
    from phantoms.marker_placement import draw_tissue

    rng = np.random.default_rng(0)
    med = {b: {s: np.median([draw_tissue(rng, b, s) for _ in range(400)]) for s in ("ASI", "PSI", "TRO")}
           for b in ("child", "adult", "obese")}
    for s in ("ASI", "PSI", "TRO"):
        assert med["child"][s] < med["adult"][s] < med["obese"][s]
    assert med["obese"]["PSI"] > 0.035 and med["adult"]["ASI"] < 0.012


def test_no_fibula_mesh_keeps_fibula_landmarks_on_the_tibia(icl, tmp_path):
    """Without a fibula mesh the tibia mesh carries the fibula as a second component; HFB/ANK still ride on tibia_r."""
    import trimesh

    out, truth = _write(tmp_path, icl, "nofib", marker_set="ior", lab="z-up", meshes=True, fibula_mesh=False)
    assert not (out / "meshes" / "fibula_r.ply").exists()
    tib = trimesh.load(out / "meshes" / "tibia_r.ply", force="mesh")
    assert len(tib.split(only_watertight=False)) >= 2
    ms = read_marker_set(out / "markers.json")
    assert ms.markers["RHFB"].segment == "tibia_r" and ms.markers["RANK"].landmark == "RANK"
    assert truth["anatomy"]["fibula_mesh_written"] is False


def test_lhdl_ct_tibia_with_fibula_component(shared_data, tmp_path, opensim):
    """LHDL-CT (no fibula mesh: the fibula is the tibia mesh's second component; a toes body): OpenSim IK < 0.5 mm."""
    from kinematics.io.opensim_io import opensim_inverse_kinematics
    from phantoms.real_anatomy import load_real_anatomy

    anat = load_real_anatomy(shared_data / "bones" / "LHDL_CT", shared_data / "reference_models" / "manual_LHDL_CT.osim")
    assert anat.fibula_from == "tibia component" and "mtp_angle_l" in anat.model.coordinate_names
    out, _ = _write(tmp_path, anat, "lhdl", marker_set="ior", lab="z-up", gait_trials=0)
    r = opensim_inverse_kinematics(out / "truth_model.osim", out / "truth" / "static_markers.trc")
    assert r["rms"].max() < 5e-4


def test_bad_inputs_are_one_line_errors(shared_data, tmp_path):
    from lowerlimb.errors import InputError
    from phantoms.lab import make_lab
    from phantoms.real_anatomy import load_real_anatomy

    with pytest.raises(InputError, match="anatomy folder not found"):
        load_real_anatomy(tmp_path / "nope", shared_data / "reference_models" / "manual_ICL_MRI.osim")
    # the expert model of other bones: its joints lie far from these meshes
    with pytest.raises(InputError, match="mm from its bones"):
        load_real_anatomy(shared_data / "bones" / "ICL_MRI", shared_data / "reference_models" / "manual_LHDL_CT.osim")
    with pytest.raises(InputError, match="vertical"):
        make_lab("y-up", "+y")


def test_cli_phantom_anatomy(shared_data, tmp_path, capsys):
    """``personalize phantom --anatomy --reference``: a Y-up ior subject with Static.c3d, TRC trials, no functional trial."""
    from personalize.cli import main

    ref = shared_data / "reference_models" / "manual_ICL_MRI.osim"
    out = tmp_path / "ph"
    code = main(["phantom", "--out", str(out), "--anatomy", str(shared_data / "bones" / "ICL_MRI"), "--reference",
                 str(ref), "--marker-set", "ior", "--lab", "y-up", "--walk", "-x", "--tissue", "obese",
                 "--static-name", "Static", "--static-frames", "7", "--no-functional", "--format", "trc",
                 "--voxel", "4", "4", "4", "--no-sta"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    assert "wrote real-anatomy phantom" in cap.out
    names = {p.name for p in out.iterdir()}
    assert {"Static.trc", "gait_01.trc", "labels.nii.gz", "markers.json", "truth_model.osim", "truth.json",
            "subject.json"} <= names and "functional_hip.trc" not in names
    truth = json.loads((out / "truth.json").read_text())
    assert truth["lab"]["forward"] == [-1.0, 0.0, 0.0] and truth["tissue"]["build"] == "obese"
    assert truth["tissue"]["thickness_m"]["PSI"] > 0.02
    for bad in (["--anatomy", str(shared_data / "bones" / "ICL_MRI")],             # no --reference
                ["--anatomy", str(tmp_path / "none"), "--reference", str(ref)],
                ["--marker-set", "ior"],                                             # analytic + other set
                ["--anatomy", str(shared_data / "bones" / "ICL_MRI"), "--reference", str(ref), "--lab", "x-up"]):
        code = main(["phantom", "--out", str(tmp_path / "bad"), *bad])
        err = capsys.readouterr().err
        assert code == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1, (bad, err)
        assert not (tmp_path / "bad").exists()


def test_gait_keeps_the_stance_foot_on_the_floor(icl):
    """Every gait frame has its lowest foot point on the floor (y = 0); each foot is on it 35-65 % of the cycle."""
    from phantoms.real_subject import (_fk, _foot_points, coordinate_signs, real_gait_coordinates,
                                       standing_coordinates)

    q0 = standing_coordinates(icl)
    signs = coordinate_signs(icl, q0)
    assert signs["hip_flexion"] == 1.0 and signs["knee_angle"] == -1.0 and signs["ankle_angle"] == 1.0
    q = real_gait_coordinates(icl, q0, signs, 100.0)
    st = _fk(icl.model, q)
    low = {}
    for k, V in _foot_points(icl):
        side = icl.model.body_names[k][-1]
        y = (np.einsum("fj,pj->fp", st.rotations[:, k, 1, :], V) + st.positions[:, k, 1][:, None]).min(axis=1)
        low[side] = np.minimum(low.get(side, np.inf), y)
    both = np.minimum(low["r"], low["l"])
    assert np.abs(both).max() < 1e-9
    for s in "rl":
        assert 0.35 < np.mean(low[s] < 0.002) < 0.65 and low[s].max() > 0.05
    ty = q[:, icl.model.coordinate_index("pelvis_ty")]
    assert 0.02 < np.ptp(ty) < 0.07


def test_force_plates_carry_the_momentum_ground_reaction(icl, tmp_path):
    """Force platforms under the stance phases read back (kinematics.io.forceplates) as the truth's reaction of
    each foot; the reaction brakes then propels, and the leading foot takes it over gradually."""
    from kinematics.io.forceplates import read_force_plates
    from kinematics.io.storage import read_sto

    out, truth = _write(tmp_path, icl, "fp", marker_set="pig", lab="z-up", walk="-y", gait_trials=1,
                        force_plates=True)
    plates = truth["force_plates"]["gait_01"]
    assert len(plates) >= 2 and {p["foot"] for p in plates} == {"r", "l"}
    g = read_sto(out / "truth" / "gait_01_grf.sto")
    col = {c: i for i, c in enumerate(g.columns)}
    F = {s: g.values[:, [col[f"{s}_ground_force_v{a}"] for a in "xyz"]] for s in "rl"}
    cop = {s: g.values[:, [col[f"{s}_ground_force_p{a}"] for a in "xyz"]] for s in "rl"}
    total = F["r"] + F["l"]
    bw = json.loads((out / "subject.json").read_text())["mass"] * 9.80665
    assert 0.95 < total[:, 2].mean() / bw < 1.05                 # momentum: mean vertical reaction = weight
    assert total[10:-10, 2].max() < 1.6 * bw and total[10:-10, 2].min() > 0.6 * bw
    walk = np.array([0.0, -1.0, 0.0])
    for t in plates:
        a, b = t["frames"]
        fa = F[t["foot"]][a:b + 1] @ walk
        n = len(fa) // 3
        # walking's fore-aft reaction (the walk's surge): braking after heel strike, propulsion before toe-off
        assert fa[:n].mean() < -0.04 * bw and fa[-n:].mean() > 0.04 * bw, (t["foot"], fa[:n].mean(), fa[-n:].mean())
        # the leading foot takes the load over the double support, not all of it at heel strike
        assert F[t["foot"]][a, 2] < 0.5 * total[a, 2]
    fp = read_force_plates(out / "gait_01.c3d")
    assert len(fp.plates) == len(plates)
    for pl, t in zip(fp.plates, plates):
        a, b = t["frames"]
        s = t["foot"]
        sl = slice(a + 2, b - 1)                                 # away from the box-averaged on/off edges
        # the reader's box average over a frame of the channels (linear between frames): 3/4 f_i + (f_i-1 + f_i+1)/8
        box = 0.75 * F[s] + 0.125 * (np.roll(F[s], 1, axis=0) + np.roll(F[s], -1, axis=0))
        assert np.abs(pl.force[sl] - box[sl]).max() < 0.005 * bw
        c = slice(a + 3, b - 1)                                  # the CoP of a load still being taken over
        d = np.linalg.norm(pl.cop[c] - cop[s][c], axis=1)
        assert np.nanmax(d) < 0.015 and np.nanmedian(d) < 5e-4      # the CoP of the box-averaged wrench
        assert np.allclose(pl.normal, [0, 0, 1])


def test_pig_wands_are_aimed_so_the_chord_finds_the_joint_centres(icl, tmp_path):
    """THI and TIB lie in the plane of the joint centres' line and their KNE / ANK marker (Plug-in-Gait's
    placement), so its chord, given the true proximal centre, lands near the true knee and ankle centres.
    Measured on ICL-MRI, adult (right, left): knee 8 and 18 mm, ankle 13 and 11 mm off (what the epicondyle's
    and the malleolus' distance from the flexion axes and their palpation leave); on the realistic set's LHDL-CT
    subjects, with TIB set straight lateral in the ground, the ankle was 75-80 mm off, and with the wands aimed
    along the flexion axes instead of the markers the knee 13-30 mm."""
    from kinematics.gait.pig import chord_joint_centre
    from kinematics.io.storage import read_trc
    from personalize.evaluation.truth import true_static_centres

    out, _ = _write(tmp_path, icl, "pig", marker_set="pig", lab="z-up", walk="+y", build="adult")
    tr = read_trc(out / "truth" / "static_markers.trc")
    mk = {n: np.nanmedian(tr.marker(n), axis=0) for n in tr.names}
    t = true_static_centres(out)
    subject = json.loads((out / "subject.json").read_text())
    for S, s, side in (("R", "r", "right"), ("L", "l", "left")):
        H, K, A = t[f"hip_{s}"], t[f"knee_{s}"], t[f"ankle_{s}"]
        for wand, prox, mark, line in (("THI", H, "KNE", (H, K)), ("TIB", K, "ANK", (K, A))):
            n = np.cross(line[0] - line[1], mk[f"{S}{mark}"] - line[1])
            assert abs((mk[f"{S}{wand}"] - line[1]) @ n) / np.linalg.norm(n) < 1e-3, (S, wand)
        knee = chord_joint_centre(mk[f"{S}THI"][None], H[None], mk[f"{S}KNE"][None],
                                  0.5 * subject[f"{side}_knee_width"] + 0.007)[0]
        ankle = chord_joint_centre(mk[f"{S}TIB"][None], K[None], mk[f"{S}ANK"][None],
                                   0.5 * subject[f"{side}_ankle_width"] + 0.007)[0]
        assert np.linalg.norm(knee - K) < 0.02 and np.linalg.norm(ankle - A) < 0.015, (S, knee - K, ankle - A)
