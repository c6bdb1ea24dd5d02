"""Per-site soft-tissue priors shared by the phantoms (draws) and the registration (prior)."""
from __future__ import annotations

import numpy as np

from kinematics.gait.soft_tissue import DEFAULT_TISSUE, SOFT_TISSUE_THICKNESS, draw_thickness, tissue_prior, tissue_site


def test_marker_names_map_to_their_site():
    assert tissue_site("RASI") == "ASI" and tissue_site("LPSI") == "PSI" and tissue_site("LKNEM") == "KNEM"
    assert tissue_site("ASIS") == "ASI"
    assert tissue_prior("RASI").mean == SOFT_TISSUE_THICKNESS["ASI"].mean
    assert tissue_prior("SACR") == SOFT_TISSUE_THICKNESS["PSI"]     # between the PSIS, over the same tissue
    assert tissue_prior("RTHI") == DEFAULT_TISSUE      # not tabulated: the stated default


def test_draws_have_the_table_mean_and_sd_and_stay_positive():
    rng = np.random.default_rng(4)
    for site in ("ASI", "PSI"):
        x = np.array([draw_thickness(rng, site) for _ in range(20000)])
        p = SOFT_TISSUE_THICKNESS[site]
        assert np.all(x > 0)
        assert abs(x.mean() - p.mean) < 0.03 * p.mean, site
        assert abs(x.std() - p.sd) < 0.06 * p.sd, site
    # seeded: the same generator state gives the same subject
    assert draw_thickness(np.random.default_rng([7, 7]), "PSI") == draw_thickness(np.random.default_rng([7, 7]), "PSI")
