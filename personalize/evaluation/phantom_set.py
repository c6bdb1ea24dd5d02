"""The phantom validation set: random phantom subjects drawn from one seed, written on demand.

`draw_subjects` draws N subjects (anatomy, imaging resolution, segmentation
noise, soft-tissue artefact and marker noise); each is a `PhantomSpec` stored as
``phantom.json`` in its subject folder.  `validation_job`, the dask task body of
`personalize.evaluation.validate.run_validation`, first materialises the
subject folder (`ensure_phantom_subject`) and then runs the per-subject job on it.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from lowerlimb.atomic import staged_dir, write_text
from lowerlimb.errors import InputError

from personalize.cohort import DEFAULT_JOB
from personalize.cohort.jobs import resolve_job

#: marker of a fully written phantom subject (written after everything else)
GENERATED = "generated.json"
SPEC = "phantom.json"
SURFACE_JOB = "personalize.evaluation.phantom_set:phantom_surfaces_job"

#: default ranges of the random draws (uniform unless noted)
DEFAULT_RANGES = {
    "stature_m": (1.50, 1.95),
    "femoral_anteversion_deg": (13.0, 7.0, -10.0, 40.0),   # normal: mean, sd, clip lo, hi
    "neck_shaft_deg": (128.0, 5.0, 112.0, 145.0),
    "tibial_torsion_deg": (25.0, 8.0, -5.0, 50.0),
    "asymmetry": (-0.03, 0.03),
    "variation": (0.02, 0.06),
    "inplane_mm": (0.8, 1.5),       # MRI in-plane voxel size
    "slice_mm": (1.0, 3.0),         # MRI slice thickness (random axis)
    "segmentation_noise": (0.0, 0.5),
    "sta_scale": (0.5, 1.5),        # soft-tissue artefact amplitude x the phantom's default
    "marker_noise_mm": (0.2, 1.0),  # marker position noise sd
}


@dataclass(frozen=True)
class PhantomSpec:
    """Random draws of one validation subject (SI units except where named).

    Attributes
    ----------
    subject : str
    seed : int
        Phantom seed (size variation, scanner placement, noise, motion).
    params : dict
        `phantoms.PhantomParams` fields (stature m, angles deg, ...).
    voxel_mm : tuple of 3 floats
        Label-volume voxel size, mm.
    segmentation_noise : float
        `phantoms.imaging` noise level 0..1.
    sta_scale : float
        Soft-tissue artefact amplitude factor.
    marker_noise_m : float
        Marker noise sd, metres.
    bones : tuple of str or None
        Bones written (None: all).
    motion : bool
        Whether motion trials are written.
    """

    subject: str
    seed: int
    params: dict
    voxel_mm: tuple
    segmentation_noise: float
    sta_scale: float
    marker_noise_m: float
    bones: tuple | None = None
    motion: bool = True

    def to_json(self) -> dict:
        d = asdict(self)
        d["voxel_mm"] = list(self.voxel_mm)
        d["bones"] = None if self.bones is None else list(self.bones)
        d["units"] = {"voxel": "mm", "marker_noise": "m", "stature": "m", "angles": "deg"}
        return d

    @classmethod
    def from_json(cls, d: dict) -> "PhantomSpec":
        return cls(subject=d["subject"], seed=int(d["seed"]), params=dict(d["params"]),
                   voxel_mm=tuple(float(v) for v in d["voxel_mm"]), segmentation_noise=float(d["segmentation_noise"]),
                   sta_scale=float(d["sta_scale"]), marker_noise_m=float(d["marker_noise_m"]),
                   bones=None if d.get("bones") is None else tuple(d["bones"]), motion=bool(d.get("motion", True)))

    def factors(self) -> dict:
        """Flat table of the draws (for metrics.csv)."""
        return {"phantom_seed": self.seed, **{k: v for k, v in self.params.items()},
                "voxel_x_mm": self.voxel_mm[0], "voxel_y_mm": self.voxel_mm[1], "voxel_z_mm": self.voxel_mm[2],
                "segmentation_noise": self.segmentation_noise, "sta_scale": self.sta_scale,
                "marker_noise_mm": self.marker_noise_m * 1e3}


def draw_subjects(n: int, seed: int, *, ranges: dict | None = None, bones: Sequence[str] | None = None,
                  motion: bool = True) -> list[PhantomSpec]:
    """Draw `n` phantom subjects from `seed` (reproducible; subject i depends only on seed and i).

    Uniform draws in ``ranges[key] = (lo, hi)``; truncated normals for
    ``(mean, sd, lo, hi)``.  The slice axis of the anisotropic voxel is random.
    """
    if not (1 <= n <= 10000):
        raise InputError("--subjects", f"{n} is outside 1-10000")
    if seed < 0:
        raise InputError("--seed", f"{seed} must be >= 0")
    r = dict(DEFAULT_RANGES, **(ranges or {}))
    out = []
    for i, ss in enumerate(np.random.SeedSequence([int(seed), 7919]).spawn(n)):
        rng = np.random.default_rng(ss)

        def draw(key):
            v = r[key]
            if len(v) == 4:
                return float(np.clip(rng.normal(v[0], v[1]), v[2], v[3]))
            return float(rng.uniform(v[0], v[1]))

        params = {"stature": draw("stature_m"), "femoral_anteversion_deg": draw("femoral_anteversion_deg"),
                  "neck_shaft_deg": draw("neck_shaft_deg"), "tibial_torsion_deg": draw("tibial_torsion_deg"),
                  "asymmetry": draw("asymmetry"), "variation": draw("variation")}
        inplane, thick = draw("inplane_mm"), draw("slice_mm")
        voxel = [inplane] * 3
        voxel[int(rng.integers(3))] = thick
        out.append(PhantomSpec(subject=f"phantom_{i + 1:03d}", seed=int(ss.generate_state(1)[0] % (2**31 - 1)),
                               params=params, voxel_mm=tuple(round(v, 4) for v in voxel),
                               segmentation_noise=draw("segmentation_noise"), sta_scale=draw("sta_scale"),
                               marker_noise_m=draw("marker_noise_mm") * 1e-3,
                               bones=None if bones is None else tuple(bones), motion=motion))
    return out


def read_spec(subject_dir: str | os.PathLike) -> PhantomSpec:
    p = Path(subject_dir) / SPEC
    try:
        return PhantomSpec.from_json(json.loads(p.read_text(encoding="utf-8")))
    except FileNotFoundError:
        raise InputError(p, "not found (not a validation phantom subject)") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(p, f"unreadable phantom spec ({type(exc).__name__}: {exc})") from None


def ensure_phantom_subject(subject_dir: str | os.PathLike, spec: PhantomSpec | None = None,
                           progress: Callable[[str], None] | None = None) -> Path:
    """Write the phantom subject of `spec` into `subject_dir` unless already complete.

    Writes ``labels.nii.gz``, ``label_map.json``, ``meshes/``, ``truth.json``
    (incl. the motion truth entries) and, with motion, the C3D trials,
    ``subject.json`` and ``truth/``; then ``generated.json`` as the completion marker.
    """
    from phantoms import make_phantom
    from phantoms.imaging import write_phantom

    d = Path(subject_dir)
    spec = spec or read_spec(d)
    if (d / GENERATED).is_file():
        return d
    ph = make_phantom(seed=spec.seed, **spec.params)
    with staged_dir(d) as stage:
        write_phantom(stage, ph, voxel=tuple(v * 1e-3 for v in spec.voxel_mm), noise=spec.segmentation_noise,
                      seed=spec.seed, bones=None if spec.bones is None else list(spec.bones), progress=progress)
        if spec.motion:
            from phantoms.motion import write_trials

            entries = write_trials(stage, ph, spec.seed, progress=progress, sta_scale=spec.sta_scale,
                                   noise_sd=spec.marker_noise_m)
            truth = json.loads((stage / "truth.json").read_text(encoding="utf-8"))
            truth.update(entries)
            write_text(stage / "truth.json", json.dumps(truth, indent=1) + "\n")
    write_text(d / GENERATED, json.dumps({"spec": spec.to_json(),
                                          "files": sorted(p.relative_to(d).as_posix() for p in d.rglob("*")
                                                          if p.is_file())}, indent=1) + "\n")
    return d


def phantom_surfaces_job(subject_dir: Path, out: Path, progress: Callable[[str], None] | None = None) -> dict:
    """Surface stage only: bone surfaces from the labels vs the exact phantom meshes.

    A light job for validation runs that test the surface stage alone (``--job`` `SURFACE_JOB`).
    Writes ``surfaces.json`` (mm, %) into `out`.
    """
    import trimesh

    from personalize.evaluation.demo import DEMO_SURFACE_BONES, surface_error
    from personalize.surfaces import load_bones

    d = Path(subject_dir)
    lmap = json.loads((d / "label_map.json").read_text(encoding="utf-8"))
    bones = [b for b in DEMO_SURFACE_BONES if b in lmap] or sorted(lmap)
    surfaces = load_bones(d / "labels.nii.gz", d / "label_map.json", bones=bones, workers=1, eager_points=False)
    rows = {}
    for b in bones:
        exact = trimesh.load(d / "meshes" / f"{b}.ply", force="mesh")
        exact.apply_scale(1e-3)  # PLY in mm
        rows[b] = surface_error(surfaces[b], exact)
    summary = {"units": {"distance": "mm", "volume": "%"}, "job": "surfaces", "surfaces": rows}
    write_text(Path(out) / "surfaces.json", json.dumps(summary, indent=1) + "\n")
    return summary


def validation_job(subject_dir: Path, out: Path, progress: Callable[[str], None] | None = None, *,
                   job: str = DEFAULT_JOB) -> dict:
    """Dask task body: materialise the phantom subject, then run `job` on it."""
    ensure_phantom_subject(subject_dir, progress=progress)
    return resolve_job(job)(Path(subject_dir), out, progress=progress)


