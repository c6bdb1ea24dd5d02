"""Soft-tissue thickness over the bony landmarks that carry skin markers.

The thickness is the skin-to-bone distance measured along the bone's outward
surface normal at the landmark (how CT, MRI and ultrasound measure it).  A
marker centre then sits at ``landmark + (thickness + marker radius) * n``.

One table serves both sides of the project: the phantoms draw each subject's
thickness around it (`draw_thickness`), the MRI-to-lab registration uses it
as its prior (mean, sd).  The prior is therefore right on average and wrong
per subject, as it is for a real patient whose tissue was not measured.

Sources
-------
ASIS and PSIS: Mantovani G, Ng KCG, Lamontagne M (2016) Regression models to
predict hip joint centers in pathological hip population. Gait & Posture
44:48-54.  Pelvic CT of 67 adults (21 controls, 46 with cam-type FAI): skin
thickness 9.7 ± 7.0 mm over the anterior and 19.6 ± 10.9 mm over the
posterior superior iliac spines, correlated with body-mass index.
The sites below the pelvis are NOT from a measured source: they are the
project's assumed values (thin tissue over the epicondyles, malleoli, heel
and metatarsal heads) and are stated as assumptions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TissuePrior", "SOFT_TISSUE_THICKNESS", "DEFAULT_TISSUE", "tissue_site", "tissue_prior", "draw_thickness"]


@dataclass(frozen=True)
class TissuePrior:
    """Population distribution of the skin-to-bone distance at one site.

    mean, sd : m (along the bone's outward normal); source : citation or "assumed"
    """

    mean: float
    sd: float
    source: str


_MANTOVANI = "Mantovani, Ng & Lamontagne 2016, Gait Posture 44:48 (CT, n=67)"

#: per-site soft-tissue thickness (m), keyed by the marker name without its side letter
SOFT_TISSUE_THICKNESS: dict[str, TissuePrior] = {
    "ASI": TissuePrior(0.0097, 0.0070, _MANTOVANI),
    "PSI": TissuePrior(0.0196, 0.0109, _MANTOVANI),
    "KNE": TissuePrior(0.005, 0.003, "assumed"),
    "KNEM": TissuePrior(0.005, 0.003, "assumed"),
    "MFC": TissuePrior(0.005, 0.003, "assumed"),
    "ANK": TissuePrior(0.003, 0.002, "assumed"),
    "ANKM": TissuePrior(0.003, 0.002, "assumed"),
    "MMA": TissuePrior(0.003, 0.002, "assumed"),
    "HEE": TissuePrior(0.006, 0.003, "assumed"),
    "TOE": TissuePrior(0.003, 0.002, "assumed"),
}
#: any other site (assumed)
DEFAULT_TISSUE = TissuePrior(0.005, 0.003, "assumed")

_ALIASES = {"ASIS": "ASI", "PSIS": "PSI"}


def tissue_site(marker: str) -> str:
    """Site key of a marker name: ``"RASI"`` -> ``"ASI"``, ``"LKNEM"`` -> ``"KNEM"``; unknown names unchanged."""
    m = str(marker).upper()
    m = _ALIASES.get(m, m)
    if m in SOFT_TISSUE_THICKNESS:
        return m
    if len(m) > 1 and m[0] in "RL":
        rest = _ALIASES.get(m[1:], m[1:])
        if rest in SOFT_TISSUE_THICKNESS:
            return rest
    return m


def tissue_prior(marker: str) -> TissuePrior:
    """Prior (mean, sd, m) of the soft tissue under `marker` (`DEFAULT_TISSUE` for sites not tabulated)."""
    return SOFT_TISSUE_THICKNESS.get(tissue_site(marker), DEFAULT_TISSUE)


def draw_thickness(rng: np.random.Generator, site: str) -> float:
    """One subject's thickness at `site` (m): log-normal with the table's mean and sd.

    Model: t = exp(μ + σ z), z ~ N(0, 1), with σ² = ln(1 + sd²/mean²) and
    μ = ln(mean) - σ²/2, so that E t = mean and sd t = sd while t > 0 (the
    measured distributions are skewed: sd close to the mean at the ASIS).
    """
    p = tissue_prior(site)
    s2 = np.log1p((p.sd / p.mean) ** 2)
    return float(np.exp(np.log(p.mean) - 0.5 * s2 + np.sqrt(s2) * rng.standard_normal()))
