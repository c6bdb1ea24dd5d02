"""Readers for bone geometry: label volumes (NIfTI, NRRD), folders of bone meshes, point clouds.

Everything leaves this module in SI units: affines map voxel indices to metres,
meshes are in metres.  The frame is the input's own (scanner) frame: NIfTI world
coordinates (RAS+) or the NRRD ``space``; nothing is re-oriented.

A mesh file's unit (m or mm) is decided from the bones' sizes (`personalize.io.units`).

Modules
-------
label_volumes
    Integer label volumes and their label maps (`read_label_volume`, `read_label_map`).
meshes
    Folders of bone meshes or point clouds (`read_mesh_folder_detailed`).
mesh_repair
    Checks and repairs of one bone mesh (`check_and_repair_mesh`).
units
    Plausible bone sizes and the unit decision (`detect_mesh_unit`).
point_clouds
    Bones given as points: reading, surface reconstruction, sampling uncertainty.
whole_foot
    A whole foot given as one mesh, split into talus, calcn and toes.
"""
from .label_volumes import (VOLUME_SUFFIXES, LabelVolume, is_label_volume_path, read_label_map,
                            read_label_volume, read_tissue_label)
from .mesh_repair import check_and_repair_mesh
from .meshes import MESH_SUFFIXES, POINT_SUFFIXES, MeshInput, read_mesh_folder, read_mesh_folder_detailed
from .units import PLAUSIBLE_EXTENT_M, detect_mesh_unit

__all__ = [
    "LabelVolume",
    "MeshInput",
    "PLAUSIBLE_EXTENT_M",
    "VOLUME_SUFFIXES",
    "MESH_SUFFIXES",
    "POINT_SUFFIXES",
    "read_label_volume",
    "read_label_map",
    "read_tissue_label",
    "read_mesh_folder",
    "read_mesh_folder_detailed",
    "check_and_repair_mesh",
    "is_label_volume_path",
    "detect_mesh_unit",
]
