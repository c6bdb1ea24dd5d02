"""OpenSim ``InverseKinematicsTool`` setup files: marker weights, coordinate tasks, time range (read and write)."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from kinematics.io.opensim_io import read_xml
from lowerlimb.errors import InputError

__all__ = ["CoordinateTask", "IKSetup", "read_ik_setup", "read_ik_tasks", "write_ik_setup"]


@dataclass(frozen=True)
class CoordinateTask:
    """Keep coordinate `name` near `value` (None: the model default) with `weight`."""

    name: str
    weight: float
    value: float | None = None


@dataclass(frozen=True)
class IKSetup:
    """Tasks of an OpenSim IK setup file (``IKMarkerTask`` / ``IKCoordinateTask``)."""

    marker_weights: Mapping[str, float] = field(default_factory=dict)
    coordinate_tasks: tuple[CoordinateTask, ...] = ()
    time_range: tuple[float, float] | None = None
    accuracy: float = 1e-5
    model_file: str | None = None
    marker_file: str | None = None
    disabled_markers: tuple[str, ...] = ()
    source: str | None = None


def _bool(text: str | None) -> bool:
    return (text or "").strip().lower() in ("true", "1", "yes")


def setup_number(text: str | None, default: float, path, what: str) -> float:
    """The number in an element's `text` (`default` when empty); `InputError` naming `path` and `what` otherwise."""
    text = (text or "").strip()
    if not text:
        return float(default)
    try:
        return float(text)
    except ValueError:
        raise InputError(path, f"{what}: {text!r} is not a number") from None


def read_ik_setup(path: str | os.PathLike) -> IKSetup:
    """Parse an OpenSim ``InverseKinematicsTool`` setup file (defusedxml).

    IKMarkerTask weights (tasks with ``apply`` false are dropped), IKCoordinateTask
    targets (``default_value``: the model default; ``manual_value``: ``value``,
    rotational values in radians as in OpenSim; ``from_file`` is rejected),
    ``time_range``, ``accuracy``, ``model_file``, ``marker_file``.
    """
    path = Path(path)
    root = read_xml(path, "IK setup file not found", "not an OpenSim IK setup: the file is not XML")
    tool = root if root.tag == "InverseKinematicsTool" else root.find("InverseKinematicsTool")
    if tool is None:
        raise InputError(path, "not an OpenSim IK setup: no <InverseKinematicsTool> element")
    weights, disabled, ctasks = read_ik_tasks(tool, path)
    tr = (tool.findtext("time_range") or "").split()
    time_range = (float(tr[0]), float(tr[1])) if len(tr) == 2 else None
    acc = float((tool.findtext("accuracy") or "1e-5").strip())
    return IKSetup(weights, ctasks, time_range, acc, (tool.findtext("model_file") or "").strip() or None,
                   (tool.findtext("marker_file") or "").strip() or None, disabled, os.fspath(path))


def read_ik_tasks(element, path) -> tuple[dict, tuple[str, ...], tuple[CoordinateTask, ...]]:
    """The IK tasks under an XML `element` (an ``InverseKinematicsTool``, a ``MarkerPlacer``'s ``IKTaskSet``).

    Returns
    -------
    marker_weights : dict marker -> weight of the applied ``IKMarkerTask`` with weight > 0
    disabled : tuple of str, marker tasks not applied (or weight 0)
    coordinate_tasks : tuple of CoordinateTask of the applied ``IKCoordinateTask`` (``default_value``: value None,
        the model default; ``manual_value``: ``value``, radians for rotations as in OpenSim)

    Raises
    ------
    InputError
        A coordinate task ``from_file`` (not supported), naming `path`.
    """
    weights, disabled, ctasks = {}, [], []
    for t in element.iter("IKMarkerTask"):
        name = t.get("name")
        w = setup_number(t.findtext("weight"), 1.0, path, f"IKMarkerTask {t.get('name')!r} weight")
        if _bool(t.findtext("apply") or "true") and w > 0:
            weights[name] = w
        else:
            disabled.append(name)
    for t in element.iter("IKCoordinateTask"):
        if not _bool(t.findtext("apply") or "true"):
            continue
        w = setup_number(t.findtext("weight"), 1.0, path, f"IKCoordinateTask {t.get('name')!r} weight")
        vt = (t.findtext("value_type") or "default_value").strip()
        if vt == "default_value":
            ctasks.append(CoordinateTask(t.get("name"), w, None))
        elif vt == "manual_value":
            ctasks.append(CoordinateTask(t.get("name"), w, setup_number(t.findtext("value"), 0.0, path,
                                                                f"IKCoordinateTask {t.get('name')!r} value")))
        else:
            raise InputError(path, f"IKCoordinateTask {t.get('name')!r}: value_type {vt!r} is not supported "
                                   "(use default_value or manual_value)")
    return weights, tuple(disabled), tuple(ctasks)


def write_ik_setup(path: str | os.PathLike, *, model_file: str, marker_file: str, output_motion_file: str,
                   marker_weights: Mapping[str, float], time_range: tuple[float, float], accuracy: float = 1e-5,
                   coordinate_tasks=(), name: str = "ik") -> Path:
    """Write an OpenSim ``InverseKinematicsTool`` setup with the opensim API (its own printer, so OpenSim reads it).

    File names are written as given (relative names resolve against the setup file's folder, as OpenSim does);
    constraints are strictly enforced (``constraint_weight`` Infinity); marker errors are reported.

    Parameters
    ----------
    marker_weights : marker -> weight of its IKMarkerTask (markers left out are not tracked)
    time_range : (start, end) s
    coordinate_tasks : CoordinateTask sequence (value None: the model default)
    """
    from lowerlimb.atomic import atomic_path

    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    path = Path(path)
    tool = osim.InverseKinematicsTool()
    tool.setName(name)
    tool.set_model_file(model_file)
    tool.setMarkerDataFileName(marker_file)
    tool.setOutputMotionFileName(output_motion_file)
    tool.set_results_directory(".")
    tool.setStartTime(float(time_range[0]))
    tool.setEndTime(float(time_range[1]))
    tool.set_accuracy(float(accuracy))
    tool.set_constraint_weight(float("inf"))
    tool.set_report_errors(True)
    tasks = tool.upd_IKTaskSet()
    for m, w in marker_weights.items():
        t = osim.IKMarkerTask()
        t.setName(m)
        t.setApply(True)
        t.setWeight(float(w))
        tasks.cloneAndAppend(t)
    for c in coordinate_tasks:
        t = osim.IKCoordinateTask()
        t.setName(c.name)
        t.setApply(True)
        t.setWeight(float(c.weight))
        if c.value is None:
            t.setValueType(osim.IKCoordinateTask.DefaultValue)
        else:
            t.setValueType(osim.IKCoordinateTask.ManualValue)
            t.setValue(float(c.value))
        tasks.cloneAndAppend(t)
    with atomic_path(path) as tmp:
        if not tool.printToXML(os.fspath(tmp)):
            raise InputError(path, "OpenSim could not write the IK setup")
    return path
