"""Triangle meshes as text files other tools open: Wavefront OBJ and ASCII PLY (``aumesh predict``).

Pure functions from arrays to text; the caller writes the file (atomically). Triangles come from
:func:`aumesh.geometry.face.triangulate`, wound by :func:`aumesh.geometry.face.outward_triangles`.
"""

from __future__ import annotations

import numpy as np


def obj_text(vertices: np.ndarray, triangles: np.ndarray, comment: str = "") -> str:
    """Wavefront OBJ: ``v x y z`` lines, then ``f i j k`` with 1-based indices.

    Parameters
    ----------
    vertices : array-like, shape (V, 3)
    triangles : array-like, shape (T, 3), int, 0-based
    comment : str
        Written as ``#`` lines at the top.
    """
    v, t = np.asarray(vertices, dtype=np.float64), np.asarray(triangles, dtype=np.int64)
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
    lines += [f"f {i + 1} {j + 1} {k + 1}" for i, j, k in t]
    return "\n".join(lines) + "\n"


def ply_text(vertices: np.ndarray, triangles: np.ndarray, comment: str = "") -> str:
    """ASCII PLY 1.0 with ``vertex`` (float x, y, z) and ``face`` (list of vertex indices) elements.

    Parameters
    ----------
    vertices : array-like, shape (V, 3)
    triangles : array-like, shape (T, 3), int, 0-based
    comment : str
        Written as ``comment`` header lines.
    """
    v, t = np.asarray(vertices, dtype=np.float64), np.asarray(triangles, dtype=np.int64)
    header = [
        "ply",
        "format ascii 1.0",
        *(f"comment {line}" for line in comment.splitlines()),
        f"element vertex {len(v)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(t)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    body = [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in v] + [f"3 {i} {j} {k}" for i, j, k in t]
    return "\n".join(header + body) + "\n"
