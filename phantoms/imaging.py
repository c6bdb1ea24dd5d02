"""Synthetic MRI-like label volumes, reference meshes and truth files of a phantom.

Labelling model
---------------
A voxel of size ``h = (hx, hy, hz)`` belongs to a bone when at least half of
it lies inside the bone.  The inside fraction is estimated from signed
distances ``d`` (metres, negative inside).  For a surface that is planar
across the voxel the half-volume rule is exactly ``d(centre) <= 0``; curvature
``1/R`` shifts it by about ``h^2 / (8 R)``, so voxels with
``|d| < max(h)^2 / (8 * 1.5 mm)`` are supersampled with
``n_i = 2 max(1, round(h_i / min h))`` points per axis and
``fraction = mean_s clip(1/2 - d_s / delta, 0, 1)``,
``delta = (prod h_i / n_i)^(1/3)`` (linear partial volume of each sub-voxel).
SDFs are evaluated coarse to fine inside each bone's box only
(`phantoms.grid.sample_grid`).  Where two bones claim a voxel, the one whose
surface is farther (most negative ``d``) wins.

Noise (all seeded): the boundary is displaced by a smooth random field
(``d -> d + a f(x)``, ``a = level * mean(h)``, wavelengths 8-30 mm), small holes
(balls of 1-2 voxels removed just inside the surface) and spurious islands
(balls of 1-2 voxels added 1-5 voxels outside the surface).

Skin (body) label
-----------------
With ``skin=True`` (and the pelvis rasterised) the volume also carries the
soft-tissue envelope of the pelvis region, label ``skin`` in the label map
(everything inside the skin that is not bone; bones are labelled over it).
Model: the body is ``{x : d_pelvis(x) <= T(x)}``, an offset of the pelvis by
a smooth thickness field ``T(x) = Σ w_k v_k / Σ w_k``, ``w_k = 1 / (|x - s_k|² + ε²)``
(inverse-distance weighting, flat at its nodes) with nodes ``s_k = p_k + t_k n_k``
the skin points over the four pelvic marker sites (landmark ``p_k``, outward
normal ``n_k`` and the subject's drawn thickness ``t_k``, exactly as
`phantoms.skeleton.phantom_skeleton` places the markers).  The node values
``v_k`` solve ``T(s_k) = d_pelvis(s_k)``, so the skin passes exactly through
every marker's skin point (the first exit of the ray ``p_k + s n_k`` is at
``s = t_k``: checked by the tests); between the sites the thickness is the
interpolated node values.  A voxel is body when its centre is inside (no partial
volume, no segmentation noise); enclosed cavities are filled.  The legs are
not enveloped and the pelvic ring stays open: only the tissue over the pelvic
marker sites is meant to be realistic.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from lowerlimb.atomic import atomic_path, write_text
from lowerlimb.errors import InputError
from lowerlimb.bones import DEFAULT_LABEL_MAP, DEFAULT_TISSUE_LABEL, TISSUE_LABEL_NAME

from .anatomy import Phantom
from .grid import sample_grid


# --------------------------------------------------------------------------- helpers
def _check_voxel(voxel) -> np.ndarray:
    h = np.asarray(voxel, float).reshape(-1)
    if h.size == 1:
        h = np.repeat(h, 3)
    if h.size != 3 or not np.all(np.isfinite(h)) or np.any(h <= 0):
        raise InputError("voxel", f"voxel spacing must be three positive numbers, got {voxel!r}")
    if np.any(h > 0.02) or np.any(h < 5e-5):
        raise InputError("voxel", f"voxel spacing {h.tolist()} m is outside 0.05-20 mm (give metres)")
    return h


def _fov_box(ph: Phantom, fov) -> tuple[np.ndarray, np.ndarray] | None:
    """Scanner box (lo, hi) of a truncated field of view, or None."""
    if fov is None:
        return None
    if isinstance(fov, (tuple, list)) and len(fov) == 3 and isinstance(fov[0], str):
        bone, f0, f1 = fov
        if bone not in ph.bone_names:
            raise InputError("fov", f"unknown bone {bone!r}")
        if not (0.0 <= f0 < f1 <= 1.0):
            raise InputError("fov", f"fractions must satisfy 0 <= {f0} < {f1} <= 1")
        lo, hi = ph.bounds(bone)
        ax = int(np.argmax(hi - lo))          # the image axis along the bone's length
        lo2, hi2 = np.full(3, -np.inf), np.full(3, np.inf)
        lo2[ax] = lo[ax] + f0 * (hi[ax] - lo[ax])
        hi2[ax] = lo[ax] + f1 * (hi[ax] - lo[ax])
        return lo2, hi2
    box = np.asarray(fov, float)
    if box.shape != (2, 3) or np.any(box[1] <= box[0]):
        raise InputError("fov", "give [[xmin, ymin, zmin], [xmax, ymax, zmax]] in scanner metres, or (bone, f0, f1)")
    return box[0], box[1]


class _Jitter:
    """Smooth random scalar field ``f(x)`` in [-1, 1] (sum of random plane waves), seeded."""

    def __init__(self, rng: np.random.Generator, n: int = 6):
        k = rng.normal(size=(n, 3))
        k /= np.linalg.norm(k, axis=1, keepdims=True)
        lam = rng.uniform(0.008, 0.030, size=n)
        self.k = k * (2 * np.pi / lam)[:, None]
        self.phase = rng.uniform(0, 2 * np.pi, size=n)
        self.scale = 1.0 / np.sqrt(n / 2.0)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        return np.clip(self.scale * np.sin(np.einsum("ij,kj->ik", p, self.k) + self.phase).sum(axis=1), -1, 1)


def _ball_offsets(radius: float) -> np.ndarray:
    r = int(np.ceil(radius))
    g = np.indices((2 * r + 1,) * 3).reshape(3, -1).T - r
    return g[np.einsum("ij,ij->i", g, g) <= radius * radius + 1e-9]


def _stamp(mask_idx: np.ndarray, shape, radius: float) -> tuple[np.ndarray, ...]:
    off = _ball_offsets(radius)
    pts = (mask_idx[:, None, :] + off[None]).reshape(-1, 3)
    ok = np.all((pts >= 0) & (pts < np.asarray(shape)), axis=1)
    pts = pts[ok]
    return pts[:, 0], pts[:, 1], pts[:, 2]


# --------------------------------------------------------------------------- skin envelope
class SkinField:
    """The pelvis-region skin envelope: ``d_pelvis(x) - T(x) <= 0`` (see the module docstring).

    Attributes
    ----------
    sites : dict name -> (landmark (3,), outward normal (3,), thickness t) scanner frame, m
    nodes : (K, 3) skin points s_k = p_k + t_k n_k; values : (K,) solved node values v_k, m
    """

    EPS = 0.01  # m, IDW regulariser

    def __init__(self, sites: dict, values: np.ndarray):
        self.sites = sites
        self.nodes = np.array([p + t * n for p, n, t in sites.values()])
        self.values = np.asarray(values, float)

    def thickness(self, x: np.ndarray) -> np.ndarray:
        """T(x) (N,) m at scanner points x (N, 3)."""
        d2 = np.sum((np.asarray(x, float)[:, None, :] - self.nodes[None]) ** 2, axis=2)
        w = 1.0 / (d2 + self.EPS**2)
        return (w @ self.values) / w.sum(axis=1)

    def implicit(self, ph: Phantom, x: np.ndarray) -> np.ndarray:
        """d_pelvis(x) - T(x): negative inside the body."""
        return ph.sdf("pelvis", x) - self.thickness(x)

    def crossing(self, ph: Phantom, name: str, s_max: float = 0.2) -> float:
        """Distance s (m) at which the ray p + s n of site `name` first leaves the body (first root of the implicit)."""
        from scipy.optimize import brentq

        p, n, _ = self.sites[name]
        s = np.arange(0.0, s_max, 2.5e-4)
        g = self.implicit(ph, p + s[:, None] * n)
        i = int(np.argmax(g > 0))                 # first sample outside: the FIRST exit
        if g[i] <= 0:
            return float("inf")
        f = lambda x: float(self.implicit(ph, (p + x * n)[None])[0])  # noqa: E731
        return float(brentq(f, s[i - 1], s[i], xtol=1e-8)) if i > 0 else 0.0

    @classmethod
    def of(cls, ph: Phantom, tissue_seed: int) -> "SkinField":
        """The field of `ph` with the thickness draw of `tissue_seed`.

        The node values solve T(s_k) = d_pelvis(s_k) for every k (a K x K linear system of the
        IDW weights): the skin passes exactly through each marker's skin point s_k = p_k + t_k n_k.
        """
        from .skeleton import pelvis_skin_sites

        sites = pelvis_skin_sites(ph, tissue_seed)
        field_ = cls(sites, np.zeros(len(sites)))
        d2 = np.sum((field_.nodes[:, None, :] - field_.nodes[None]) ** 2, axis=2)
        w = 1.0 / (d2 + cls.EPS**2)
        W = w / w.sum(axis=1, keepdims=True)
        return cls(sites, np.linalg.solve(W, ph.sdf("pelvis", field_.nodes)))

    def box(self, ph: Phantom, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Scanner box enclosing the envelope: the pelvis box grown by the largest thickness (SDF Lipschitz 1.3)."""
        return ph.bounds("pelvis", pad=1.3 * float(np.max(np.abs(self.values))) + 3 * h)

    def rasterise(self, ph: Phantom, origin: np.ndarray, steps: np.ndarray, shape: tuple) -> np.ndarray:
        """Body mask (voxel centre inside), enclosed cavities filled."""
        from scipy import ndimage

        d, _ = sample_grid(lambda p: self.implicit(ph, p), origin, steps, shape,
                           band=float(np.abs(steps).max()) + 1e-6, lipschitz=2.5)
        return ndimage.binary_fill_holes(d <= 0)


