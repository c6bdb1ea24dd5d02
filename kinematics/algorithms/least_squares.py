"""Batched, inequality-constrained Levenberg-Marquardt over the frames of a trial.

Each step solves the equality-constrained damped normal equations

    [J^T J + lambda I   A_W^T] [dz]   [-J^T r]
    [A_W                0    ] [mu] = [ s_W  ]

for the working set W of inequality rows (slack s = b - A z), an active-set
clamping loop: rows with mu < 0 leave W, rows the step would cross enter W,
until the step is feasible.  `solve_stream` iterates a pipelined window of
frames, vectorised: new frames enter the window warm-started from the newest
nearly-solved frame extrapolated at the velocity of the last solved frames,
and leave it once the estimated distance to their optimum (last step times
rho / (1 - rho), rho the observed linear convergence rate) is below
``tolerance``.  `solve_block` solves a block of frames from given starts;
`repair_jumps` re-solves frames whose solution jumps away from a neighbour's.

The problem is any object with ``cmap`` (a `CoordinateMap`: ``ineq_matrix``,
``ineq_rhs``, ``basis``, ``n_z``), ``wrap(z)`` (an equivalent z of the same
poses) and ``evaluate(z, y, ok, jac=True) -> (r, J, q, x)`` (residuals
(n, m), Jacobians (n, m, n_z) in z).
"""
from __future__ import annotations

import numpy as np

__all__ = ["constrained_step", "lm_direction", "feasible", "solve_stream", "solve_block", "repair_jumps"]

_EXTRAP = 4


def constrained_step(H, g, A, s, tol=1e-12, max_loops=None):
    """Active-set solution of min 1/2 d^T H d + g^T d  s.t.  A d <= s, for a batch.

    H (n,p,p), g (n,p), A (m,p), s (n,m) slack (>= -tol).  Returns d (n,p).
    """
    n, p = g.shape
    m = A.shape[0]
    d_free = np.linalg.solve(H, -g[..., None])[..., 0]
    if m == 0:
        return d_free
    W = s <= 1e-10                                # rows already on their bound
    need = W.any(1) | (d_free @ A.T > s + tol).any(1)
    if not need.any():
        return d_free                             # no bound touched: the plain damped step
    if not need.all():
        d_free[need] = constrained_step(H[need], g[need], A, s[need], tol, max_loops)
        return d_free
    max_loops = max_loops or 2 * m + 2
    d = None
    for _ in range(max_loops):
        K = np.zeros((n, p + m, p + m))
        K[:, :p, :p] = H
        Aw = A[None, :, :] * W[..., None]
        K[:, :p, p:] = np.swapaxes(Aw, 1, 2)
        K[:, p:, :p] = Aw
        K[:, p:, p:] = np.eye(m)[None] * (~W)[:, :, None] * -1.0
        rhs = np.concatenate([-g, np.where(W, s, 0.0)], axis=1)
        sol = np.linalg.solve(K, rhs[..., None])[..., 0]
        d, mu = sol[:, :p], sol[:, p:]
        changed = np.zeros(n, bool)
        # Drop rows whose multiplier pulls inward (the bound is not binding).
        drop = W & (mu < -1e-12)
        if drop.any():
            # one at a time per frame: the most negative multiplier
            k = np.argmin(np.where(drop, mu, np.inf), axis=1)
            rowsel = drop.any(1)
            W[np.flatnonzero(rowsel), k[rowsel]] = False
            changed |= rowsel
        viol = (~W) & (d @ A.T > s + tol)
        if viol.any():
            # Clamp the row crossed first along the step.
            Ad = d @ A.T
            t = np.where(viol, s / np.where(Ad > 0, Ad, 1.0), np.inf)
            k = np.argmin(t, axis=1)
            rowsel = viol.any(1) & ~changed
            W[np.flatnonzero(rowsel), k[rowsel]] = True
            changed |= rowsel
        if not changed.any():
            break
    return d


