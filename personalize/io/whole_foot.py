"""A whole foot given as one mesh, split into the bodies of an OpenSim foot: talus, calcn and toes.

Segmentations often export the foot as one file (``foot_r.ply``) whose bones
are separate connected pieces.  An OpenSim / gait2392 foot has three bodies:
``talus``, ``calcn`` (calcaneus, the other tarsals and the metatarsals) and
``toes`` (the phalanges).  The pieces are assigned by rules that hold for any
adult or child foot and do not depend on its pose in the scanner:

* **talus**: the piece lying on the tibia: smallest 5th percentile of its
  vertices' distances to the tibia's vertices, accepted when below
  `TALUS_CONTACT_M` (the talocrural joint space; a segmentation's gap between
  the tibial plafond and the talar dome is 1-4 mm, the next tarsal lies
  > 10 mm from the tibia);
* **calcaneus**: the largest remaining piece by volume (the calcaneus is the
  largest bone of the foot);
* **toes**: with ``a`` the unit vector from the calcaneus's centroid to the
  centroid of the other pieces (the foot's long axis, heel to toes) and ``L``
  the foot length along ``a`` from the back of the heel, the pieces that start
  beyond `TOES_START_FRACTION` x L.  Metatarsal bases lie at 0.35-0.56 L, the
  bases of the proximal phalanges at 0.72-0.78 L (both MC22 feet: the largest
  start of a metatarsal piece is 0.57 L, the smallest of a phalanx 0.74 L).

Without a tibia, or when the foot is one connected piece, no talus can be
told apart: the whole foot is read as the calcn and the output says so.
"""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

__all__ = ["split_whole_foot", "TALUS_CONTACT_M", "TOES_START_FRACTION"]

#: largest 5th-percentile distance (m) of a piece to the tibia that makes it the talus
TALUS_CONTACT_M = 6e-3
#: a piece starting beyond this fraction of the foot length (from the heel) belongs to the toes
TOES_START_FRACTION = 0.65


def split_whole_foot(foot: trimesh.Trimesh, side: str, *, tibia: trimesh.Trimesh | None = None
                     ) -> tuple[dict[str, trimesh.Trimesh], str]:
    """Split a whole-foot mesh (metres) into ``talus_<side>``, ``calcn_<side>``, ``toes_<side>``.

    Parameters
    ----------
    foot : trimesh.Trimesh
        The foot's bones, each a separate connected piece (small islands
        already removed), metres.
    side : {"r", "l"}
    tibia : trimesh.Trimesh, optional
        The same leg's tibia (metres, same frame); needed to find the talus.

    Returns
    -------
    pieces : dict[str, trimesh.Trimesh]
        The bodies found (the calcn always).
    note : str
        What was done, for the output's notes.
    """
    parts = foot.split(only_watertight=False)
    if len(parts) < 3 or tibia is None:
        why = "one connected piece" if len(parts) < 3 else "no tibia to find the talus on"
        return {f"calcn_{side}": foot}, (f"whole foot read as calcn_{side} ({why}): no talus or toes taken from it, "
                                         "so the ankle, subtalar and mtp joints are not built")
    tree = cKDTree(np.asarray(tibia.vertices))
    contact = np.array([np.percentile(tree.query(np.asarray(p.vertices))[0], 5) for p in parts])
    ti = int(np.argmin(contact))
    if contact[ti] > TALUS_CONTACT_M:
        return {f"calcn_{side}": foot}, (f"whole foot read as calcn_{side}: no piece lies on the tibia (nearest "
                                         f"{contact[ti] * 1e3:.1f} mm), so no talus; ankle and subtalar joints "
                                         "are not built")
    vols = np.array([abs(p.volume) for p in parts])
    vols[ti] = -np.inf
    ci = int(np.argmax(vols))
    rest = [i for i in range(len(parts)) if i not in (ti, ci)]
    c0 = parts[ci].vertices.mean(axis=0)
    cr = np.concatenate([parts[i].vertices for i in rest]).mean(axis=0)
    a = (cr - c0) / np.linalg.norm(cr - c0)
    heel = float((parts[ci].vertices @ a).min())
    length = max(float((p.vertices @ a).max()) for p in parts) - heel
    start = {i: (float((parts[i].vertices @ a).min()) - heel) / length for i in rest}
    toes = [i for i in rest if start[i] > TOES_START_FRACTION]
    calcn = [ci] + [i for i in rest if i not in toes]
    out = {f"talus_{side}": parts[ti], f"calcn_{side}": trimesh.util.concatenate([parts[i] for i in calcn])}
    if toes:
        out[f"toes_{side}"] = trimesh.util.concatenate([parts[i] for i in toes])
    note = (f"whole foot split into talus_{side} (the piece on the tibia, {contact[ti] * 1e3:.1f} mm from it), "
            f"calcn_{side} (calcaneus + {len(calcn) - 1} tarsal/metatarsal pieces) and "
            + (f"toes_{side} ({len(toes)} pieces starting beyond {TOES_START_FRACTION:.2f} of the foot length)"
               if toes else f"no toes (no piece beyond {TOES_START_FRACTION:.2f} of the foot length)"))
    return out, note