# --------------------------------------------------------------------------- label volume
def label_volume(ph: Phantom, voxel=(1e-3, 1e-3, 1e-3), noise: float = 0.0, seed: int = 0, fov=None,
                 bones: Iterable[str] | None = None, supersample: bool = True,
                 progress: Callable[[str], None] | None = None, skin: bool = False,
                 tissue_seed: int | None = None, physes: float = 0.0):
    """Rasterise phantom bones into an integer label volume.

    Parameters
    ----------
    ph : Phantom
    voxel : 3 floats
        Voxel spacing along the image axes, metres (anisotropic allowed).
    noise : float
        Segmentation-noise level in [0, 1] (0: clean).
    seed : int
        Seeds the noise.
    fov : None, array (2, 3) or (bone, f0, f1)
        Truncated field of view: a scanner box in metres, or the fraction
        ``[f0, f1]`` of `bone`'s extent along the image axis it spans most.
    bones : iterable of str, optional
        Subset of bones to rasterise; the volume is cropped to them.
    supersample : bool
        Estimate partial volumes near the surface by supersampling.
    skin : bool
        Also label the soft-tissue envelope of the pelvis region (``skin``, see the
        module docstring); needs the pelvis among the rasterised bones.
    tissue_seed : int, optional
        Seed of the subject's soft-tissue draw (`phantoms.skeleton.pelvis_tissue_thickness`;
        default `seed`): the motion trials' seed, so that the markers sit on this skin.
    physes : float
        Width (m) of open growth plates left unlabelled, as in a child's bone
        segmentation (see `physis_slabs`); 0 (default): fused adult bones.

    Returns
    -------
    labels : ndarray int16 (I, J, K)
    affine : ndarray (4, 4)
        Voxel index -> scanner coordinates in MILLIMETRES (NIfTI convention).
    label_map : dict[str, int]
    """
    h = _check_voxel(voxel)
    noise = float(noise)
    if not (0.0 <= noise <= 1.0):
        raise InputError("noise", f"noise level {noise} is outside 0..1")
    names = tuple(ph.bone_names if bones is None else bones)
    for b in names:
        if b not in ph.bone_names:
            raise InputError("bones", f"unknown bone {b!r} (this phantom has {', '.join(ph.bone_names)})")
    if not names:
        raise InputError("bones", "no bone to rasterise")
    label_map = {b: DEFAULT_LABEL_MAP[b] for b in names}
    amp = noise * float(np.mean(h))                 # boundary jitter amplitude, m
    # padding independent of the noise level so clean and noisy volumes share one grid
    boxes = {b: ph.bounds(b, pad=3 * float(h.max())) for b in names}
    skin_field = None
    if not (0.0 <= float(physes) <= 0.01):
        raise InputError("physes", f"growth-plate width {physes} m is outside 0..0.01 m")
    slabs = physis_slabs(ph) if physes > 0 else {}
    if skin and "pelvis" in names:
        skin_field = SkinField.of(ph, seed if tissue_seed is None else tissue_seed)
        boxes_all = dict(boxes, skin=skin_field.box(ph, float(h.max())))
    else:
        boxes_all = boxes
    lo = np.min([bx[0] for bx in boxes_all.values()], axis=0)
    hi = np.max([bx[1] for bx in boxes_all.values()], axis=0)
    fbox = _fov_box(ph, fov)
    if fbox is not None:
        lo, hi = np.maximum(lo, fbox[0]), np.minimum(hi, fbox[1])
        if np.any(hi <= lo):
            raise InputError("fov", "the field of view does not contain any of the bones")
    i0 = np.floor(lo / h).astype(np.int64)
    i1 = np.ceil(hi / h).astype(np.int64)
    shape = tuple(int(x) for x in (i1 - i0 + 1))
    origin = i0 * h
    labels = np.zeros(shape, np.int16)
    steps = np.diag(h)
    half_diag = 0.5 * float(np.linalg.norm(h))
    nsub = 2 * np.maximum(1, np.round(h / h.min())).astype(int) if supersample else np.ones(3, int)
    sub_off = ((np.indices(nsub).reshape(3, -1).T + 0.5) / nsub - 0.5) * h          # (S, 3) metres
    delta = float(np.prod(h / nsub) ** (1 / 3))
    # For a locally planar surface the >= 50 % rule is exactly "d(centre) <= 0"; it
    # differs only where curvature within the voxel shifts the half-volume surface,
    # by ~h^2 / (8 R): supersample voxels with |d| below that for R >= ~1.5 mm.
    ss_band = min(half_diag, float(h.max()) ** 2 / (8 * 1.5e-3) + 1e-6) if supersample else 0.0
    for bi, b in enumerate(names):
        if progress:
            progress(b)
        blo, bhi = boxes[b]
        a = np.clip(np.floor(blo / h).astype(np.int64) - i0, 0, shape)
        c = np.clip(np.ceil(bhi / h).astype(np.int64) - i0 + 1, 0, shape)
        if np.any(c <= a):
            continue
        sub_shape = tuple(int(x) for x in (c - a))
        sub_origin = origin + a * h
        fn = lambda p, b=b: ph.sdf(b, p)  # noqa: E731
        d, exact = sample_grid(fn, sub_origin, steps, sub_shape, band=ss_band + amp + 1e-6, lipschitz=1.3)
        rng = np.random.default_rng([int(seed), bi, 11])
        jit = _Jitter(rng) if amp > 0 else None
        near = np.nonzero(exact & (np.abs(d) < ss_band + amp))
        nidx = np.column_stack(near)
        pts = sub_origin + nidx * h
        dn = d[near].astype(float)
        if jit is not None:
            # the jitter displaces the boundary: new sign within the jitter band
            dn = dn + amp * jit(pts)
        inside = d <= 0
        inside[near] = dn <= 0
        if supersample:
            # partial volume of the voxels the (displaced) surface actually crosses
            sel = np.nonzero(np.abs(dn) < ss_band)[0]
            if len(sel):
                ds = np.empty((len(sel), len(sub_off)))
                for s0 in range(0, len(sel), 200_000):
                    ii = sel[s0:s0 + 200_000]
                    pp = (pts[ii, None, :] + sub_off[None]).reshape(-1, 3)
                    ds[s0:s0 + 200_000] = fn(pp).reshape(-1, len(sub_off)) + (dn[ii] - d[near][ii])[:, None]
                frac = np.clip(0.5 - ds / delta, 0.0, 1.0).mean(axis=1)
                inside[tuple(nidx[sel].T)] = frac >= 0.5
        if noise > 0:
            _add_noise(inside, d, h, noise, rng)
        if b in slabs:
            idx = np.column_stack(np.nonzero(inside))
            pts_in = sub_origin + idx * h
            cut = np.zeros(len(idx), bool)
            for centre, normal, reach in slabs[b]:
                q = pts_in - centre
                cut |= (np.abs(q @ normal) < 0.5 * physes) & (np.linalg.norm(q, axis=1) < reach)
            inside[tuple(idx[cut].T)] = False
        lab = label_map[b]
        region = labels[a[0]:c[0], a[1]:c[1], a[2]:c[2]]
        conflict = inside & (region != 0)
        if conflict.any():
            cidx = np.column_stack(np.nonzero(conflict))
            cpts = sub_origin + cidx * h
            mine = d[conflict].astype(float)
            others = region[conflict]
            win = np.ones(len(cidx), bool)
            for ob in np.unique(others):
                oname = next(k for k, v in label_map.items() if v == ob)
                sel = others == ob
                win[sel] = mine[sel] < ph.sdf(oname, cpts[sel])
            inside[conflict] = win
        region[inside] = lab
    if skin_field is not None:
        if progress:
            progress(TISSUE_LABEL_NAME)
        blo, bhi = boxes_all["skin"]
        a = np.clip(np.floor(blo / h).astype(np.int64) - i0, 0, shape)
        c = np.clip(np.ceil(bhi / h).astype(np.int64) - i0 + 1, 0, shape)
        if np.all(c > a):
            body = skin_field.rasterise(ph, origin + a * h, steps, tuple(int(x) for x in (c - a)))
            region = labels[a[0]:c[0], a[1]:c[1], a[2]:c[2]]
            region[body & (region == 0)] = DEFAULT_TISSUE_LABEL
            label_map[TISSUE_LABEL_NAME] = DEFAULT_TISSUE_LABEL
    affine = np.eye(4)
    affine[:3, :3] = np.diag(h * 1000.0)
    affine[:3, 3] = origin * 1000.0
    return labels, affine, label_map