def converged(dq, prev, acc, tol, lam):
    """Accepted, (nearly) undamped steps whose estimated remaining error is below `tol`.

    Gauss-Newton on a problem with non-zero residuals converges linearly;
    with the observed rate rho = |dq_k| / |dq_k-1| the distance of the new
    iterate to the optimum is about |dq_k| rho / (1 - rho).  A step shortened
    by strong damping says nothing about convergence, hence ``lam`` (the
    relative damping the step used) must be small.
    """
    rho = np.clip(np.where(np.isfinite(prev) & (prev > 0), dq / np.where(prev > 0, prev, 1.0), 1.0), 0.0, 0.9)
    est = np.where(np.isfinite(prev), dq * rho / (1.0 - rho), dq)
    return acc & (lam <= 1e-4) & (np.minimum(est, dq) < tol)


def lm_direction(J, r, lam, z, A, bnd):
    """Damped Gauss-Newton step for a batch, restricted by the active inequalities."""
    Jt = np.swapaxes(J, 1, 2)
    H = Jt @ J
    g = (Jt @ r[..., None])[..., 0]
    p = H.shape[1]
    scale = np.maximum(np.trace(H, axis1=1, axis2=2) / p, 1e-12)
    H[:, np.arange(p), np.arange(p)] += (lam * scale)[:, None]
    s = (bnd - z @ A.T) if A.shape[0] else np.zeros((z.shape[0], 0))
    return constrained_step(H, g, A, np.maximum(s, 0.0))


def feasible(z, A, bnd):
    """Move z onto the inequality rows it violates (coordinate limits are axis rows in practice)."""
    if not A.shape[0]:
        return z
    z = z.copy()
    for _ in range(3):
        viol = z @ A.T - bnd
        if not (viol > 0).any():
            break
        for k in range(A.shape[0]):
            v = viol[:, k] > 0
            if v.any():
                z[v] -= np.outer(viol[v, k], A[k]) / (A[k] @ A[k])
    return z


