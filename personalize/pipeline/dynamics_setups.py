"""OpenSim inverse-dynamics and static-optimisation set-ups of every trial with force plates, runnable as written.

For each C3D motion trial whose plates carry a foot (`kinematics.gait.inverse_dynamics.loads_from_c3d`: each
loaded interval assigned to a foot from its markers, ``calcn_r`` / ``calcn_l``), `write_dynamics_setups` writes
into the run's ``kinematics/`` folder, beside the trial's ``<trial>.mot`` (IK) and ``<trial>.trc``:

* ``<trial>_grf.mot`` / ``<trial>_grf.xml``: the ground reactions (force N, centre of pressure m, free torque N m)
  in the model's ground (x_ground = G R_lab x_lab: X the static pose's facing, Y up, Z right; the lab's origin)
  and the ExternalLoads applying them to the feet;
* ``<trial>_id_setup.xml``: OpenSim's InverseDynamicsTool on ``<trial>.mot`` with those loads (coordinates
  filtered at 6 Hz), output ``<trial>_opensim_id.sto`` (N m, N);
* ``<trial>_so_setup.xml``: OpenSim's AnalyzeTool with a StaticOptimization analysis of the same trial and loads,
  with the model's forces and ``../reserve_actuators.xml`` (`kinematics.io.dynamics_setup.write_reserve_actuators`:
  residuals on the pelvis, reserves on every other free coordinate).

The set-ups' time range is the trial's longest stretch in which every frame's ground reaction is known: no foot
on the ground off the plates, no plate with two feet or a centre of pressure outside it (the intervals
`loads_from_c3d` excludes); moments outside it would be computed with a missing ground reaction.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lowerlimb.atomic import inside
from lowerlimb.errors import FitError, InputError

__all__ = ["write_dynamics_setups", "known_load_window", "DYNAMICS_CUTOFF_HZ", "MIN_WINDOW_FRAMES",
           "RESERVE_ACTUATORS"]

#: low-pass cut-off of the coordinates in the written set-ups (Hz; OpenSim's usual choice for gait)
DYNAMICS_CUTOFF_HZ = 6.0
#: fewest frames of a set-up's time range
MIN_WINDOW_FRAMES = 10
#: the actuator set of the static optimisations, beside model.osim
RESERVE_ACTUATORS = "reserve_actuators.xml"
#: the knee's secondary rotations: their moments go to joint-reaction actuators in the static optimisation
KNEE_REACTIONS = tuple(f"knee_{c}_{s}" for c in ("adduction", "rotation") for s in "rl")


def known_load_window(time: np.ndarray, exclude, load_time: np.ndarray) -> tuple[float, float] | None:
    """The longest run of `time` (s, (F,)) inside the loads' time span and outside every excluded interval.

    exclude : (t0, t1, reason) intervals whose ground reaction is unknown; returns (start, end) s or None when
    no run has `MIN_WINDOW_FRAMES` frames.
    """
    t = np.asarray(time, float)
    ok = (t >= load_time[0] - 1e-9) & (t <= load_time[-1] + 1e-9)
    for t0, t1, _ in exclude:
        ok &= ~((t >= t0 - 1e-9) & (t <= t1 + 1e-9))
    best, start = (0, 0), None
    for i, v in enumerate(np.append(ok, False)):
        if v and start is None:
            start = i
        elif not v and start is not None:
            if i - start > best[1] - best[0]:
                best = (start, i)
            start = None
    if best[1] - best[0] < MIN_WINDOW_FRAMES:
        return None
    return float(t[best[0]]), float(t[best[1] - 1])


def write_dynamics_setups(pm, inputs, stage: Path, ik: dict, say, notes: list) -> dict:
    """Write the ground reactions and the ID and SO set-ups of every trial with loaded force plates (module
    docstring) into `stage` (the run's folder, model.osim already in it).

    ik : trial -> IK result (`personalize.pipeline.trials.solve_trials`); `notes` receives why a trial with plates
    got no set-up.  Returns summary.json's ``dynamics_setups``: trial -> files, time range, loaded bodies.
    """
    from kinematics.gait.inverse_dynamics import loads_from_c3d
    from kinematics.io.dynamics_setup import write_id_setup, write_reserve_actuators, write_so_setup
    from kinematics.io.external_loads import write_external_loads

    out: dict = {}
    if inputs.lab is None:
        return out
    R = np.asarray(pm.G, float) @ inputs.lab.internal_from_lab           # x_ground = R x_lab
    kin = inside(stage, "kinematics")
    for name, trial in sorted(inputs.trials.items()):
        src = trial.source
        if name not in ik or not src or Path(src).suffix.lower() != ".c3d":
            continue
        try:
            tl = loads_from_c3d(src, pm.model, rotation=R)
        except (InputError, FitError) as exc:
            notes.append(f"dynamics set-ups of {name}: {exc}")
            continue
        if not tl.loads:
            if tl.contacts:
                notes.append(f"dynamics set-ups of {name}: no plate contact applicable to one foot")
            continue
        res = ik[name]
        if not np.all(np.isfinite(res.q)):
            notes.append(f"dynamics set-ups of {name}: the IK left frames unsolved, no set-up written")
            continue
        window = known_load_window(res.time, tl.exclude, tl.loads[0].time)
        if window is None:
            notes.append(f"dynamics set-ups of {name}: no stretch of {MIN_WINDOW_FRAMES} frames with every ground "
                         "reaction known (a foot off the plates, two feet on one)")
            continue
        say(f"dynamics set-ups {name}")
        if not out:
            write_reserve_actuators(inside(stage, RESERVE_ACTUATORS), inside(stage, "model.osim"),
                                    reactions=KNEE_REACTIONS)
        write_external_loads(kin, f"{name}_grf", tl.loads,
                             frame="the model's ground (X the static pose's facing, Y up, Z right; lab origin)")
        common = dict(model_file="../model.osim", coordinates_file=f"{name}.mot",
                      external_loads_file=f"{name}_grf.xml", time_range=window, cutoff_hz=DYNAMICS_CUTOFF_HZ)
        write_id_setup(kin / f"{name}_id_setup.xml", output_gen_force_file=f"{name}_opensim_id.sto",
                       name=f"{name}_id", **common)
        write_so_setup(kin / f"{name}_so_setup.xml", force_set_files=[f"../{RESERVE_ACTUATORS}"], name=f"{name}_so",
                       **common)
        out[name] = {"time_range_s": list(window), "loaded_bodies": [ld.body for ld in tl.loads],
                     "files": {"ground_reactions": f"kinematics/{name}_grf.mot", "external_loads": f"kinematics/{name}_grf.xml",
                               "id_setup": f"kinematics/{name}_id_setup.xml", "so_setup": f"kinematics/{name}_so_setup.xml",
                               "actuators": RESERVE_ACTUATORS},
                     "outputs": {"id": f"kinematics/{name}_opensim_id.sto",
                                 "so_forces": f"kinematics/{name}_so_StaticOptimization_force.sto"},
                     "cutoff_hz": DYNAMICS_CUTOFF_HZ,
                     "units": "forces N, points m, torques N m, model ground (X facing, Y up, Z right)",
                     "excluded_intervals_s": [[a, b, why] for a, b, why in tl.exclude]}
    return out
