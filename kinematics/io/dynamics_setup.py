"""OpenSim ``InverseDynamicsTool`` and ``AnalyzeTool`` (static optimisation) set-ups, and the reserve actuators
static optimisation needs on a model without muscles; written with the opensim API (its own printer, so OpenSim's
tools read them as they are).

File names are written as given: relative names resolve against the set-up file's folder, as OpenSim's GUI and
``opensim-cmd run-tool`` resolve them.  Every file states its units in a leading XML comment.

Reserve actuators (`write_reserve_actuators`): one ``CoordinateActuator`` on every free coordinate of the model
(not locked, not the dependent coordinate of a ``CoordinateCouplerConstraint``), the ground-to-pelvis ones named
``residual_<coordinate>`` (the residual forces and moments on the pelvis), the others ``reserve_<coordinate>``;
controls unbounded.  With one actuator per free coordinate and nothing else, the static optimisation's
acceleration constraints have a unique solution: the actuators' forces are the inverse-dynamics generalised forces.
With muscles added to the model, the same file gives the usual weak reserves (optimal force 1 N m: a reserve
moment of M N m costs M² in the activation objective).  The ``reactions`` coordinates (the personalised model's
knee ab/adduction and axial rotation: moments that contact and ligaments carry, which gait2392's muscles, made for
a one-degree-of-freedom knee, are not meant to balance) get ``reaction_<coordinate>`` actuators as strong as the
residuals, so the optimisation leaves those moments to them as a one-degree-of-freedom knee leaves them to its
joint reaction.
"""
from __future__ import annotations

import os
from pathlib import Path

from lowerlimb.errors import InputError

__all__ = ["write_id_setup", "write_so_setup", "write_reserve_actuators", "free_coordinates", "run_setup",
           "RESERVE_OPTIMAL_FORCE", "RESIDUAL_OPTIMAL_FORCE", "REACTION_OPTIMAL_FORCE"]

#: optimal force of the reserve actuators on the joints (N m per unit control, or N for a translation)
RESERVE_OPTIMAL_FORCE = 1.0
#: optimal force of the residual actuators on the pelvis (N or N m per unit control)
RESIDUAL_OPTIMAL_FORCE = 1.0
#: optimal force of the joint-reaction actuators (N m per unit control): strong, so that they cost little
REACTION_OPTIMAL_FORCE = 1000.0


def _print(obj, path: Path, comment: str, what: str) -> Path:
    """Print an OpenSim object to `path` atomically, `comment` as an XML comment after the declaration."""
    from lowerlimb.atomic import atomic_path

    with atomic_path(path) as tmp:
        if not obj.printToXML(os.fspath(tmp)):
            raise InputError(path, f"OpenSim could not write the {what}")
        text = tmp.read_text(encoding="utf-8")
        head, sep, rest = text.partition("?>")
        body = f"{head}{sep}\n<!-- {comment.replace('--', '-')} -->{rest}" if sep else f"<!-- {comment} -->\n{text}"
        tmp.write_text(body, encoding="utf-8")
    return Path(path)


def free_coordinates(model_file: str | os.PathLike) -> list[tuple[str, str, bool]]:
    """The coordinates an actuator can drive: (name, 'rotational' | 'translational', on the ground joint).

    Locked coordinates and the dependent coordinates of coupler constraints are left out.
    """
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    om = osim.Model(os.fspath(model_file))
    s = om.initSystem()
    dependent = set()
    cs = om.getConstraintSet()
    for i in range(cs.getSize()):
        c = osim.CoordinateCouplerConstraint.safeDownCast(cs.get(i))
        if c is not None:
            dependent.add(c.getDependentCoordinateName())
    out = []
    coords = om.getCoordinateSet()
    for i in range(coords.getSize()):
        c = coords.get(i)
        if c.getLocked(s) or c.getName() in dependent:
            continue
        kind = "rotational" if int(c.getMotionType()) == 1 else "translational"
        on_ground = c.getJoint().getParentFrame().findBaseFrame().getName() == om.getGround().getName()
        out.append((c.getName(), kind, bool(on_ground)))
    return out


