"""The realistic validation set: real and analytic anatomy, marker sets, labs and files as labs record them.

`draw_realistic_subjects` mixes the factors so that any 12 consecutive subjects
cover every level; each subject is a `RealisticSpec` stored as ``realistic.json``
and materialised on demand (`ensure_realistic_subject`) by the dask task body
`realistic_validation_job`.  `coverage_metrics` checks the stated covariances
against the truth; `realistic_table` summarises per marker set and lab.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from lowerlimb.atomic import staged_dir, write_text
from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian

from personalize.cohort import DEFAULT_JOB
from personalize.cohort.jobs import resolve_job
from personalize.evaluation.metrics import SOURCES
from personalize.pipeline.calibration import CHI2_2_95, CHI2_3_95
from personalize.evaluation.phantom_set import GENERATED
from personalize.evaluation.truth import true_static_centres

#: the real anatomies of the realistic set: folder under the data root -> expert model
REAL_ANATOMIES = {"ICL_MRI": "manual_ICL_MRI.osim", "LHDL_CT": "manual_LHDL_CT.osim"}
REALISTIC_SPEC = "realistic.json"


@dataclass(frozen=True)
class RealisticSpec:
    """One subject of the realistic set (`draw_realistic_subjects`).

    anatomy : ``analytic`` or a key of `REAL_ANATOMIES`; marker_set : pig, ior, cast, opensim;
    lab : z-up / y-up; walk : walking direction; tissue : child, adult, obese (analytic: its own adult prior);
    functional : functional hip trial written; imaging : ``labels`` (label volume) or ``meshes`` (bones/ folder);
    voxel_mm, segmentation_noise, marker_noise_m, sta_scale : as `PhantomSpec`; static_name, trial_format,
    static_frames : how the lab names and records its files; fibula_mesh : fibula as its own bone; palpation :
    the bony markers misplaced as palpation misplaces them (`phantoms.marker_placement`); False places them
    exactly, an ablation that shows what palpation costs (real-anatomy subjects only).
    """

    subject: str
    seed: int
    anatomy: str
    marker_set: str
    lab: str
    walk: str
    tissue: str
    functional: bool
    imaging: str
    voxel_mm: float
    segmentation_noise: float
    marker_noise_m: float
    sta_scale: float
    static_name: str
    trial_format: str
    static_frames: int
    fibula_mesh: bool
    data_root: str = ""
    palpation: bool = True

    def to_json(self) -> dict:
        return {**asdict(self), "units": {"voxel": "mm", "marker_noise": "m"}}

    @classmethod
    def from_json(cls, d: dict) -> "RealisticSpec":
        d = {k: v for k, v in d.items() if k != "units"}
        return cls(**d)

    def factors(self) -> dict:
        return {"anatomy": self.anatomy, "marker_set": self.marker_set, "lab": self.lab, "walk": self.walk,
                "tissue": self.tissue, "functional": int(self.functional), "imaging": self.imaging,
                "voxel_mm": self.voxel_mm, "segmentation_noise": self.segmentation_noise,
                "marker_noise_mm": self.marker_noise_m * 1e3, "sta_scale": self.sta_scale,
                "static_file": self.static_name, "format": self.trial_format, "static_frames": self.static_frames,
                "fibula_mesh": int(self.fibula_mesh), "palpation": int(self.palpation),
                "phantom_seed": self.seed}


def draw_realistic_subjects(n: int, seed: int, data_root: str | os.PathLike | None = None, *,
                            palpation: bool = True) -> list[RealisticSpec]:
    """The realistic validation set: `n` subjects mixing anatomy, marker set, lab, tissue and files.

    Factors rotate with the subject index so that any 12 consecutive subjects cover every level:
    anatomy analytic / ICL_MRI / LHDL_CT (real anatomies only when `data_root` holds them); marker sets
    pig on the analytic anatomy, ior, cast, opensim and pig on the real ones; labs y-up and z-up (both
    anatomies); tissue child / adult / obese (the analytic phantom: its own adult prior); a functional hip trial in every other
    subject; a label volume or a mesh folder; ``Static.c3d`` or ``static.c3d``, C3D or TRC trials,
    static trials of 7 to 200 frames.  Continuous draws (voxel size, segmentation and marker noise, STA
    scale, walking direction) from `seed`.  ``palpation=False``: every real-anatomy subject's bony markers sit
    exactly on their landmarks (`RealisticSpec.palpation`), the draws otherwise the same.
    """
    if not (1 <= n <= 10000):
        raise InputError("--subjects", f"{n} is outside 1-10000")
    root = Path(data_root) if data_root else None
    reals = [k for k, f in REAL_ANATOMIES.items()
             if root is not None and (root / "bones" / k).is_dir() and (root / "reference_models" / f).is_file()]
    real_sets = ("ior", "cast", "opensim", "pig")
    builds = ("child", "adult", "obese")
    out = []
    r = -1                                   # index among the real-anatomy subjects
    for i, ss in enumerate(np.random.SeedSequence([int(seed), 4271]).spawn(n)):
        rng = np.random.default_rng(ss)
        real = bool(reals) and i % 3 != 0
        if real:
            r += 1
        anatomy = reals[r % len(reals)] if real else "analytic"
        ms = real_sets[(r // 2) % len(real_sets)] if real else "pig"
        a = i // 3                            # index among the analytic subjects
        lab = ("y-up", "z-up")[((r // 2) + (r // 8)) % 2] if real else ("z-up", "y-up")[a % 2]
        walk = str(rng.choice(["+x", "-x", "+z", "-z"] if lab == "y-up" else ["+x", "-x", "+y", "-y"])) \
            if (real or lab == "y-up") else "+x"
        out.append(RealisticSpec(
            subject=f"subject_{i + 1:03d}", seed=int(ss.generate_state(1)[0] % (2**31 - 1)), anatomy=anatomy,
            marker_set=ms, lab=lab, walk=walk, tissue=builds[r % 3] if real else "adult",
            functional=(i % 2 == 0), imaging="meshes" if (real and r % 5 == 2) else "labels",
            voxel_mm=round(float(rng.uniform(1.0, 1.6)), 3), segmentation_noise=round(float(rng.uniform(0.0, 0.4)), 3),
            marker_noise_m=round(float(rng.uniform(0.2, 0.8)), 3) * 1e-3, sta_scale=round(float(rng.uniform(0.6, 1.4)), 3),
            static_name="Static" if (real and r % 4 == 1) else "static",
            trial_format="trc" if (real and r % 5 == 4) else "c3d",
            static_frames=int(rng.choice([7, 20, 200])) if real else 50, fibula_mesh=bool(r % 6 != 5),
            data_root=os.fspath(root) if root else "", palpation=bool(palpation)))
    return out


_ANATOMY_CACHE: dict = {}


def _real_anatomy(root: Path, name: str):
    from phantoms.real_anatomy import load_real_anatomy

    key = (os.fspath(root), name)
    if key not in _ANATOMY_CACHE:
        _ANATOMY_CACHE[key] = load_real_anatomy(root / "bones" / name, root / "reference_models" / REAL_ANATOMIES[name])
    return _ANATOMY_CACHE[key]


def ensure_realistic_subject(subject_dir: str | os.PathLike, progress: Callable[[str], None] | None = None) -> Path:
    """Write the subject of ``realistic.json`` in `subject_dir` unless complete (``generated.json``)."""
    d = Path(subject_dir)
    if (d / GENERATED).is_file():
        return d
    try:
        spec = RealisticSpec.from_json(json.loads((d / REALISTIC_SPEC).read_text(encoding="utf-8")))
    except (OSError, ValueError, TypeError) as exc:
        raise InputError(d / REALISTIC_SPEC, f"unreadable realistic subject spec ({exc})") from None
    with staged_dir(d) as stage:
        if spec.anatomy == "analytic":
            from phantoms import make_phantom
            from phantoms.imaging import write_phantom
            from phantoms.motion import write_trials

            from phantoms.lab import make_lab

            ph = make_phantom(seed=spec.seed)
            write_phantom(stage, ph, voxel=(spec.voxel_mm * 1e-3,) * 3, noise=spec.segmentation_noise,
                          seed=spec.seed, progress=progress, meshes=True)
            lab = None if (spec.lab == "z-up" and spec.walk == "+x") else make_lab(spec.lab, spec.walk)
            entries = write_trials(stage, ph, spec.seed, progress=progress, sta_scale=spec.sta_scale, lab=lab,
                                   static_name=spec.static_name, trial_format=spec.trial_format,
                                   noise_sd=spec.marker_noise_m, gait_trials=1, gait_cycles=1.0, crouch_angles=(0,),
                                   crouch_duration=2.0, functional_ranges=(45,) if spec.functional else (),
                                   functional_time_scale=0.5, static_duration=0.5)
            truth = json.loads((stage / "truth.json").read_text(encoding="utf-8"))
            truth.update(entries)
            write_text(stage / "truth.json", json.dumps(truth, indent=1) + "\n")
        else:
            from phantoms.real_subject import write_real_subject

            anat = _real_anatomy(Path(spec.data_root), spec.anatomy)
            write_real_subject(stage, anat, marker_set=spec.marker_set, lab=spec.lab, walk=spec.walk,
                               build=spec.tissue, seed=spec.seed, voxel=(spec.voxel_mm * 1e-3,) * 3,
                               noise=spec.segmentation_noise, fibula_mesh=spec.fibula_mesh,
                               labels=spec.imaging == "labels", meshes=True,
                               mesh_folder="meshes" if spec.imaging == "labels" else "bones",
                               functional=spec.functional, static_frames=spec.static_frames,
                               static_name=spec.static_name, trial_format=spec.trial_format,
                               sta_scale=spec.sta_scale, noise_sd=spec.marker_noise_m, palpation=spec.palpation,
                               progress=progress)
    write_text(d / GENERATED, json.dumps({"spec": spec.to_json()}, indent=1) + "\n")
    return d


def realistic_validation_job(subject_dir: Path, out: Path, progress: Callable[[str], None] | None = None, *,
                             job: str = DEFAULT_JOB) -> dict:
    """Dask task body: materialise the realistic subject, then run `job` on it (without gait2392's muscles unless
    ``$PERSONALIZE_MUSCLES`` asks for them: the validation measures joints and kinematics, and the muscles would add
    about 25 s per subject)."""
    from personalize.pipeline.run import MUSCLES_ENV

    os.environ.setdefault(MUSCLES_ENV, "none")
    ensure_realistic_subject(subject_dir, progress=progress)
    return resolve_job(job)(Path(subject_dir), out, progress=progress)


def coverage_metrics(summary: dict, subject_dir: Path) -> dict:
    """Per joint and source: 1 when the truth lies inside the stated 95 % ellipsoid (chi-square 3 dof), else 0;
    per knee and ankle axis (``coverage.knee_axis_r.fused``): 1 when the angular error lies inside the stated
    95 % cone (θ/σ)² <= χ²₂(0.95), σ the stated 1-sd angle per tangent direction.

    The estimates (summary ``estimates.<joint>_centre``: mean and covariance, the run's internal frame)
    are compared with the true static centres mapped by the summary's ``lab.internal_from_lab``.
    Returns ``{"coverage.hip_r.fused": 1.0, ...}`` and the squared Mahalanobis distances ``mahalanobis2.<joint>.<source>``.
    """
    truth = true_static_centres(Path(subject_dir), (summary.get("lab") or {}).get("internal_from_lab"))
    est = summary.get("estimates") or {}
    out: dict[str, float] = {}
    for joint, t in (truth or {}).items():
        e = est.get(f"{joint}_centre")
        if not e:
            continue
        for src in SOURCES:
            if src == "fused":
                f = e.get("fused") or {}
                mean, cov = f.get("mean"), f.get("cov")
            else:
                mean, cov = e.get(src), e.get(f"{src}_cov")
            if mean is None or cov is None:
                continue
            try:
                d2 = Gaussian(mean, cov).mahalanobis2(t)
            except np.linalg.LinAlgError:
                continue
            out[f"mahalanobis2.{joint}.{src}"] = d2
            out[f"coverage.{joint}.{src}"] = float(d2 <= CHI2_3_95)
    # axes: the angular error against the stated 1-sd angle per tangent direction, (θ/σ)² ~ χ²₂
    for side, per in (summary.get("errors_per_side") or {}).items():
        for jn in ("knee", "ankle"):
            e, err = est.get(f"{jn}_{side}_axis"), per.get(f"{jn}_axis_deg")
            if not e or not err:
                continue
            for src in SOURCES:
                sd = (e.get(src) or {}).get("sd_deg")
                if sd and err.get(src) is not None and np.isfinite(err[src]):
                    z2 = (float(err[src]) / float(sd)) ** 2
                    out[f"mahalanobis2.{jn}_axis_{side}.{src}"] = z2
                    out[f"coverage.{jn}_axis_{side}.{src}"] = float(z2 <= CHI2_2_95)
    return out


def realistic_table(rows: Sequence[dict]) -> list[dict]:
    """Per marker set and lab: subjects, completed, refused, median fused hip/knee/ankle errors, 95 % coverage."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r.get("marker_set"), r.get("lab")), []).append(r)
    out = []
    for (ms, lab), rs in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), str(kv[0][1]))):
        ok = [r for r in rs if r["status"] == "ok"]
        row = {"marker_set": ms, "lab": lab, "subjects": len(rs), "completed": len(ok), "refused": len(rs) - len(ok)}
        for q in ("hip_centre_mm", "knee_centre_mm", "ankle_centre_mm", "knee_axis_deg", "ankle_axis_deg"):
            v = [r.get(f"errors.{q}.fused") for r in ok]
            v = [x for x in v if isinstance(x, float) and math.isfinite(x)]
            row[f"median_fused_{q}"] = float(np.median(v)) if v else float("nan")
        cov = [r[c] for r in ok for c in r if c.startswith("coverage.") and c.endswith(".fused")
               and isinstance(r[c], float) and math.isfinite(r[c])]
        row["coverage95_fused"] = float(np.mean(cov)) if cov else float("nan")
        ang = [r[c] for r in ok for c in r if c.startswith("angle_rmse_deg.") and isinstance(r[c], float)]
        row["median_angle_rmse_deg"] = float(np.median(ang)) if ang else float("nan")
        out.append(row)
    return out

