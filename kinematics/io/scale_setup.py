"""OpenSim ``ScaleTool`` setup files and ``MarkerSet`` files, read with defusedxml (untrusted input).

A Scale setup holds what OpenSim's ScaleTool needs besides the files it names:

* ``ModelScaler``: the ``MeasurementSet`` (per measurement, the marker pairs whose distance ratio gives a scale
  factor and the bodies, with axes, that it scales), the manual ``ScaleSet`` (per body, three factors), the
  ``scaling_order`` (``measurements``, ``manualScale``, in sequence: a later step overrides an earlier one for the
  bodies it names), the ``time_range`` over which marker-pair distances are averaged and
  ``preserve_mass_distribution``;
* ``MarkerPlacer``: the ``IKTaskSet`` of the static-pose IK (`kinematics.io.ik_setup.read_ik_tasks`), its
  ``time_range`` (marker positions averaged over it) and whether it is applied;
* the subject's ``mass`` (kg).

File names in the setup (``model_file``, ``marker_set_file``, ``marker_file``, outputs) are kept as text only:
the caller names its inputs and outputs itself.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from kinematics.io.ik_setup import CoordinateTask, _bool, read_ik_tasks, setup_number
from kinematics.io.opensim_io import read_xml
from lowerlimb.errors import InputError

__all__ = ["Measurement", "ManualScale", "ScaleSetup", "read_scale_setup", "MarkerDefinition", "read_marker_set_xml"]

_AXES = ("X", "Y", "Z")


@dataclass(frozen=True)
class Measurement:
    """One ScaleTool measurement: a scale factor from marker pairs, applied to bodies along axes.

    Attributes
    ----------
    name : str
    pairs : tuple of (marker, marker)
    bodies : dict body -> tuple of bool (3,), the body axes X, Y, Z it scales
    apply : bool
    """

    name: str
    pairs: tuple[tuple[str, str], ...]
    bodies: dict
    apply: bool = True


@dataclass(frozen=True)
class ManualScale:
    """A manual scale of a body: factors (3,) along its X, Y, Z axes."""

    body: str
    factors: tuple[float, float, float]
    apply: bool = True


@dataclass(frozen=True)
class ScaleSetup:
    """The scaling problem of an OpenSim Scale setup (module docstring).

    Attributes
    ----------
    mass : float or None, subject mass (kg); None when the setup gives none (or a non-positive one)
    measurements : tuple of Measurement
    manual_scales : tuple of ManualScale
    scaling_order : tuple of str, ``measurements`` and / or ``manualScale`` in order
    scaler_applied : bool, ``ModelScaler`` ``apply``
    scaler_time_range : (t0, t1) s or None
    preserve_mass_distribution : bool
    placer_applied : bool, ``MarkerPlacer`` ``apply``
    placer_time_range : (t0, t1) s or None
    marker_weights : dict marker -> weight of the placer's IK marker tasks
    coordinate_tasks : tuple of CoordinateTask of the placer's IK
    disabled_markers : tuple of str, the placer's marker tasks not applied
    model_file, marker_set_file, marker_file : file names as the setup gives them (not opened)
    source : str, the setup file
    name : str, the ScaleTool's name (the subject's; ScaleTool names the scaled model so)
    """

    mass: float | None = None
    measurements: tuple[Measurement, ...] = ()
    manual_scales: tuple[ManualScale, ...] = ()
    scaling_order: tuple[str, ...] = ("measurements",)
    scaler_applied: bool = True
    scaler_time_range: tuple[float, float] | None = None
    preserve_mass_distribution: bool = True
    placer_applied: bool = True
    placer_time_range: tuple[float, float] | None = None
    marker_weights: dict = field(default_factory=dict)
    coordinate_tasks: tuple[CoordinateTask, ...] = ()
    disabled_markers: tuple[str, ...] = ()
    model_file: str | None = None
    marker_set_file: str | None = None
    marker_file: str | None = None
    source: str | None = None
    name: str = ""


def _time_range(el, path, where: str) -> tuple[float, float] | None:
    if el is None:
        return None
    parts = (el.findtext("time_range") or "").split()
    if not parts:
        return None
    if len(parts) != 2:
        raise InputError(path, f"{where} time_range must hold two times (s), not {' '.join(parts)!r}")
    t0, t1 = (setup_number(p, 0.0, path, f"{where} time_range") for p in parts)
    if t1 < t0:
        raise InputError(path, f"{where} time_range ends ({t1} s) before it starts ({t0} s)")
    return t0, t1


def _axes(text: str | None, path, where: str) -> tuple[bool, bool, bool]:
    names = (text or "X Y Z").upper().split()
    bad = [a for a in names if a not in _AXES]
    if bad or not names:
        raise InputError(path, f"{where}: axes must be among X Y Z, not {text!r}")
    return tuple(a in names for a in _AXES)


def read_scale_setup(path: str | os.PathLike) -> ScaleSetup:
    """Parse an OpenSim ``ScaleTool`` setup file (module docstring).

    Raises
    ------
    InputError
        Missing file, not XML or unsafe XML, no ``<ScaleTool>``, a marker pair that does not name two markers,
        axes other than X Y Z, an unknown ``scaling_order`` step, a non-number where a number belongs, an IK
        coordinate task ``from_file``.
    """
    path = Path(path)
    root = read_xml(path, "scale setup file not found", "not an OpenSim scale setup: the file is not XML")
    tool = root if root.tag == "ScaleTool" else root.find("ScaleTool")
    if tool is None:
        raise InputError(path, f"not an OpenSim scale setup: no <ScaleTool> element (root <{root.tag}>)")
    mass = setup_number(tool.findtext("mass"), -1.0, path, "mass")
    gmm = tool.find("GenericModelMaker")
    scaler = tool.find("ModelScaler")
    placer = tool.find("MarkerPlacer")

    measurements, manual, order = [], [], ("measurements",)
    if scaler is not None:
        order = tuple((scaler.findtext("scaling_order") or "measurements").split())
        bad = [s for s in order if s not in ("measurements", "manualScale")]
        if bad:
            raise InputError(path, f"scaling_order: unknown step(s) {', '.join(bad)} (measurements, manualScale)")
        for m in scaler.iter("Measurement"):
            name = m.get("name") or ""
            pairs = []
            for mp in m.iter("MarkerPair"):
                names = (mp.findtext("markers") or "").split()
                if len(names) != 2:
                    raise InputError(path, f"measurement {name!r}: a marker pair must name two markers, not "
                                           f"{' '.join(names)!r}")
                pairs.append((names[0], names[1]))
            bodies = {bs.get("name"): _axes(bs.findtext("axes"), path, f"measurement {name!r} body {bs.get('name')!r}")
                      for bs in m.iter("BodyScale")}
            measurements.append(Measurement(name, tuple(pairs), bodies, _bool(m.findtext("apply") or "true")))
        ss = scaler.find("ScaleSet")
        for sc in (ss.iter("Scale") if ss is not None else ()):
            body = (sc.findtext("segment") or "").strip()
            f = (sc.findtext("scales") or "").split()
            if len(f) != 3:
                raise InputError(path, f"manual scale of {body!r}: three factors expected, not {' '.join(f)!r}")
            factors = tuple(setup_number(v, 1.0, path, f"manual scale of {body!r}") for v in f)
            manual.append(ManualScale(body, factors, _bool(sc.findtext("apply") or "true")))
    weights, disabled, ctasks = ({}, (), ())
    if placer is not None:
        weights, disabled, ctasks = read_ik_tasks(placer, path)

    def text(el, tag):
        v = (el.findtext(tag) or "").strip() if el is not None else ""
        return v if v and v != "Unassigned" else None

    return ScaleSetup(
        mass=mass if mass > 0 else None, measurements=tuple(measurements), manual_scales=tuple(manual),
        scaling_order=order, scaler_applied=scaler is not None and _bool(scaler.findtext("apply") or "true"),
        scaler_time_range=_time_range(scaler, path, "ModelScaler"),
        preserve_mass_distribution=_bool(scaler.findtext("preserve_mass_distribution") or "true")
        if scaler is not None else True,
        placer_applied=placer is not None and _bool(placer.findtext("apply") or "true"),
        placer_time_range=_time_range(placer, path, "MarkerPlacer"),
        marker_weights=weights, coordinate_tasks=ctasks, disabled_markers=disabled,
        model_file=text(gmm, "model_file"), marker_set_file=text(gmm, "marker_set_file"),
        marker_file=text(scaler, "marker_file"), source=os.fspath(path), name=(tool.get("name") or "").strip())


@dataclass(frozen=True)
class MarkerDefinition:
    """A marker of an OpenSim MarkerSet file: its body, location in the body frame (3,) m, and ``fixed`` flag."""

    name: str
    body: str
    location: tuple[float, float, float]
    fixed: bool = False


def read_marker_set_xml(path: str | os.PathLike) -> tuple[MarkerDefinition, ...]:
    """The markers of an OpenSim ``MarkerSet`` file (OpenSim 3 ``<body>`` or OpenSim 4 ``<socket_parent_frame>``).

    Raises
    ------
    InputError
        Missing file, not XML or unsafe XML, no ``<MarkerSet>`` with a ``<Marker>``, a marker without a body or
        without a location of three numbers, two markers of one name.
    """
    from kinematics.io.marker_sets import PRESETS

    path = Path(path)
    if path.suffix.lower() == ".json" or (not path.exists() and str(path).strip().lower() in PRESETS):
        raise InputError(path, "scaling needs an OpenSim MarkerSet (.xml) that places each marker on a body of the "
                               "model; a markers.json or preset names the segments only")
    root = read_xml(path, "marker set file not found", "not an OpenSim marker set: the file is not XML")
    ms = root if root.tag == "MarkerSet" else root.find("MarkerSet")
    if ms is None:
        raise InputError(path, f"not an OpenSim marker set: no <MarkerSet> element (root <{root.tag}>)")
    out: dict[str, MarkerDefinition] = {}
    for m in ms.iter("Marker"):
        name = m.get("name") or ""
        frame = (m.findtext("socket_parent_frame") or m.findtext("body") or "").strip()
        body = frame.rstrip("/").split("/")[-1]
        loc = (m.findtext("location") or "").split()
        if not name or not body:
            raise InputError(path, f"marker {name!r} names no body (<body> or <socket_parent_frame>)")
        if len(loc) != 3:
            raise InputError(path, f"marker {name!r}: location must be three numbers (m), not {' '.join(loc)!r}")
        if name in out:
            raise InputError(path, f"marker {name!r} is defined twice")
        out[name] = MarkerDefinition(name, body, tuple(setup_number(v, 0.0, path, f"marker {name!r} location")
                                                        for v in loc), _bool(m.findtext("fixed") or "false"))
    if not out:
        raise InputError(path, "the marker set holds no <Marker>")
    return tuple(out.values())
