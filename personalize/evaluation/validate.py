"""Validation runs: the per-subject job on random phantom subjects, errors against truth.

`run_validation` draws N phantom subjects (anatomy, imaging resolution,
segmentation noise, soft-tissue artefact and marker noise, all from one seed),
runs one dask task per subject through `personalize.cohort.run_batch` (the task
first materialises its phantom subject folder, then runs the job on it), and
collects every numeric entry of each subject's ``summary.json`` into
``metrics.csv`` and a ``report.html`` with their distributions.

Layout of ``OUT``::

    manifest.csv              subject,path of the phantom subjects
    subjects/<id>/            phantom.json (the draws) + the written phantom subject
    results/<id>/             the job's outputs and summary.json
    results/batch.csv         status per subject
    metrics.csv               one row per subject: draws + flattened metrics
    fusion.json               fused vs each source: fractions of subjects / legs, medians (pipeline job)
    report.html               tables and distribution plots (self-contained)

Metrics are whatever the job's summary holds, flattened with dots: for the full
pipeline ``errors.hip_centre_mm.mri|motion|fused``, ``errors.knee_axis_deg.*``,
``errors.ankle_axis_deg.*``, ``ik_rms_mm``, ``angle_rmse_deg.<angle>``; for the
surface job ``surfaces.<bone>.mean_abs_distance_mm`` etc.
"""
from __future__ import annotations

import csv
import importlib.util
import io
import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lowerlimb.atomic import inside, staged_dir, write_text
from lowerlimb.errors import InputError

from personalize.cohort import DEFAULT_JOB, BatchResult, Subject, resolve_job, run_batch, write_manifest

