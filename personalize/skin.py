"""Soft-tissue thickness under the skin markers, measured in the MRI's body/skin label.

Model
-----
A landmark p (scanner frame, m) on the bone surface with outward unit normal n
carries a skin marker whose centre sits at ``p + (t + r) n`` (t the skin-to-bone
distance along n, r the marker radius; `personalize.registration`).  When the
label volume has a body label (``skin``/``body``/``soft_tissue`` in the label
map: everything inside the skin, bones labelled over it), t is measured as the
distance at which the ray ``x(s) = p + s n`` leaves the body:

    t̂ = min { s > 0 : o(x(s)) = 1/2 and o(x(s')) < 1/2 for s' in (s, s + 3 mm] },

with o the trilinear interpolation of the occupancy (label != 0) between voxel
centres (sampled every h/4 along the ray, the crossing refined linearly).  For
a voxel grid labelled by the half-volume rule the 1/2-level lies on average on
the true skin, with a uniform error of one voxel across it.  Its variance is

    σ_t² = σ_vox² + nᵀ C_p n + σ_n² + σ_posture²,

* σ_vox = h_m / (√12 |m·n|): quantisation (h_m the voxel size along the skin
  normal m, the occupancy gradient at the exit; |m·n| clipped at 0.3);
* nᵀ C_p n: the landmark's own error along the ray (C_p its covariance);
* σ_n² = Σ_i [(t̂(+σ e_i) - t̂(-σ e_i)) / 2]² + [(t̂(+) + t̂(-) - 2 t̂) / 2]²: the
  ray re-measured with the normal tilted by ± its angular sd σ about two
  tangent axes e_i (slope and curvature of the skin seen from the landmark);
* σ_posture = `POSTURE_SD` (ASSUMPTION, 2 mm): an MRI is usually scanned supine
  (tissue over the PSIS compressed by the table, gravity shifting it relative
  to standing) and a taped marker presses on the skin, while the static trial is
  standing.  No bias is modelled; the sd is not from a measured source.

Plausibility: a measurement outside [0, `MAX_THICKNESS`] (80 mm), a landmark not
inside the body, or a ray that never leaves the body (or leaves the image
first) keeps the population prior (`personalize.registration.skin_prior`) and
a "low confidence" note.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from lowerlimb.errors import InputError

__all__ = ["SkinThickness", "measure_skin_thickness", "measure_pelvis_skin", "estimated_skin", "PELVIS_SKIN_MARKERS",
           "MAX_THICKNESS", "POSTURE_SD"]

#: pelvic markers whose tissue is measured (the pelvis registration's skin markers)
PELVIS_SKIN_MARKERS = ("RASI", "LASI", "RPSI", "LPSI")
#: largest plausible skin-to-bone distance (m); beyond it the prior is kept
MAX_THICKNESS = 0.080
#: ASSUMED sd (m) of supine-MRI vs standing-with-marker tissue thickness (posture, marker pressure)
POSTURE_SD = 0.002
#: the ray must stay outside the body this far (m) after the exit (a gap in the label is not the skin)
EXIT_CLEARANCE = 0.003
#: how far (m) the ray is followed
RAY_LENGTH = 0.100


@dataclass(frozen=True)
class SkinThickness:
    """Soft tissue under one marker, along the bone's outward normal.

    Attributes
    ----------
    marker : str
    thickness, sd : m, what the registration uses
    source : "MRI" (measured in the body label), "registration" (its scale estimated with the registration
        from the static trial, `estimated_skin`) or "prior" (population table)
    note : why the prior was kept ("" when measured)
    components : dict of sd components (m): voxel, landmark, normal, posture (measured only)
    exit_point : (3,) scanner m, where the ray leaves the body (measured only)
    """

    marker: str
    thickness: float
    sd: float
    source: str
    note: str = ""
    components: dict = field(default_factory=dict)
    exit_point: np.ndarray | None = None

    def summary(self) -> dict:
        """JSON-ready (mm)."""
        out = {"thickness_mm": self.thickness * 1e3, "sd_mm": self.sd * 1e3, "source": self.source}
        if self.note:
            out["note"] = self.note
        if self.components:
            out["sd_components_mm"] = {k: v * 1e3 for k, v in self.components.items()}
        return out


class _Ray:
    """Occupancy (label != 0) of a label volume, trilinearly interpolated along rays."""

    def __init__(self, labels: np.ndarray, affine_m: np.ndarray):
        self.labels = labels
        self.A = np.asarray(affine_m, float)
        self.Ainv = np.linalg.inv(self.A)
        self.h = np.linalg.norm(self.A[:3, :3], axis=0)
        self.shape = np.asarray(labels.shape)

    def voxel(self, x: np.ndarray) -> np.ndarray:
        return x @ self.Ainv[:3, :3].T + self.Ainv[:3, 3]

    def occupancy(self, x: np.ndarray) -> tuple[np.ndarray, bool]:
        """o at scanner points x (N, 3), and whether all points are inside the image."""
        ijk = self.voxel(x)
        inside = bool(np.all((ijk >= 0) & (ijk <= self.shape - 1)))
        lo = np.clip(np.floor(ijk.min(axis=0)).astype(int) - 1, 0, self.shape - 1)
        hi = np.clip(np.ceil(ijk.max(axis=0)).astype(int) + 2, 1, self.shape)
        crop = (self.labels[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] != 0).astype(np.float32)
        o = ndimage.map_coordinates(crop, (ijk - lo).T, order=1, mode="constant", cval=0.0)
        return o, inside

    def exit(self, p: np.ndarray, n: np.ndarray) -> tuple[float | None, str]:
        """Distance (m) at which p + s n leaves the body, or (None, reason)."""
        ds = float(self.h.min()) / 4.0
        s = np.arange(0.0, RAY_LENGTH + ds, ds)
        o, in_image = self.occupancy(p + s[:, None] * n)
        if o[0] < 0.5:
            return None, "the landmark is not inside the body label"
        out = o < 0.5
        k_clear = int(np.ceil(EXIT_CLEARANCE / ds))
        for i in np.nonzero(out[1:] & ~out[:-1])[0] + 1:
            if np.all(out[i:i + k_clear]) and i + k_clear <= len(out):
                ijk = self.voxel((p + s[i] * n)[None])[0]
                if np.any(ijk < 0) or np.any(ijk > self.shape - 1):
                    return None, "the ray leaves the image before it leaves the body"
                # linear refinement of the 1/2 crossing between samples i-1 and i
                f = (o[i - 1] - 0.5) / max(o[i - 1] - o[i], 1e-9)
                return float(s[i - 1] + f * ds), ""
        if not in_image:
            return None, "the ray leaves the image before it leaves the body"
        return None, f"the ray never leaves the body within {RAY_LENGTH * 1e3:.0f} mm"

    def skin_normal(self, x: np.ndarray) -> np.ndarray | None:
        """Outward skin normal at x: minus the occupancy gradient (central differences, one voxel)."""
        E = np.diag(self.h)
        g = np.array([(self.occupancy((x + E[i])[None])[0][0] - self.occupancy((x - E[i])[None])[0][0]) / (2 * self.h[i])
                      for i in range(3)])
        ng = np.linalg.norm(g)
        return None if ng < 1e-9 else -g / ng


def _tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def measure_skin_thickness(volume, points: dict, normals: dict, *, normal_sd_deg: float | dict = 10.0,
                           priors: dict | None = None) -> dict[str, SkinThickness]:
    """Skin-to-bone distance under each marker, from the volume's body label (see the module docstring).

    Parameters
    ----------
    volume : personalize.io.LabelVolume with ``tissue_label`` (else every site keeps its prior)
    points : {marker: (position (3,) m, cov (3, 3) m² or None)}, scanner frame
    normals : {marker: (3,) outward bone normal}, scanner frame
    normal_sd_deg : angular sd (deg) of each normal, one value or {marker: deg}
    priors : {marker: (mean, sd) m}; default `personalize.registration.skin_prior`

    Returns
    -------
    dict marker -> SkinThickness (source "MRI" or "prior")
    """
    from .registration import skin_prior

    def prior(name: str, why: str) -> SkinThickness:
        m, s = (priors or {}).get(name) or skin_prior(name)
        return SkinThickness(name, float(m), float(s), "prior", why)

    if getattr(volume, "tissue_label", None) is None:
        return {k: prior(k, "no body/skin label in the label volume") for k in points}
    ray = _Ray(volume.labels, volume.affine_m)
    out = {}
    for name, (p, cov) in points.items():
        p = np.asarray(p, float).reshape(3)
        if name not in normals:
            out[name] = prior(name, "low confidence: no bone normal at the landmark; population prior kept")
            continue
        n = np.asarray(normals[name], float).reshape(3)
        nn = np.linalg.norm(n)
        if not np.all(np.isfinite(p)) or not np.isfinite(nn) or nn < 1e-9:
            raise InputError(name, "landmark position or normal is not finite")
        n = n / nn
        t, why = ray.exit(p, n)
        if t is None:
            out[name] = prior(name, f"low confidence: {why}; population prior kept")
            continue
        if not 0.0 <= t <= MAX_THICKNESS:
            out[name] = prior(name, f"low confidence: measured {t * 1e3:.1f} mm is outside 0-{MAX_THICKNESS * 1e3:.0f} mm; "
                                    "population prior kept")
            continue
        x = p + t * n
        m = ray.skin_normal(x)
        cos = 1.0 if m is None else max(abs(float(m @ n)), 0.3)
        h_m = float(np.sqrt(np.sum((ray.h * (n if m is None else m)) ** 2)))
        s_vox = float(h_m / np.sqrt(12.0) / cos)
        C = np.zeros((3, 3)) if cov is None else np.asarray(cov, float).reshape(3, 3)
        s_lm = float(np.sqrt(max(n @ C @ n, 0.0)))
        sd_n = np.radians(float(normal_sd_deg.get(name, 10.0) if isinstance(normal_sd_deg, dict) else normal_sd_deg))
        var_n = 0.0
        for e in _tangents(n):
            tp, _ = ray.exit(p, np.cos(sd_n) * n + np.sin(sd_n) * e)
            tm, _ = ray.exit(p, np.cos(sd_n) * n - np.sin(sd_n) * e)
            if tp is None or tm is None:
                # the tilted ray finds no skin: count the full thickness as the normal's uncertainty
                var_n += t * t
                continue
            var_n += ((tp - tm) / 2.0) ** 2 + ((tp + tm - 2 * t) / 2.0) ** 2
        comp = {"voxel": s_vox, "landmark": s_lm, "normal": float(np.sqrt(var_n)), "posture": POSTURE_SD}
        sd = float(np.sqrt(sum(v * v for v in comp.values())))
        out[name] = SkinThickness(name, float(t), sd, "MRI", "", comp, x)
    return out


def measure_pelvis_skin(volume, pelvis, pelvis_mesh, *, markers=PELVIS_SKIN_MARKERS,
                        normal_sd_deg: float | None = None) -> dict[str, SkinThickness]:
    """`measure_skin_thickness` for the pelvic markers of the pelvis' `BoneLandmarks` (scanner frame, m).

    The normals are the pelvis surface's vertex normals nearest to each landmark, as the pelvis
    registration takes them (`personalize.marker_registration.register_segments`), with its sd
    (`personalize.registration.SURFACE_NORMAL_SD_DEG`).  Markers without a landmark are left out.
    """
    from .marker_registration import surface_normal
    from .registration import SURFACE_NORMAL_SD_DEG

    lms = pelvis.landmarks
    pts = {k: (lms[k].position, lms[k].cov) for k in markers if k in lms}
    # the ray is cast along the landmark vertex's own normal, the direction the measured-path scales were
    # calibrated with (an 8 mm mean normal moved the measured PSIS tissue 4.5 mm on the analytic phantom)
    nrm = {k: surface_normal(pelvis_mesh, v[0], radius=0.0) for k, v in pts.items()}
    return measure_skin_thickness(volume, pts, nrm,
                                  normal_sd_deg=SURFACE_NORMAL_SD_DEG if normal_sd_deg is None else normal_sd_deg)


def estimated_skin(reg) -> dict:
    """{marker: `SkinThickness`} of the tissue a registration estimated (`personalize.registration.register_landmarks`
    with a tissue prior): thickness k μ and its sd, source "registration"; {} when none was estimated."""
    if getattr(reg, "tissue_scale", None) is None:
        return {}
    note = f"scale {reg.tissue_scale:.2f} x the site table (log sd {reg.tissue_scale_log_sd:.2f}), {reg.segment} registration"
    return {k: SkinThickness(k, float(t), float(sd), "registration", note) for k, (t, sd) in reg.tissue.items()}
