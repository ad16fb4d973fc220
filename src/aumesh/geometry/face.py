"""aumesh's own face-like 478-vertex template, its face frame and its triangulation.

Everything here is the project's own documented data, generated deterministically
by code. Nothing is copied from MediaPipe's canonical model (no vertex position of
``canonical_face_model.obj`` or any other MediaPipe data file): the *index numbers*
of the MediaPipe FaceMesh topology say which vertex sits at which anatomical
landmark (e.g. 1 = nose tip, 33/263 = outer eye corners; about 200 of them, with
the eye, brow, lip and face-oval contours), and the other vertices are placed
from the topology:

* **with the ``mediapipe`` package installed** (extra ``mediapipe``; in the test
  extra), its face tessellation (``FaceLandmarksConnections.
  FACE_LANDMARKS_TESSELATION``: 852 triangles over vertices 0-467) is read from
  the installed package and every vertex that is not a named landmark is put at
  the average of its tessellation neighbours: the harmonic embedding of the mesh
  graph (uniform weights, Tutte 1963) with the named landmarks as fixed
  constraints, solved as one sparse linear system in the frontal (x, y) plane;
  depth is the smooth face-depth function of this module. Every tessellation edge
  is then short (median 0.07, max 0.42 inter-ocular distances, against 0.62 and
  1.70 for the fallback; ``tests/test_face.py`` checks max < 0.5), so MediaPipe's
  triangles and py-feat's drawings of them form a face. The embedding is not
  guaranteed planar with fixed interior landmarks: 20 of the 852 triangles fold
  over in the frontal projection, small ones at the eye and mouth corners and the
  nostrils;
* **without it** (the documented fallback), the other vertices are spread evenly
  over the face by farthest-point sampling; then MediaPipe's edges on the
  template are long, and figures use the project's own triangulation.

:func:`template_source` says which of the two a process uses; ``aumesh synth``
tables depend on it (the demo data was made with ``mediapipe`` installed).

Orientation convention (the "face frame", used by every function here)
-----------------------------------------------------------------------
Image orientation, like py-feat's pixel meshes:

* ``x`` grows to image right, which is the **subject's left**
  (``T[263, 0] > T[33, 0]``);
* ``y`` grows **down** (``T[152, 1] > T[10, 1]``: chin below forehead);
* ``z`` grows **away from the camera** (the nose tip ``1`` has the smallest z).

``(x, y, z)`` is right-handed (``x × y = z``). Units: inter-ocular distance
(outer eye corners 33 ↔ 263, 3-D) is 1.0; the template is centred at the mean of
its vertices.

:func:`face_frame` recovers this frame from *any* mesh with the MediaPipe
topology (any rotation, scale, translation, or y-up / mirrored convention), from
the landmarks alone: up = forehead 10 − chin 152, subject's left = 33 → 263,
out of face = their cross product, sign fixed so the nose tip 1 is in front.

The landmark vocabulary (which index is which anatomical point: ``LANDMARKS``, ``REGIONS``, ``AREA_SEEDS``, the
contours) is :mod:`aumesh.geometry.landmarks`; measurements of a face in this frame (its areas and proportions) are
:mod:`aumesh.geometry.measures`; the synthetic FACS displacement fields live in ``aumesh.synthetic.truth``.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from aumesh.core.schema import N_VERTICES
from aumesh.geometry.landmarks import (
    BROW_LOWER_LEFT,
    BROW_LOWER_RIGHT,
    BROW_UPPER_LEFT,
    BROW_UPPER_RIGHT,
    CHIN_MIDLINE,
    EYE_CONTOUR_LEFT,
    EYE_CONTOUR_RIGHT,
    FACE_OVAL,
    IRIS_LEFT,
    IRIS_RIGHT,
    LIPS_INNER,
    LIPS_OUTER,
    NOSE_MIDLINE,
)

# --------------------------------------------------------------------------- layout
# Named landmark positions in (u, v): u = subject's left (= image right), v = up,
# inter-ocular units; converted to the face frame (x = u, y = -v) below.
_OVAL_CENTRE_V, _OVAL_A, _OVAL_B = -0.15, 0.78, 1.08


def _oval_uv(n: int = len(FACE_OVAL)) -> np.ndarray:
    theta = 2.0 * np.pi * np.arange(n) / n  # 0 at top, clockwise toward +u
    c, s = np.cos(theta), np.sin(theta)
    taper = 1.0 - 0.3 * np.where(c < 0, c**2, 0.0)  # narrower jaw
    return np.stack([_OVAL_A * s * taper, _OVAL_CENTRE_V + _OVAL_B * c], axis=1)


def _named_uv() -> dict[int, tuple[float, float]]:
    p: dict[int, tuple[float, float]] = {}
    for idx, (u, v) in zip(FACE_OVAL, _oval_uv(), strict=True):
        p[idx] = (float(u), float(v))
    for idx, v in zip((151, 9, 8), (0.66, 0.40, 0.24), strict=True):
        p[idx] = (0.0, v)
    for idx, v in zip(NOSE_MIDLINE, (0.12, 0.02, -0.10, -0.21, -0.30, -0.37, -0.42), strict=True):
        p[idx] = (0.0, v)
    p[2] = (0.0, -0.50)
    for idx, v in zip(CHIN_MIDLINE[:-1], (-0.93, -1.00, -1.07, -1.15), strict=True):
        p[idx] = (0.0, v)
    # Eyes: lower lid outer->inner (9 pts incl. corners), upper lid inner->outer.
    for contour, iris, sgn in ((EYE_CONTOUR_RIGHT, IRIS_RIGHT, -1), (EYE_CONTOUR_LEFT, IRIS_LEFT, 1)):
        outer, inner = 0.5 * sgn, 0.17 * sgn
        t = np.arange(9) / 8.0
        for idx, ti in zip(contour[:9], t, strict=True):
            p[idx] = (outer + ti * (inner - outer), -0.045 * np.sin(np.pi * ti))
        for idx, ti in zip(contour[9:], 1.0 - t[1:8], strict=True):
            p[idx] = (outer + ti * (inner - outer), 0.055 * np.sin(np.pi * ti) ** 0.8)
        cu, r = 0.335 * sgn, 0.03
        p[iris[0]] = (cu, 0.002)
        for idx, ang in zip(iris[1:], (0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi), strict=True):
            p[idx] = (cu + r * np.cos(ang), 0.002 + r * np.sin(ang))
    # Brows, outer->inner, mirrored.
    bu = np.array([0.58, 0.47, 0.36, 0.25, 0.14])
    bv = np.array([0.22, 0.26, 0.275, 0.27, 0.25])
    for up, lo, sgn in ((BROW_UPPER_RIGHT, BROW_LOWER_RIGHT, -1), (BROW_UPPER_LEFT, BROW_LOWER_LEFT, 1)):
        for i in range(5):
            p[up[i]] = (sgn * bu[i], bv[i])
            p[lo[i]] = (sgn * (bu[i] - 0.01), bv[i] - 0.05)
    # Lips. Upper outer / inner: 11 pts right corner -> left corner.
    t = np.linspace(-1.0, 1.0, 11)
    for idx, ti in zip(LIPS_OUTER[:11], t, strict=True):
        p[idx] = (0.27 * ti, -0.72 + 0.075 * (1 - ti**2) ** 0.8)
    for idx, ti in zip(LIPS_INNER[:11], t, strict=True):
        p[idx] = (0.23 * ti, -0.73 + 0.015 * (1 - ti**2))
    t9 = t[1:10][::-1]  # lower lip runs left -> right
    for idx, ti in zip(LIPS_OUTER[11:], t9, strict=True):
        p[idx] = (0.27 * ti, -0.72 - 0.12 * (1 - ti**2) ** 0.8)
    for idx, ti in zip(LIPS_INNER[11:], t9, strict=True):
        p[idx] = (0.23 * ti, -0.73 - 0.015 * (1 - ti**2))
    # Nose base and cheeks: (right index, left index, |u|, v).
    for r_i, l_i, u, v in (
        (48, 278, 0.11, -0.33),
        (64, 294, 0.15, -0.42),
        (98, 327, 0.10, -0.46),
        (116, 345, 0.62, -0.12),
        (117, 346, 0.48, -0.16),
        (123, 352, 0.60, -0.30),
        (50, 280, 0.36, -0.30),
        (187, 411, 0.50, -0.48),
        (205, 425, 0.34, -0.48),
    ):
        p[r_i] = (-u, v)
        p[l_i] = (u, v)
    return p


def _points_in_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd rule point-in-polygon. points (N, 2), polygon (M, 2) -> bool (N,)."""
    x, y = points[:, 0][:, None], points[:, 1][:, None]
    x0, y0 = polygon[:, 0][None, :], polygon[:, 1][None, :]
    x1, y1 = np.roll(polygon[:, 0], -1)[None, :], np.roll(polygon[:, 1], -1)[None, :]
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return (crosses & (x < x_at)).sum(axis=1) % 2 == 1