#: estimate sources, in display order
SOURCES = ("mri", "motion", "fused")
#: summary keys that are settings, not metrics
NOT_METRICS = {"seed", "voxel_mm", "units", "version", "worker_pid", "n_frames", "frames"}
#: summary roots plotted in the report, in this order (errors vs truth, IK residuals, angle errors, surfaces)
FIGURE_ROOTS = ("errors", "ik_rms_mm", "angle_rmse_deg", "ik", "surfaces")
#: summary roots kept out of the report's tables (estimated coordinates, not errors; still in metrics.csv)
TABLE_ONLY_EXCLUDED = ("estimates", "truth_frame")
#: marker of a fully written phantom subject (written after everything else)
GENERATED = "generated.json"
SPEC = "phantom.json"
SURFACE_JOB = "personalize.evaluation.validate:phantom_surfaces_job"

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

    The job validation runs use while the full pipeline (`personalize.pipeline.run_subject`)
    is not available.  Writes ``surfaces.json`` (mm, %) into `out`.
    """
    import trimesh

    from personalize.evaluation.demo import DEMO_SURFACE_BONES
    from personalize.surfaces import load_bones, surface_distance

    d = Path(subject_dir)
    lmap = json.loads((d / "label_map.json").read_text(encoding="utf-8"))
    bones = [b for b in DEMO_SURFACE_BONES if b in lmap] or sorted(lmap)
    surfaces = load_bones(d / "labels.nii.gz", d / "label_map.json", bones=bones, workers=1, eager_points=False)
    rows = {}
    for b in bones:
        exact = trimesh.load(d / "meshes" / f"{b}.ply", force="mesh")
        exact.apply_scale(1e-3)  # PLY in mm
        dist = surface_distance(surfaces[b].mesh, exact, n=20000, seed=0)
        rows[b] = {"mean_abs_distance_mm": dist["mean"] * 1e3, "max_distance_mm": dist["max"] * 1e3,
                   "volume_error_pct": 100.0 * (surfaces[b].volume - abs(exact.volume)) / abs(exact.volume)}
    summary = {"units": {"distance": "mm", "volume": "%"}, "job": "surfaces", "surfaces": rows}
    write_text(Path(out) / "surfaces.json", json.dumps(summary, indent=1) + "\n")
    return summary


def validation_job(subject_dir: Path, out: Path, progress: Callable[[str], None] | None = None, *,
                   job: str = DEFAULT_JOB) -> dict:
    """Dask task body: materialise the phantom subject, then run `job` on it."""
    ensure_phantom_subject(subject_dir, progress=progress)
    return resolve_job(job)(Path(subject_dir), out, progress=progress)


def default_validation_job() -> str:
    """The full pipeline when it is installed, else the surface stage."""
    if importlib.util.find_spec("personalize.pipeline") is not None:
        return DEFAULT_JOB
    return SURFACE_JOB


# --------------------------------------------------------------------------- metrics
def flatten_metrics(summary: dict, prefix: str = "") -> dict[str, float]:
    """Numeric leaves of a summary as ``{"errors.hip_centre_mm.fused": 3.1, ...}`` (settings excluded)."""
    out: dict[str, float] = {}
    for k, v in summary.items():
        if k in NOT_METRICS:
            continue
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_metrics(v, key + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[key] = float(v)
    return out


def metric_groups(columns: Sequence[str]) -> dict[str, list[tuple[str, str]]]:
    """Group metric columns for plotting: {group: [(label, column), ...]}.

    ``a.b.<source>`` (source in mri/motion/fused) -> group ``a.b``, one box per source;
    ``a.<item>.<quantity>`` -> group ``a.<quantity>``, one box per item (e.g. bone);
    ``a.<item>`` -> group ``a``; a top-level scalar is its own group.
    """
    groups: dict[str, list[tuple[str, str]]] = {}
    for c in columns:
        parts = c.split(".")
        if parts[-1] in SOURCES and len(parts) >= 2:
            g, label = ".".join(parts[:-1]), parts[-1]
        elif len(parts) >= 3:
            g, label = ".".join(parts[:-2] + parts[-1:]), parts[-2]
        elif len(parts) == 2:
            g, label = parts[0], parts[1]
        else:
            g, label = c, c
        groups.setdefault(g, []).append((label, c))
    for g, items in groups.items():
        if all(lbl in SOURCES for lbl, _ in items):
            items.sort(key=lambda t: SOURCES.index(t[0]))
    return groups


def metric_statistics(rows: Sequence[dict], columns: Sequence[str]) -> list[dict]:
    """n, mean, sd, median, 95th percentile and max of each metric column over subjects."""
    stats = []
    for c in columns:
        v = np.array([r[c] for r in rows if isinstance(r.get(c), float) and math.isfinite(r[c])])
        if v.size == 0:
            continue
        stats.append({"metric": c, "n": int(v.size), "mean": float(v.mean()),
                      "sd": float(v.std(ddof=1)) if v.size > 1 else float("nan"),
                      "median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())})
    return stats


def _write_csv(path: Path, columns: Sequence[str], rows: Sequence[dict]) -> Path:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow(["" if r.get(c) is None or (isinstance(r.get(c), float) and math.isnan(r[c])) else
                    (f"{r[c]:.6g}" if isinstance(r[c], float) else r[c]) for c in columns])
    return write_text(path, buf.getvalue())


def read_metrics(path: str | os.PathLike) -> list[dict]:
    """Rows of a metrics.csv; numeric cells as floats, empty cells as NaN."""
    rows = []
    with open(path, newline="", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            row: dict[str, Any] = {}
            for k, v in r.items():
                if k in ("subject", "status", "error"):
                    row[k] = v
                else:
                    try:
                        row[k] = float(v) if v != "" else float("nan")
                    except ValueError:
                        row[k] = v
            rows.append(row)
    return rows


#: quantities estimated by both sources and fused (summary ``errors`` keys)
FUSED_QUANTITIES = ("hip_centre_mm", "knee_axis_deg", "ankle_axis_deg", "knee_centre_mm", "ankle_centre_mm")


def fusion_statistics(rows: Sequence[dict]) -> list[dict]:
    """How the fused estimates compare with each source, per subject (worst side) and per leg.

    For every quantity of `FUSED_QUANTITIES` present in the rows' metrics
    (``errors.<q>.<source>`` worst side; ``errors_per_side.<side>.<q>.<source>`` per leg):
    the fraction of cases where the fused error is below both sources', below
    the MRI-only one and below the motion-only one, and the median error of each source.
    """
    out = []
    for q in FUSED_QUANTITIES:
        for unit, prefixes in (("subject (worst side)", [f"errors.{q}."]),
                               ("leg", [f"errors_per_side.{s}.{q}." for s in ("r", "l")])):
            e = []
            for r in rows:
                for p in prefixes:
                    v = [r.get(p + src) for src in SOURCES]
                    if all(isinstance(x, float) and math.isfinite(x) for x in v):
                        e.append(v)
            if not e:
                continue
            e = np.array(e)
            out.append({"quantity": q, "unit": unit, "n": len(e),
                        "fused_below_both": float(np.mean(e[:, 2] < e[:, :2].min(axis=1))),
                        "fused_below_mri": float(np.mean(e[:, 2] < e[:, 0])),
                        "fused_below_motion": float(np.mean(e[:, 2] < e[:, 1])),
                        **{f"median_{src}": float(np.median(e[:, i])) for i, src in enumerate(SOURCES)}})
    return out


# --------------------------------------------------------------------------- report
def _box_figure(group: str, items: list[tuple[str, str]], rows: Sequence[dict]):
    from personalize.presentation.html_report import new_figure

    fig = new_figure(max(3.5, 1.1 * len(items) + 1.5), 3.4)
    ax = fig.add_subplot()
    data, labels = [], []
    for label, c in items:
        v = np.array([r[c] for r in rows if isinstance(r.get(c), float) and math.isfinite(r[c])])
        data.append(v)
        labels.append(f"{label}\n(n={v.size})")
    ax.boxplot(data, showfliers=False)
    ax.set_xticks(range(1, len(labels) + 1), labels)
    jit = np.random.default_rng(0)
    for i, v in enumerate(data, start=1):
        ax.plot(i + jit.uniform(-0.12, 0.12, v.size), v, "o", ms=3.5, alpha=0.6, color="tab:blue")
    ax.set_ylabel(group.split(".")[-1])
    ax.set_title(group, fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    return fig


def _hist_figure(column: str, rows: Sequence[dict]):
    from personalize.presentation.html_report import new_figure

    fig = new_figure(4.0, 3.0)
    ax = fig.add_subplot()
    v = np.array([r[column] for r in rows if isinstance(r.get(column), float) and math.isfinite(r[column])])
    ax.hist(v, bins=max(5, min(30, v.size // 2 or 1)), color="tab:blue", alpha=0.8)
    ax.set_xlabel(column)
    ax.set_ylabel("subjects")
    ax.set_title(column, fontsize=10)
    return fig


def validation_report(path: str | os.PathLike, rows: Sequence[dict], metric_columns: Sequence[str],
                      factor_columns: Sequence[str], *, seed: int, job: str, batch: BatchResult | None = None) -> Path:
    """Write ``report.html``: cohort, metric statistics, distribution plots, failures, draws."""
    from personalize.presentation.html_report import Figure, Section, Table, render_report

    ok = [r for r in rows if r["status"] in ("ok", "skipped")]
    failed = [r for r in rows if r["status"] == "error"]
    sections = [Section("Cohort", [
        f"{len(rows)} phantom subjects drawn from seed {seed}: random anatomy, MRI voxel size, segmentation "
        f"noise, soft-tissue artefact and marker noise; job {job}. {len(ok)} completed, {len(failed)} failed.",
        "Errors are against the phantoms' exact truth; angles in degrees, distances in millimetres "
        "(per metric name). metrics.csv holds one row per subject.",
    ])]
    # headline metrics get statistics and plots; the rest (per-side errors, registration, ...) a second table;
    # estimates themselves (coordinates) are only in metrics.csv
    def root_rank(c):
        r = c.split(".")[0]
        return FIGURE_ROOTS.index(r) if r in FIGURE_ROOTS else len(FIGURE_ROOTS)

    primary = sorted((c for c in metric_columns if root_rank(c) < len(FIGURE_ROOTS)), key=root_rank)
    if not primary:
        primary = list(metric_columns)
    headline = [c for c in primary if c.split(".")[0] != "ik"]  # per-trial IK residuals: plotted, tabled below
    other = [c for c in metric_columns if c not in headline and c.split(".")[0] not in TABLE_ONLY_EXCLUDED]
    stats = metric_statistics(ok, headline)
    items: list[Any] = [Table.from_records(stats, caption="Per-metric statistics over the completed subjects")
                        if stats else "No metric was produced."]
    if "angle_rmse_deg" not in {c.split(".")[0] for c in metric_columns}:
        items.append("The job's summary has no joint-angle RMSE against truth (angle_rmse_deg); none is reported.")
    for g, members in metric_groups(primary).items():
        if len(members) == 1 and members[0][1] == g:
            items.append(Figure(_hist_figure(g, ok), caption=f"Distribution of {g} over subjects"))
        else:
            items.append(Figure(_box_figure(g, members, ok),
                                caption=f"{g}: box = quartiles, whiskers = 1.5 IQR, dots = subjects"))
    sections.append(Section("Metrics", items))
    fus = fusion_statistics(ok)
    if fus:
        sections.append(Section("Fusion against each source", [Table.from_records(
            fus, caption="Fraction of subjects (worst side) and of legs where the fused error is below both "
                         "sources', below the MRI-only and below the motion-only error; median errors (mm or deg)")]))
    other_stats = metric_statistics(ok, other)
    if other_stats:
        sections.append(Section("Other summary quantities", [Table.from_records(
            other_stats, caption="Per-trial IK residuals, per-side errors, registration and other summary entries")]))
    if failed:
        sections.append(Section("Failed subjects", [Table.from_records(
            [{"subject": r["subject"], "error": r.get("error", "")} for r in failed])]))
    sections.append(Section("Draws per subject", [Table.from_records(
        [{c: r.get(c) for c in ["subject", "status", *factor_columns]} for r in rows],
        caption="Random factors of each phantom subject (stature m, angles deg, voxel mm, marker noise mm)")]))
    if batch is not None:
        sections.append(Section("Run", [f"{batch.workers} dask workers; {batch.compute_seconds:.1f} s of compute wall time "
                                         f"for {batch.counts['ok'] + batch.counts['error']} subjects run, "
                                         f"{batch.counts['skipped']} already complete."]))
    return render_report(path, "Validation on phantom subjects", sections, meta=f"personalize validate, seed {seed}")


# --------------------------------------------------------------------------- driver
@dataclass(frozen=True)
class ValidationResult:
    """Outcome of `run_validation`: the paths written and the per-subject rows."""

    out: Path
    metrics_csv: Path
    report: Path
    rows: tuple
    metric_columns: tuple
    batch: BatchResult


def run_validation(n: int, seed: int, out: str | os.PathLike, *, scheduler=None, workers: int = 2,
                   job: str | None = None, ranges: dict | None = None, bones: Sequence[str] | None = None,
                   motion: bool = True, progress: bool = True, console=None) -> ValidationResult:
    """Draw, write and run `n` phantom subjects; write ``metrics.csv`` and ``report.html`` into `out`.

    Parameters
    ----------
    n, seed : number of subjects and master seed (same values -> same subjects)
    out : output folder (re-running with the same n and seed resumes)
    scheduler, workers : see `personalize.cohort.run_batch`
    job : per-subject job (dotted path); default: the full pipeline if installed, else the surface stage
    ranges : overrides of `DEFAULT_RANGES`
    bones : write only these bones (default all)
    motion : write the motion trials too
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    job = job or default_validation_job()
    resolve_job(job)
    specs = draw_subjects(n, seed, ranges=ranges, bones=bones, motion=motion)
    subjects = []
    for s in specs:
        d = inside(out, f"subjects/{s.subject}")
        spec_text = json.dumps(s.to_json(), indent=1) + "\n"
        if (d / SPEC).is_file() and (d / SPEC).read_text(encoding="utf-8") != spec_text:
            raise InputError(out, f"holds a validation run with other settings ({s.subject} differs); "
                                  "use a new --out folder")
        if not (d / SPEC).is_file():
            write_text(d / SPEC, spec_text)
        subjects.append(Subject(s.subject, d))
    write_manifest(inside(out, "manifest.csv"), subjects)
    batch = run_batch(subjects, inside(out, "results"), job=validation_job, job_kwargs={"job": job},
                      scheduler=scheduler, workers=workers, progress=progress, console=console)
    status = batch.by_subject()
    rows, metric_cols = [], {}
    factor_cols: dict[str, None] = {}
    for s in specs:
        r = status[s.subject]
        # a subject completed by an earlier run counts as ok here (batch.csv says "skipped")
        row: dict[str, Any] = {"subject": s.subject, "status": "ok" if r.status == "skipped" else r.status,
                               "error": r.error}
        f = s.factors()
        factor_cols.update(dict.fromkeys(f))
        row.update(f)
        if r.status in ("ok", "skipped"):
            m = flatten_metrics(json.loads((Path(r.output) / "summary.json").read_text(encoding="utf-8")))
            metric_cols.update(dict.fromkeys(m))
            row.update(m)
        rows.append(row)
    mcols = list(metric_cols)
    csv_path = _write_csv(inside(out, "metrics.csv"), ["subject", "status", *factor_cols, *mcols, "error"], rows)
    fus = fusion_statistics([r for r in rows if r["status"] == "ok"])
    if fus:
        write_text(inside(out, "fusion.json"), json.dumps({"units": "fractions; medians in mm or deg as named",
                                                            "rows": fus}, indent=1) + "\n")
    rep = validation_report(inside(out, "report.html"), rows, mcols, list(factor_cols), seed=seed, job=job,
                            batch=batch)
    return ValidationResult(out, csv_path, rep, tuple(rows), tuple(mcols), batch)


