"""The release as a glTF 2.0 blendshape rig (``au_to_mesh.glb``), written with pygltflib.

The model is linear, so at pose 0 it *is* a blendshape rig (card, "Inference":
``flat = x @ coef + intercept``): the base mesh is the prediction at AU = 0, pose = 0
(``intercept``), and morph target ``k`` is AU ``k``'s displacement field at one unit of
intensity (row ``k`` of ``coef``). With weights ``w`` (the AU intensities) a glTF viewer
shows ``base + sum_k w_k * target_k``, exactly the model's mesh at pose 0 (up to float32,
the NPZ's own precision). Target names (``AU01`` ... ``AU43``) are in the mesh's
``extras.targetNames``, the convention three.js, Blender and Babylon.js read.

Coordinates are the NPZ's, unchanged (the release's frame and units); triangles are the
project's triangulation of the base mesh, wound so their fronts face out of the face (toward
the nose tip); normals are the base mesh's area-weighted vertex normals.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.data.schema import AU_COLUMNS, INPUT_COLUMNS, unflatten_axis_major
from aumesh.geometry import face

GLB_NAME = "au_to_mesh.glb"


def rig_arrays(npz: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Base mesh, AU morph targets, triangles and normals of a release.

    Parameters
    ----------
    npz : mapping
        Release arrays with the card's ``coef`` (23, 1434), ``intercept`` (1434,) and
        ``input_columns`` (AU rows are selected by name).

    Returns
    -------
    dict
        ``base`` (478, 3) float32 = ``intercept`` as a mesh; ``targets`` (20, 478, 3) float32,
        ``targets[k]`` = ``coef[AU_COLUMNS[k]]`` as a mesh; ``triangles`` (T, 3) uint16, fronts
        facing out of the face; ``normals`` (478, 3) float32 unit vertex normals of ``base``.
    """
    coef = np.asarray(npz["coef"], dtype=np.float32)
    columns = [str(c) for c in np.asarray(npz["input_columns"]).tolist()]
    if columns != list(INPUT_COLUMNS):
        raise ValueError(f"release 'input_columns' is {columns}, expected the card's {list(INPUT_COLUMNS)}")
    base = unflatten_axis_major(np.asarray(npz["intercept"], dtype=np.float32)).astype(np.float32)
    targets = np.stack([unflatten_axis_major(coef[columns.index(au)]) for au in AU_COLUMNS]).astype(np.float32)
    triangles = face.outward_triangles(base, face.triangulate(base))
    return {
        "base": base,
        "targets": targets,
        "triangles": triangles.astype(np.uint16),
        "normals": vertex_normals(base.astype(np.float64), triangles).astype(np.float32),
    }


def vertex_normals(mesh: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals; vertices in no triangle (the irises) get the face's forward direction."""
    n = np.cross(mesh[triangles[:, 1]] - mesh[triangles[:, 0]], mesh[triangles[:, 2]] - mesh[triangles[:, 0]])
    acc = np.zeros_like(mesh)
    for corner in range(3):
        np.add.at(acc, triangles[:, corner], n)
    length = np.linalg.norm(acc, axis=1)
    _, axes, _ = face.face_frame(mesh)
    acc[length == 0] = -axes[2]
    return acc / np.linalg.norm(acc, axis=1, keepdims=True)


def glb_bytes(
    npz: Mapping[str, Any], name: str = "aumesh AU-to-mesh", extras: Mapping[str, Any] | None = None
) -> bytes:
    """The rig as a binary glTF 2.0 (GLB) file's bytes; see the module docstring for the contents."""
    import pygltflib as g

    rig = rig_arrays(npz)
    blobs: list[bytes] = []
    views: list[g.BufferView] = []
    accessors: list[g.Accessor] = []
    offset = 0

    def add(array: np.ndarray, component: int, kind: str, target: int, with_bounds: bool) -> int:
        nonlocal offset
        data = np.ascontiguousarray(array).tobytes()
        views.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
        pad = (-len(data)) % 4
        blobs.append(data + b"\0" * pad)
        offset += len(data) + pad
        bounds = {"min": array.min(axis=0).tolist(), "max": array.max(axis=0).tolist()} if with_bounds else {}
        accessors.append(
            g.Accessor(bufferView=len(views) - 1, componentType=component, count=len(array), type=kind, **bounds)
        )
        return len(accessors) - 1

    position = add(rig["base"], g.FLOAT, g.VEC3, g.ARRAY_BUFFER, True)
    normal = add(rig["normals"], g.FLOAT, g.VEC3, g.ARRAY_BUFFER, False)
    targets = [{"POSITION": add(t, g.FLOAT, g.VEC3, g.ARRAY_BUFFER, True)} for t in rig["targets"]]
    indices = add(rig["triangles"].reshape(-1), g.UNSIGNED_SHORT, g.SCALAR, g.ELEMENT_ARRAY_BUFFER, False)
    binary = b"".join(blobs)
    primitive = g.Primitive(
        attributes=g.Attributes(POSITION=position, NORMAL=normal),
        indices=indices,
        targets=targets,
        material=0,
        mode=g.TRIANGLES,
    )
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator=f"aumesh (pygltflib {g.__version__})", extras=dict(extras or {})),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=[g.Node(mesh=0, name=name)],
        meshes=[
            g.Mesh(
                name=name,
                primitives=[primitive],
                weights=[0.0] * len(AU_COLUMNS),
                extras={"targetNames": list(AU_COLUMNS)},
            )
        ],
        materials=[
            g.Material(
                name="skin",
                pbrMetallicRoughness=g.PbrMetallicRoughness(
                    baseColorFactor=[0.85, 0.68, 0.58, 1.0], metallicFactor=0.0, roughnessFactor=0.7
                ),
            )
        ],
        accessors=accessors,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=len(binary))],
    )
    gltf.set_binary_blob(binary)
    return b"".join(gltf.save_to_bytes())


def write_glb(npz: Mapping[str, Any], path: str | Path, source: str | None = None) -> Path:
    """Write the rig of release arrays ``npz`` to ``path`` atomically; ``source`` (the NPZ's name) goes in ``asset.extras``."""
    from aumesh.utils.io import atomic_path

    extras = {
        "inputs": "morph target weights = AU intensities (AU01..AU43); pose = 0",
        "units_and_frame": "the release NPZ's (see its model card)",
        "source": source,
    }
    with atomic_path(path, suffix=".glb") as tmp:
        tmp.write_bytes(glb_bytes(npz, extras=extras))
    return Path(path)


__all__ = ["GLB_NAME", "glb_bytes", "rig_arrays", "write_glb"]
