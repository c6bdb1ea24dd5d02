"""Real bone meshes voxelised into a label volume, as a segmentation would give them (not a test module)."""
from __future__ import annotations

import json
from pathlib import Path

import trimesh


def voxelised_bones(folder: Path, label_map: dict, voxel_m: float, out: Path):
    """`personalize.io.LabelVolume` of the bones of `label_map` (bone -> label; PLY meshes in mm in `folder`)
    rasterised at `voxel_m` isotropic (`phantoms.real_anatomy.mesh_label_volume`) and written to `out`."""
    from phantoms.imaging import write_label_nifti
    from phantoms.real_anatomy import mesh_label_volume
    from personalize.io import read_label_volume

    meshes = {}
    for b in label_map:
        m = trimesh.load(folder / f"{b}.ply", process=False)
        m.apply_scale(1e-3)
        meshes[b] = m
    labels, affine, _ = mesh_label_volume(meshes, voxel=(voxel_m,) * 3, label_map=label_map)
    write_label_nifti(out / "labels.nii.gz", labels, affine)
    (out / "label_map.json").write_text(json.dumps(label_map))
    return read_label_volume(out / "labels.nii.gz", out / "label_map.json")