# --------------------------------------------------------------------------- realistic validation set
#: the real anatomies of the realistic set: folder under the data root -> expert model
REAL_ANATOMIES = {"ICL_MRI": "manual_ICL_MRI.osim", "LHDL_CT": "manual_LHDL_CT.osim"}
#: chi-square 95 % quantile with 3 degrees of freedom (coverage of a 3-D ellipsoid)
CHI2_3_95 = 7.814727903251178
REALISTIC_SPEC = "realistic.json"


@dataclass(frozen=True)
class RealisticSpec:
    """One subject of the realistic set (`draw_realistic_subjects`).

    anatomy : ``analytic`` or a key of `REAL_ANATOMIES`; marker_set : pig, ior, cast, opensim;
    lab : z-up / y-up; walk : walking direction; tissue : child, adult, obese (analytic: its own adult prior);
    functional : functional hip trial written; imaging : ``labels`` (label volume) or ``meshes`` (bones/ folder);
    voxel_mm, segmentation_noise, marker_noise_m, sta_scale : as `PhantomSpec`; static_name, trial_format,
    static_frames : how the lab names and records its files; fibula_mesh : fibula as its own bone.
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
                "fibula_mesh": int(self.fibula_mesh), "phantom_seed": self.seed}


def draw_realistic_subjects(n: int, seed: int, data_root: str | os.PathLike | None = None) -> list[RealisticSpec]:
    """The realistic validation set: `n` subjects mixing anatomy, marker set, lab, tissue and files.

    Factors rotate with the subject index so that any 12 consecutive subjects cover every level:
    anatomy analytic / ICL_MRI / LHDL_CT (real anatomies only when `data_root` holds them); marker sets
    pig on the analytic anatomy, ior, cast, opensim and pig on the real ones; labs y-up and z-up (both
    anatomies); tissue child / adult / obese (the analytic phantom: its own adult prior); a functional hip trial in every other
    subject; a label volume or a mesh folder; ``Static.c3d`` or ``static.c3d``, C3D or TRC trials,
    static trials of 7 to 200 frames.  Continuous draws (voxel size, segmentation and marker noise, STA
    scale, walking direction) from `seed`.
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
            data_root=os.fspath(root) if root else ""))
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
                               sta_scale=spec.sta_scale, noise_sd=spec.marker_noise_m, progress=progress)
    write_text(d / GENERATED, json.dumps({"spec": spec.to_json()}, indent=1) + "\n")
    return d