def _depth(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smooth face-depth function, z away from camera, inter-ocular units."""
    z = 0.55 * (u / 0.85) ** 2 + 0.25 * ((v + 0.15) / 1.1) ** 2  # rounded face
    prof = np.where(v >= -0.42, np.clip((0.12 - v) / 0.54, 0.0, 1.0) ** 1.3, np.exp(-(((v + 0.42) / 0.07) ** 2)))
    width = 0.05 + 0.08 * prof
    z = z - 0.28 * prof * np.exp(-(u**2) / (2 * width**2))  # nose
    for cu in (-0.335, 0.335):
        z = z + 0.06 * np.exp(-((u - cu) ** 2 + v**2) / (2 * 0.12**2))  # eye sockets
    z = z - 0.03 * np.exp(-((v - 0.22) ** 2) / (2 * 0.06**2))  # brow ridge
    z = z - 0.06 * np.exp(-0.5 * ((u / 0.2) ** 2 + ((v + 0.73) / 0.1) ** 2))  # lips
    z = z - 0.05 * np.exp(-0.5 * ((u / 0.2) ** 2 + ((v + 1.05) / 0.12) ** 2))  # chin
    return z


# --------------------------------------------------------------------------- MediaPipe's topology
@lru_cache(maxsize=1)
def mediapipe_triangles() -> np.ndarray | None:
    """MediaPipe's face tessellation from the installed ``mediapipe`` package, or None without it.

    Returns
    -------
    np.ndarray, shape (852, 3), int64, or None
        Triangles over vertices 0-467 (the irises 468-477 are not part of it).

    Notes
    -----
    ``FaceLandmarksConnections.FACE_LANDMARKS_TESSELATION`` (``mediapipe.tasks.python.vision.
    face_landmarker``) lists each triangle as three consecutive edges ``a->b, b->c, c->a``. The list
    is read from the installed module's source with :mod:`ast` instead of importing it: importing
    ``mediapipe`` takes seconds and imports ``matplotlib.pyplot``. ``tests/test_face.py`` checks the
    result against the imported attribute.
    """
    import ast
    import importlib.util

    spec = importlib.util.find_spec("mediapipe")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / "tasks" / "python" / "vision" / "face_landmarker.py"
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    edges = None
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and node.target.id == "FACE_LANDMARKS_TESSELATION"
            and isinstance(node.value, ast.List)
        ):
            calls = [call for call in node.value.elts if isinstance(call, ast.Call)]
            edges = np.array([[ast.literal_eval(a) for a in call.args] for call in calls], dtype=np.int64)
    if edges is None or edges.ndim != 2 or edges.shape[1] != 2 or len(edges) % 3:
        raise RuntimeError(
            f"{path}: FACE_LANDMARKS_TESSELATION not found as a list of Connection(start, end) triples; "
            f"this mediapipe version is not supported (uninstall it to use the fallback template)"
        )
    triples = edges.reshape(-1, 3, 2)
    if not np.array_equal(triples[:, :, 1], np.roll(triples[:, :, 0], -1, axis=1)):
        raise RuntimeError(f"{path}: FACE_LANDMARKS_TESSELATION is not a list of closed triangles")
    return triples[:, :, 0].copy()


def mediapipe_edges() -> np.ndarray | None:
    """Unique undirected edges (E, 2) of :func:`mediapipe_triangles`, or None without ``mediapipe``."""
    tri = mediapipe_triangles()
    if tri is None:
        return None
    e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def template_source() -> str:
    """``"mediapipe-topology"`` (harmonic embedding of MediaPipe's tessellation) or ``"fallback"``."""
    return "mediapipe-topology" if mediapipe_triangles() is not None else "fallback"


def _harmonic_uv(named: dict[int, tuple[float, float]], edges: np.ndarray) -> np.ndarray:
    """(478, 2): named vertices fixed, every other vertex the mean of its graph neighbours (sparse solve)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    n = N_VERTICES
    i, j = np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]])
    adjacency = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    laplacian = (
        coo_matrix((np.asarray(adjacency.sum(axis=1)).ravel(), (np.arange(n), np.arange(n))), shape=(n, n)) - adjacency
    ).tocsr()
    fixed = np.array(sorted(named))
    free = np.setdiff1d(np.arange(n), fixed)
    isolated = free[np.asarray(adjacency[free].sum(axis=1)).ravel() == 0]
    if len(isolated):  # pragma: no cover - MediaPipe's tessellation reaches every non-iris vertex
        raise RuntimeError(f"vertices {isolated[:10].tolist()} are neither named nor in the tessellation")
    uv = np.zeros((n, 2))
    uv[fixed] = [named[k] for k in fixed]
    rhs = -laplacian[free][:, fixed] @ uv[fixed]
    uv[free] = spsolve(laplacian[free][:, free].tocsc(), rhs).reshape(len(free), 2)
    return uv


def _farthest_point_uv(named: dict[int, tuple[float, float]]) -> np.ndarray:
    """(478, 2): named vertices, the rest spread evenly over the face (no topology needed)."""
    n_fill = N_VERTICES - len(named)
    fixed = np.array(list(named.values()))
    # Candidate grid inside the (slightly shrunk) oval, outside eyes and mouth opening.
    oval = _oval_uv(360) * np.array([0.97, 1.0]) + np.array([0.0, 0.03 * _OVAL_CENTRE_V])
    g = np.arange(-1.3, 1.3, 0.012)
    cand = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    keep = _points_in_polygon(cand, oval)
    for contour in (EYE_CONTOUR_RIGHT, EYE_CONTOUR_LEFT, LIPS_INNER):
        poly = np.array([named[i] for i in contour])
        centre = poly.mean(axis=0)
        keep &= ~_points_in_polygon(cand, centre + 1.25 * (poly - centre))
    cand = cand[keep]
    # Farthest-point sampling seeded with the named landmarks (deterministic).
    d = np.min(np.linalg.norm(cand[:, None, :] - fixed[None, :, :], axis=2), axis=1)
    picked = []
    for _ in range(n_fill):
        k = int(np.argmax(d))
        picked.append(cand[k])
        d = np.minimum(d, np.linalg.norm(cand - cand[k], axis=1))
    chosen = np.array(picked)
    chosen = chosen[np.lexsort((chosen[:, 0], np.round(-chosen[:, 1], 6)))]  # top->bottom
    uv = np.zeros((N_VERTICES, 2))
    free = [i for i in range(N_VERTICES) if i not in named]
    for i, (u, v) in named.items():
        uv[i] = (u, v)
    uv[free] = chosen
    return uv


@lru_cache(maxsize=1)
def _template_cached() -> np.ndarray:
    named = _named_uv()
    edges = mediapipe_edges()
    uv = _farthest_point_uv(named) if edges is None else _harmonic_uv(named, edges)
    mesh = np.column_stack([uv[:, 0], -uv[:, 1], _depth(uv[:, 0], uv[:, 1])])
    # Express the template exactly in its own face frame (so face_frame(T) is identity).
    mesh = to_face_frame(mesh)
    mesh.setflags(write=False)
    return mesh


def canonical_template() -> np.ndarray:
    """The project's face-like 478-vertex template in the face frame.

    Returns
    -------
    np.ndarray, shape (478, 3), float64
        Vertex ``i`` sits at the anatomical position of MediaPipe FaceMesh vertex
        ``i`` for every index in :data:`~aumesh.geometry.landmarks.LANDMARKS` and the contours of that
        module; the other indices fill the face evenly. x = subject's left,
        y = down, z = away from camera; inter-ocular distance 1; mean-centred.
        A fresh writable copy on every call.
    """
    return np.array(_template_cached(), dtype=np.float64, copy=True)


# --------------------------------------------------------------------------- frames
def face_frame(mesh: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Recover the face frame of any mesh with the MediaPipe topology.

    Parameters
    ----------
    mesh : array-like, shape (478, 3)
        Vertices in any rotation / scale / translation / handedness.

    Returns
    -------
    origin : np.ndarray, shape (3,)
        Mean of the vertices.
    axes : np.ndarray, shape (3, 3)
        Rows are the face-frame unit axes expressed in the input coordinates:
        ``axes[0]`` = subject's left, ``axes[1]`` = down, ``axes[2]`` = away from
        camera (sign chosen so the nose tip 1 is in front of the eye corners).
        Orthonormal; may be a reflection if the input is mirrored.
    scale : float
        Inter-ocular distance |mesh[263] - mesh[33]| in input units.

    Notes
    -----
    ``to_face_frame(mesh) == (mesh - origin) @ axes.T / scale``.
    """
    m = np.asarray(mesh, dtype=np.float64)
    if m.shape != (N_VERTICES, 3):
        raise ValueError(f"mesh must have shape ({N_VERTICES}, 3), got {m.shape}")
    if not np.all(np.isfinite(m[[10, 152, 33, 263, 1]])):
        raise ValueError("mesh landmarks 10, 152, 33, 263, 1 must be finite to find the face frame")
    left = m[263] - m[33]
    scale = float(np.linalg.norm(left))
    if scale == 0.0:
        raise ValueError("mesh has coincident outer eye corners 33 and 263; cannot find the face frame")
    ex = left / scale
    up = m[10] - m[152]
    up = up - (up @ ex) * ex
    nu = np.linalg.norm(up)
    if nu == 0.0:
        raise ValueError("forehead 10 - chin 152 is parallel to 33 -> 263; cannot find 'up'")
    ey = -up / nu  # down
    ez = np.cross(ex, ey)
    eyes = 0.25 * (m[33] + m[263] + m[133] + m[362])
    if (m[1] - eyes) @ ez > 0:  # nose tip must be toward the camera (smaller z)
        ez = -ez
    return m.mean(axis=0), np.stack([ex, ey, ez]), scale


def to_face_frame(mesh: np.ndarray) -> np.ndarray:
    """Express a mesh (478, 3) in the face frame (x left, y down, z away, IOD units, centred)."""
    origin, axes, scale = face_frame(mesh)
    return (np.asarray(mesh, dtype=np.float64) - origin) @ axes.T / scale


# --------------------------------------------------------------------------- triangulation
def triangulate(mesh: np.ndarray | None = None) -> np.ndarray:
    """Triangles to draw a 478-vertex mesh with: MediaPipe's where ``mediapipe`` is installed, else the project's.

    With ``mediapipe`` installed: its face tessellation (:func:`mediapipe_triangles`, 852 triangles).
    Without it: the project's own Delaunay triangulation (:func:`delaunay_triangles`). Either way the
    iris vertices 468-477 lie inside the eye openings and are not referenced.

    Parameters
    ----------
    mesh : array-like, shape (478, 3), optional
        Defaults to :func:`canonical_template`; any orientation (found from the anatomy).

    Returns
    -------
    np.ndarray, shape (T, 3), int64
        Vertex indices, counter-clockwise in the displayed frontal view
        (x right, y down is drawn with y flipped).
    """
    m = canonical_template() if mesh is None else to_face_frame(mesh)
    tri = mediapipe_triangles()
    tri = delaunay_triangles(m) if tri is None else tri.copy()
    # Consistent winding: counter-clockwise as seen with y up on screen.
    xy = m[:, :2]
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (-(c[:, 1] - a[:, 1])) - (-(b[:, 1] - a[:, 1])) * (c[:, 0] - a[:, 0])
    flip = cross < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return tri


def delaunay_triangles(mesh: np.ndarray) -> np.ndarray:
    """The project's own triangulation of a mesh in the face frame (:func:`to_face_frame`), (T, 3) int64.

    Delaunay triangulation of the frontal (x, y) projection, dropping triangles whose centroid lies
    inside an eye opening (eye contours), inside the mouth opening (inner-lip contour) or outside
    the face oval, and over-long triangles (longest edge > 4 x median edge). This is *not*
    MediaPipe's tessellation; it needs no topology, so it works on any vertex layout.
    """
    from scipy.spatial import Delaunay

    xy = np.asarray(mesh, dtype=np.float64)[:, :2]
    tri = Delaunay(xy).simplices.astype(np.int64)
    cen = xy[tri].mean(axis=1)
    drop = np.zeros(len(tri), dtype=bool)
    for contour in (EYE_CONTOUR_RIGHT, EYE_CONTOUR_LEFT, LIPS_INNER):
        drop |= _points_in_polygon(cen, xy[list(contour)])
    drop |= ~_points_in_polygon(cen, xy[list(FACE_OVAL)])
    edges = np.linalg.norm(xy[tri] - xy[np.roll(tri, -1, axis=1)], axis=2)
    drop |= edges.max(axis=1) > 4.0 * np.median(edges)
    return tri[~drop]


def outward_triangles(mesh: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles wound so their normals ``(b - a) x (c - a)`` point out of the face.

    Parameters
    ----------
    mesh : array-like, shape (478, 3)
        Vertices in any frame (the face frame is found from the anatomy, :func:`face_frame`).
    triangles : array-like, shape (T, 3), int
        Vertex indices, e.g. :func:`triangulate`.

    Returns
    -------
    np.ndarray, shape (T, 3), int64
        The same triangles, each counter-clockwise seen from in front of the face (the usual
        front-face convention of OBJ, PLY and glTF viewers).
    """
    m = np.asarray(mesh, dtype=np.float64)
    tri = np.array(triangles, dtype=np.int64, copy=True)
    _, axes, _ = face_frame(m)
    toward_viewer = -axes[2]  # axes[2] points away from the camera, behind the face
    a, b, c = m[tri[:, 0]], m[tri[:, 1]], m[tri[:, 2]]
    flip = np.cross(b - a, c - a) @ toward_viewer < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return tri
