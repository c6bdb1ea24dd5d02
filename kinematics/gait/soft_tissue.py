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

Body-build prior of a subject's tissue scale
--------------------------------------------
One subject's tissue is modelled as the table scaled by one factor k per
registration segment, t_i = k μ_i exp(e_i), e_i ~ N(0, `SITE_LOG_SD`²) (sites of
one person do not scale exactly together), with the prior

    ln k ~ N(ln k₀, σ_k²),   k₀ = FMI / FMI_ref,   FMI = BF · BMI

(`tissue_scale_prior`): subcutaneous tissue is fat over the bone, and fat
mass per body surface scales with the fat-mass index FMI = fat mass / height²
(body surface ∝ height²).  The body-fat fraction BF comes from BMI, age and
sex by Deurenberg, Weststrate & Seidell 1991 (Br J Nutr 65:105; densitometry,
n = 1229): adults BF% = 1.2 BMI + 0.23 age - 10.8 sex - 5.4, children (age
< 16) BF% = 1.51 BMI - 0.70 age - 3.6 sex + 1.4 (sex 1 male, 0 female, 0.5
unknown; age unknown: `REFERENCE_AGE`).  FMI_ref is that of the table's
cohort, taken as `REFERENCE_BMI` and `REFERENCE_AGE` (ASSUMED: Mantovani et
al. 2016 studied young and middle-aged adults of normal to overweight BMI and
report the tissue correlated with BMI, without the regression used here).
σ_k: the table's spread is ln(1 + CV²) = 0.42 (ASIS) and 0.27 (PSIS) in log
variance, 0.35 pooled; with one shared scale and `SITE_LOG_SD` per site (0.4,
fitted on the realistic phantoms), σ_k = 0.5 without a body build (`SCALE_LOG_SD`) and 0.4 with one
(`SCALE_LOG_SD_BODY_BUILD`, BMI taken to explain about a third of the
variance of ln k: an assumption).  The registration then estimates k from the
static trial (`personalize.registration.register_landmarks`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TissuePrior", "SOFT_TISSUE_THICKNESS", "DEFAULT_TISSUE", "tissue_site", "tissue_prior", "draw_thickness",
           "TissueScalePrior", "tissue_scale_prior", "body_fat_fraction", "SITE_LOG_SD", "SCALE_LOG_SD",
           "SCALE_LOG_SD_BODY_BUILD", "REFERENCE_BMI", "REFERENCE_AGE"]


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
    # lateral of the greater trochanter (DXA, older men, n = 222; women thicker): Nielson et al. 2009
    "TRO": TissuePrior(0.0310, 0.0115, "Nielson, Bouxsein et al. 2009, J Clin Endocrinol Metab 94:491"),
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

_ALIASES = {"ASIS": "ASI", "PSIS": "PSI", "SACR": "PSI"}   # a sacral marker lies between the PSIS, over the same tissue


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


#: log sd of one site's tissue about the subject's scaled table (sites do not scale exactly together): pooled sd
#: of ln(t_site / t0_site) about each subject's mean over its four pelvic markers, realistic phantoms' real-anatomy
#: subjects (benchmarks/realistic_calibration.py's training draw, seed 1000, 12 subjects: 0.405; checked on seed 0:
#: 0.412); was an assumed 0.3, which refused obese subjects whose ASIS tissue outgrows the PSIS's (34 / 27 mm)
SITE_LOG_SD = 0.4
#: log sd of a subject's tissue scale k without a body build (from the table's spread, see the module docstring)
SCALE_LOG_SD = 0.5
#: log sd of k about the body-build prior k₀ (ASSUMED: BMI explains about a third of the variance of ln k)
SCALE_LOG_SD_BODY_BUILD = 0.4
#: BMI (kg/m²) and age (years) taken for the table's cohort (ASSUMED, see the module docstring)
REFERENCE_BMI = 24.5
REFERENCE_AGE = 35.0
#: children's formula below this age (years), Deurenberg et al. 1991
_CHILD_AGE = 16.0


def body_fat_fraction(bmi: float, age: float | None = None, sex: float | None = None) -> float:
    """Body-fat fraction (0-1) from BMI (kg/m²), age (years) and sex (1 male, 0 female), Deurenberg et al. 1991.

    Adults: BF% = 1.2 BMI + 0.23 age - 10.8 sex - 5.4; age < 16: BF% = 1.51 BMI - 0.70 age - 3.6 sex + 1.4.
    Unknown age: `REFERENCE_AGE` (adult formula); unknown sex: 0.5.  Clipped to 3-60 %.
    """
    a = REFERENCE_AGE if age is None else float(age)
    x = 0.5 if sex is None else float(sex)
    if a < _CHILD_AGE:
        bf = 1.51 * bmi - 0.70 * a - 3.6 * x + 1.4
    else:
        bf = 1.2 * bmi + 0.23 * a - 10.8 * x - 5.4
    return float(np.clip(bf, 3.0, 60.0)) / 100.0


@dataclass(frozen=True)
class TissueScalePrior:
    """Prior of a subject's tissue scale k (t_i = k μ_i): ln k ~ N(ln median, log_sd²); site_log_sd per site.

    basis : how the median was chosen (body build or population)
    """

    median: float
    log_sd: float
    site_log_sd: float
    basis: str

    def summary(self) -> dict:
        return {"median": self.median, "log_sd": self.log_sd, "site_log_sd": self.site_log_sd, "basis": self.basis}


def tissue_scale_prior(height: float | None = None, mass: float | None = None, age: float | None = None,
                       sex: float | None = None) -> TissueScalePrior:
    """Body-build prior of the tissue scale k from height (m), mass (kg), age (years), sex (1 male, 0 female).

    k₀ = BF(BMI, age, sex) BMI / (BF(`REFERENCE_BMI`, `REFERENCE_AGE`) `REFERENCE_BMI`) (module docstring),
    log sd `SCALE_LOG_SD_BODY_BUILD`; without a usable height and mass k₀ = 1 (the table) with `SCALE_LOG_SD`.
    """
    ok = all(v is not None and np.isfinite(v) for v in (height, mass)) and 0.5 < float(height) < 2.5 \
        and 5.0 < float(mass) < 300.0
    if not ok:
        return TissueScalePrior(1.0, SCALE_LOG_SD, SITE_LOG_SD, "population table (no height and mass)")
    bmi = float(mass) / float(height) ** 2
    fmi = body_fat_fraction(bmi, age, sex) * bmi
    ref = body_fat_fraction(REFERENCE_BMI, REFERENCE_AGE, 0.5) * REFERENCE_BMI
    basis = f"fat-mass index from BMI {bmi:.1f}" + (f", age {float(age):g}" if age is not None else "") \
        + " (Deurenberg 1991) over the table's cohort"
    return TissueScalePrior(float(fmi / ref), SCALE_LOG_SD_BODY_BUILD, SITE_LOG_SD, basis)
