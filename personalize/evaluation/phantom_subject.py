"""Phantom subject folders for tests, the demo and benchmarks: a `personalize run` SUBJECT_DIR with its truth."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from lowerlimb.atomic import staged_dir

__all__ = ["SHORT_TRIALS", "write_phantom_subject"]

#: trial options of a small phantom subject (tests, demo): one gait cycle, one crouch, a short star-arc
SHORT_TRIALS = dict(gait_trials=1, gait_cycles=1.0, crouch_angles=(0,), crouch_duration=2.0, functional_ranges=(45,),
                    functional_time_scale=0.5, static_duration=0.5)


def write_phantom_subject(out: str | Path, seed: int = 0, *, voxel_mm: float = 2.0, short: bool = True,
                          bones=None, progress: Callable[[str], None] | None = None, skin: bool = True) -> Path:
    """Write a phantom SUBJECT_DIR (labels.nii.gz, label_map.json, C3D trials, subject.json, truth.json, truth/).

    The same content as ``personalize phantom`` plus its motion trials, without the
    exact reference meshes (the pipeline does not read them).  `bones` restricts
    the labelled bones (e.g. one side only); ``skin=False`` leaves out the body/skin label
    (a bone-only volume: the pelvis registration then uses the soft-tissue prior).  Staged:
    published only when complete.
    """
    from phantoms import make_phantom
    from phantoms.subject import write_subject

    say = progress or (lambda m: None)
    say(f"phantom {seed}: label volume ({voxel_mm:g} mm) and motion trials")
    with staged_dir(out) as stage:
        write_subject(stage, make_phantom(seed=seed), voxel=(voxel_mm * 1e-3,) * 3, seed=seed, bones=bones,
                      trials=SHORT_TRIALS if short else None, meshes=False, progress=say, skin=skin)
    return Path(out)