def physis_slabs(ph: Phantom) -> dict[str, list[tuple[np.ndarray, np.ndarray, float]]]:
    """Growth plates of a child's femur and tibia: ``bone -> [(centre, normal, reach)]`` (scanner, m).

    A plate is the slab ``|(x - centre) . normal| < w / 2`` within ``reach`` of
    its centre: the capital femoral physis across the neck, 0.4 head radii
    from the head centre towards the shaft (reach 1.3 head radii, so the
    trochanter stays whole); the distal femoral physis 1.1 condyle radii
    above the intercondylar midpoint; the proximal tibial physis 0.9 and the
    distal 0.5 condyle radii from the plateau and plafond centres, all across
    the shaft axis (reach: the whole bone).
    """
    t = ph.truth()["landmarks"]["bones"]
    out: dict[str, list] = {}
    for s in ("r", "l"):
        fem, tib = t.get(f"femur_{s}"), t.get(f"tibia_{s}")
        if fem is None or tib is None:
            continue
        L = lambda bone, k: np.asarray(bone["landmarks"][k]["position"], float)  # noqa: E731
        head, knee = L(fem, "femoral_head_centre"), L(fem, "intercondylar_midpoint")
        r_head = float(fem["scalars"]["femoral_head_radius"]["value"])
        r_cond = float(fem["scalars"]["medial_condyle_a"]["value"])
        neck = np.asarray(fem["axes"]["neck_axis"]["direction"], float)
        neck = neck if neck @ (knee - head) > 0 else -neck        # towards the shaft
        up_f = np.asarray(fem["axes"]["shaft_axis"]["direction"], float)
        up_f = up_f if up_f @ (head - knee) > 0 else -up_f
        plateau, plafond = L(tib, "plateau_centre"), L(tib, "plafond_centre")
        up_t = plateau - plafond
        up_t /= np.linalg.norm(up_t)
        out[f"femur_{s}"] = [(head + 0.4 * r_head * neck, neck, 1.3 * r_head),
                             (knee + 1.1 * r_cond * up_f, up_f, np.inf)]
        out[f"tibia_{s}"] = [(plateau - 0.9 * r_cond * up_t, up_t, np.inf),
                             (plafond + 0.5 * r_cond * up_t, up_t, np.inf)]
    return out


