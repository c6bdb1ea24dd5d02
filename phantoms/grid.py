"""Coarse-to-fine sampling of a signed distance function on a regular grid.

A block of ``b^3`` voxels whose centre value satisfies
``|d(c)| >= L r_b + band`` (``r_b`` = largest centre-to-voxel distance,
``L`` a Lipschitz bound of the SDF) lies entirely on one side of the surface,
so only blocks near the surface are subdivided (8 -> 4 -> 2 -> 1).  Far voxels
receive their block-centre value (correct sign, approximate magnitude);
voxels within `band` of the surface are evaluated exactly.
"""
from __future__ import annotations

from typing import Callable

import numpy as np


def _chunked(fn: Callable[[np.ndarray], np.ndarray], pts: np.ndarray, chunk: int = 1_000_000) -> np.ndarray:
    if len(pts) <= chunk:
        return np.asarray(fn(pts), float)
    return np.concatenate([np.asarray(fn(pts[i:i + chunk]), float) for i in range(0, len(pts), chunk)])


def sample_grid(fn: Callable[[np.ndarray], np.ndarray], origin, steps, shape, band: float = 0.0,
                lipschitz: float = 1.5, block: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate `fn` on the grid ``x(i,j,k) = origin + steps @ (i,j,k)``, coarse to fine.

    Parameters
    ----------
    fn : callable
        ``(N, 3) -> (N,)`` signed distance, metres.
    origin : array (3,)
        Position of voxel (0, 0, 0), metres.
    steps : array (3, 3)
        Columns are the grid step vectors along i, j, k, metres.
    shape : tuple of 3 int
    band : float
        Voxels with ``|d| < band`` are guaranteed to be evaluated exactly, metres.
    lipschitz : float
        Bound on ``|grad fn|`` (1 for an exact SDF; larger for smooth unions
        and normalised implicit functions).
    block : int
        Top-level block size (power of two).

    Returns
    -------
    d : ndarray float32, `shape`
        Signed distances (exact where `exact`, block-centre values elsewhere).
    exact : ndarray bool, `shape`
    """
    origin = np.asarray(origin, float)
    steps = np.asarray(steps, float)
    shape = np.asarray(shape, int)
    reach = np.linalg.norm(np.abs(steps).sum(axis=1))

    def centres(org, b):
        return origin + np.einsum("ij,kj->ik", org + (b - 1) / 2.0, steps)

    def thr(b):
        return lipschitz * 0.5 * (b - 1) * reach + band

    B = int(block)
    nb = -(-shape // B)
    top = np.indices(nb).reshape(3, -1).T * B
    vals = _chunked(fn, centres(top, B))
    d = vals.reshape(tuple(nb)).astype(np.float32)
    for ax in range(3):
        d = np.repeat(d, B, axis=ax)
    d = np.ascontiguousarray(d[: shape[0], : shape[1], : shape[2]])
    exact = np.zeros(tuple(shape), bool)
    cand = top[np.abs(vals) < thr(B)]
    b = B
    while b > 1 and len(cand):
        b2 = b // 2
        off = np.indices((2, 2, 2)).reshape(3, -1).T * b2
        sub = (cand[:, None, :] + off[None]).reshape(-1, 3)
        sub = sub[np.all(sub < shape, axis=1)]
        v = _chunked(fn, centres(sub, b2))
        if b2 > 1:
            o2 = np.indices((b2,) * 3).reshape(3, -1).T
            vox = (sub[:, None, :] + o2[None]).reshape(-1, 3)
            rep = np.repeat(v, b2 ** 3)
            ok = np.all(vox < shape, axis=1)
            vox = vox[ok]
            d[vox[:, 0], vox[:, 1], vox[:, 2]] = rep[ok]
        else:
            d[sub[:, 0], sub[:, 1], sub[:, 2]] = v
            exact[sub[:, 0], sub[:, 1], sub[:, 2]] = True
        cand = sub[np.abs(v) < thr(b2)]
        b = b2
    return d, exact
