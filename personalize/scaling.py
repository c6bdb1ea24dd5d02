r"""A generic OpenSim model scaled to a subject from a static trial, as OpenSim's ScaleTool does.

`scale_model` reads the static trial (C3D or TRC, any lab orientation: the lab's vertical and the pose's facing
are read from the markers, `personalize.pipeline.lab`, and the trial is expressed in OpenSim's ground, Y up,
X the facing, metres), the generic model (``.osim``), an OpenSim ``MarkerSet`` file (optional; its markers
replace or join the model's, as ScaleTool's GenericModelMaker does) and an OpenSim Scale setup
(`kinematics.io.scale_setup.read_scale_setup`: the measurements, manual scales, time ranges, subject mass and
the marker-placement IK tasks).  Then, as ScaleTool does:

1. Measurement scale factors.  For measurement :math:`k` with marker pairs :math:`(a_j, b_j)`,
   :math:`j = 1..J_k`,

   .. math::

       s_k = \frac{1}{J_k} \sum_j \frac{\bar d^{exp}_j}{d^{mod}_j}, \qquad
       \bar d^{exp}_j = \frac{1}{|F_j|} \sum_{f \in F_j} \lVert y_{a_j,f} - y_{b_j,f} \rVert, \qquad
       d^{mod}_j = \lVert x_{a_j}(q_0) - x_{b_j}(q_0) \rVert

   with :math:`F_j` the frames of the ModelScaler's time range where both markers are seen (OpenSim would
   average a NaN in; a gap frame is left out here) and :math:`q_0` the model's default pose (m).  Each body the
   measurement lists is scaled by :math:`s_k` along the axes it names (its own body frame); the setup's
   ``scaling_order`` is followed, so a manual ``ScaleSet`` after ``measurements`` overrides the bodies it names.
   Bodies nobody names keep factor 1.
2. The model is scaled with OpenSim's ``Model.scale`` (bodies, joints' frames, markers, muscle paths and
   geometry), the masses preserving their distribution to the subject's mass :math:`M`:
   :math:`m_i' = m_i M / \sum_i m_i` (``preserve_mass_distribution``; without a mass the generic masses stay).
3. Marker placement.  The static's marker positions are averaged over the MarkerPlacer's time range
   (:math:`\bar y_m`, NaN frames left out), the scaled model is posed by one frame of inverse kinematics
   minimising OpenSim's objective with the placer's tasks

   .. math::

       E(q) = \sum_m w_m \lVert x_m(q) - \bar y_m \rVert^2 + \sum_c w_c (q_c - \bar q_c)^2

   (`kinematics.algorithms.ik.solve_ik`, the toolkit's solver rather than OpenSim's assembler: it starts from a
   rigid fit of the pelvis and converges to 1e-5 rad / m, where OpenSim's MarkerPlacer stops at its assembler's
   1e-4 accuracy; on gait2392 / subject01 it reaches the weighted objective E = 6.0451 against ScaleTool's 6.0483,
   with a marker RMS of 33.6 mm against 33.2 mm: a lower E, not a lower unweighted RMS, is what both minimise),
   and every non-fixed model marker seen
   in the static is moved to :math:`\bar y_m`, expressed in its body's frame at that pose.  The reported marker
   RMS and maximum are those of that IK, before the markers move (what OpenSim's MarkerPlacer reports):
   :math:`\mathrm{RMS} = \sqrt{\frac{1}{M}\sum_m \lVert x_m(q^*) - \bar y_m \rVert^2}` over the tracked markers.

`write_scaled_model` writes the results into one folder, replaced whole (`personalize.outputs.replaced_dir`).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lowerlimb.errors import InputError

__all__ = ["PairMeasurement", "MeasurementResult", "ScaledModel", "scale_model", "scale_report", "write_scaled_model",
           "static_in_ground", "SCALE_FILES"]

#: files `write_scaled_model` writes into the output folder
SCALE_FILES = {"model": "scaled_model.osim", "report": "scale.json", "pose": "static_pose.mot",
               "static": "static_ground.trc"}


@dataclass(frozen=True)
class PairMeasurement:
    """One marker pair of a measurement: model distance at the default pose and mean experimental distance (m)."""

    markers: tuple[str, str]
    model_distance: float
    experimental_distance: float
    frames: int

    @property
    def ratio(self) -> float:
        """experimental / model distance."""
        return self.experimental_distance / self.model_distance


@dataclass(frozen=True)
class MeasurementResult:
    """A measurement's scale factor (mean of its pairs' ratios) and the bodies (with axes) it scales."""

    name: str
    factor: float
    pairs: tuple[PairMeasurement, ...]
    bodies: dict


@dataclass(frozen=True, eq=False)
class ScaledModel:
    """A generic model scaled to a subject (`scale_model`).

    Attributes
    ----------
    model : opensim.Model, the scaled model with its markers placed
    scale_factors : dict body -> ndarray (3,), dimensionless factors along the body's own X, Y, Z axes
    measurements : tuple of MeasurementResult
    manual : dict body -> (3,) factors of the setup's manual scales that were applied
    mass_generic, mass_scaled : float, total model mass before and after (kg)
    coordinates : tuple of str, the model's coordinates
    rotational : tuple of str, its rotational coordinates
    pose : ndarray (n_q,), the static-pose IK solution (rad, m); NaN when markers were not placed
    markers : tuple of str, the markers tracked by that IK
    marker_errors : ndarray (M,), |x_m(q*) - y_m| before the markers moved (m)
    moved : tuple of str, the markers moved to the static's positions
    static : kinematics.io.markers.MarkerTrial, the static trial in the model's ground (m)
    static_mean : dict marker -> (3,) its mean position over the placer's time range in ground (m)
    scaler_time, placer_time : (t0, t1) s, the time ranges used
    lab : kinematics.gait.lab_frame.LabFrame of the static
    warnings : tuple of str
    inputs : dict, the input files
    """

    model: object
    scale_factors: dict
    measurements: tuple[MeasurementResult, ...]
    manual: dict
    mass_generic: float
    mass_scaled: float
    coordinates: tuple[str, ...]
    rotational: tuple[str, ...]
    pose: np.ndarray
    markers: tuple[str, ...]
    marker_errors: np.ndarray
    moved: tuple[str, ...]
    static: object
    static_mean: dict
    scaler_time: tuple[float, float]
    placer_time: tuple[float, float]
    lab: object
    warnings: tuple[str, ...] = ()
    inputs: dict = field(default_factory=dict)

    @property
    def marker_rms(self) -> float:
        """Static-pose marker RMS (m) over the tracked markers, before the markers moved; NaN without placement."""
        e = self.marker_errors
        return float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")

    @property
    def marker_max(self) -> float:
        """Largest static-pose marker error (m); NaN without placement."""
        return float(np.max(self.marker_errors)) if self.marker_errors.size else float("nan")

    @property
    def worst_marker(self) -> str | None:
        return self.markers[int(np.argmax(self.marker_errors))] if self.marker_errors.size else None


def static_in_ground(trial):
    """The static trial (lab coordinates, m) in OpenSim's ground (Y up, X the pose's facing) and its lab.

    :math:`x_{ground} = G R x_{lab}` with :math:`R` the lab's ``internal_from_lab``
    (`personalize.pipeline.lab.read_lab`) and :math:`G` `personalize.model_builder.GROUND_FROM_INTERNAL`;
    exact (axes moved and negated) when the lab's axes are the subject's.

    Returns
    -------
    (MarkerTrial in ground, LabFrame)

    Raises
    ------
    InputError
        The lab cannot be read from the trial (`kinematics.gait.lab_frame.detect_lab`).
    """
    from dataclasses import replace

    from .model_builder import GROUND_FROM_INTERNAL
    from .pipeline.lab import read_lab, rotate_points

    lab = read_lab(trial, [])
    M = GROUND_FROM_INTERNAL @ lab.internal_from_lab
    return replace(trial, positions=rotate_points(M, trial.positions),
                   extra={**trial.extra, "ground_from_lab": M.tolist()}), lab


def _window(time: np.ndarray, rng, start, end, source) -> tuple[np.ndarray, tuple[float, float]]:
    """Frames of `time` within the range (`start` / `end` first, then the setup's `rng`, else all), clamped to the
    data as OpenSim does."""
    t0 = start if start is not None else (rng[0] if rng is not None else -np.inf)
    t1 = end if end is not None else (rng[1] if rng is not None else np.inf)
    if t1 < t0:
        raise InputError("--end", f"end time {t1} s is before start time {t0} s")
    t0, t1 = max(t0, float(time[0])), min(t1, float(time[-1]))
    sel = (time >= t0 - 1e-9) & (time <= t1 + 1e-9)
    if not sel.any():
        raise InputError(source, f"no frame between {t0} s and {t1} s (the trial spans {time[0]:.3f}-{time[-1]:.3f} s)")
    return sel, (float(time[sel][0]), float(time[sel][-1]))


def _apply_marker_set(om, defs, source) -> None:
    """Replace or add the model's markers by the MarkerSet file's (ScaleTool's GenericModelMaker)."""
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    bodies = {om.getBodySet().get(i).getName() for i in range(om.getBodySet().getSize())}
    ground = om.getGround().getName()
    unknown = sorted({d.body for d in defs if d.body not in bodies and d.body != ground})
    if unknown:
        raise InputError(source, f"markers on bodies the model lacks: {', '.join(unknown)}")
    ms = om.updMarkerSet()
    for d in defs:
        frame = om.getGround() if d.body == ground else om.getBodySet().get(d.body)
        loc = osim.Vec3(*d.location)
        if ms.contains(d.name):
            m = ms.get(d.name)
            m.connectSocket_parent_frame(frame)
            m.set_location(loc)
        else:
            m = osim.Marker(d.name, frame, loc)
            om.addMarker(m)
        m.set_fixed(bool(d.fixed))
    om.finalizeConnections()


def scale_model(static: str | os.PathLike, model: str | os.PathLike, *, setup: str | os.PathLike,
                marker_set: str | os.PathLike | None = None, mass: float | None = None,
                start: float | None = None, end: float | None = None) -> ScaledModel:
    """Scale the generic `model` to the subject of the `static` trial (module docstring).

    Parameters
    ----------
    static : static trial (``.c3d`` or ``.trc``), any lab orientation and length unit
    model : generic OpenSim model (``.osim``)
    setup : OpenSim Scale setup (``.xml``): measurements, manual scales, time ranges, mass, placement IK tasks
    marker_set : OpenSim MarkerSet file (``.xml``), optional; default the model's own markers
    mass : subject mass (kg), optional; overrides the setup's
    start, end : time window (s) for both the measurements and the placement, overriding the setup's

    Returns
    -------
    ScaledModel

    Raises
    ------
    InputError
        Missing or unreadable files, a lab the trial does not tell, a measurement marker absent from the model
        or from the trial (or never seen together with its pair partner), a body or coordinate the model
        lacks, a non-positive mass.
    """
    from kinematics.algorithms.ik import solve_ik
    from kinematics.io.markers import MarkerTrial
    from kinematics.io.opensim_io import from_opensim, import_opensim, open_osim_model
    from kinematics.io.scale_setup import read_marker_set_xml, read_scale_setup
    from kinematics.io.trials import read_trial

    osim = import_opensim()
    static, model, setup = Path(static), Path(model), Path(setup)
    su = read_scale_setup(setup)
    defs = read_marker_set_xml(marker_set) if marker_set is not None else None
    if mass is not None and not mass > 0:
        raise InputError("--mass", f"must be a positive mass in kg, not {mass}")
    trial, lab = static_in_ground(read_trial(static))
    om = open_osim_model(model)
    if defs is not None:
        _apply_marker_set(om, defs, marker_set)
    markers_src = marker_set if marker_set is not None else model
    warnings: list[str] = []

    # 1. measurement scale factors at the default pose
    s = om.initSystem()
    mset = om.getMarkerSet()
    bodies = [om.getBodySet().get(i).getName() for i in range(om.getBodySet().getSize())]
    sel, scaler_time = _window(trial.time, su.scaler_time_range, start, end, static)
    results = []
    for meas in su.measurements:
        if not meas.apply:
            continue
        pairs = []
        for a, b in meas.pairs:
            for m in (a, b):
                if not mset.contains(m):
                    raise InputError(markers_src, f"measurement {meas.name!r} of {setup.name} pairs marker {m!r}, "
                                                  "which is not in the model's marker set")
                if m not in trial.names:
                    raise InputError(static, f"measurement {meas.name!r} of {setup.name} pairs marker {m!r}, "
                                             "which the trial lacks")
            d = np.linalg.norm(trial.marker(a)[sel] - trial.marker(b)[sel], axis=1)
            ok = np.isfinite(d)
            if not ok.any():
                raise InputError(static, f"markers {a} and {b} (measurement {meas.name!r}) are never seen together "
                                         f"between {scaler_time[0]} and {scaler_time[1]} s")
            xa = np.array(mset.get(a).getLocationInGround(s).to_numpy())
            xb = np.array(mset.get(b).getLocationInGround(s).to_numpy())
            dm = float(np.linalg.norm(xa - xb))
            if not dm > 0:
                raise InputError(markers_src, f"markers {a} and {b} coincide on the model: no scale factor")
            pairs.append(PairMeasurement((a, b), dm, float(d[ok].mean()), int(ok.sum())))
        if not pairs:
            warnings.append(f"measurement {meas.name!r} has no marker pair: not applied")
            continue
        absent = [b for b in meas.bodies if b not in bodies]
        if absent:      # ScaleTool skips them too
            warnings.append(f"measurement {meas.name!r}: bodies the model lacks, not scaled: {', '.join(absent)}")
        results.append(MeasurementResult(meas.name, float(np.mean([p.ratio for p in pairs])), tuple(pairs),
                                         {b: ax for b, ax in meas.bodies.items() if b in bodies}))
    factors = {b: np.ones(3) for b in bodies}
    manual = {}
    if su.scaler_applied:
        for step in su.scaling_order:
            if step == "measurements":
                for r in results:
                    for b, axes in r.bodies.items():
                        factors[b][np.asarray(axes, bool)] = r.factor
            else:
                for ms in su.manual_scales:
                    if not ms.apply:
                        continue
                    if ms.body not in factors:
                        warnings.append(f"manual scale of {ms.body!r}: the model has no such body, ignored")
                        continue
                    factors[ms.body] = np.asarray(ms.factors, float)
                    manual[ms.body] = np.asarray(ms.factors, float)
    else:
        warnings.append("the setup's ModelScaler is not applied: the model keeps its size")

    # 2. scale with OpenSim (bodies, frames, markers, muscles, geometry; masses)
    mass_generic = float(om.getTotalMass(s))
    subject_mass = mass if mass is not None else su.mass
    scale_set = osim.ScaleSet()
    for b, f in factors.items():
        sc = osim.Scale()
        sc.setSegmentName(b)
        sc.setScaleFactors(osim.Vec3(*map(float, f)))
        sc.setApply(True)
        scale_set.cloneAndAppend(sc)
    if not om.scale(s, scale_set, bool(su.preserve_mass_distribution),
                    float(subject_mass) if subject_mass is not None else -1.0):
        raise InputError(model, "OpenSim could not scale the model")
    s = om.initSystem()
    mass_scaled = float(om.getTotalMass(s))
    if subject_mass is not None and not su.preserve_mass_distribution:
        warnings.append("preserve_mass_distribution is false: masses scaled with the segments' volumes, "
                        f"total {mass_scaled:.2f} kg (subject {subject_mass:.2f} kg)")

    # 3. marker placement: IK of the averaged static on the scaled model, then the markers moved there
    psel, placer_time = _window(trial.time, su.placer_time_range, start, end, static)
    P = trial.positions[psel]                                                   # (F, M, 3)
    seen = np.isfinite(P).all(axis=2)                                           # (F, M)
    n_seen = seen.sum(axis=0)
    mean = np.where(seen[..., None], P, 0.0).sum(axis=0) / np.maximum(n_seen, 1)[:, None]   # (M, 3)
    mean[n_seen == 0] = np.nan
    static_mean = {n: mean[i] for i, n in enumerate(trial.names) if np.all(np.isfinite(mean[i]))}
    km = from_opensim(om, source=os.fspath(model))
    coords = tuple(km.coordinate_names)
    rot = tuple(c.name for c in km.coordinates if c.kind == "rotational")
    pose, tracked, errs, moved = np.full(len(coords), np.nan), (), np.zeros(0), ()
    if su.placer_applied:
        weights = {m: w for m, w in (su.marker_weights or {m: 1.0 for m in km.marker_names}).items()
                   if m in km.marker_names and m in static_mean}
        skipped = [m for m in su.marker_weights if m not in weights]
        if skipped:
            warnings.append(f"placement tasks without a model marker or a static position, not tracked: "
                            f"{', '.join(skipped)}")
        if not weights:
            raise InputError(static, "no marker of the placement IK is both on the model and in the trial")
        bad = [c.name for c in su.coordinate_tasks if c.name not in coords]
        if bad:
            raise InputError(setup, f"coordinate tasks name coordinates the model lacks: {', '.join(bad)}")
        names = tuple(weights)
        one = MarkerTrial(names, np.array([static_mean[m] for m in names])[None], trial.rate,
                          np.array([placer_time[0]]), os.fspath(static))
        ik = solve_ik(km, one, weights, su.coordinate_tasks)
        pose, tracked, errs = ik.q[0], tuple(ik.markers), np.asarray(ik.marker_errors[0], float)
        cs = om.getCoordinateSet()
        for name, v in zip(coords, pose):
            cs.get(name).setValue(s, float(v), False)
        om.realizePosition(s)
        moved_list = []
        ground = om.getGround()
        mset = om.updMarkerSet()
        for i in range(mset.getSize()):
            m = mset.get(i)
            if m.get_fixed() or m.getName() not in static_mean:
                continue
            loc = ground.findStationLocationInAnotherFrame(s, osim.Vec3(*map(float, static_mean[m.getName()])),
                                                           m.getParentFrame())
            m.set_location(loc)
            moved_list.append(m.getName())
        moved = tuple(moved_list)
        unplaced = [mset.get(i).getName() for i in range(mset.getSize())
                    if mset.get(i).getName() not in static_mean and not mset.get(i).get_fixed()]
        if unplaced:
            warnings.append(f"markers not seen in the static, left where scaling put them: {', '.join(unplaced)}")
    else:
        warnings.append("the setup's MarkerPlacer is not applied: markers stay where scaling put them")
    om.setName(su.name or static.stem)
    om.finalizeConnections()
    return ScaledModel(model=om, scale_factors=factors, measurements=tuple(results), manual=manual,
                       mass_generic=mass_generic, mass_scaled=mass_scaled, coordinates=coords, rotational=rot,
                       pose=pose, markers=tracked, marker_errors=errs, moved=moved, static=trial,
                       static_mean=static_mean, scaler_time=scaler_time, placer_time=placer_time, lab=lab,
                       warnings=tuple(warnings),
                       inputs={"static": os.fspath(static), "model": os.fspath(model), "setup": os.fspath(setup),
                               "marker_set": None if marker_set is None else os.fspath(marker_set),
                               "mass_kg": subject_mass})


def scale_report(res: ScaledModel) -> dict:
    """The content of ``scale.json``: factors per body, measurements, masses, marker placement errors, lab."""
    return {
        "scale_factors": {b: [float(v) for v in f] for b, f in res.scale_factors.items()},
        "scale_factors_frame": "each body's own frame of the generic model: factors along its X, Y, Z axes "
                               "(dimensionless, new length / generic length)",
        "measurements": [{"name": m.name, "factor": m.factor, "bodies": {b: [a for a, on in zip("XYZ", ax) if on]
                                                                         for b, ax in m.bodies.items()},
                          "pairs": [{"markers": list(p.markers), "model_distance_m": p.model_distance,
                                     "experimental_distance_m": p.experimental_distance, "ratio": p.ratio,
                                     "frames": p.frames} for p in m.pairs]} for m in res.measurements],
        "manual_scales": {b: [float(v) for v in f] for b, f in res.manual.items()},
        "measurement_time_range_s": list(res.scaler_time),
        "mass_kg": {"generic": res.mass_generic, "scaled": res.mass_scaled},
        "marker_placement": {
            "time_range_s": list(res.placer_time),
            "errors": "static-pose IK of the scaled model before the markers moved (OpenSim MarkerPlacer's report), "
                      "|model - measured| in the model's ground, m",
            "rms_m": res.marker_rms, "max_m": res.marker_max, "worst_marker": res.worst_marker,
            "per_marker_m": {m: float(e) for m, e in zip(res.markers, res.marker_errors)},
            "moved_markers": list(res.moved)},
        "ground_frame": "OpenSim ground: X the static pose's facing, Y up, Z to the right, m; "
                        "x_ground = ground_from_lab @ x_lab",
        "ground_from_lab": res.static.extra.get("ground_from_lab"),
        "lab": res.lab.to_json(),
        "inputs": res.inputs,
        "files": dict(SCALE_FILES),
        "warnings": list(res.warnings),
    }


def write_scaled_model(res: ScaledModel, out: str | os.PathLike) -> Path:
    """Write `res` into the folder `out`, replaced whole (check it first with `personalize.outputs.check_output_dir`).

    Files (`SCALE_FILES`): ``scaled_model.osim`` (the scaled model, markers placed), ``scale.json``
    (`scale_report`), ``static_pose.mot`` (the static-pose IK, degrees) and ``static_ground.trc`` (the static
    trial in the model's ground, mm).
    """
    from kinematics.io.opensim_io import write_osim
    from kinematics.io.storage import write_mot, write_trc
    from lowerlimb.atomic import write_text

    from .outputs import replaced_dir

    with replaced_dir(out) as stage:
        write_osim(res.model, stage / SCALE_FILES["model"])
        write_text(stage / SCALE_FILES["report"], json.dumps(scale_report(res), indent=1, default=float) + "\n")
        if np.all(np.isfinite(res.pose)):
            write_mot(stage / SCALE_FILES["pose"], res.coordinates, np.array([res.placer_time[0]]), res.pose[None],
                      rotational=res.rotational, name="static pose")
        write_trc(stage / SCALE_FILES["static"], res.static, units="mm")
    return Path(out)
