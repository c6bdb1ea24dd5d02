"""A complete phantom subject folder: what a user brings to ``personalize run``.

``write_subject`` writes the imaging half (``labels.nii.gz``, ``label_map.json``,
``meshes/``; the label volume carries the pelvis's skin envelope, label ``skin``) and, for two-legged phantoms, the motion half (``static.c3d``,
gait, crouch and functional trials, ``subject.json``, ``truth/``), with one
``truth.json`` holding the anatomy, the joints and the knee laws.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterable

from .anatomy import Phantom
from .imaging import write_phantom


def write_subject(out_dir: str | os.PathLike, ph: Phantom, *, voxel=(1e-3, 1e-3, 1e-3), noise: float = 0.0,
                  seed: int = 0, motion: bool = True, trials: dict | None = None, fov=None,
                  bones: Iterable[str] | None = None, meshes: bool = True,
                  progress: Callable[[str], None] | None = None, skin: bool = True,
                  physes: float = 0.0) -> dict[str, Path]:
    """Write a phantom subject folder into `out_dir` (stage it with `lowerlimb.atomic.staged_dir`).

    Parameters
    ----------
    out_dir : folder
    ph : Phantom
    voxel : (3,) voxel spacing, metres
    noise : segmentation noise level 0..1
    seed : seeds the segmentation noise and the motion (soft-tissue artefact, marker noise, knee laws)
    motion : also write the motion trials (needs a two-legged phantom)
    trials : keyword arguments for `phantoms.motion.make_trials` (e.g. ``gait_trials=1``)
    fov, bones, meshes, progress, physes : as for `phantoms.imaging.write_phantom`
    skin : also label the pelvis's soft-tissue envelope (label ``skin``; the markers of the motion
        trials sit on it: both use the tissue drawn from `seed`)

    Returns
    -------
    dict of written paths by role (motion entries under ``"motion"``).
    """
    extra: dict = {}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if motion:
        from .motion import write_trials

        extra = write_trials(out, ph, seed, progress=progress, **(trials or {}))
    paths = write_phantom(out, ph, voxel=voxel, noise=noise, seed=seed, fov=fov, bones=bones,
                          progress=progress, extra_truth=extra, meshes=meshes, skin=skin, physes=physes)
    if motion:
        paths["motion"] = out
    return paths
