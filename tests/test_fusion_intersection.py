"""Covariance intersection (personalize.fusion.fuse_intersection): consistent for correlated sources."""
from __future__ import annotations

import numpy as np
from scipy import stats

from personalize.fusion import fuse_gaussian, fuse_intersection


def test_the_same_estimate_twice_is_not_counted_twice():
    a = (np.array([0.1, 0.2, 0.3]), np.diag([1.0, 4.0, 9.0]) * 1e-4)
    f = fuse_intersection([a, a], ("mri", "motion"))
    np.testing.assert_allclose(f.mean, a[0], atol=1e-12)
    np.testing.assert_allclose(f.cov, a[1], rtol=1e-5)
    np.testing.assert_allclose(fuse_gaussian([a, a]).cov, a[1] / 2.0, rtol=1e-12)   # the product halves it


def test_two_axis_aligned_sources_weight_each_where_it_is_sharp():
    a = (np.zeros(3), np.diag([1.0, 4.0, 1.0]) * 1e-4)
    b = (np.array([0.01, 0.0, 0.0]), np.diag([4.0, 1.0, 1.0]) * 1e-4)
    f = fuse_intersection([a, b])
    # ω = 1/2 by symmetry: C = (½ A⁻¹ + ½ B⁻¹)⁻¹ = diag(1.6, 1.6, 1) 1e-4, x = 0.2 × 10 mm
    np.testing.assert_allclose(np.diag(f.cov), [1.6e-4, 1.6e-4, 1e-4], rtol=1e-4)
    np.testing.assert_allclose(f.mean, [0.002, 0.0, 0.0], atol=1e-7)
    assert np.all(np.linalg.eigvalsh(f.cov - fuse_gaussian([a, b]).cov) > -1e-15)     # never tighter than the product


def test_covers_the_truth_when_the_sources_share_their_error():
    # two 3-D estimates of one point whose errors correlate 0.8 (the same palpated markers under both)
    rng = np.random.default_rng(0)
    A, B = np.diag([4.0, 9.0, 1.0]) * 1e-4, np.diag([9.0, 4.0, 4.0]) * 1e-4
    La, Lb = np.linalg.cholesky(A), np.linalg.cholesky(B)
    lim = stats.chi2.ppf(0.95, 3)
    inside_ci = inside_prod = 0
    n = 2000
    for _ in range(n):
        z = rng.standard_normal(3)
        w = 0.8 * z + 0.6 * rng.standard_normal(3)
        ea, eb = La @ z, Lb @ w
        for fuse, hit in ((fuse_intersection, "ci"), (fuse_gaussian, "prod")):
            f = fuse([(ea, A), (eb, B)])
            d2 = f.mean @ np.linalg.solve(f.cov, f.mean)
            if d2 <= lim:
                if hit == "ci":
                    inside_ci += 1
                else:
                    inside_prod += 1
    assert inside_ci / n >= 0.95 and inside_prod / n < 0.92
