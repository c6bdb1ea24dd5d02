"""Readers: label volumes (NIfTI, NRRD), label maps, mesh folders, unit detection,
bad input (one-line InputError, exit 2, nothing written), and the real meshes."""
from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np
import pytest
import trimesh

from lowerlimb.errors import InputError
from personalize.io import (detect_mesh_unit, read_label_map, read_label_volume, read_mesh_folder,
                            read_mesh_folder_detailed)
from personalize.surfaces import load_bones


def _cli(args):
    """Run ``personalize`` in-process; returns (exit code)."""
    import personalize.cli as cli

    if len(cli.app.registered_commands) == 1:  # Typer runs a lone command without its name
        args = args[1:]
    return cli.main(args)


def _labels():
    lab = np.zeros((30, 24, 40), np.uint8)
    lab[5:25, 4:20, 5:35] = 2  # a 20 x 16 x 30 voxel box of femur_r
    return lab


AFF_MM = np.array([[-0.8, 0, 0, 10.0], [0, 0.8, 0, -20.0], [0, 0, 1.5, 30.0], [0, 0, 0, 1]])


def test_nifti_and_nrrd_agree(tmp_path):
    lab = _labels()
    img = nib.Nifti1Image(lab, AFF_MM)
    img.header.set_xyzt_units("mm")
    nib.save(img, str(tmp_path / "a.nii.gz"))
    nrrd.write(str(tmp_path / "a.nrrd"), lab, {"space": "right-anterior-superior",
                                                "space directions": AFF_MM[:3, :3].T.tolist(),
                                                "space origin": AFF_MM[:3, 3].tolist()})
    a = read_label_volume(tmp_path / "a.nii.gz")
    b = read_label_volume(tmp_path / "a.nrrd")
    for v in (a, b):
        assert v.labels.dtype == np.uint8 and np.array_equal(v.labels, lab)
        assert np.allclose(v.affine_m, AFF_MM * np.array([[1e-3], [1e-3], [1e-3], [1.0]]))
        assert np.allclose(v.spacing_m, [0.8e-3, 0.8e-3, 1.5e-3])
        assert v.unit == "mm" and v.label_map_source == "default"


def test_nifti_in_metres_and_float_labels(tmp_path):
    aff_m = AFF_MM.copy()
    aff_m[:3, :] *= 1e-3
    img = nib.Nifti1Image(_labels().astype(np.float32), aff_m)
    img.header.set_xyzt_units("meter")
    nib.save(img, str(tmp_path / "m.nii"))
    v = read_label_volume(tmp_path / "m.nii")
    assert v.unit == "m" and np.allclose(v.affine_m, aff_m)
    assert np.issubdtype(v.labels.dtype, np.integer) and v.labels.max() == 2


def test_label_map_json_both_directions(tmp_path):
    (tmp_path / "a.json").write_text(json.dumps({"pelvis_no_sacrum": 1, "femur_r": 7}))
    (tmp_path / "b.json").write_text(json.dumps({"1": "pelvis", "7": "femur_r"}))
    a, _ = read_label_map(tmp_path / "a.json")
    b, _ = read_label_map(tmp_path / "b.json")
    assert a == b == {"pelvis": 1, "femur_r": 7}
    (tmp_path / "c.json").write_text(json.dumps({"femur_x": 3}))
    with pytest.raises(InputError, match="unknown bone name 'femur_x'"):
        read_label_map(tmp_path / "c.json")
    (tmp_path / "d.json").write_text(json.dumps({"femur_r": 3, "tibia_r": 3}))
    with pytest.raises(InputError, match="label 3 is used for two bones"):
        read_label_map(tmp_path / "d.json")
    (tmp_path / "e.json").write_text("{not json")
    with pytest.raises(InputError, match="JSON"):
        read_label_map(tmp_path / "e.json")


