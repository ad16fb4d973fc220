"""Template, landmark orientation, triangulation and synthetic AU fields of aumesh.geometry.face and .landmarks."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aumesh.core.schema import ANCHOR_INDICES, AU_COLUMNS, N_VERTICES
from aumesh.geometry import face, landmarks
from aumesh.synthetic import truth


@pytest.fixture(scope="module")
def tpl() -> np.ndarray:
    return face.canonical_template()


def test_template_has_478_unique_finite_vertices(tpl):
    assert tpl.shape == (N_VERTICES, 3) and tpl.dtype == np.float64
    assert np.isfinite(tpl).all()
    assert len(np.unique(tpl.round(9), axis=0)) == N_VERTICES


def test_template_is_deterministic_and_returns_a_copy(tpl):
    again = face.canonical_template()
    again[0] = 99.0
    assert np.array_equal(face.canonical_template(), tpl)


def test_orientation_image_convention_left_right_down_and_nose_in_front(tpl):
    assert tpl[263, 0] > tpl[33, 0]  # subject's left is image right
    assert tpl[362, 0] > tpl[133, 0]
    assert tpl[152, 1] > tpl[10, 1]  # y down: chin below forehead
    assert tpl[17, 1] > tpl[0, 1] and tpl[145, 1] > tpl[159, 1]
    midline = [10, 151, 9, 8, 168, 6, 197, 195, 5, 4, 1, 2, 0, 13, 14, 17, 18, 200, 199, 175, 152]
    assert tpl[midline, 2].argmin() == midline.index(1)  # nose tip nearest the camera
    assert np.isclose(np.linalg.norm(tpl[263] - tpl[33]), 1.0)
    assert np.allclose(tpl.mean(axis=0), 0.0, atol=1e-12)


def test_anchors_distinct_and_regions_valid(tpl):
    anchors = tpl[list(ANCHOR_INDICES)]
    d = np.linalg.norm(anchors[:, None] - anchors[None], axis=2) + np.eye(len(anchors))
    assert d.min() > 0.02
    for name, idx in landmarks.REGIONS.items():
        assert idx.size and idx.min() >= 0 and idx.max() < N_VERTICES, name
        side = landmarks.region_side(name)
        if side:
            assert np.all(np.sign(tpl[idx, 0]) == side), f"{name} on the wrong side"


def test_triangulation_indices_valid_and_covers_face(tpl):
    tri = face.triangulate()
    assert tri.ndim == 2 and tri.shape[1] == 3 and len(tri) > 700
    assert tri.min() >= 0 and tri.max() < N_VERTICES
    used = set(np.unique(tri).tolist())
    iris = set(landmarks.IRIS_RIGHT + landmarks.IRIS_LEFT)
    assert set(range(N_VERTICES)) - iris <= used  # every non-iris vertex is in a triangle
    # Total area close to the face oval's area.
    xy = tpl[:, :2]
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    area = 0.5 * np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]).sum()
    oval = xy[list(landmarks.FACE_OVAL)]
    oval_area = 0.5 * abs(np.dot(oval[:, 0], np.roll(oval[:, 1], -1)) - np.dot(oval[:, 1], np.roll(oval[:, 0], -1)))
    assert 0.9 * oval_area < area <= oval_area * 1.0001


@pytest.mark.parametrize("contour", ["EYE_CONTOUR_RIGHT", "EYE_CONTOUR_LEFT", "LIPS_INNER"])
def test_no_triangle_spans_an_eye_or_mouth_opening(tpl, contour):
    """Two vertices of one triangle on an opening's contour are neighbours along it (no chord across)."""
    ring = list(getattr(face, contour))
    pos = {v: k for k, v in enumerate(ring)}
    for tri in (face.triangulate(), face.delaunay_triangles(tpl)):
        for t in tri:
            on = sorted(pos[v] for v in t if v in pos)
            for a, b in pairwise(on):
                assert min(b - a, len(ring) - (b - a)) == 1, t


def test_project_triangulation_has_no_triangle_inside_an_opening(tpl):
    tri = face.delaunay_triangles(tpl)
    cen = tpl[tri, :2].mean(axis=1)
    for contour in (landmarks.EYE_CONTOUR_RIGHT, landmarks.EYE_CONTOUR_LEFT, landmarks.LIPS_INNER):
        assert not face._points_in_polygon(cen, tpl[list(contour), :2]).any()


