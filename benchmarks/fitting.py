"""Benchmark: robust shape fitting (`personalize.fitting`, issue F2).

For each primitive (sphere, cylinder, plane, ellipsoid, superquadric) and each
condition -- one factor varied at a time around a base case: noise (0.5-5 % of
the size), outlier fraction (0-50 %, uniform in the enlarged bounding box),
coverage (cap half-angle / arc / half-surface) and N (500-20 000) -- seeded
synthetic draws with known truth are fitted twice from the same closed-form
start: the robust fit (Gaussian-uniform mixture EM) and plain unweighted least
squares (``robust=False``).  Reported per method: median and 95th-percentile
error, error / Cramér-Rao ratio (median error over the median error implied by
the Cramér-Rao bound at the truth; sphere, cylinder, plane), success rate and
median single-thread CPU time per fit (``time.thread_time``, which a
shared machine does not inflate).  BLAS threads are pinned to 1.

Geometry is in metres (femoral-head-like sizes); errors are reported in mm
and degrees.  Targets (issue F2): sphere < 5 ms, superquadric < 30 ms at N = 5000.

Usage::

    python benchmarks/fitting.py [--json benchmarks/results/fitting.json] [--draws 1.0]
        [--only sphere cylinder ...]
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
           "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"          # before numpy is imported: single-thread timings

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import zlib  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from lowerlimb.atomic import write_text  # noqa: E402
from personalize.fitting import (FittingError, fit_cylinder, fit_ellipsoid,  # noqa: E402
                                 fit_plane, fit_sphere, fit_superquadric)
from personalize.fitting.synthetic import (add_outliers, cylinder_arc, cylinder_crb,  # noqa: E402
                                           random_rotation, sphere_cap, sphere_crb,
                                           superquadric_surface)

MM, DEG = 1e3, 180.0 / np.pi


def _crb_median(cov, rng, n=100_000):
    """Median norm of a zero-mean Gaussian vector with covariance ``cov``."""
    z = rng.multivariate_normal(np.zeros(len(cov)), cov, size=n)
    return float(np.median(np.linalg.norm(z, axis=1)))


# --------------------------------------------------------------------------- primitives
# Each spec: size (m), base condition, variations, draw(rng, cond) -> (points, truth),
# error(fit, truth) -> (error, success), crb(truth, cond) -> covariance or None.

def _sphere_draw(rng, c):
    R = 0.024
    Rm, ctr = random_rotation(rng), rng.uniform(-0.1, 0.1, 3)
    P, exact = sphere_cap(rng, int(round(c["n"] * (1 - c["outliers"]))), R,
                          np.radians(c["coverage"]), c["noise"] * R, ctr, Rm)
    Q, _ = add_outliers(rng, P, c["outliers"])
    return Q, dict(centre=ctr, exact=exact, R=R)


def _sphere_error(f, t):
    e = np.linalg.norm(f.centre - t["centre"])
    return e * MM, e < 0.02 * t["R"]


def _sphere_crb(t, c):
    return sphere_crb(t["exact"], t["centre"], c["noise"] * t["R"])[:3, :3] * MM ** 2


def _cyl_draw(rng, c):
    R, L = 0.020, 0.035
    Rm, pt = random_rotation(rng), rng.uniform(-0.1, 0.1, 3)
    P, exact = cylinder_arc(rng, int(round(c["n"] * (1 - c["outliers"]))), R,
                            np.radians(c["coverage"]), L, c["noise"] * R, pt, Rm)
    Q, _ = add_outliers(rng, P, c["outliers"])
    return Q, dict(point=pt, axis=Rm[:, 2], exact=exact, R=R)


def _cyl_error(f, t):
    ang = np.arccos(min(1.0, abs(f.axis @ t["axis"]))) * DEG
    d = f.point - t["point"]
    pos = np.linalg.norm(d - (d @ t["axis"]) * t["axis"])
    return ang, bool(ang < 1.0 and pos < 0.02 * t["R"])


def _cyl_crb(t, c):
    return cylinder_crb(t["exact"], t["point"], t["axis"], c["noise"] * t["R"])[2:4, 2:4] * DEG ** 2


def _plane_draw(rng, c):
    S = 0.040
    Rm = random_rotation(rng)
    n_in = int(round(c["n"] * (1 - c["outliers"])))
    local = np.column_stack([rng.uniform(-S / 2, S / 2, (n_in, 2)), np.zeros(n_in)])
    exact = local @ Rm.T
    P = exact + rng.normal(0, c["noise"] * S, n_in)[:, None] * Rm[:, 2]
    Q, _ = add_outliers(rng, P, c["outliers"])
    return Q, dict(normal=Rm[:, 2], exact=exact, S=S, Rm=Rm)


def _plane_error(f, t):
    ang = np.arccos(min(1.0, abs(f.normal @ t["normal"]))) * DEG
    return ang, ang < 1.0


def _plane_crb(t, c):
    Y = t["exact"] - t["exact"].mean(0)
    J = np.column_stack([-np.ones(len(Y)), Y @ t["Rm"][:, 0], Y @ t["Rm"][:, 1]])
    return (c["noise"] * t["S"]) ** 2 * np.linalg.inv(J.T @ J)[1:, 1:] * DEG ** 2


def _ell_draw(rng, c):
    a = np.array([0.030, 0.020, 0.012])
    Rm, ctr = random_rotation(rng), rng.uniform(-0.1, 0.1, 3)
    n_in = int(round(c["n"] * (1 - c["outliers"])))
    frac = c["coverage"] / 100.0
    P, exact = superquadric_surface(rng, int(n_in / frac) + 1, a, (1.0, 1.0),
                                    c["noise"] * a.mean(), ctr, Rm)
    if frac < 1:
        # keep the part of the surface with the largest body-x coordinates
        xb = (exact - ctr) @ Rm[:, 0]
        keep = np.argsort(-xb)[:n_in]
        P = P[keep]
    Q, _ = add_outliers(rng, P[:n_in], c["outliers"])
    return Q, dict(centre=ctr, a=a)


def _ell_error(f, t):
    e = np.linalg.norm(f.centre - t["centre"])
    ok = e < 0.02 * t["a"].mean() and np.all(np.abs(f.radii - t["a"]) < 0.02 * t["a"])
    return e * MM, bool(ok)


_GRID = (0.3, 0.7, 1.0, 1.5)


def _sq_draw(rng, c):
    e1, e2 = rng.choice(_GRID), rng.choice(_GRID)
    while True:
        a = rng.uniform(0.010, 0.030, 3)
        s = np.sort(a)
        if s[1] > 1.15 * s[0] and s[2] > 1.15 * s[1]:
            break
    if a[1] > a[0]:
        a[[0, 1]] = a[[1, 0]]
    Rm, ctr = random_rotation(rng), rng.uniform(-0.1, 0.1, 3)
    P, _ = superquadric_surface(rng, int(round(c["n"] * (1 - c["outliers"]))), a, (e1, e2),
                                c["noise"] * a.mean(), ctr, Rm)
    Q, _ = add_outliers(rng, P, c["outliers"])
    return Q, dict(centre=ctr, a=a, R=Rm, eps=np.array([e1, e2]))


def _sq_error(f, t):
    a, Rm, (e1, e2) = t["a"], t["R"], t["eps"]
    e = np.linalg.norm(f.centre - t["centre"])
    if e1 == e2:
        Rt, Rf = Rm[:, np.argsort(a)], f.rotation[:, np.argsort(f.scale)]
    else:
        Rt, Rf = Rm, f.rotation
    ok = (e < 0.02 * a.mean() and np.all(np.abs(f.shape - t["eps"]) < 0.1)
          and np.all(np.abs(np.sum(Rt * Rf, axis=0)) > np.cos(np.radians(3.0))))
    return e / a.mean() * 100.0, bool(ok)


def _vary(base, **lists):
    conds = {tuple(sorted(base.items())): dict(base)}
    for key, values in lists.items():
        for v in values:
            c = dict(base, **{key: v})
            conds.setdefault(tuple(sorted(c.items())), c)
    return list(conds.values())


SPECS = {
    "sphere": dict(
        fit=fit_sphere, draw=_sphere_draw, error=_sphere_error, crb=_sphere_crb,
        error_name="centre_error_mm", coverage="cap half-angle (deg)",
        conditions=_vary(dict(noise=0.02, outliers=0.0, coverage=60, n=2000),
                         noise=[0.005, 0.01, 0.05], outliers=[0.1, 0.3, 0.5],
                         coverage=[45, 90, 180], n=[500, 5000, 20000]),
        draws=40),
    "cylinder": dict(
        fit=fit_cylinder, draw=_cyl_draw, error=_cyl_error, crb=_cyl_crb,
        error_name="axis_error_deg", coverage="arc (deg)",
        conditions=_vary(dict(noise=0.025, outliers=0.0, coverage=120, n=2000),
                         noise=[0.005, 0.05], outliers=[0.1, 0.3, 0.5],
                         coverage=[90, 180, 360], n=[500, 5000, 20000]),
        draws=30),
    "plane": dict(
        fit=fit_plane, draw=_plane_draw, error=_plane_error, crb=_plane_crb,
        error_name="normal_error_deg", coverage="full 40 x 40 mm patch",
        conditions=_vary(dict(noise=0.01, outliers=0.0, coverage=100, n=2000),
                         noise=[0.005, 0.05], outliers=[0.1, 0.3, 0.5], n=[500, 5000, 20000]),
        draws=30),
    "ellipsoid": dict(
        fit=fit_ellipsoid, draw=_ell_draw, error=_ell_error, crb=None,
        error_name="centre_error_mm", coverage="surface kept (%)",
        conditions=_vary(dict(noise=0.01, outliers=0.0, coverage=100, n=3000),
                         noise=[0.005, 0.05], outliers=[0.2, 0.5], coverage=[50],
                         n=[500, 5000, 20000]),
        draws=20),
    "superquadric": dict(
        fit=fit_superquadric, draw=_sq_draw, error=_sq_error, crb=None,
        error_name="centre_error_pct_of_size", coverage="full surface",
        conditions=_vary(dict(noise=0.01, outliers=0.2, coverage=100, n=3000),
                         noise=[0.005, 0.02, 0.05], outliers=[0.0, 0.5], n=[500, 5000, 20000]),
        draws=24),
}


def _stats(errors, ok, times, crb_med):
    e = np.asarray(errors, float)
    finite = np.isfinite(e)
    out = {
        "median_error": float(np.median(e)) if finite.all() or finite.mean() > 0.5 else None,
        "p95_error": float(np.percentile(e, 95)) if finite.mean() >= 0.95 else None,
        "success_rate": float(np.mean(ok)),
        "failed_fits": int((~finite).sum()),
        "median_time_ms": float(np.median(times) * 1e3),
    }
    if crb_med is not None and out["median_error"] is not None:
        out["crb_median_error"] = crb_med
        out["error_over_crb"] = out["median_error"] / crb_med
    return out


def run(names, draws_scale, progress):
    results = {}
    for name in names:
        spec = SPECS[name]
        rows = []
        for cond in spec["conditions"]:
            big = 0.4 if cond["n"] >= 20000 else 1.0          # fewer draws for N = 20 000
            nd = max(5, int(round(spec["draws"] * draws_scale * big)))
            rng = np.random.default_rng(zlib.crc32(repr((name, sorted(cond.items()))).encode()))
            per = {m: dict(err=[], ok=[], t=[]) for m in ("robust", "plain")}
            crbs = []
            for _ in range(nd):
                P, truth = spec["draw"](rng, cond)
                if spec["crb"] is not None:
                    crbs.append(spec["crb"](truth, cond))
                for method, robust in (("robust", True), ("plain", False)):
                    # CPU time of this thread: robust to other processes on a shared
                    # machine; equals wall time on an idle core (BLAS pinned to 1 thread).
                    t0 = time.thread_time()
                    try:
                        f = spec["fit"](P, robust=robust)
                        dt = time.thread_time() - t0
                        err, ok = spec["error"](f, truth)
                    except FittingError:
                        dt, err, ok = time.thread_time() - t0, np.inf, False
                    per[method]["err"].append(err)
                    per[method]["ok"].append(ok)
                    per[method]["t"].append(dt)
                progress()
            crb_med = _crb_median(np.mean(crbs, 0), np.random.default_rng(0)) if crbs else None
            row = {"condition": dict(cond, noise_pct=cond["noise"] * 100,
                                     outliers_pct=cond["outliers"] * 100), "draws": nd}
            for m in per:
                row[m] = _stats(per[m]["err"], per[m]["ok"], per[m]["t"], crb_med)
            rows.append(row)
        results[name] = {"error": spec["error_name"], "coverage": spec["coverage"], "rows": rows}
    return results


def _table(results):
    lines = []
    for name, res in results.items():
        lines.append(f"\n{name}  (error = {res['error']}; coverage = {res['coverage']})")
        lines.append(f"{'noise%':>6} {'out%':>5} {'cov':>5} {'N':>6} | "
                     f"{'med':>8} {'p95':>8} {'/CRB':>5} {'succ':>5} {'ms':>6} | "
                     f"{'plain med':>9} {'p95':>8} {'/CRB':>5} {'succ':>5} {'ms':>6}")
        for r in res["rows"]:
            c = r["condition"]

            def f(v, fmt):
                return format(v, fmt) if v is not None else "-".rjust(len(format(0.0, fmt)))
            cells = []
            for m in ("robust", "plain"):
                s = r[m]
                cells.append(f"{f(s['median_error'], '8.4f')} {f(s['p95_error'], '8.4f')} "
                             f"{f(s.get('error_over_crb'), '5.2f')} {s['success_rate']:5.2f} "
                             f"{s['median_time_ms']:6.1f}")
            lines.append(f"{c['noise_pct']:6.1f} {c['outliers_pct']:5.0f} {c['coverage']:5} "
                         f"{c['n']:6d} | {cells[0]} | {' ' + cells[1]}")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "fitting.json"))
    ap.add_argument("--draws", type=float, default=1.0, help="scale the number of draws")
    ap.add_argument("--only", nargs="*", choices=list(SPECS), default=list(SPECS))
    args = ap.parse_args(argv)
    from rich.progress import Progress

    total = sum(max(5, int(round(SPECS[n]["draws"] * args.draws
                                 * (0.4 if c["n"] >= 20000 else 1.0))))
                for n in args.only for c in SPECS[n]["conditions"])
    with Progress(transient=True) as prog:
        task = prog.add_task("fitting draws", total=total)
        results = run(args.only, args.draws, lambda: prog.advance(task))
    doc = {
        "benchmark": "personalize.fitting robust vs plain least squares",
        "units": {"centre_error_mm": "mm", "axis_error_deg": "degree", "normal_error_deg": "degree",
                  "centre_error_pct_of_size": "percent of mean semi-axis",
                  "median_time_ms": "ms of thread CPU time (time.thread_time), single thread, "
                                    "one fit including its closed-form start and restarts",
                  "geometry": "metres (sphere R 24 mm, cylinder R 20 mm x 35 mm, plane 40 mm, "
                              "ellipsoid 30/20/12 mm, superquadric semi-axes 10-30 mm)"},
        "frame": "synthetic, random rigid pose per draw",
        "targets": {"sphere_ms_at_N5000": 5.0, "superquadric_ms_at_N5000": 30.0},
        "machine": {"python": platform.python_version(), "numpy": np.__version__,
                    "cpu_count": os.cpu_count(), "loadavg_at_end": os.getloadavg()},
        "results": results,
    }
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, json.dumps(doc, indent=1))
    print(_table(results))
    print(f"\nwritten {out}")


if __name__ == "__main__":
    main()
