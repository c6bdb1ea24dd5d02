"""A fibula labelled with its tibia (one label, touching at both tibiofibular joints) is parted again:
`surfaces.masks.split_fibula` on real bones (LHDL_CT of ../shared/data, voxelised at 1.3 mm)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

VOXEL = 1.3e-3


def _mesh_m(path):
    m = trimesh.load(path, process=False)
    if m.extents.max() > 10.0:        # the data set's meshes are in mm
        m.apply_scale(1e-3)
    return m


@pytest.fixture(scope="module")
def lhdl(shared_data, tmp_path_factory):
    """LHDL_CT's tibia_r (the fibula is its second component) and tibia_no_fib_r, each as the only label of a volume."""
    from phantoms.imaging import write_label_nifti
    from phantoms.real_anatomy import mesh_label_volume

    folder = shared_data / "bones" / "LHDL_CT"
    root = tmp_path_factory.mktemp("fibula_split")
    out = {}
    for name, file in (("with_fibula", "tibia_r.ply"), ("tibia_only", "tibia_no_fib_r.ply")):
        mesh = _mesh_m(folder / file)
        labels, affine, _ = mesh_label_volume({"tibia_r": mesh}, voxel=(VOXEL,) * 3, label_map={"tibia_r": 4})
        d = root / name
        d.mkdir()
        write_label_nifti(d / "labels.nii.gz", labels, affine)
        (d / "label_map.json").write_text(json.dumps({"tibia_r": 4}))
        out[name] = d
    out["meshes"] = folder
    return out


def test_fibula_labelled_with_the_tibia_is_parted_at_the_joints(lhdl):
    """The one-label tibia + fibula comes out as two components; the fibula landmarks (fibular head HFB, lateral
    malleolus ANK) lie within 2 mm of those the mesh pair gives (measured 0.3 and 0.5 mm), and the tibia's own
    (tuberosity, medial malleolus) within 3 mm (1.0 mm each; without the split 77 and 56 mm: the fibula then
    made the tibia's frame).  landmarks.json says where the fibula came from."""
    from personalize.bone_set import analyse_bones
    from personalize.io import read_label_volume
    from personalize.surfaces import load_bones, surfaces_from_labels

    d = lhdl["with_fibula"]
    vol = read_label_volume(d / "labels.nii.gz", d / "label_map.json")
    surf = surfaces_from_labels(vol, eager_points=False)
    rep = surf["tibia_r"].report["fibula_split"]
    assert 0 < rep["erosion_m"] <= 0.004
    # the fibula is about a sixth of the pair's volume
    assert 0.08 < rep["fibula_voxels"] / surf["tibia_r"].report["voxels"] < 0.25
    assert len(surf["tibia_r"].mesh.split(only_watertight=False)) >= 2
    labels = analyse_bones(surf, input=d / "labels.nii.gz")
    ref = analyse_bones(load_bones(lhdl["meshes"], bones=["tibia_r"], eager_points=False), input=lhdl["meshes"])
    for bone, names, tol in (("fibula_r", ("RHFB", "RANK"), 0.002), ("tibia_r", ("RTTB", "RMMA"), 0.003)):
        for n in names:
            a = labels.landmarks.bones[bone].landmarks[n].position
            b = ref.landmarks.bones[bone].landmarks[n].position
            assert np.linalg.norm(a - b) < tol, (n, np.linalg.norm(a - b))
    doc = labels.landmarks_json()
    assert "parted from the tibia_r label" in doc["inputs"]["tibia_r"]["fibula_split"]["note"]
    assert any("second component of tibia_r" in n for n in doc["bones"]["fibula_r"]["notes"])


def test_tibia_alone_is_not_split(lhdl):
    """A tibia label without a fibula has no long second core at any erosion up to 4 mm: nothing is parted."""
    from personalize.io import read_label_volume
    from personalize.surfaces import surfaces_from_labels

    d = lhdl["tibia_only"]
    surf = surfaces_from_labels(read_label_volume(d / "labels.nii.gz", d / "label_map.json"), eager_points=False)
    assert "fibula_split" not in surf["tibia_r"].report
    assert len(surf["tibia_r"].mesh.split(only_watertight=False)) == 1