def solve_stream(problem, z_start, Y, ok, tolerance, max_iterations, admit, lam0=1e-6, progress=None,
                  admit_step=None):
    """Pipelined Levenberg-Marquardt over consecutive frames.

    A window of frames is iterated together (one vectorised evaluation per
    iteration).  New frames (up to `admit` per iteration) enter once the last
    frame of the window is nearly solved (its last step below `admit_step`,
    default 10 x `tolerance`), started from that frame's iterate plus the
    velocity of the last solved frames; converged frames leave.  Every frame
    thus starts next to an almost-solved neighbour (warm start) while the
    per-evaluation overhead is shared by the whole window.  The admission step
    must be small: a start extrapolated from an iterate still moving (e.g.
    0.05 rad from its optimum) lands, on nearly singular problems (hip and knee
    rotation with Plug-in-Gait markers only), in another local minimum that
    the warm starts then carry over the following frames.
    """
    if admit_step is None:
        admit_step = 10.0 * tolerance
    cmap = problem.cmap
    A, bnd = cmap.ineq_matrix, cmap.ineq_rhs
    F, nz = Y.shape[0], cmap.n_z
    Z = np.full((F, nz), np.nan)
    its = np.zeros(F, int)
    conv = np.zeros(F, bool)
    win = np.zeros(0, int)
    z = np.zeros((0, nz))
    r = J = None
    cost = lam = last = np.zeros(0)
    it = np.zeros(0, int)
    nxt = 0
    solved = {-1: np.asarray(z_start, float)}      # frame -> solution (converged frames; -1: the start)
    done = 0

    def velocity():
        # The newest pair of consecutive solved frames (a bounded look-back keeps long trials linear).
        top = max(solved)
        for b in range(top, max(top - 64, 0), -1):
            if b in solved and b - 1 in solved:
                return solved[b] - solved[b - 1]
        return np.zeros(nz)

    while nxt < F or win.size:
        if win.size:
            d = lm_direction(J, r, lam, z, A, bnd)
            zt = z + d
        else:
            d = zt = np.zeros((0, nz))
        n_new = min(admit, F - nxt)
        if n_new and win.size and last[-1] > admit_step:
            n_new = 0                                # wait: the newest frame is not solved well enough yet
        if n_new:
            if win.size:
                base_f, base = win[-1], z[-1]
            else:
                base_f = max(solved)
                base = solved[base_f]
            new = np.arange(nxt, nxt + n_new)
            steps = np.minimum(new - base_f, _EXTRAP)[:, None]
            zi = feasible(problem.wrap(base[None] + steps * velocity()[None]), A, bnd)
            nxt += n_new
        else:
            zi = np.zeros((0, nz))
            new = np.zeros(0, int)
        idx = np.concatenate([win, new])
        rr, JJ, _, _ = problem.evaluate(np.concatenate([zt, zi]), Y[idx], ok[idx])
        cc = np.einsum("ni,ni->n", rr, rr)
        m = win.size
        if m:
            acc = cc[:m] <= cost * (1 + 1e-12) + 1e-30
            z[acc], r[acc], J[acc], cost[acc] = zt[acc], rr[:m][acc], JJ[:m][acc], cc[:m][acc]
            dq = np.abs(d @ cmap.basis.T).max(axis=1)
            small = converged(dq, last, acc, tolerance, lam) | ((~acc) & (dq < tolerance) & (lam <= 1e-4))
            lam = np.where(acc, np.maximum(lam / 10.0, 1e-14), lam * 10.0)
            it += 1
            last = np.where(acc, dq, last)
            leave = small | (~acc & (lam > 1e12)) | (it >= max_iterations)
            if leave.any():
                Z[win[leave]] = z[leave]
                its[win[leave]] = it[leave]
                conv[win[leave]] = small[leave]
                for f, zf, c in zip(win[leave], z[leave], small[leave]):
                    if c:
                        solved[int(f)] = zf
                newest = max(solved)                 # never empty: the warm start needs a solved frame
                for f in [k for k in solved if k < nxt - 256 and k != newest]:
                    del solved[f]
                keep = ~leave
                win, z, r, J = win[keep], z[keep], r[keep], J[keep]
                cost, lam, it, last = cost[keep], lam[keep], it[keep], last[keep]
                done += int(leave.sum())
                if progress is not None:
                    progress(done, F)
        if new.size:
            win = np.concatenate([win, new])
            z = np.concatenate([z, zi])
            r = rr[m:] if r is None or r.shape[0] == 0 else np.concatenate([r, rr[m:]])
            J = JJ[m:] if J is None or J.shape[0] == 0 else np.concatenate([J, JJ[m:]])
            cost = np.concatenate([cost, cc[m:]])
            lam = np.concatenate([lam, np.full(new.size, lam0)])
            it = np.concatenate([it, np.zeros(new.size, int)])
            last = np.concatenate([last, np.full(new.size, np.inf)])
    return Z, its, conv