def realistic_validation_job(subject_dir: Path, out: Path, progress: Callable[[str], None] | None = None, *,
                             job: str = DEFAULT_JOB) -> dict:
    """Dask task body: materialise the realistic subject, then run `job` on it."""
    ensure_realistic_subject(subject_dir, progress=progress)
    return resolve_job(job)(Path(subject_dir), out, progress=progress)


def _truth_centres_static_lab(subject_dir: Path) -> dict | None:
    """True hip/knee/ankle centres in the static lab (truth/static_centres.trc, median over frames)."""
    from kinematics.io.storage import read_trc

    p = subject_dir / "truth" / "static_centres.trc"
    if not p.is_file():
        return None
    cen = read_trc(p)
    names = {"RHJC": "hip_r", "LHJC": "hip_l", "RKJC": "knee_r", "LKJC": "knee_l", "RAJC": "ankle_r", "LAJC": "ankle_l"}
    return {names[n]: np.nanmedian(cen.marker(n), axis=0) for n in cen.names if n in names}


def coverage_metrics(summary: dict, subject_dir: Path) -> dict:
    """Per joint and source: 1 when the truth lies inside the stated 95 % ellipsoid (chi-square 3 dof), else 0.

    The estimates (summary ``estimates.<joint>_centre``: mean and covariance, static lab frame) are
    compared with the true static centres.  Returns ``{"coverage.hip_r.fused": 1.0, ...}`` and the
    squared Mahalanobis distances ``mahalanobis2.<joint>.<source>``.
    """
    truth = _truth_centres_static_lab(Path(subject_dir))
    est = summary.get("estimates") or {}
    out: dict[str, float] = {}
    if not truth:
        return out
    for joint, t in truth.items():
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
            r = np.asarray(mean, float) - t
            try:
                d2 = float(r @ np.linalg.solve(np.asarray(cov, float), r))
            except np.linalg.LinAlgError:
                continue
            out[f"mahalanobis2.{joint}.{src}"] = d2
            out[f"coverage.{joint}.{src}"] = float(d2 <= CHI2_3_95)
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


