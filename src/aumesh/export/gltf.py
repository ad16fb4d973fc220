"""The release as a glTF 2.0 blendshape rig (``au_to_mesh.glb``), written with pygltflib.

The model is linear, so at pose 0 it *is* a blendshape rig (card, "Inference":
``flat = x @ coef + intercept``): the base mesh is the prediction at AU = 0, pose = 0
(``intercept``), and morph target ``k`` is AU ``k``'s displacement field at one unit of
intensity (row ``k`` of ``coef``). With weights ``w`` (the AU intensities) a glTF viewer
shows ``base + sum_k w_k * target_k``, exactly the model's mesh at pose 0 (up to float32,
the NPZ's own precision). Target names (``AU01`` ... ``AU43``) are in the mesh's
``extras.targetNames``, the convention three.js, Blender and Babylon.js read.

A family release (issue 46; :mod:`aumesh.model.family_inference`) is rigged the same way: its rig
(``<family>_to_mesh.glb``) has one morph target per input, ``coef``'s row of that input, named by the family's own names
in its order: MediaPipe's 52 ARKit-style blendshape names (``_neutral`` kept as MediaPipe names it: no ARKit shape has
that name, so an ARKit-named avatar, which maps targets by name, leaves it out; :data:`NEUTRAL_NOTE`) or py-feat's
7 emotions; ``asset.extras`` says the family and the support of its inputs.

Coordinates are the NPZ's, unchanged (the release's frame and units); triangles are the
project's triangulation of the base mesh, wound so their fronts face out of the face (toward
the nose tip); normals are the base mesh's area-weighted vertex normals.

The identification screen (issue 43; :mod:`aumesh.export.identification`), when the release records it, is in
``asset.extras["au_identification"]`` (``{"flag_below", "aus": {AU: {"sigma_star" (null: beyond the screen's grid),
"flagged", "partner", "group"}}, "flagged", "groups", "note"}``) and the flagged morph targets are
named in the mesh's ``extras.unidentifiedTargets``: a rig user should drive a flagged target only with its partner,
by the same weight (the group's field).

With an :class:`Animation` (``aumesh animate``, :mod:`aumesh.export.gltf_clip`) the file also
holds one glTF animation: a LINEAR sampler on the mesh node's morph ``weights`` (``n * 20``
floats, a keyframe per frame) and optionally a LINEAR ``rotation`` sampler (quaternions) on a
parent node that turns the face about a pivot (the mesh node is moved by ``-pivot``, its parent
by ``+pivot``: at the identity rotation the vertices are the NPZ's).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS, unflatten_axis_major
from aumesh.export.identification import release_identification
from aumesh.geometry import face

GLB_NAME = "au_to_mesh.glb"


def target_names(npz: Mapping[str, Any]) -> list[str]:
    """The rig's morph-target names: ``AU01 .. AU43`` for an AU release, the family's own names for a family release
    (issue 46: MediaPipe's 52 ARKit-style blendshape names in ``MP_BLENDSHAPE_NAMES`` order, ``_neutral`` first and
    kept as it is named; py-feat's 7 ``FEAT_EMOTION_COLUMNS``)."""
    from aumesh.model.family_inference import release_family

    if release_family(npz) == "au":
        return list(AU_COLUMNS)
    return [str(c) for c in np.asarray(npz["feature_columns"]).tolist()]


def glb_name(npz: Mapping[str, Any]) -> str:
    """The rig's file name: :data:`GLB_NAME` for an AU release, ``<family>_to_mesh.glb`` for a family release
    (contract item 3: ``blendshapes_to_mesh.glb``, ``emotions_to_mesh.glb``)."""
    from aumesh.model.family_inference import release_family

    family = release_family(npz)
    return GLB_NAME if family == "au" else f"{family}_to_mesh.glb"


def rig_arrays(npz: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Base mesh, morph targets, triangles and normals of a release.

    Parameters
    ----------
    npz : mapping
        Release arrays: an AU release (the card's ``coef`` (23, 1434), ``intercept`` (1434,) and ``input_columns``;
        AU rows are selected by name) or a family release (contract item 3: ``coef`` (p, 1434) with rows
        ``input_columns``, the family's ``feature_columns`` first).

    Returns
    -------
    dict
        ``base`` (478, 3) float32 = ``intercept`` as a mesh; ``targets`` (k, 478, 3) float32, ``targets[j]`` =
        the ``coef`` row of input ``target_names(npz)[j]`` as a mesh (k = 20 AUs, 52 blendshapes or 7 emotions);
        ``names`` (k,) those names; ``triangles`` (T, 3) uint16, fronts facing out of the face; ``normals``
        (478, 3) float32 unit vertex normals of ``base``.
    """
    names = target_names(npz)
    coef = np.asarray(npz["coef"], dtype=np.float32)
    columns = [str(c) for c in np.asarray(npz["input_columns"]).tolist()]
    if names == list(AU_COLUMNS) and columns != list(INPUT_COLUMNS):
        raise ValueError(f"release 'input_columns' is {columns}, expected the card's {list(INPUT_COLUMNS)}")
    if columns[: len(names)] != names and names != list(AU_COLUMNS):
        raise ValueError(f"release 'input_columns' must start with its feature_columns {names[:3]} ...")
    base = unflatten_axis_major(np.asarray(npz["intercept"], dtype=np.float32)).astype(np.float32)
    targets = np.stack([unflatten_axis_major(coef[columns.index(n)]) for n in names]).astype(np.float32)
    triangles = face.outward_triangles(base, face.triangulate(base))
    return {
        "base": base,
        "targets": targets,
        "names": np.array(names),
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


@dataclass(frozen=True)
class Animation:
    """Keyframes of the rig over time (LINEAR interpolation between them).

    Attributes
    ----------
    times : (n,) seconds, strictly increasing (written as float32).
    weights : (n, k) morph-target weights in the rig's target order (:func:`target_names`: k = 20 AU intensities in
        :data:`~aumesh.core.schema.AU_COLUMNS` order, or a family's k inputs in its order).
    rotations : (n, 4) unit quaternions ``x, y, z, w`` (glTF's order, SciPy's ``as_quat()``) or None (no rotation).
    pivot : (3,) the point the rotation turns about (NPZ coordinates); needed with ``rotations``.
    name : the animation's name.
    """

    times: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray | None = None
    pivot: np.ndarray | None = None
    name: str = "clip"


def glb_bytes(
    npz: Mapping[str, Any],
    name: str = "aumesh AU-to-mesh",
    extras: Mapping[str, Any] | None = None,
    animation: Animation | None = None,
) -> bytes:
    """The rig as a binary glTF 2.0 (GLB) file's bytes, with ``animation`` when given; see the module docstring.
    ``extras`` go in ``asset.extras``, with ``au_identification`` added when the release records the screen
    (:meth:`aumesh.export.identification.AuIdentification.to_json`)."""
    import pygltflib as g

    rig = rig_arrays(npz)
    names = [str(n) for n in rig["names"].tolist()]
    blobs: list[bytes] = []
    views: list[g.BufferView] = []
    accessors: list[g.Accessor] = []
    offset = 0

    def add(array: np.ndarray, component: int, kind: str, target: int | None, with_bounds: bool) -> int:
        nonlocal offset
        data = np.ascontiguousarray(array).tobytes()
        views.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
        pad = (-len(data)) % 4
        blobs.append(data + b"\0" * pad)
        offset += len(data) + pad
        bounds = (
            {"min": np.atleast_1d(array.min(axis=0)).tolist(), "max": np.atleast_1d(array.max(axis=0)).tolist()}
            if with_bounds
            else {}
        )
        accessors.append(
            g.Accessor(bufferView=len(views) - 1, componentType=component, count=len(array), type=kind, **bounds)
        )
        return len(accessors) - 1

    position = add(rig["base"], g.FLOAT, g.VEC3, g.ARRAY_BUFFER, True)
    normal = add(rig["normals"], g.FLOAT, g.VEC3, g.ARRAY_BUFFER, False)
    targets = [{"POSITION": add(t, g.FLOAT, g.VEC3, g.ARRAY_BUFFER, True)} for t in rig["targets"]]
    indices = add(rig["triangles"].reshape(-1), g.UNSIGNED_SHORT, g.SCALAR, g.ELEMENT_ARRAY_BUFFER, False)
    nodes, roots, animations = [g.Node(mesh=0, name=name)], [0], []
    if animation is not None:
        # animation data: no bufferView target (the spec reserves targets for vertex and index data)
        times = np.asarray(animation.times, np.float32)
        weights = np.asarray(animation.weights, np.float32)
        if times.ndim != 1 or weights.shape != (len(times), len(names)) or not len(times):
            raise ValueError(
                f"animation: times {times.shape} and weights {weights.shape}: need (n,) and (n, {len(names)})"
            )
        if (np.diff(times) <= 0).any():
            raise ValueError("animation: times (as float32) must be strictly increasing")
        time_acc = add(times, g.FLOAT, g.SCALAR, None, True)
        samplers = [g.AnimationSampler(input=time_acc, output=add(weights.reshape(-1), g.FLOAT, g.SCALAR, None, False))]
        channels = [g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=0, path="weights"))]
        if animation.rotations is not None:
            pivot = np.asarray(animation.pivot, np.float64).reshape(3).tolist()
            rotations = np.asarray(animation.rotations, np.float32).reshape(len(times), 4)
            nodes = [
                g.Node(mesh=0, name=name, translation=[-v for v in pivot]),
                g.Node(name="head", children=[0], translation=pivot),
            ]
            roots = [1]
            samplers.append(g.AnimationSampler(input=time_acc, output=add(rotations, g.FLOAT, g.VEC4, None, False)))
            channels.append(g.AnimationChannel(sampler=1, target=g.AnimationChannelTarget(node=1, path="rotation")))
        animations = [g.Animation(name=animation.name, samplers=samplers, channels=channels)]
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
        scenes=[g.Scene(nodes=roots)],
        nodes=nodes,
        animations=animations,
        meshes=[
            g.Mesh(
                name=name,
                primitives=[primitive],
                weights=[0.0] * len(names),
                extras={"targetNames": names},
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
    data = b"".join(gltf.save_to_bytes())
    identification = release_identification(npz)
    if identification is None:
        return data
    flagged = list(identification.flagged)

    def add_identification(doc: dict[str, Any]) -> None:
        doc["asset"].setdefault("extras", {})["au_identification"] = identification.to_json()
        doc["meshes"][0].setdefault("extras", {})["unidentifiedTargets"] = flagged

    return edit_glb_json(data, add_identification)


def edit_glb_json(data: bytes, edit: Callable[[dict[str, Any]], None]) -> bytes:
    """A GLB's bytes with its JSON chunk changed in place by ``edit`` (the BIN chunk byte for byte as it was).

    pygltflib drops every ``None``, empty list and empty dict from the JSON it writes, extras included; the
    identification's ``sigma_star`` is null for a field that did not turn within the screen's grid and its lists may be
    empty, so they are written here, by the GLB 2.0 container's layout (a 12-byte header; a JSON chunk padded with spaces
    to 4 bytes, so the BIN chunk that follows stays aligned), in strict JSON (no NaN).
    """
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    json_length, kind = struct.unpack_from("<I4s", data, 12)
    if (magic, version, length, kind) != (b"glTF", 2, len(data), b"JSON"):
        raise ValueError("edit_glb_json: not a GLB 2.0 file with its JSON chunk first")
    doc = json.loads(data[20 : 20 + json_length])
    edit(doc)
    text = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")
    text += b" " * (-len(text) % 4)
    rest = data[20 + json_length :]  # the BIN chunk, header and all
    return (
        struct.pack("<4sII", b"glTF", 2, 20 + len(text) + len(rest))
        + struct.pack("<I4s", len(text), b"JSON")
        + text
        + rest
    )


def support_extras(npz: Mapping[str, Any]) -> dict[str, Any]:
    """What the rig's ``asset.extras`` says of its training data's support, when the release records it
    (:func:`aumesh.model.support.release_support`): ``training_range`` ({AU: {"max", "p99"}}: morph weights above
    ``max`` are beyond the data), ``unsupported_targets`` (AUs the data never expressed) and ``detector``; ``{}`` for
    a release that records none. For a family release the same, of its inputs (its ``feature_p99`` and
    ``unsupported_features``)."""
    from aumesh.model import support

    found = support.release_support(npz)
    if found is None:
        return {}
    names = target_names(npz)
    ranges = {
        a: {found.bound: found.upper[a]}
        | ({"p99": found.p99[a]} if found.bound == "max" and np.isfinite(found.p99.get(a, np.nan)) else {})
        for a in names
        if a in found.upper and np.isfinite(found.upper[a])
    }
    return {
        "training_range": ranges,
        "unsupported_targets": [a for a in names if a in found.unsupported],
        "detector": found.detector,
    }


def write_glb(npz: Mapping[str, Any], path: str | Path, source: str | None = None) -> Path:
    """Write the rig of release arrays ``npz`` to ``path`` atomically; ``source`` (the NPZ's name) goes in ``asset.extras``."""
    from aumesh.core.io import atomic_path

    extras = {
        "inputs": inputs_note(npz) + "; pose = 0",
        "units_and_frame": "the release NPZ's (see its model card)",
        "source": source,
        **family_extras(npz),
        **support_extras(npz),
    }
    with atomic_path(path, suffix=".glb") as tmp:
        tmp.write_bytes(glb_bytes(npz, name=rig_name(npz), extras=extras))
    return Path(path)


#: What a family rig's weights are, by family (``asset.extras["inputs"]``).
_FAMILY_INPUTS = {
    "blendshapes": "MediaPipe's 52 blendshape scores (0..1; py-feat's MP_BLENDSHAPE_NAMES, ARKit-style names)",
    "emotions": "py-feat's 7 emotion probabilities (0..1; FEAT_EMOTION_COLUMNS: anger .. neutral)",
}
#: MediaPipe's ``_neutral`` has no ARKit blendshape of its name (ARKit's 52 are MediaPipe's other 51 and
#: ``tongueOut``); the rig keeps it, named as MediaPipe and py-feat name it, so its targets are exactly the model's
#: inputs in their order (weight j = the table's column j) and an ARKit-named avatar, which maps targets by name,
#: finds no target of that name and leaves it out (docs/families.md, "Rig, viewer, animation").
NEUTRAL_NOTE = (
    "'_neutral' (MediaPipe's neutral-face score) is kept as MediaPipe names it: no ARKit blendshape has that name, so "
    "an ARKit-named avatar leaves it out; the other 51 targets carry ARKit's names"
)


def inputs_note(npz: Mapping[str, Any]) -> str:
    """What the rig's morph weights are, in words."""
    from aumesh.model.family_inference import release_family

    family = release_family(npz)
    if family == "au":
        return "morph target weights = AU intensities (AU01..AU43)"
    return f"morph target weights = {_FAMILY_INPUTS[family]}"


def rig_name(npz: Mapping[str, Any]) -> str:
    """The rig's mesh and node name: ``aumesh AU-to-mesh`` or ``aumesh <family>-to-mesh``."""
    from aumesh.model.family_inference import release_family

    family = release_family(npz)
    return "aumesh AU-to-mesh" if family == "au" else f"aumesh {family}-to-mesh"


def family_extras(npz: Mapping[str, Any]) -> dict[str, Any]:
    """A family rig's ``asset.extras``: ``family`` and, for the blendshapes, ``neutral_target`` (:data:`NEUTRAL_NOTE`);
    ``{}`` for an AU release."""
    from aumesh.model.family_inference import release_family

    family = release_family(npz)
    if family == "au":
        return {}
    return {"family": family} | ({"neutral_target": NEUTRAL_NOTE} if family == "blendshapes" else {})


__all__ = [
    "GLB_NAME",
    "Animation",
    "edit_glb_json",
    "family_extras",
    "glb_bytes",
    "glb_name",
    "inputs_note",
    "rig_arrays",
    "rig_name",
    "target_names",
    "write_glb",
]
