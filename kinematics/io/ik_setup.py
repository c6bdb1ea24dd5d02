"""OpenSim ``InverseKinematicsTool`` setup files: marker weights, coordinate tasks, time range."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from kinematics.io.opensim_io import read_xml
from lowerlimb.errors import InputError

__all__ = ["CoordinateTask", "IKSetup", "read_ik_setup"]


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
    weights, disabled, ctasks = {}, [], []
    for t in tool.iter("IKMarkerTask"):
        name = t.get("name")
        w = float((t.findtext("weight") or "1").strip())
        if _bool(t.findtext("apply") or "true") and w > 0:
            weights[name] = w
        else:
            disabled.append(name)
    for t in tool.iter("IKCoordinateTask"):
        if not _bool(t.findtext("apply") or "true"):
            continue
        w = float((t.findtext("weight") or "1").strip())
        vt = (t.findtext("value_type") or "default_value").strip()
        if vt == "default_value":
            ctasks.append(CoordinateTask(t.get("name"), w, None))
        elif vt == "manual_value":
            ctasks.append(CoordinateTask(t.get("name"), w, float((t.findtext("value") or "0").strip())))
        else:
            raise InputError(path, f"IKCoordinateTask {t.get('name')!r}: value_type {vt!r} is not supported "
                                   "(use default_value or manual_value)")
    tr = (tool.findtext("time_range") or "").split()
    time_range = (float(tr[0]), float(tr[1])) if len(tr) == 2 else None
    acc = float((tool.findtext("accuracy") or "1e-5").strip())
    return IKSetup(weights, tuple(ctasks), time_range, acc, (tool.findtext("model_file") or "").strip() or None,
                   (tool.findtext("marker_file") or "").strip() or None, tuple(disabled), os.fspath(path))