def run_realistic_validation(n: int, seed: int, out: str | os.PathLike, *, data_root: str | os.PathLike | None = None,
                             scheduler=None, workers: int = 2, job: str | None = None, progress: bool = True,
                             console=None) -> ValidationResult:
    """`draw_realistic_subjects`, write and run them; ``metrics.csv`` (refusals as rows with their reason) and report.

    Metrics per subject: every numeric summary entry (joint centre and axis errors of the MRI-only,
    motion-only and fused estimates, IK angle RMSE, IK residuals) plus `coverage_metrics`.
    """
    from personalize.presentation.html_report import Section, Table, render_report

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    job = job or default_validation_job()
    resolve_job(job)
    if data_root is None:
        data_root = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    specs = draw_realistic_subjects(n, seed, data_root if Path(data_root).is_dir() else None)
    subjects = []
    for s in specs:
        d = inside(out, f"subjects/{s.subject}")
        text = json.dumps(s.to_json(), indent=1) + "\n"
        if (d / REALISTIC_SPEC).is_file() and (d / REALISTIC_SPEC).read_text(encoding="utf-8") != text:
            raise InputError(out, f"holds a validation run with other settings ({s.subject} differs); use a new --out folder")
        if not (d / REALISTIC_SPEC).is_file():
            write_text(d / REALISTIC_SPEC, text)
        subjects.append(Subject(s.subject, d))
    write_manifest(inside(out, "manifest.csv"), subjects)
    batch = run_batch(subjects, inside(out, "results"), job=realistic_validation_job, job_kwargs={"job": job},
                      scheduler=scheduler, workers=workers, progress=progress, console=console)
    status = batch.by_subject()
    rows, metric_cols, factor_cols = [], {}, {}
    for s in specs:
        r = status[s.subject]
        row: dict[str, Any] = {"subject": s.subject, "status": "ok" if r.status == "skipped" else r.status,
                               "error": (r.error or "").strip().splitlines()[-1] if r.error else ""}
        f = s.factors()
        factor_cols.update(dict.fromkeys(f))
        row.update(f)
        if r.status in ("ok", "skipped"):
            summary = json.loads((Path(r.output) / "summary.json").read_text(encoding="utf-8"))
            m = flatten_metrics({k: v for k, v in summary.items() if k not in TABLE_ONLY_EXCLUDED})
            m.update(coverage_metrics(summary, Path(subjects[specs.index(s)].path)))
            metric_cols.update(dict.fromkeys(m))
            row.update(m)
        rows.append(row)
    mcols = list(metric_cols)
    csv_path = _write_csv(inside(out, "metrics.csv"), ["subject", "status", *factor_cols, *mcols, "error"], rows)
    table = realistic_table(rows)
    write_text(inside(out, "table.json"), json.dumps({"units": "mm, deg, fractions", "rows": table}, indent=1,
                                                     default=float) + "\n")
    ok = [r for r in rows if r["status"] == "ok"]
    cov_rows = []
    for src in SOURCES:
        v = [r[c] for r in ok for c in r if c.startswith("coverage.") and c.endswith(f".{src}")]
        if v:
            cov_rows.append({"source": src, "joints": len(v), "inside_95pct_ellipsoid": float(np.mean(v))})
    sections = [
        Section("Realistic set", [
            f"{len(rows)} subjects from seed {seed}: anatomy analytic / ICL-MRI / LHDL-CT, marker sets "
            f"{', '.join(sorted({s.marker_set for s in specs}))}, labs {', '.join(sorted({s.lab for s in specs}))}, "
            f"tissue {', '.join(sorted({s.tissue for s in specs}))}, {sum(not s.functional for s in specs)} without a "
            f"functional trial, {sum(s.imaging == 'meshes' for s in specs)} with a mesh folder instead of a label "
            f"volume; job {job}. {len(ok)} completed, {len(rows) - len(ok)} refused or failed."]),
        Section("Per marker set and lab", [Table.from_records(table, caption="Fused errors (median, mm / deg), "
                                                                           "95 % coverage of the stated covariances")]),
    ]
    if cov_rows:
        sections.append(Section("Coverage", [Table.from_records(cov_rows, caption="Fraction of true joint centres "
                                                                                   "inside the stated 95 % ellipsoid")]))
    stats = metric_statistics(ok, [c for c in mcols if c.split(".")[0] in ("errors", "angle_rmse_deg", "ik_rms_mm")])
    if stats:
        sections.append(Section("Metrics", [Table.from_records(stats, caption="Completed subjects")]))
    sections.append(Section("Subjects", [Table.from_records(
        [{c: r.get(c) for c in ["subject", "status", *factor_cols, "error"]} for r in rows],
        caption="Each subject's factors and, when refused, the one-line reason")]))
    rep = render_report(inside(out, "report.html"), "Realistic validation", sections,
                        meta=f"personalize validate --realistic, seed {seed}")
    return ValidationResult(out, csv_path, rep, tuple(rows), tuple(mcols), batch)