# --------------------------------------------------------------------------- MediaPipe's topology
def _imported_tessellation() -> np.ndarray:
    """MediaPipe's tessellation through the package's public attribute (the independent reference)."""
    mp = pytest.importorskip("mediapipe.tasks.python.vision.face_landmarker")
    return np.array([(c.start, c.end) for c in mp.FaceLandmarksConnections.FACE_LANDMARKS_TESSELATION])


def test_tessellation_read_from_the_installed_package_is_mediapipes():
    edges = _imported_tessellation()
    assert np.array_equal(face.mediapipe_triangles(), edges.reshape(-1, 3, 2)[:, :, 0])
    assert face.template_source() == "mediapipe-topology"


def test_no_mediapipe_tessellation_edge_longer_than_half_the_inter_ocular_distance(tpl):
    edges = _imported_tessellation()
    length = np.linalg.norm(tpl[edges[:, 0]] - tpl[edges[:, 1]], axis=1)
    iod = np.linalg.norm(tpl[263] - tpl[33])
    assert length.max() < 0.5 * iod, (edges[length.argmax()], length.max() / iod)
    assert np.median(length) < 0.1 * iod  # dense like a face mesh, not a few long strands


def test_figures_draw_mediapipes_triangles_where_installed(tpl):
    edges = _imported_tessellation()
    tri = face.triangulate()
    assert {frozenset(t) for t in tri.tolist()} == {frozenset(t) for t in edges.reshape(-1, 3, 2)[:, :, 0].tolist()}


@pytest.fixture
def without_mediapipe(monkeypatch):
    """The process as if ``mediapipe`` were not installed (the fallback)."""
    monkeypatch.setattr(face, "mediapipe_triangles", lambda: None)
    face._template_cached.cache_clear()
    yield
    face._template_cached.cache_clear()


@pytest.mark.slow
def test_fallback_without_mediapipe_keeps_the_landmarks_and_the_projects_triangles(tpl, without_mediapipe):
    assert face.template_source() == "fallback"
    fallback = face.canonical_template()
    named = sorted(face._named_uv())
    # same named layout (the frames differ only by centring, the mean of the other vertices)
    shift = (fallback[named] - tpl[named]).mean(axis=0)
    np.testing.assert_allclose(fallback[named], tpl[named] + shift, atol=1e-9)
    assert np.array_equal(face.triangulate(), face.triangulate(fallback))
    tri = face.triangulate()
    assert len(tri) > 700 and tri.max() < 468


def test_triangulation_is_orientation_agnostic(tpl):
    R = Rotation.from_euler("xyz", [0.4, -0.3, 2.0]).as_matrix()
    moved = 37.0 * tpl @ R.T + np.array([5.0, -3.0, 100.0])
    assert np.array_equal(face.triangulate(moved), face.triangulate())


def test_face_frame_recovers_template_from_rotated_scaled_y_up_mesh(tpl):
    R = Rotation.from_euler("xyz", [0.2, 0.5, -0.7]).as_matrix()
    for mesh in (200.0 * tpl @ R.T + 3.0, tpl * np.array([1.0, -1.0, 1.0]), tpl * np.array([1.0, -1.0, -1.0])):
        assert np.allclose(face.to_face_frame(mesh), tpl, atol=1e-9)


def test_au_fields_shape_magnitude_and_key_directions(tpl):
    f = truth.facs_displacement_fields()
    assert f.shape == (len(AU_COLUMNS), N_VERTICES, 3)
    mags = np.linalg.norm(f, axis=2).max(axis=1)
    assert np.all((mags >= 0.02) & (mags <= 0.2)), dict(zip(AU_COLUMNS, mags.round(3), strict=True))
    k = AU_COLUMNS.index
    assert f[k("AU12"), 291, 1] < 0 and f[k("AU12"), 291, 0] > 0 and f[k("AU12"), 61, 0] < 0  # up and out
    assert f[k("AU26"), 152, 1] > 0 and abs(f[k("AU26"), 13, 1]) < 0.01  # jaw drops, upper lip stays
    assert f[k("AU01"), 107, 1] < 0 and f[k("AU04"), 107, 1] > 0 and f[k("AU04"), 107, 0] > 0
    assert f[k("AU43"), 159, 1] > 0 and abs(f[k("AU43"), 145, 1]) < 0.01  # upper lid down only


def test_au_fields_follow_the_template_orientation(tpl):
    R = Rotation.from_euler("xyz", [0.1, 0.8, 0.3]).as_matrix()
    moved = 4.0 * tpl @ R.T - 1.0
    assert np.allclose(truth.facs_displacement_fields(moved), 4.0 * truth.facs_displacement_fields() @ R.T)