def test_label_map_beside_volume_is_used(tmp_path):
    lab = _labels()
    nib.save(nib.Nifti1Image(lab, AFF_MM), str(tmp_path / "labels.nii.gz"))
    (tmp_path / "label_map.json").write_text(json.dumps({"tibia_l": 2}))
    surf = load_bones(tmp_path / "labels.nii.gz")
    assert list(surf) == ["tibia_l"]
    # the box is 20 x 16 x 30 voxels of 0.8 x 0.8 x 1.5 mm
    assert surf["tibia_l"].report["mask_volume_m3"] == pytest.approx(20 * 16 * 30 * 0.8 * 0.8 * 1.5e-9)
    # a smoothed box loses its sharp edges, but not more than a few percent
    assert surf["tibia_l"].volume == pytest.approx(20 * 16 * 30 * 0.96e-9, rel=0.01)


@pytest.mark.parametrize("case,problem", [
    ("missing", "not found"),
    ("garbage", "cannot read NIfTI"),
    ("intensity", "not an integer label map"),
    ("empty", "label volume is empty"),
    ("fourd", "must be 3-D"),
    ("units", "implausible size for femur_r"),
])
def test_bad_label_volumes(tmp_path, case, problem):
    path = tmp_path / "v.nii.gz"
    if case == "garbage":
        path.write_bytes(b"\x1f\x8b this is not a nifti file")
    elif case == "intensity":
        nib.save(nib.Nifti1Image(np.random.default_rng(0).random((8, 8, 8)).astype(np.float32), AFF_MM), str(path))
    elif case == "empty":
        nib.save(nib.Nifti1Image(np.zeros((8, 8, 8), np.uint8), AFF_MM), str(path))
    elif case == "fourd":
        nib.save(nib.Nifti1Image(np.ones((4, 4, 4, 3), np.uint8), AFF_MM), str(path))
    elif case == "units":  # spacing written in metres while the header says mm
        img = nib.Nifti1Image(_labels(), AFF_MM * np.array([[1e-3], [1e-3], [1e-3], [1.0]]))
        img.header.set_xyzt_units("mm")
        nib.save(img, str(path))
    with pytest.raises(InputError, match=problem) as exc:
        load_bones(path)
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)


# --------------------------------------------------------------------------- meshes
def _capsule(length_m, radius_m):
    return trimesh.creation.capsule(height=length_m - 2 * radius_m, radius=radius_m, count=[24, 24])


def _write_folder(folder: Path, scale: float, bones=("femur_r", "tibia_r", "patella_r"), ext="ply"):
    folder.mkdir(parents=True, exist_ok=True)
    sizes = {"femur_r": (0.44, 0.015), "tibia_r": (0.38, 0.014), "patella_r": (0.045, 0.012),
             "pelvis_no_sacrum": (0.25, 0.05), "toes_r": (0.08, 0.01)}
    out = {}
    for b in bones:
        m = _capsule(*sizes[b])
        m.apply_scale(scale)
        m.export(str(folder / f"{b}.{ext}"))
        out[b] = m
    return out


@pytest.mark.parametrize("dtype", [np.int64, float])
def test_unique_rows_is_numpys_unique_along_rows(dtype):
    from personalize.io.mesh_repair import _unique_rows

    rng = np.random.default_rng(3)
    a = rng.integers(0, 6, (4000, 3)).astype(dtype) * (0.37 if dtype is float else 1)
    want = np.unique(a, axis=0, return_index=True, return_inverse=True, return_counts=True)
    got = _unique_rows(a, return_index=True, return_inverse=True, return_counts=True)
    assert len(want[0]) == 216  # all 6**3 rows, each repeated
    for w, g in zip(want, got):
        assert np.array_equal(np.reshape(w, -1), np.reshape(g, -1)) and np.shape(w)[0] == np.shape(g)[0]
    assert _unique_rows(a[:0]).shape == (0, 3) and np.array_equal(_unique_rows(a[:1]), a[:1])