def write_reserve_actuators(path: str | os.PathLike, model_file: str | os.PathLike, *,
                            reserve_optimal_force: float = RESERVE_OPTIMAL_FORCE,
                            residual_optimal_force: float = RESIDUAL_OPTIMAL_FORCE,
                            reactions=(), reaction_optimal_force: float = REACTION_OPTIMAL_FORCE) -> tuple[Path, list[str]]:
    """Write a ``ForceSet`` of CoordinateActuators on every free coordinate of `model_file` (module docstring).

    reactions : coordinate names whose actuator is a joint reaction (``reaction_<coordinate>``, optimal force
        `reaction_optimal_force`) rather than a weak reserve

    Returns (path, actuator names).
    """
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    fs = osim.ForceSet()
    fs.setName("reserve_actuators")
    names = []
    for c, kind, on_ground in free_coordinates(model_file):
        a = osim.CoordinateActuator(c)
        kind_name = "residual" if on_ground else "reaction" if c in reactions else "reserve"
        a.setName(f"{kind_name}_{c}")
        a.setOptimalForce(float({"residual": residual_optimal_force, "reaction": reaction_optimal_force,
                                 "reserve": reserve_optimal_force}[kind_name]))
        a.setMinControl(-float("inf"))
        a.setMaxControl(float("inf"))
        fs.cloneAndAppend(a)
        names.append(a.getName())
    unit = "N m (rotational) or N (translational)"
    comment = (f"Reserve and residual actuators of {Path(model_file).name}: one CoordinateActuator per free "
               f"coordinate (residual_* on the ground-pelvis joint, reaction_* on the knee's ab/adduction and rotation, "
               f"reserve_* on the others); force = control x "
               f"optimal_force, {unit} in the coordinate's direction; controls unbounded.")
    return _print(fs, Path(path), comment, "actuator set"), names


def write_id_setup(path: str | os.PathLike, *, model_file: str, coordinates_file: str, external_loads_file: str,
                   output_gen_force_file: str, time_range: tuple[float, float], cutoff_hz: float = 6.0,
                   name: str = "id", excluded_forces=("Muscles",)) -> Path:
    """Write an OpenSim ``InverseDynamicsTool`` setup.

    Parameters
    ----------
    model_file, coordinates_file (``.mot``, e.g. an IK result), external_loads_file (ExternalLoads ``.xml``),
        output_gen_force_file : names as OpenSim reads them (relative: against the setup's folder)
    time_range : (start, end) s
    cutoff_hz : low-pass cut-off of the coordinates (OpenSim's filter; <= 0: none)
    excluded_forces : the model's forces left out of the equations of motion (``Muscles``: the generalised
        forces are the net joint moments)
    """
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    tool = osim.InverseDynamicsTool()
    tool.setName(name)
    tool.setModelFileName(model_file)
    tool.setCoordinatesFileName(coordinates_file)
    tool.setExternalLoadsFileName(external_loads_file)
    tool.setOutputGenForceFileName(output_gen_force_file)
    tool.setResultsDir(".")
    tool.setStartTime(float(time_range[0]))
    tool.setEndTime(float(time_range[1]))
    tool.setLowpassCutoffFrequency(float(cutoff_hz) if cutoff_hz and cutoff_hz > 0 else -1.0)
    ex = osim.ArrayStr()
    for f in excluded_forces:
        ex.append(f)
    tool.setExcludedForces(ex)
    comment = (f"OpenSim inverse dynamics of {coordinates_file} on {model_file} with the ground reactions of "
               f"{external_loads_file}, {time_range[0]:.4f}-{time_range[1]:.4f} s, coordinates low-pass filtered at "
               f"{cutoff_hz:g} Hz; output {output_gen_force_file}: generalised forces, *_moment N m, *_force N, in the "
               "model's coordinates (model ground: X forward, Y up, Z right).")
    return _print(tool, Path(path), comment, "inverse-dynamics setup")


