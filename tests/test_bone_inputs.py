"""Bone inputs as labs give them: repaired meshes, one bad bone left out, lab file names, a whole foot,
point clouds, and names or sides the shapes contradict (refused).  Real files where the case needs them."""
from __future__ import annotations

import json
import os

import nibabel as nib
import numpy as np
import pytest
import trimesh

from personalize.cli import main
from lowerlimb.errors import InputError
from personalize.io import read_mesh_folder_detailed
from personalize.io.meshes import _load_mesh_file


def _nonmanifold(faces) -> int:
    e = np.sort(np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return int(np.sum(np.unique(e, axis=0, return_counts=True)[1] > 2))


def _link(folder, src_dir, names):
    folder.mkdir(parents=True, exist_ok=True)
    for src, dst in names.items():
        os.symlink(src_dir / f"{src}.ply", folder / f"{dst}.ply")


def _cli(args, capsys):
    capsys.readouterr()
    code = main(args)
    return code, capsys.readouterr().err.strip()


# --------------------------------------------------------------------------- repairs
def test_merging_a_zero_length_edge_drops_its_two_faces(tmp_path):
    """Two coincident vertices joined by an edge (as marching cubes leaves them on the phantom's meshes):
    merging them collapses the edge; the two faces on it must go, or their edges sit on three faces."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    v, f = s.vertices.copy(), s.faces.copy()
    a, b = s.edges_unique[0]
    on = np.flatnonzero(np.sum(np.isin(f, [a, b]), axis=1) == 2)
    m = len(v)
    v = np.vstack([v, v[a]])                          # new vertex m at a's position, on edge (m, b)
    new = []
    for fi in on:                                     # split both faces of edge (a, b) at m
        tri = list(f[fi])
        i, j = tri.index(a), tri.index(b)
        t1, t2 = tri.copy(), tri.copy()
        t1[j], t2[i] = m, m
        new += [t1, t2]
    f = np.vstack([np.delete(f, on, axis=0), new])
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and _nonmanifold(f) == 0
    mesh.export(str(tmp_path / "femur_r.ply"))
    # what the old reader did: a plain vertex merge keeps the collapsed faces
    merged = trimesh.Trimesh(v, f, process=True, validate=False)
    assert _nonmanifold(merged.faces) == 2
    got, rep = _load_mesh_file(tmp_path / "femur_r.ply")
    assert rep["collapsed_faces_removed"] == 2 and _nonmanifold(got.faces) == 0 and got.is_watertight
    assert got.volume == pytest.approx(s.volume, rel=1e-6)  # float32 PLY


def test_lhdl_ct_calcaneus_repaired_and_lab_names(shared_data, tmp_path):
    lhdl = shared_data / "bones" / "LHDL_CT"
    meshes, rep = read_mesh_folder_detailed(lhdl, bones=["calcn_r", "tibia_r"])
    cal = meshes["calcn_r"]
    # two triangles stored 8 times each made 6 edges non-manifold: 14 copies removed, the specks dropped
    assert cal.report["duplicate_faces_removed"] == 14 and cal.mesh.is_watertight
    assert _nonmanifold(cal.mesh.faces) == 0
    assert any("repeated faces" in r for r in cal.report["repairs"])
    # tibia_r (with its fibula) is preferred to tibia_no_fib_r
    assert os.path.basename(meshes["tibia_r"].source) == "tibia_r.ply" and "tibia_no_fib_r.ply" in rep["ignored_files"]
    # a lone tibia_no_fib_r is the tibia
    _link(tmp_path / "nofib", lhdl, {"tibia_no_fib_r": "tibia_no_fib_r"})
    alone, _ = read_mesh_folder_detailed(tmp_path / "nofib")
    assert list(alone) == ["tibia_r"] and len(alone["tibia_r"].mesh.split()) == 1


def test_pelvis_next_to_pelvis_no_sacrum(shared_data):
    meshes, rep = read_mesh_folder_detailed(shared_data / "bones" / "MC22", bones=["pelvis"])
    assert os.path.basename(meshes["pelvis"].source) == "pelvis_no_sacrum.ply" and "pelvis.ply" in rep["ignored_files"]


def test_one_bad_bone_drops_only_its_joints(shared_data, tmp_path, capsys):
    icl = shared_data / "bones" / "ICL_MRI"
    d = tmp_path / "bones"
    _link(d, icl, {"tibia_r": "tibia_r", "talus_r": "talus_r", "fibula_r": "fibula_r"})
    fem = trimesh.load(str(icl / "femur_r.ply"), process=False)
    # a small hole (one vertex's fan) is closed, noted
    top = int(np.argmax(fem.vertices[:, 2]))
    small = trimesh.Trimesh(fem.vertices, fem.faces[~np.any(fem.faces == top, axis=1)], process=False)
    small.export(str(tmp_path / "femur_r.ply"))
    got, _ = read_mesh_folder_detailed(tmp_path, bones=["femur_r"])
    assert got["femur_r"].report["holes_closed"] and got["femur_r"].mesh.is_watertight
    assert "small holes closed" in got["femur_r"].report["repairs"]
    # the femur's distal half missing: left out, the knee dropped naming the file, the ankle kept
    big = trimesh.Trimesh(fem.vertices, fem.faces[fem.triangles_center[:, 2] > np.median(fem.vertices[:, 2])])
    big.export(str(d / "femur_r.ply"))
    code, err = _cli(["bones", str(d), "--out", str(tmp_path / "out"), "--no-png", "--quiet"], capsys)
    assert code == 0, err
    joints = json.loads((tmp_path / "out" / "joints.json").read_text())
    lm = json.loads((tmp_path / "out" / "landmarks.json").read_text())
    assert "ankle_r" in joints["joints"] and "knee_r" not in joints["joints"]
    assert "femur_r.ply: open mesh" in joints["dropped"]["knee_r"]
    assert "femur_r.ply: open mesh" in lm["rejected"]["femur_r"]


def test_stray_specks_and_an_implausible_bone(shared_data, tmp_path):
    mc22 = shared_data / "bones" / "MC22"
    # MC22's patella_r spans 301 mm: a 40 mm patella plus two 8-face specks 26 cm away (also in tibia_r)
    meshes, _ = read_mesh_folder_detailed(mc22, bones=["patella_r"])
    pat = meshes["patella_r"]
    assert len(pat.report["islands_removed"]) == 2 and 0.035 < np.max(pat.mesh.extents) < 0.045
    # a "patella" of 30 cm without specks is no patella: left out with the reason, the femur kept
    d = tmp_path / "b"
    _link(d, shared_data / "bones" / "ICL_MRI", {"femur_r": "femur_r"})
    p = trimesh.load(str(shared_data / "bones" / "ICL_MRI" / "patella_r.ply"), process=False)
    p.apply_scale(7.0)
    p.export(str(d / "patella_r.ply"))
    meshes, rep = read_mesh_folder_detailed(d)
    assert list(meshes) == ["femur_r"] and "implausible size for a patella_r" in rep["rejected"]["patella_r"]
    with pytest.raises(InputError, match="patella_r.ply: implausible size"):
        read_mesh_folder_detailed(d, bones=["patella_r"])


def test_whole_foot_split_into_talus_calcn_toes(shared_data):
    meshes, rep = read_mesh_folder_detailed(shared_data / "bones" / "MC22", bones=["tibia_r", "talus_r", "calcn_r", "toes_r"])
    assert {"talus_r", "calcn_r", "toes_r"} <= set(meshes)
    assert any(n.startswith("foot_r.ply: whole foot split into talus_r") for n in rep["notes"])
    tal, cal = meshes["talus_r"].mesh, meshes["calcn_r"].mesh
    assert 15e-6 < tal.volume < 40e-6 and len(tal.split()) == 1          # one adult talus, 15-40 cm^3
    assert cal.volume > 2 * tal.volume
    assert meshes["toes_r"].mesh.volume < 0.2 * cal.volume


# --------------------------------------------------------------------------- names and sides
def test_tibia_named_femur_and_mirrored_femur_are_refused(shared_data, tmp_path, capsys):
    icl = shared_data / "bones" / "ICL_MRI"
    d = tmp_path / "tib"
    _link(d, icl, {"tibia_r": "femur_r"})
    code, err = _cli(["bones", str(d), "--out", str(tmp_path / "o1"), "--no-png", "--quiet"], capsys)
    assert code == 2 and err.startswith("error: ") and "\n" not in err
    assert "femur_r.ply" in err and "is this mesh a femur" in err and not (tmp_path / "o1").exists()
    m = tmp_path / "mirror"
    m.mkdir()
    fem = trimesh.load(str(icl / "femur_r.ply"), process=False)
    fem.vertices[:, 0] *= -1
    fem.invert()                                      # a left femur, outward normals, named right
    fem.export(str(m / "femur_r.ply"))
    code, err = _cli(["bones", str(m), "--out", str(tmp_path / "o2"), "--no-png", "--quiet"], capsys)
    assert code == 2 and "\n" not in err and "femur_r.ply" in err and "left bone" in err
    code, err = _cli(["bones", str(m), "--out", str(tmp_path / "o3"), "--no-png", "--quiet", "--trust-names"], capsys)
    assert code == 0, err
    flags = json.loads((tmp_path / "o3" / "landmarks.json").read_text())["bones"]["femur_r"]["flags"]
    assert "side_mismatch" in flags


def test_swapped_label_map_is_refused(tmp_path, capsys):
    from phantoms.anatomy import make_phantom
    from phantoms.imaging import label_volume
    from lowerlimb.bones import mirror_name

    lab, aff, lmap = label_volume(make_phantom(seed=3), voxel=(2e-3,) * 3, bones=["femur_l"])
    img = nib.Nifti1Image(lab.astype(np.int16), aff)
    img.header.set_xyzt_units("mm")
    nib.save(img, str(tmp_path / "labels.nii.gz"))
    (tmp_path / "map.json").write_text(json.dumps(lmap))
    (tmp_path / "swapped.json").write_text(json.dumps({mirror_name(k): v for k, v in lmap.items()}))
    args = ["bones", str(tmp_path / "labels.nii.gz"), "--no-png", "--quiet", "--label-map"]
    code, err = _cli(args + [str(tmp_path / "map.json"), "--out", str(tmp_path / "ok")], capsys)
    assert code == 0, err
    code, err = _cli(args + [str(tmp_path / "swapped.json"), "--out", str(tmp_path / "bad")], capsys)
    assert code == 2 and "\n" not in err and "labels.nii.gz" in err and "check the label map" in err
    assert not (tmp_path / "bad").exists()


# --------------------------------------------------------------------------- point clouds
def _cloud(src, frac, seed=0):
    m = trimesh.load(str(src), process=False)
    keep = np.random.default_rng(seed).random(len(m.vertices)) < frac
    return m, np.asarray(m.vertices)[keep]


def test_point_cloud_files_are_read_and_surfaced(shared_data, tmp_path):
    """A talus given as points only (PLY without faces, XYZ text, PCD): normals estimated and turned
    outward, a closed surface reconstructed near the mesh the points came from, the sampling sd stated."""
    import open3d as o3d

    from personalize.io.point_clouds import read_point_cloud, reconstruct_surface

    mesh, pts = _cloud(shared_data / "bones" / "ICL_MRI" / "talus_r.ply", 0.2)
    trimesh.PointCloud(pts).export(str(tmp_path / "a.ply"))
    np.savetxt(tmp_path / "a.xyz", pts, fmt="%.5f", header="x y z (mm)")
    o3d.io.write_point_cloud(str(tmp_path / "a.pcd"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    for name in ("a.ply", "a.xyz", "a.pcd"):
        got, nrm = read_point_cloud(tmp_path / name)
        assert nrm is None and np.allclose(got, pts, atol=1e-4), name
    surf, rep = reconstruct_surface(pts)
    assert surf.is_watertight and surf.volume == pytest.approx(mesh.volume, rel=0.03)
    # reproducible to the vertex order (threaded Poisson reordered them, and the detectors thin by index)
    again, _ = reconstruct_surface(pts)
    assert np.array_equal(again.vertices, surf.vertices) and np.array_equal(again.faces, surf.faces)
    _, d, _ = trimesh.proximity.closest_point(mesh, surf.vertices)
    assert np.median(d) < 0.3 and rep["normals"] == "estimated"          # mm
    # the same cloud as a bone folder: read, reconstructed, sampling sd in metres (sub-millimetre here)
    d2 = tmp_path / "bones"
    d2.mkdir()
    trimesh.PointCloud(pts).export(str(d2 / "talus_r.ply"))
    meshes, _ = read_mesh_folder_detailed(d2)
    r = meshes["talus_r"].report
    assert r["input"] == "point cloud" and 1e-5 < r["sampling_sd_m"] < 1e-3
    assert any("reconstructed from" in x for x in r["repairs"])
    with pytest.raises(InputError, match="b.xyz: point cloud holds 50 points"):
        np.savetxt(tmp_path / "b.xyz", pts[:50])
        read_point_cloud(tmp_path / "b.xyz")


# --------------------------------------------------------------------------- whole sets
def _length(j, a, b):
    return float(np.linalg.norm(np.subtract(j[a]["origin"], j[b]["origin"])))


@pytest.mark.slow
@pytest.mark.parametrize("name,expected", [
    ("MC22", {f"{j}_{s}" for j in ("hip", "knee", "ankle", "subtalar", "mtp") for s in "rl"}),
    ("TLEM2_MRI", {f"{j}_{s}" for j in ("hip", "knee", "ankle", "subtalar", "mtp") for s in "rl"}),
    ("VAKHUM_CT", {"hip_r", "knee_r", "ankle_r"}),        # no pelvis (hip from the femoral head), no foot
])
def test_real_sets_give_every_joint_their_bones_allow(shared_data, tmp_path, capsys, name, expected):
    from personalize.bone_set import read_bone_set

    res = {"joints": read_bone_set(shared_data / "bones" / name).joints_json()}
    joints = res["joints"]["joints"]
    assert expected <= set(joints), (set(joints), res["joints"]["dropped"])
    if name == "VAKHUM_CT":
        assert set(res["joints"]["dropped"]) == {"subtalar_r", "mtp_r"}
    else:
        for a, b in (("hip", "knee"), ("knee", "ankle")):
            r, l = _length(joints, f"{a}_r", f"{b}_r"), _length(joints, f"{a}_l", f"{b}_l")
            assert abs(r / l - 1) < 0.02, (a, b, r, l)


@pytest.mark.slow
def test_icl_bones_as_point_clouds(shared_data, tmp_path):
    """ICL_MRI given as point clouds (a random 20 % of each mesh's vertices): the hip, knee and ankle are
    built and lie within 3 stated sd of the mesh result.  Here (draw 0) 0.2-0.6 mm, 0.2-1.2 deg; over draws 0-3
    hip 0.05-0.25 mm (its pelvis-side axis 0.4-5.6 deg: thin iliac wings at a 4 mm spacing turn normals), knee
    0.2-0.6 mm / 0.1-0.4 deg, ankle 0.5-2.5 mm / 0.4-2.5 deg.  The issue's 0.5 mm / 0.5 deg is NOT met; subtalar
    (3.7-4.6 mm, or not built) is further off: the calcaneus and toes clouds hold several touching bones (0-3 mm
    apart, below the 4 mm spacing), whose gaps the reconstruction fills.  So no metatarsal head is told apart and
    the mtp, from the plantar head spheres on the bridged forefoot (23 mm, 30 deg from the mesh's: 4.4 stated sd),
    is dropped."""
    from personalize.bone_set import read_bone_set

    icl = shared_data / "bones" / "ICL_MRI"
    d = tmp_path / "clouds"
    d.mkdir()
    for i, b in enumerate(("pelvis_no_sacrum", "femur_r", "tibia_r", "fibula_r", "patella_r", "talus_r",
                           "calcn_r", "toes_r")):
        _, pts = _cloud(icl / f"{b}.ply", 0.2, seed=i)
        trimesh.PointCloud(pts).export(str(d / f"{b}.ply"))
    mesh = read_bone_set(icl).joints_json()["joints"]
    doc = read_bone_set(d).joints_json()
    cloud = doc["joints"]
    assert {"hip_r", "knee_r", "ankle_r"} <= set(cloud) and set(mesh) == {f"{j}_r" for j in
                                                                         ("hip", "knee", "ankle", "subtalar", "mtp")}
    assert "mtp_r" not in cloud and "reconstructed from points" in doc["dropped"]["mtp_r"]
    for j in ("hip_r", "knee_r", "ankle_r"):
        a, b = mesh[j], cloud[j]
        dist = np.linalg.norm(np.subtract(a["origin"], b["origin"]))
        sd = np.sqrt(np.trace(np.add(a["origin_cov"], b["origin_cov"])) / 3)
        ang = np.degrees(np.arccos(np.clip(np.array(a["rotation"])[:, 2] @ np.array(b["rotation"])[:, 2], -1, 1)))
        assert dist < 3 * sd and ang < 3 * np.hypot(a["axis_sd_deg"], b["axis_sd_deg"]), (j, dist, sd, ang)


def test_a_fibula_joined_to_the_tibia_still_fixes_its_sides(shared_data, tmp_path):
    """LHDL_CT's tibia as a point cloud (a random 20 % of its vertices): the reconstruction joins the fibula to
    the tibia at the tibiofibular joints, so the fibula is no longer a component of its own.  Its shaft, still
    apart from the tibia's in the middle third, gives the lateral side: the knee and ankle axes keep the mesh
    result's direction (9.2 and 0.8 deg; 171 and 179 deg when the lowest point, the fibula's malleolus, was
    taken for the medial malleolus)."""
    from personalize.landmarks import detect_landmarks
    from personalize.surfaces import load_bones

    _, pts = _cloud(shared_data / "bones" / "LHDL_CT" / "tibia_r.ply", 0.2, seed=2)
    trimesh.PointCloud(pts).export(str(tmp_path / "tibia_r.ply"))
    (tmp_path / "mesh").mkdir()
    trimesh.load(str(shared_data / "bones" / "LHDL_CT" / "tibia_r.ply"), process=False).export(
        str(tmp_path / "mesh" / "tibia_r.ply"))
    mesh = detect_landmarks(load_bones(tmp_path / "mesh"), trust_names=True).bones["tibia_r"]
    cloud = detect_landmarks(load_bones(tmp_path), trust_names=True).bones["tibia_r"]
    assert any("fibula joined to the tibia" in n for n in cloud.notes)
    for ax in ("knee_axis", "ankle_axis"):
        ang = np.degrees(np.arccos(mesh.axes[ax].direction @ cloud.axes[ax].direction))
        assert ang < 15.0, (ax, ang)
