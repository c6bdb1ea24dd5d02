"""Bone surfaces and point clouds from label volumes or mesh folders.

Modules
-------
extraction
    The surface of a bone mask: blurred marching cubes, Taubin smoothing, volume match, decimation.
masks
    Bone masks cleaned before surfacing (`clean_mask`).
sampling
    Point clouds on a surface (`point_cloud`) and surface distances (`surface_distance`).
bone_surfaces
    Every bone of a label volume or mesh folder as a `BoneSurface` (`load_bones`).
"""
from .bone_surfaces import BoneSurface, BoneSurfaces, load_bones, surfaces_from_labels
from .extraction import decimate, extract_surface, taubin_smooth
from .masks import clean_mask
from .sampling import PointCloud, point_cloud, surface_distance

__all__ = [
    "BoneSurface",
    "BoneSurfaces",
    "PointCloud",
    "clean_mask",
    "extract_surface",
    "point_cloud",
    "surface_distance",
    "surfaces_from_labels",
    "load_bones",
    "taubin_smooth",
    "decimate",
]
