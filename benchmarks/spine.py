"""Benchmark: the coupled spine of Raunhardt & Boulic (2007), section 5, coupled against uncoupled.

(a) Isolated 24-vertebra spine (17 swing + 7 twist joints, 32 equalities, 12
    inequalities) with a high-priority head orientation task and a
    low-priority head position task: task error per iteration (% of the
    initial error), time per iteration, norm of the joint variation (Fig. 5),
    swing components (s_x extension, s_y bending) per region (Fig. 6).
    Uncoupled: the same joints, no coupling, every joint limited.
(b) Full-body mannequin with the simplified spine (coupled: 8 swing + 5 twist
    joints; uncoupled: 8 exponential-map ball joints with the same per-joint
    ranges), balanced posture: COM over the left foot (priority 0), left foot
    on the ground (1), right toe backwards and hands reaching (2), head
    looking forward (3).  Count of torsion-direction changes between
    successive vertebrae inside a region (Fig. 8).
(c) Mannequins, hands on a figure eight (COM between the feet, feet on
    the ground, head forward), one IK step per goal sample: joint-space drift
    of the posture after 1, 5, 50, 100, 200, 600 and 2000 cycles from the
    posture after the first cycle (Fig. 9).  ``drift_rad`` is the spine drift
    (geodesic distance of the vertebral rotations, parametrisation-free, rad);
    ``drift_posture_rad`` the same over every joint of the body (whole
    posture, parametrisation-free); ``drift_all_rad`` the Euclidean distance
    over every rotational coordinate.  Variants (see ``drift_variants``):
    ``coupled``; ``uncoupled`` = the like-for-like baseline, the same
    swing/twist joints and the SAME limit set (first joint of each region)
    without the coupling constraints; ``uncoupled_all_joints_limited`` (ball
    joints, every vertebral range enforced); ``uncoupled_unlimited`` (ball
    joints, no vertebral range).  ``drift_bound_rad``: the a-priori bound of
    the spine drift from the limits and couplings (`spine_drift_bound`).

Usage::

    python benchmarks/spine.py [--json benchmarks/results/spine.json] [--out benchmarks/results/spine]
                               [--cycles 2000] [--steps-per-cycle 12] [--quick]

Writes the JSON (SI units: s, rad, m) and the plots (PNG) into the folder.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from rich.progress import Progress  # noqa: E402

from lowerlimb.atomic import staged_dir, write_text  # noqa: E402
from kinematics.algorithms.fk import forward_kinematics  # noqa: E402
from kinematics.algorithms.prioritized import PrioritizedIK  # noqa: E402
from kinematics.algorithms.tasks import KinematicTasks  # noqa: E402
from kinematics.mechanisms.spine import isolated_spine, mannequin, spine_layout  # noqa: E402
from kinematics.mechanisms.spine_measures import (spine_drift_bound, swing_components,  # noqa: E402
                                                  torsion_direction_changes, vertebral_twist)
from spine_experiments import balanced_posture_tasks, isolated_spine_tasks, periodic_drift  # noqa: E402

CHECKPOINTS = (1, 5, 50, 100, 200, 600, 2000)

# figure-eight variants: mannequin keyword arguments and a statement of their spine limits
DRIFT_VARIANTS = {
    "coupled": (dict(coupled=True), "swing/twist vertebral joints (8 swing, 5 twist); ranges enforced on the first "
                "swing and first twist joint of each region only (vl5, vl3 twist, vt10, vc7); 12 coupling equalities "
                "and 12 inter-region inequalities keep the other joints in range"),
    "uncoupled": (dict(coupled=False, joint_style="swing_twist", spine_limits="first"),
                  "like-for-like baseline (uncoupled_same_limit_set): the same swing/twist joints and the SAME limit "
                  "set as 'coupled' (first joint of each region: vl5, vl3 twist, vt10, vc7), no coupling constraints"),
    "uncoupled_all_joints_limited": (dict(coupled=False), "8 exponential-map ball joints, every vertebral range "
                                     "enforced (region range / number of joints), no coupling constraints"),
    "uncoupled_unlimited": (dict(coupled=False, limit_spine=False), "8 exponential-map ball joints, no vertebral "
                            "range enforced, no coupling constraints"),
}


def _solve_timed(model, tasks, iterations, repeats):
    """Run the IK `repeats` times from the default pose; median time per iteration over all runs."""
    ik = PrioritizedIK.from_model(model, tasks)
    per_iter = []
    res = None
    for _ in range(repeats):
        res = ik.solve(model.default_q, max_iterations=iterations, tol=0.0)
        per_iter.append(res.times)
    return ik, res, float(np.median(np.concatenate(per_iter)))


def experiment_isolated(repeats: int) -> dict:
    out = {}
    for label, coupled in (("coupled", True), ("uncoupled", False)):
        model = isolated_spine("full", coupled)
        kt = KinematicTasks(model)
        ik, res, t_iter = _solve_timed(model, isolated_spine_tasks(model, kt), 30, repeats)
        cons = ik.constraints
        out[label] = {
            "model": model, "q": res.q,
            "error_percent": (100.0 * res.errors / res.errors[0]).tolist(),
            "errors": res.errors.tolist(), "step_norm_rad": res.step_norms.tolist(),
            "time_per_iteration_s": t_iter,
            "final_task_error": res.errors[-1].tolist(),
            "max_equality_residual": float(np.max(np.abs(cons.equality_residual(res.q)), initial=0.0)),
            "max_inequality_excess": float(np.max(cons.inequality_excess(res.q), initial=0.0)),
            "swing": {k: v.tolist() for k, v in swing_components(model, res.q).items()},
            "dofs": model.n_q, "equalities": int(len(cons.b)), "inequalities": int(len(cons.h)),
        }
    return out


def experiment_balanced(repeats: int, spine: str = "simplified") -> dict:
    out = {}
    for label, coupled in (("coupled", True), ("uncoupled", False)):
        model = mannequin(spine, coupled)
        kt = KinematicTasks(model)
        ik = PrioritizedIK.from_model(model, balanced_posture_tasks(model, kt))
        res = ik.solve(model.default_q, max_iterations=300, tol=1e-6)
        times = [ik.solve(model.default_q, max_iterations=20, tol=0.0).times for _ in range(repeats)]
        changes = torsion_direction_changes(model, res.q)
        out[label] = {
            "model": model, "q": res.q, "iterations": res.iterations, "converged": res.converged,
            "final_task_error": res.errors[-1].tolist(),
            "torsion_direction_changes": changes, "total_changes": int(sum(changes.values())),
            "vertebral_twist_rad": {k: v.tolist() for k, v in vertebral_twist(model, res.q).items()},
            "time_per_iteration_s": float(np.median(np.concatenate(times))),
        }
    return out


def experiment_drift(cycles: int, steps_per_cycle: int) -> dict:
    out = {}
    with Progress() as progress:
        for label, (kw, _) in DRIFT_VARIANTS.items():
            model = mannequin("simplified", **kw)
            task = progress.add_task(f"figure eight, {label}", total=cycles)
            t0 = time.perf_counter()
            res = periodic_drift(model, cycles, steps_per_cycle, CHECKPOINTS,
                                 progress=lambda c: progress.update(task, completed=c))
            res["wall_s"] = time.perf_counter() - t0
            res["model"] = model
            res["bound"] = spine_drift_bound(model)
            out[label] = res
    return out


# ----------------------------------------------------------------------------- plots
def _segments(model, q):
    st = forward_kinematics(model, q)
    p = st.positions[0]
    return [(p[model.parent[i]], p[i]) for i in range(2, model.n_bodies)] + [(p[0] * 0 + p[1], p[1])]


def _draw(ax, model, q, view, **kw):
    h = 2 if view == "front" else 0
    for a, b in _segments(model, q):
        ax.plot([a[h], b[h]], [a[1], b[1]], "-", **kw)
    ax.set_aspect("equal")


def plot_all(folder: Path, iso: dict, bal: dict, drift: dict | None) -> list[str]:
    files = []
    # Figure 5: convergence, time, joint variation
    fig, axs = plt.subplots(1, 3, figsize=(13, 4))
    for label, ls in (("coupled", "-"), ("uncoupled", "--")):
        e = np.array(iso[label]["error_percent"])
        axs[0].plot(e[:, 0], ls, label=f"orientation, {label}")
        axs[0].plot(e[:, 1], ls, label=f"position, {label}")
        axs[1].plot(iso[label]["step_norm_rad"], ls, label=label)
        axs[2].bar(label, 1e3 * iso[label]["time_per_iteration_s"])
    axs[0].set(xlabel="iteration", ylabel="task error (% of initial)", title="error convergence")
    axs[1].set(xlabel="iteration", ylabel="|dq| (rad)", title="norm of the joint variation")
    axs[2].set(ylabel="median time per iteration (ms)", title="time per iteration")
    axs[0].legend(fontsize=7)
    axs[1].legend()
    fig.tight_layout()
    fig.savefig(folder / "fig5_isolated_spine_convergence.png", dpi=120)
    plt.close(fig)
    files.append("fig5_isolated_spine_convergence.png")
    # Figure 6: swing components per region
    fig, axs = plt.subplots(1, 2, figsize=(10, 4.5), sharex=True, sharey=True)
    for ax, label in zip(axs, ("uncoupled", "coupled")):
        for region, mk in (("lumbar", "o"), ("thoracic", "s"), ("cervical", "^")):
            s = np.degrees(np.array(iso[label]["swing"][region]))
            ax.scatter(s[:, 0], s[:, 1], marker=mk, label=region)
        ax.set(title=label, xlabel="s_x extension (deg)", ylabel="s_y lateral bending (deg)")
        ax.axhline(0, color="0.8", lw=0.5)
        ax.axvline(0, color="0.8", lw=0.5)
        ax.legend()
    fig.tight_layout()
    fig.savefig(folder / "fig6_swing_distribution.png", dpi=120)
    plt.close(fig)
    files.append("fig6_swing_distribution.png")
    # Figure 8: vertebral torsion, balanced posture
    fig, axs = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, label in zip(axs, ("uncoupled", "coupled")):
        names, vals, cols = [], [], []
        for region, col in (("lumbar", "C0"), ("thoracic", "C1"), ("cervical", "C2")):
            tw = np.degrees(bal[label]["vertebral_twist_rad"][region])
            reg = [r for r in spine_layout("simplified").regions if r.name == region][0]
            names += list(reg.joints)
            vals += list(tw)
            cols += [col] * len(tw)
        ax.bar(names, vals, color=cols)
        ax.set(title=f"{label}: {bal[label]['total_changes']} torsion-direction change(s)",
               ylabel="torsion relative to the vertebra below (deg)")
    fig.tight_layout()
    fig.savefig(folder / "fig8_vertebral_torsion.png", dpi=120)
    plt.close(fig)
    files.append("fig8_vertebral_torsion.png")
    # Figure 9: drift
    if drift:
        fig, axs = plt.subplots(1, 2, figsize=(11, 4.5))
        for label, res in drift.items():
            cs = [c for c in sorted(res["drift_rad"]) if c > 1]
            axs[0].plot(cs, [res["drift_spine_rad"][c] for c in cs], "o-", label=label)
            axs[1].plot(cs, [res["drift_posture_rad"][c] for c in cs], "o-", label=label)
        axs[0].axhline(drift["coupled"]["bound"]["geodesic_rad"], color="C0", ls=":", label="coupled: a-priori bound")
        axs[0].set(xscale="log", xlabel="cycles", ylabel="spine drift (rad, geodesic)", title="spine")
        axs[1].set(xscale="log", xlabel="cycles", ylabel="drift, every joint (rad, geodesic)", title="whole posture")
        axs[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(folder / "fig9_drift.png", dpi=120)
        plt.close(fig)
        files.append("fig9_drift.png")
    # Postures (Figs. 4, 7, 9)
    ncol = 4 if drift else 2
    fig, axs = plt.subplots(2, ncol, figsize=(3.2 * ncol, 8))
    axs = np.atleast_2d(axs)
    for view, ax in zip(("front", "left"), axs[:, 0]):
        for label, col in (("uncoupled", "C3"), ("coupled", "C0")):
            m = iso[label]["model"]
            if label == "coupled":
                _draw(ax, m, m.default_q, view, color="0.7")
            _draw(ax, m, iso[label]["q"], view, color=col, marker=".", ms=3)
        ax.set_title(f"isolated spine, {view} (blue coupled, red uncoupled)", fontsize=8)
    for view, ax in zip(("front", "left"), axs[:, 1]):
        for label, col in (("uncoupled", "C3"), ("coupled", "C0")):
            m = bal[label]["model"]
            _draw(ax, m, bal[label]["q"], view, color=col, lw=1)
        ax.set_title(f"balanced posture, {view}", fontsize=8)
    if drift:
        for j, label in enumerate(("coupled", "uncoupled")):
            res = drift[label]
            m = res["model"]
            last = max(res["postures"])
            for view, ax in zip(("front", "left"), axs[:, 2 + j]):
                _draw(ax, m, res["postures"][1], view, color="0.7", lw=1)
                _draw(ax, m, res["postures"][last], view, color="C0" if label == "coupled" else "C3", lw=1)
                ax.set_title(f"{label}: cycle 1 (grey) vs {last}, {view}", fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "postures.png", dpi=120)
    plt.close(fig)
    files.append("postures.png")
    return files


def _finite(x: float) -> float | None:
    """JSON has no infinity: unbounded -> null."""
    return float(x) if np.isfinite(x) else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "spine.json"))
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "spine"))
    ap.add_argument("--cycles", type=int, default=2000)
    ap.add_argument("--steps-per-cycle", type=int, default=12)
    ap.add_argument("--repeats", type=int, default=5, help="repetitions of the timed IK runs")
    ap.add_argument("--quick", action="store_true", help="20 cycles, 2 repeats (smoke run)")
    args = ap.parse_args(argv)
    if args.quick:
        args.cycles, args.repeats = 20, 2

    t0 = time.perf_counter()
    iso = experiment_isolated(args.repeats)
    bal = experiment_balanced(args.repeats)
    drift = experiment_drift(args.cycles, args.steps_per_cycle) if args.cycles > 0 else None

    def key(d):
        return {str(k): v for k, v in sorted(d.items())}

    result = {
        "units": "seconds (s), radians (rad), metres (m); frames: ground, y up",
        "machine": {"python": platform.python_version(), "platform": platform.platform()},
        "torsion_direction_changes": {k: bal[k]["total_changes"] for k in ("coupled", "uncoupled")},
        "torsion_direction_changes_per_region": {k: bal[k]["torsion_direction_changes"] for k in ("coupled", "uncoupled")},
        "time_per_iteration_s": {k: iso[k]["time_per_iteration_s"] for k in ("coupled", "uncoupled")},
        "time_per_iteration_mannequin_s": {k: bal[k]["time_per_iteration_s"] for k in ("coupled", "uncoupled")},
        "final_task_error": {
            "isolated_spine_per_level": {k: iso[k]["final_task_error"] for k in ("coupled", "uncoupled")},
            "balanced_posture_per_level": {k: bal[k]["final_task_error"] for k in ("coupled", "uncoupled")},
        },
        "isolated_spine": {k: {kk: vv for kk, vv in v.items() if kk not in ("model", "q")} for k, v in iso.items()},
        "balanced_posture": {k: {kk: vv for kk, vv in v.items() if kk not in ("model", "q")} for k, v in bal.items()},
    }
    if drift:
        result["drift_measures"] = {
            "drift_rad": "spine: sqrt(sum_v theta_v^2), theta_v the angle between vertebra v's rotation "
                         "relative to the vertebra below after c cycles and after cycle 1 (rad)",
            "drift_posture_rad": "whole posture: the same over every body relative to its parent (pelvis to ground; "
                                 "translations excluded) (rad)",
            "drift_all_rad": "whole posture: Euclidean |q(c) - q(1)| over every rotational coordinate (rad; depends on "
                             "the joint parametrisation)"}
        result["drift_variants"] = {
            k: {"mannequin_kwargs": kw, "limits": text, "model": drift[k]["model"].name,
                "clamped_spine_coordinates": [c.name for c in drift[k]["model"].coordinates
                                              if c.clamped and c.name in drift[k]["bound"]["span_rad"]]}
            for k, (kw, text) in DRIFT_VARIANTS.items()}
        result["drift_rad"] = {k: key(v["drift_spine_rad"]) for k, v in drift.items()}
        result["drift_posture_rad"] = {k: key(v["drift_posture_rad"]) for k, v in drift.items()}
        result["drift_all_rad"] = {k: key(v["drift_rad"]) for k, v in drift.items()}
        result["drift_bound_rad"] = {
            k: {"note": "a-priori bounds of the spine drift from the enforced limits and couplings "
                        "(spine_drift_bound); null = unbounded (some spine coordinate has no limit)",
                "a_priori_geodesic": _finite(v["bound"]["geodesic_rad"]),
                "a_priori_coordinate": _finite(v["bound"]["coordinate_rad"]),
                "observed_max_over_checkpoints": max(v["drift_spine_rad"].values())}
            for k, v in drift.items()}
        result["final_task_error"]["periodic_max_per_level"] = {k: v["max_task_error"] for k, v in drift.items()}
        result["periodic"] = {"cycles": args.cycles, "steps_per_cycle": args.steps_per_cycle,
                              "wall_s": {k: v["wall_s"] for k, v in drift.items()},
                              "max_equality_residual": {k: v["max_equality_residual"] for k, v in drift.items()},
                              "max_inequality_or_limit_excess": {k: v["max_inequality_or_limit_excess"]
                                                                 for k, v in drift.items()}}
        last = str(max(int(c) for c in result["drift_rad"]["coupled"]))
        result["drift_ratio_uncoupled_over_coupled"] = {
            measure: {k: result[measure][k][last] / max(result[measure]["coupled"][last], 1e-300)
                      for k in result[measure] if k != "coupled"}
            for measure in ("drift_rad", "drift_posture_rad", "drift_all_rad")}
        result["drift_ratio_uncoupled_over_coupled"]["at_cycles"] = int(last)
    result["wall_s"] = time.perf_counter() - t0
    with staged_dir(args.out) as stage:
        result["plots"] = plot_all(stage, iso, bal, drift)
    write_text(args.json, json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in ("torsion_direction_changes", "time_per_iteration_s",
                                            "time_per_iteration_mannequin_s", "final_task_error")
                      if k in result}, indent=1))
    if drift:
        print(json.dumps({k: result[k] for k in ("drift_rad", "drift_posture_rad", "drift_all_rad", "drift_bound_rad",
                                                 "drift_ratio_uncoupled_over_coupled")},
                         indent=1))
    print(f"wrote {args.json} and {args.out}/")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