def solve_block(problem, z0, y, ok, tolerance, max_iterations, lam0):
    """LM on a block of frames; returns z, iterations, converged, r."""
    cmap = problem.cmap
    A, bnd = cmap.ineq_matrix, cmap.ineq_rhs
    n = z0.shape[0]
    z = feasible(z0, A, bnd) if A.shape[0] else z0.copy()      # start feasible (a copy either way)
    r, J, q, _ = problem.evaluate(z, y, ok)
    cost = np.einsum("ni,ni->n", r, r)
    lam = np.full(n, lam0)
    it = np.zeros(n, int)
    conv = np.zeros(n, bool)
    act = np.ones(n, bool)
    prev = np.full(n, np.inf)
    qtol = tolerance
    for _ in range(max_iterations):
        ia = np.flatnonzero(act)
        if ia.size == 0:
            break
        Ja, ra = J[ia], r[ia]
        d = lm_direction(Ja, ra, lam[ia], z[ia], A, bnd)
        zt = z[ia] + d
        rt, Jt, qt, _ = problem.evaluate(zt, y[ia], ok[ia])
        ct = np.einsum("ni,ni->n", rt, rt)
        acc = ct <= cost[ia] * (1 + 1e-12) + 1e-30
        it[ia] += 1
        ai = ia[acc]
        z[ai], r[ai], J[ai], cost[ai], q[ai] = zt[acc], rt[acc], Jt[acc], ct[acc], qt[acc]
        dq = np.abs(d @ cmap.basis.T).max(axis=1) if d.size else np.zeros(ia.size)
        lam_used = lam[ia].copy()
        done_acc = converged(dq, prev[ia], acc, qtol, lam_used)
        lam[ai] = np.maximum(lam[ai] / 10.0, 1e-14)
        ri = ia[~acc]
        lam[ri] = lam[ri] * 10.0
        prev[ia] = np.where(acc, dq, prev[ia])
        conv[ia[done_acc]] = True
        # A rejected tiny step means we are at the minimum to working precision.
        # A rejected, undamped, tiny step: the cost cannot decrease any more (optimum to round-off).
        at_min = (~acc) & (dq < qtol) & (lam_used <= 1e-4)
        done_rej = at_min | ((~acc) & (lam[ia] > 1e12))
        conv[ia[done_rej]] = at_min[done_rej]
        act[ia[done_acc | done_rej]] = False
    return z, it, conv, r, q


def repair_jumps(prob, Zs, its, conv, frames, Y, ok, tolerance, max_iterations, max_passes=3, sweep_gain=1e-3):
    """Re-solve frames whose solution jumps away from a neighbour's, keeping the lower cost.

    A warm start far from the solution (fast motion, extrapolation, a nearly
    singular problem such as hip and knee rotation with Plug-in-Gait markers
    only) can land in another local minimum, e.g. an angle 2 pi away that a
    coupling makes distinct.  Each frame whose coordinates differ from a
    neighbour's by more than max(0.1, 5 x the median inter-frame change) is
    solved again from that neighbour; the result replaces it when its cost is
    lower.  While a replacement lowers the cost by more than `sweep_gain`
    (relative: another minimum, not round-off), the repair walks on, re-solving
    the next frame from the repaired one, because the warm starts chain the
    wrong minimum over the whole run of frames that follows (or precedes) the
    jump.  Repeated forwards and backwards.
    """
    if frames.size < 2:
        return

    def cost(idx, z):
        r = prob.evaluate(z, Y[idx], ok[idx], jac=False)[0]
        return np.einsum("ni,ni->n", r, r)

    for _ in range(max_passes):
        Z = Zs[frames]
        jump = np.abs(np.diff(Z, axis=0)).max(axis=1)
        thr = max(0.1, 5.0 * float(np.median(jump)))
        bad = np.flatnonzero(jump > thr)
        if bad.size == 0:
            return
        c = cost(frames, Z)
        changed = False
        for k in bad:
            for src, dst in ((k, k + 1), (k + 1, k)):
                step = dst - src
                while 0 <= dst < frames.size:
                    f = frames[dst]
                    zb, ib, cb, _, _ = solve_block(prob, Zs[frames[src]][None], Y[f:f + 1], ok[f:f + 1], tolerance,
                                                    max_iterations, 1e-3)
                    cn = cost(np.array([f]), zb)[0]
                    if not cn < c[dst] * (1 - 1e-9):
                        break
                    Zs[f], its[f], conv[f] = zb[0], its[f] + ib[0], cb[0]
                    gain, c[dst] = cn < c[dst] * (1 - sweep_gain), cn
                    changed = True
                    if not gain:
                        break
                    src, dst = dst, dst + step
        if not changed:
            return