def _add_noise(inside: np.ndarray, d: np.ndarray, h: np.ndarray, level: float, rng: np.random.Generator) -> None:
    """Small holes just inside and spurious islands just outside the surface (in place)."""
    hm = float(h.max())
    shell_in = np.column_stack(np.nonzero(inside & (d > -3 * hm)))
    shell_out = np.column_stack(np.nonzero(~inside & (d > hm) & (d < 5 * hm)))
    n_holes = int(round(level * len(shell_in) / 400))
    n_isl = int(round(level * len(shell_out) / 1500))
    # holes punched inside the surface, then islands stamped outside it (this order: the seeded draws)
    for shell, n, radii, value in ((shell_in, n_holes, (1.0, 1.5), False), (shell_out, n_isl, (0.0, 1.0), True)):
        if n and len(shell):
            pick = shell[rng.choice(len(shell), size=min(n, len(shell)), replace=False)]
            for r in radii:
                sel = pick[rng.random(len(pick)) < 0.5]
                if len(sel):
                    inside[_stamp(sel, inside.shape, r)] = value


# --------------------------------------------------------------------------- writers
def write_ply_mm(path: str | os.PathLike, mesh, comment: str) -> Path:
    """Binary little-endian PLY of `mesh` (metres) written in MILLIMETRES with a header comment.

    Coordinates are float32: ~3e-5 mm resolution at 500 mm from the origin,
    far below the surfaces' own error.
    """
    v = np.asarray(mesh.vertices, float) * 1000.0
    f = np.asarray(mesh.faces, np.int32)
    header = ("ply\nformat binary_little_endian 1.0\n"
              + "".join(f"comment {line}\n" for line in comment.splitlines())
              + f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
              + f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    faces = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = f
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(v.astype("<f4").tobytes())
            fh.write(faces.tobytes())
    return Path(path)


def write_label_nifti(path: str | os.PathLike, labels: np.ndarray, affine_mm: np.ndarray) -> Path:
    """NIfTI-1 label volume (int16), affine in mm, scanner frame (qform/sform code 1)."""
    import nibabel as nib

    img = nib.Nifti1Image(np.asarray(labels, np.int16), affine_mm)
    img.header.set_xyzt_units("mm")
    img.set_qform(affine_mm, code=1)
    img.set_sform(affine_mm, code=1)
    img.header["descrip"] = b"personalize phantom labels, mm, scanner"
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))
    return Path(path)