def test_each_bone_step_is_announced_before_it_runs(tmp_path):
    written = _write_folder(tmp_path / "bones", 1e3, bones=("femur_r", "patella_r"))
    done, said = [], []
    got = load_bones(tmp_path / "bones", target_faces=500, eager_points=False, progress=done.append,
                     status=said.append)
    assert done == ["femur_r", "patella_r"]  # one step per bone, as without status
    for b in done:
        n = len(written[b].faces)
        size = (tmp_path / "bones" / f"{b}.ply").stat().st_size / 1e6
        assert [m for m in said if m.startswith(b + ":")] == [
            f"{b}: reading {b}.ply ({size:.1f} MB)", f"{b}: checking and repairing {n:,} faces",
            f"{b}: decimating {n:,} faces to 500"]
    quiet = load_bones(tmp_path / "bones", target_faces=500, eager_points=False)
    assert all(np.array_equal(got[b].mesh.vertices, quiet[b].mesh.vertices) for b in done)


@pytest.mark.parametrize("scale,unit,ext", [(1e3, "mm", "ply"), (1.0, "m", "stl"), (1e3, "mm", "obj")])
def test_mesh_folder_units(tmp_path, scale, unit, ext):
    written = _write_folder(tmp_path / "bones", scale, bones=("femur_r", "patella_r", "pelvis_no_sacrum"), ext=ext)
    meshes, rep = read_mesh_folder_detailed(tmp_path / "bones")
    assert rep["unit"] == unit
    assert set(meshes) == {"femur_r", "patella_r", "pelvis"}
    for b, mi in meshes.items():
        src = "pelvis_no_sacrum" if b == "pelvis" else b
        assert mi.mesh.volume == pytest.approx(written[src].volume / scale**3, rel=1e-4)
        assert np.max(mi.mesh.extents) < 0.5
    assert set(read_mesh_folder(tmp_path / "bones")) == {"femur_r", "patella_r", "pelvis"}


def test_unit_detection_ranges():
    assert detect_mesh_unit("femur_l", 420.0, "f") == "mm"
    assert detect_mesh_unit("femur_l", 0.42, "f") == "m"
    assert detect_mesh_unit("patella_r", 45.0, "f") == "mm"
    with pytest.raises(InputError, match="implausible size for a femur_l"):
        detect_mesh_unit("femur_l", 42.0, "f")  # centimetres: neither mm nor m


def test_mixed_and_implausible_units(tmp_path):
    _write_folder(tmp_path / "mixed", 1e3, bones=("femur_r",))
    _write_folder(tmp_path / "mixed", 1.0, bones=("tibia_r", "patella_r"))
    with pytest.raises(InputError, match="femur_r.ply: units differ"):
        read_mesh_folder(tmp_path / "mixed")
    _write_folder(tmp_path / "cm", 1e2, bones=("femur_r",))
    with pytest.raises(InputError, match="femur_r.ply: implausible size"):
        read_mesh_folder(tmp_path / "cm")


def test_inside_out_mesh_refused_or_fixed(tmp_path):
    folder = tmp_path / "inv"
    written = _write_folder(folder, 1e3, bones=("femur_r",))
    inv = written["femur_r"].copy()
    inv.invert()
    inv.export(str(folder / "femur_r.ply"))
    with pytest.raises(InputError, match="femur_r.ply: inside-out mesh"):
        read_mesh_folder(folder)
    meshes, _ = read_mesh_folder_detailed(folder, fix_orientation=True)
    assert meshes["femur_r"].report["inverted"] and meshes["femur_r"].mesh.volume > 0


def test_partly_flipped_winding_is_repaired(tmp_path):
    folder = tmp_path / "wind"
    written = _write_folder(folder, 1e3, bones=("femur_r",))
    m = written["femur_r"].copy()
    faces = m.faces.copy()
    faces[:40] = faces[:40, ::-1]  # a patch of faces wound the wrong way
    trimesh.Trimesh(m.vertices, faces, process=False).export(str(folder / "femur_r.ply"))
    meshes, _ = read_mesh_folder_detailed(folder)
    got = meshes["femur_r"]
    assert got.report["winding_repaired_components"] == 1
    assert got.mesh.is_winding_consistent and got.mesh.volume == pytest.approx(m.volume * 1e-9, rel=1e-6)