def write_so_setup(path: str | os.PathLike, *, model_file: str, coordinates_file: str, external_loads_file: str,
                   force_set_files, time_range: tuple[float, float], cutoff_hz: float = 6.0, name: str = "so",
                   activation_exponent: float = 2.0, convergence: float = 1e-4, max_iterations: int = 100) -> Path:
    """Write an OpenSim ``AnalyzeTool`` setup with one ``StaticOptimization`` analysis.

    The model's own forces are kept and the actuators of `force_set_files` (e.g. `write_reserve_actuators`) are
    added to them.  Outputs go to the setup's folder: ``<name>_StaticOptimization_force.sto`` (actuator forces,
    N m or N) and ``<name>_StaticOptimization_activation.sto`` (controls).

    Parameters
    ----------
    force_set_files : sequence of actuator-set file names (relative: against the setup's folder)
    time_range : (start, end) s; cutoff_hz : low-pass cut-off of the coordinates (<= 0: none)
    activation_exponent, convergence, max_iterations : the StaticOptimization analysis' settings
    """
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    tool = osim.AnalyzeTool()
    tool.setName(name)
    tool.setModelFilename(model_file)
    tool.setCoordinatesFileName(coordinates_file)
    tool.setExternalLoadsFileName(external_loads_file)
    tool.setLowpassCutoffFrequency(float(cutoff_hz) if cutoff_hz and cutoff_hz > 0 else -1.0)
    tool.setResultsDir(".")
    tool.setInitialTime(float(time_range[0]))
    tool.setFinalTime(float(time_range[1]))
    tool.setReplaceForceSet(False)
    files = osim.ArrayStr()
    for f in force_set_files:
        files.append(f)
    tool.setForceSetFiles(files)
    so = osim.StaticOptimization()
    so.setName("StaticOptimization")
    so.setStartTime(float(time_range[0]))
    so.setEndTime(float(time_range[1]))
    so.setUseModelForceSet(True)
    so.setActivationExponent(float(activation_exponent))
    so.setUseMusclePhysiology(True)
    so.setConvergenceCriterion(float(convergence))
    so.setMaxIterations(int(max_iterations))
    so.setInDegrees(True)
    tool.updAnalysisSet().cloneAndAppend(so)
    comment = (f"OpenSim static optimisation of {coordinates_file} on {model_file} with the actuators of "
               f"{', '.join(force_set_files)} and the ground reactions of {external_loads_file}, "
               f"{time_range[0]:.4f}-{time_range[1]:.4f} s, coordinates low-pass filtered at {cutoff_hz:g} Hz; "
               f"outputs {name}_StaticOptimization_force.sto (actuator forces: N m or N) and "
               f"{name}_StaticOptimization_activation.sto.")
    return _print(tool, Path(path), comment, "static-optimisation setup")


#: OpenSim tools `run_setup` runs, by their setup file's element
_TOOLS = ("InverseKinematicsTool", "InverseDynamicsTool", "AnalyzeTool")


def run_setup(path: str | os.PathLike) -> str:
    """Run an OpenSim IK, ID or Analyze setup file as it is written, as ``opensim-cmd run-tool`` does: relative
    names resolve against the setup's folder, outputs go where the setup says.  Returns the tool's element name.

    Raises
    ------
    InputError : not one of those tools' setups, or the tool failed
    """
    from kinematics.io.opensim_io import import_opensim, read_xml

    path = Path(path).resolve()
    root = read_xml(path, "setup file not found", "not an OpenSim setup: the file is not XML")
    tool = next((t for t in _TOOLS if root.tag == t or root.find(t) is not None), None)
    if tool is None:
        raise InputError(path, f"not an OpenSim setup of {', '.join(_TOOLS)}")
    osim = import_opensim()
    cwd = os.getcwd()
    try:
        os.chdir(path.parent)                    # OpenSim resolves relative names against the working directory
        if not getattr(osim, tool)(os.fspath(path)).run():
            raise InputError(path, f"OpenSim's {tool} failed")
    finally:
        os.chdir(cwd)
    return tool
