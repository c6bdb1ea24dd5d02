"""The detectors' surface preparation against the library code it replaces (trimesh) and against analytic values."""
import numpy as np
import trimesh
from trimesh.remesh import subdivide_to_size

from personalize.landmarks.surface import (SUBDIVIDED_EDGE, _is_closed, _split_long_edges, as_surface,
                                           edge_curvature, even_sampling)


def _coarse_sphere(radius=0.03):
    m = trimesh.creation.icosphere(subdivisions=2, radius=radius)    # edges about 6-7 mm
    rng = np.random.default_rng(3)
    m.vertices = m.vertices * (1.0 + 0.05 * rng.standard_normal((len(m.vertices), 1)))  # uneven edges
    return m


def test_long_edges_are_split_exactly_as_trimesh_splits_them():
    m = _coarse_sphere()
    V, F = np.asarray(m.vertices), np.asarray(m.faces, np.int64)
    v1, f1 = subdivide_to_size(V, F, max_edge=SUBDIVIDED_EDGE, max_iter=12)
    v2, f2, lengths = _split_long_edges(V, F, SUBDIVIDED_EDGE)
    assert np.array_equal(v1, v2) and np.array_equal(f1, f2)          # vertex and face order included
    assert np.allclose(np.sort(lengths), np.sort(m.edges_unique_length))
    out, note = even_sampling(m, "femur_r")
    assert out.edges_unique_length.max() <= SUBDIVIDED_EDGE + 1e-12
    assert note is not None and "coarse mesh" in note                 # every edge of this sphere was long


def test_closedness_is_trimeshs_watertightness_on_a_closed_and_an_open_mesh():
    m = _coarse_sphere()
    assert _is_closed(np.asarray(m.faces, np.int64), len(m.vertices)) is True
    holed = trimesh.Trimesh(m.vertices, m.faces[3:], process=False)
    assert not holed.is_watertight
    assert _is_closed(np.asarray(holed.faces, np.int64), len(holed.vertices)) is False
    assert as_surface(holed, "femur_r").closed is False


def test_edge_curvature_of_a_sphere_is_one_over_its_radius():
    r = 0.025
    s = as_surface(trimesh.creation.icosphere(subdivisions=4, radius=r), "femur_r")
    H = edge_curvature(s)
    # exact normals give 1/r on every chord; the mesh's area-weighted vertex normals lean a few per cent inwards
    assert np.all(np.abs(H * r - 1.0) < 0.08) and abs(np.median(H) * r - 1.0) < 0.05
    assert np.all(edge_curvature(as_surface(trimesh.Trimesh(s.vertices, s.faces[:, ::-1], process=False))) > 0)


def test_hough_peak_is_the_sphere_centre_with_its_ball_count_of_votes():
    from scipy.spatial import cKDTree

    from personalize.landmarks.shape_fits import hough_centres
    rng = np.random.default_rng(5)
    m = trimesh.creation.icosphere(subdivisions=4, radius=0.024)
    cap = m.vertices[:, 2] > 0.0                                       # a head: the upper half sphere
    centre = np.array([0.01, -0.02, 0.03])
    P = m.vertices[cap] + centre + 2e-4 * rng.standard_normal((cap.sum(), 3))
    N = m.vertex_normals[cap]
    radii = np.linspace(0.018, 0.030, 7)
    (support, c, r), = hough_centres(P, N, radii, inward=False, tol=1e-3)
    assert np.linalg.norm(c - centre) < 1e-3 and abs(r - 0.024) < 1e-9
    votes = np.concatenate([P - q * N for q in radii])
    assert support == max(len(i) for i in cKDTree(votes).query_ball_point(votes, 1e-3))