def test_open_and_nonmanifold_meshes(tmp_path):
    folder = tmp_path / "open"
    written = _write_folder(folder, 1e3, bones=("femur_r", "toes_r"))
    # a big hole: drop all faces above the middle of the femur
    f = written["femur_r"]
    keep = f.triangles_center[:, 2] < 0
    trimesh.Trimesh(f.vertices, f.faces[keep]).export(str(folder / "femur_r.ply"))
    # one bad bone does not stop the rest: it is left out and listed, unless asked for by name
    meshes, rep = read_mesh_folder_detailed(folder)
    assert set(meshes) == {"toes_r"} and "femur_r.ply: open mesh" in rep["rejected"]["femur_r"]
    with pytest.raises(InputError, match="femur_r.ply: open mesh"):
        read_mesh_folder(folder, bones=["femur_r"])
    # toes may be open (as in the real data): flagged, not refused
    t = written["toes_r"]
    trimesh.Trimesh(t.vertices, t.faces[t.triangles_center[:, 2] < 0]).export(str(folder / "toes_r.ply"))
    meshes, _ = read_mesh_folder_detailed(folder, bones=["toes_r"])
    assert meshes["toes_r"].report["open"] is True
    # three faces on one edge: non-manifold
    v = np.array([[0, 0, 0], [0.45, 0, 0], [0, 0.01, 0], [0, -0.01, 0], [0, 0, 0.01]]) * 1e3
    nm = trimesh.Trimesh(v, [[0, 1, 2], [1, 0, 3], [0, 1, 4]], process=False)
    nm.export(str(folder / "femur_r.ply"))
    with pytest.raises(InputError, match="femur_r.ply: non-manifold mesh .1 edges.*open after repair"):
        read_mesh_folder(folder, bones=["femur_r"])


def test_small_mesh_islands_removed_and_reported(tmp_path):
    folder = tmp_path / "isl"
    written = _write_folder(folder, 1e3, bones=("femur_r",))
    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    speck.apply_translation([100, 0, 0])
    trimesh.util.concatenate([written["femur_r"], speck]).export(str(folder / "femur_r.ply"))
    meshes, _ = read_mesh_folder_detailed(folder)
    assert meshes["femur_r"].report["islands_removed"] == [{"faces": 80}]
    assert len(meshes["femur_r"].mesh.split()) == 1


# --------------------------------------------------------------------------- CLI
def test_cli_label_volume(tmp_path):
    lab = _labels()
    img = nib.Nifti1Image(lab, AFF_MM)
    img.header.set_xyzt_units("mm")
    nib.save(img, str(tmp_path / "seg.nii.gz"))
    out = tmp_path / "out"
    assert _cli(["surfaces", str(tmp_path / "seg.nii.gz"), "--out", str(out), "--quiet", "--points"]) == 0
    summary = json.loads((out / "surfaces.json").read_text())
    assert summary["units"] == "m" and summary["mesh_units"] == "mm"
    femur = summary["bones"]["femur_r"]
    ply = trimesh.load(str(out / "femur_r.ply"))
    assert b"comment units mm" in (out / "femur_r.ply").read_bytes()[:400]
    assert len(ply.faces) == femur["faces"] and len(ply.vertices) == femur["vertices"]
    # PLY in mm, JSON in m, both in the scanner frame of the NIfTI
    assert np.allclose(ply.bounds * 1e-3, [femur["bbox_min_m"], femur["bbox_max_m"]], atol=1e-9)
    assert ply.volume * 1e-9 == pytest.approx(femur["volume_m3"], rel=1e-5)
    corner = AFF_MM @ np.array([5, 4, 5, 1.0])  # first voxel centre of the box
    box_min = np.minimum(corner[:3], (AFF_MM @ np.array([24, 19, 34, 1.0]))[:3])
    assert np.allclose(ply.bounds[0], box_min - [0.4, 0.4, 0.75], atol=0.5)
    pts = (out / "femur_r_points.ply").read_bytes()
    assert b"property float nx" in pts[:600]