def write_phantom(out_dir: str | os.PathLike, ph: Phantom, voxel=(1e-3, 1e-3, 1e-3), noise: float = 0.0,
                  seed: int = 0, fov=None, bones: Iterable[str] | None = None,
                  progress: Callable[[str], None] | None = None, extra_truth: dict | None = None,
                  meshes: bool = True, skin: bool = True, physes: float = 0.0) -> dict[str, Path]:
    """Write ``labels.nii.gz``, ``label_map.json``, ``meshes/<bone>.ply`` (mm) and ``truth.json`` (m).

    `extra_truth` entries (e.g. the motion phantom's knee laws) are merged into ``truth.json``;
    ``meshes=False`` skips the exact reference meshes (the pipeline does not read them).
    ``skin=True`` also labels the soft-tissue envelope of the pelvis (label ``skin``, see
    `label_volume`; the subject's tissue drawn from `seed`, the motion trials' seed).
    ``physes`` > 0 leaves a child's growth plates of that width (m) unlabelled (`physis_slabs`;
    the exact meshes stay whole).

    Returns the written paths by role.  Files are written atomically; use
    `lowerlimb.atomic.staged_dir` around this call to publish the folder at once.
    """
    from lowerlimb.atomic import inside

    out = Path(out_dir)
    labels, affine, label_map = label_volume(ph, voxel=voxel, noise=noise, seed=seed, fov=fov, bones=bones,
                                             progress=(lambda b: progress(f"rasterising {b}")) if progress else None,
                                             skin=skin, tissue_seed=seed, physes=physes)
    paths = {"labels": write_label_nifti(inside(out, "labels.nii.gz"), labels, affine),
             "label_map": write_text(inside(out, "label_map.json"), json.dumps(label_map, indent=1) + "\n")}
    for b in [b for b in label_map if b != TISSUE_LABEL_NAME] if meshes else ():
        if progress:
            progress(f"meshing {b}")
        paths[f"mesh:{b}"] = write_ply_mm(
            inside(out, f"meshes/{b}.ply"), ph.mesh(b),
            f"personalize phantom bone {b} (seed {ph.seed})\nunits mm\nframe scanner (same frame as labels.nii.gz affine and truth.json)")
    truth = ph.truth()
    truth["image"] = {"file": "labels.nii.gz", "voxel_m": np.asarray(_check_voxel(voxel)).tolist(),
                      "noise": float(noise), "noise_seed": int(seed), "affine_units": "mm",
                      "shape": list(labels.shape), "growth_plates_m": float(physes),
                      "meshes": "meshes/<bone>.ply in mm, scanner frame" if meshes else None}
    if TISSUE_LABEL_NAME in label_map:
        from .skeleton import pelvis_skin_sites

        truth["image"]["skin"] = {
            "label": int(label_map[TISSUE_LABEL_NAME]), "units": "m", "frame": "scanner",
            "model": "offset of the pelvis by a smooth thickness field through the marker sites (phantoms.imaging)",
            "sites": {k: {"landmark": p.tolist(), "normal": n.tolist(), "thickness": float(t)}
                      for k, (p, n, t) in pelvis_skin_sites(ph, seed).items()}}
    truth.update(extra_truth or {})
    paths["truth"] = write_text(inside(out, "truth.json"), json.dumps(truth, indent=1) + "\n")
    return paths