@pytest.mark.parametrize("case", ["missing", "intensity", "absent_bone", "empty_label", "implausible_mesh",
                                  "out_is_input"])
def test_cli_bad_input_exit_2_nothing_written(tmp_path, capsys, case):
    out = tmp_path / "out"
    args = []
    if case == "missing":
        src = tmp_path / "nope.nii.gz"
    elif case in ("intensity", "absent_bone", "empty_label"):
        src = tmp_path / "v.nii.gz"
        data = np.random.default_rng(0).random((8, 8, 8)).astype(np.float32) if case == "intensity" else _labels()
        nib.save(nib.Nifti1Image(data, AFF_MM), str(src))
        if case == "absent_bone":
            args = ["--bones", "femur_l"]
        if case == "empty_label":
            args = ["--bones", "femur_r,tibia_r"]
    elif case == "out_is_input":
        src = out = tmp_path / "bones"
        _write_folder(src, 1e3, bones=("femur_r",))
        before = (src / "femur_r.ply").read_bytes()
    else:
        src = tmp_path / "bones"
        _write_folder(src, 1e2, bones=("femur_r",))
    capsys.readouterr()
    code = _cli(["surfaces", str(src), "--out", str(out), "--quiet", *args])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("error: ") and "\n" not in err and str(src) in err
    if case == "out_is_input":
        assert sorted(p.name for p in out.iterdir()) == ["femur_r.ply"]
        assert (src / "femur_r.ply").read_bytes() == before
    else:
        assert not out.exists() or not any(out.iterdir())
    assert not any(".staging" in p.name for p in tmp_path.iterdir())


# --------------------------------------------------------------------------- real data
def test_real_icl_mri_meshes(shared_data):
    folder = shared_data / "bones" / "ICL_MRI"
    bones = load_bones(folder, eager_points=False)
    assert set(bones) == {"pelvis", "femur_r", "tibia_r", "fibula_r", "patella_r", "talus_r", "calcn_r", "toes_r"}
    assert Path(bones["pelvis"].source).name == "pelvis_no_sacrum.ply"
    for name, b in bones.items():
        assert b.report["units_detected"] == "mm", name
        assert b.volume > 0
    femur = bones["femur_r"]
    assert 0.40 < np.max(femur.mesh.extents) < 0.55  # metres: an adult femur
    assert femur.mesh.is_watertight
    assert 500e-6 < femur.volume < 800e-6
    assert bones["toes_r"].report["open"] is True  # open in the data, flagged
    assert bones["calcn_r"].report["winding_repaired_components"] >= 1
    # points on the surface, normals outward: moving along them leaves the bone
    pts, nrm = femur.points, femur.normals
    inside = femur.mesh.contains(pts[:300] + 1e-3 * nrm[:300])
    assert inside.mean() < 0.05


def test_small_hole_closed_and_unmapped_labels_reported(tmp_path):
    folder = tmp_path / "hole"
    written = _write_folder(folder, 1e3, bones=("femur_r",))
    f = written["femur_r"]
    top = np.argmax(f.vertices[:, 2])  # the capsule's pole: remove its fan of faces
    keep = ~np.any(f.faces == top, axis=1)
    trimesh.Trimesh(f.vertices, f.faces[keep]).export(str(folder / "femur_r.ply"))
    meshes, _ = read_mesh_folder_detailed(folder)
    assert meshes["femur_r"].report["holes_closed"] is True and meshes["femur_r"].mesh.is_watertight
    assert meshes["femur_r"].mesh.volume == pytest.approx(f.volume * 1e-9, rel=1e-3)
    lab = _labels()
    lab[0:2, 0:2, 0:2] = 40  # e.g. a muscle label the map does not know
    nib.save(nib.Nifti1Image(lab, AFF_MM), str(tmp_path / "v.nii.gz"))
    surf = load_bones(tmp_path / "v.nii.gz")
    assert list(surf) == ["femur_r"] and surf["femur_r"].report["unmapped_labels"] == [40]
