"""Synthetic frame tables shaped as py-feat 2.1.5 writes them, for tests and benchmarks of the ingest of real output.

The faces are :mod:`aumesh.synthetic.tables`'s: the same videos (counts, identity and latent bases, seeds), so the clean
frames equal those of ``write_tables(spec)`` with layout ``columns``. Around them, what a real ``detect(..., save=)``
export holds:

* py-feat's column set and order, for ``MPDetector`` (``detector="mp"``: 478-vertex mesh interleaved
  ``x_0, y_0, z_0, ...``, 52 blendshapes, lower-case emotions, ``Identity_*`` all NaN) or ``Detectorv2``
  (``detector="v2"``: a 68-point block ``x_0..x_67, y_0..y_67``, the mesh axis-major ``mesh_x_*, mesh_y_*,
  mesh_z_*``, capitalised emotions, valence/arousal, identity embeddings);
* ``FaceRectX/Y/Width/Height``: the crop box the detector cut the face from, in frame pixels, around a detector box
  (the face's 2-D extent padded 8 %): Detectorv2's square of side 1.2 x the box's longer side, centred
  (``extract_face_square_pad_torch``, EXPAND_BBOX in feat/multitask/inference.py; ``_crop_affine_to_box``), and
  MPDetector's box expanded 1.25x about its centre, corners rounded to whole pixels (``extract_face_from_bbox_torch``
  called by ``MPDetector.detect_faces`` with ``face_size=256, expand_bbox=1.25``);
* the mesh's x, y in frame pixels and its z in the detector's crop units, as py-feat writes them: Detectorv2's z in
  0-1 of its chip (``z_px / FaceRectWidth``: ``Detectorv2._mesh_to_original_frame`` returns z unchanged), MPDetector's
  in pixels of its 256-px crop (``z_px * 256 / FaceRectWidth``: ``MPDetector.forward`` "leave[s] Z in original
  scale"); optionally z in frame pixels instead (``z_pixels``: the independent route of the ingest's conversion);
* frames without a face (occlusion, in runs), kept as one row whose measurements are NaN (``FaceScore`` and
  ``FaceRect*`` 0 for "mp", NaN for "v2");
* a second, smaller face in the background in some runs of frames (``Identity`` "Person_1"), before or after the
  main face's row, as the detector found them;
* ``input`` (the video path), ``frame``, ``approx_time`` ("MM:SS" at 25 fps), ``FrameHeight``/``FrameWidth``;
* optionally runs of frames with the head turned toward profile (``profile_rate``: :class:`synth.SynthSpec`'s
  ``profile_rate``, the mesh generated at that pose);
* optionally MediaPipe's normalized image units (x / width, y / height, z / width) and no frame-size columns.

Only column names are taken from py-feat; nothing of its code or data. Files are written one at a time, in chunks of
videos, so ~100k frames in one CSV stay in bounded memory.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from aumesh.core.io import atomic_path
from aumesh.core.schema import ANCHOR_INDICES, AU_COLUMNS, N_VERTICES, POSE_COLUMNS, flatten_axis_major
from aumesh.synthetic import tables as synth

FRAME_WIDTH = 640.0
FRAME_HEIGHT = 480.0
FPS = 25
DETECTORS = ("mp", "v2")
FORMATS = ("csv", "parquet", "split")

FACE_RECT_COLUMNS = ("FaceRectX", "FaceRectY", "FaceRectWidth", "FaceRectHeight")
FEX_POSE_COLUMNS = ("Pitch", "Roll", "Yaw")  # py-feat's Fex order (the model's is Pitch, Yaw, Roll)
HEAD_POSITION_COLUMNS = ("X", "Y", "Z")
BLENDSHAPE_COLUMNS: tuple[str, ...] = (
    "_neutral",
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "eyeLookDownLeft",
    "eyeLookDownRight",
    "eyeLookInLeft",
    "eyeLookInRight",
    "eyeLookOutLeft",
    "eyeLookOutRight",
    "eyeLookUpLeft",
    "eyeLookUpRight",
    "eyeSquintLeft",
    "eyeSquintRight",
    "eyeWideLeft",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawOpen",
    "jawRight",
    "mouthClose",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthFunnel",
    "mouthLeft",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthPucker",
    "mouthRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "noseSneerLeft",
    "noseSneerRight",
)
EMOTION_COLUMNS_MP = ("anger", "disgust", "fear", "happiness", "sadness", "surprise", "neutral")
EMOTION_COLUMNS_V2 = ("Neutral", "Happy", "Sad", "Surprise", "Fear", "Disgust", "Anger")
IDENTITY_COLUMNS = tuple(f"Identity_{i}" for i in range(1, 513))
GAZE_COLUMNS = ("gaze_pitch", "gaze_yaw", "gaze_angle")
FRAME_SIZE_COLUMNS = ("FrameHeight", "FrameWidth")
TRAILING_COLUMNS = ("input", "frame", "approx_time", "Identity")
# v2's 68-point block: a fixed subset of the mesh's vertices (any fixed subset serves the ingest tests).
LANDMARK68_VERTICES: tuple[int, ...] = tuple(int(i) for i in np.round(np.linspace(0, N_VERTICES - 1, 68)))

#: The detectors' crops (docs/conventions.md "py-feat's mesh units"): Detectorv2's square side over the detector
#: box's longer side (EXPAND_BBOX, feat/multitask/inference.py), MPDetector's expansion and crop size
#: (``MPDetector.detect_faces``).
V2_EXPAND = 1.2
MP_EXPAND = 1.25
MP_CROP = 256.0
_DETECTOR_PAD = 0.08  # the detector box: the face's 2-D extent padded 8 % each side

_CHUNK_ROWS = 4096  # rows per DataFrame written (whole videos; a longer video is one chunk)
_NO_FACE_RUN = (1, 10)  # occlusions: 1-10 consecutive frames
_EXTRA_FACE_RUN = (5, 40)  # a person in the background for a while


def mesh_columns(detector: str) -> list[str]:
    """The 478-vertex mesh's columns as the detector writes them (mp interleaved, v2 axis-major ``mesh_*``)."""
    if detector == "mp":
        return [f"{a}_{i}" for i in range(N_VERTICES) for a in "xyz"]
    return [f"mesh_{a}_{i}" for a in "xyz" for i in range(N_VERTICES)]


def landmark68_columns() -> list[str]:
    """v2's 68-point block ``x_0..x_67, y_0..y_67``."""
    return [f"{a}_{i}" for a in "xy" for i in range(68)]


def pyfeat_columns(detector: str = "mp", frame_size: bool = True, mesh: bool = True) -> list[str]:
    """Columns of a py-feat 2.1.5 table in order (``mesh=False``: without the 478-vertex mesh, the split layout)."""
    _check_detector(detector)
    size = list(FRAME_SIZE_COLUMNS) if frame_size else []
    head = list(FACE_RECT_COLUMNS) + ["FaceScore"]
    pose = list(FEX_POSE_COLUMNS) + list(HEAD_POSITION_COLUMNS)
    mesh_cols = mesh_columns(detector) if mesh else []
    if detector == "mp":
        cols = (
            head
            + mesh_cols
            + pose
            + list(BLENDSHAPE_COLUMNS)
            + list(AU_COLUMNS)
            + list(EMOTION_COLUMNS_MP)
            + list(IDENTITY_COLUMNS)
            + list(GAZE_COLUMNS)
        )
    else:
        cols = (
            head
            + landmark68_columns()
            + pose
            + list(AU_COLUMNS)
            + list(EMOTION_COLUMNS_V2)
            + ["valence", "arousal"]
            + list(GAZE_COLUMNS)
            + list(IDENTITY_COLUMNS)
            + mesh_cols
            + list(BLENDSHAPE_COLUMNS)
        )
    return cols + size + list(TRAILING_COLUMNS)


def clean_columns() -> list[str]:
    """The hand-cleaned table's columns (synth's ``columns`` layout): video_id, frame, AUs, Pitch, Roll, Yaw, mesh."""
    return (
        ["video_id", "frame"]
        + list(AU_COLUMNS)
        + list(FEX_POSE_COLUMNS)
        + [f"{a}_{i}" for i in range(N_VERTICES) for a in "xyz"]
    )


def _check_detector(detector: str) -> None:
    if detector not in DETECTORS:
        raise ValueError(f"detector={detector!r}: use 'mp' (MPDetector) or 'v2' (Detectorv2)")


def _synth_setup(spec: synth.SynthSpec) -> tuple[np.ndarray, tuple]:
    """Frame counts and the ``generate_video`` arguments exactly as :func:`synth.write_tables` makes them."""
    from aumesh.geometry import face

    counts = synth._frames_per_video(spec, np.random.default_rng(spec.seed))
    coef, intercept, _ = synth.true_coefficients(spec)
    template = face.canonical_template()
    identity_basis = flatten_axis_major(synth._smooth_fields(template, 10, np.random.default_rng(20_000 + spec.seed)))
    latent_basis = flatten_axis_major(synth._smooth_fields(template, 6, np.random.default_rng(30_000 + spec.seed)))
    latent_basis[
        :, np.r_[ANCHOR_INDICES, np.add(ANCHOR_INDICES, N_VERTICES), np.add(ANCHOR_INDICES, 2 * N_VERTICES)]
    ] = 0.0
    resemblance = synth.identity_resemblance(coef, identity_basis)
    return counts, (coef, intercept, identity_basis, latent_basis, resemblance)


def _runs(rng: np.random.Generator, n: int, target: int, run: tuple[int, int], allowed: np.ndarray) -> np.ndarray:
    """A mask of about ``target`` frames among ``allowed``, in runs of ``run`` consecutive frames."""
    mask = np.zeros(n, dtype=bool)
    target = min(target, int(allowed.sum()))
    for _ in range(100 * (target + 1)):
        have = int((mask & allowed).sum())
        if have >= target:
            break
        length = min(int(rng.integers(run[0], run[1] + 1)), n, max(target - have, 1))
        start = int(rng.integers(0, n - length + 1))
        mask[start : start + length] = True
    return mask & allowed


def _plan(rng: np.random.Generator, n: int, no_face_rate: float, extra_face_rate: float):
    """Which frames lose the face, which have a background face and whether it comes first."""
    every = np.ones(n, dtype=bool)
    no_face = _runs(rng, n, int(np.floor(no_face_rate * n + rng.random())), _NO_FACE_RUN, every)
    face = ~no_face
    extra = _runs(rng, n, int(np.floor(extra_face_rate * face.sum() + rng.random())), _EXTRA_FACE_RUN, face)
    extra_first = extra & (rng.random(n) < 0.5)
    return no_face, extra, extra_first


def _blendshapes(rng: np.random.Generator, au: np.ndarray) -> np.ndarray:
    """52 blendshape scores in [0, 1], loosely following the AUs."""
    m = len(au)
    out = rng.beta(0.5, 6.0, size=(m, len(BLENDSHAPE_COLUMNS)))
    idx = {name: k for k, name in enumerate(BLENDSHAPE_COLUMNS)}
    follow = {
        "browInnerUp": "AU01",
        "browOuterUpLeft": "AU02",
        "browOuterUpRight": "AU02",
        "browDownLeft": "AU04",
        "browDownRight": "AU04",
        "eyeWideLeft": "AU05",
        "eyeWideRight": "AU05",
        "cheekSquintLeft": "AU06",
        "cheekSquintRight": "AU06",
        "eyeSquintLeft": "AU07",
        "eyeSquintRight": "AU07",
        "noseSneerLeft": "AU09",
        "noseSneerRight": "AU09",
        "mouthUpperUpLeft": "AU10",
        "mouthUpperUpRight": "AU10",
        "mouthSmileLeft": "AU12",
        "mouthSmileRight": "AU12",
        "mouthDimpleLeft": "AU14",
        "mouthDimpleRight": "AU14",
        "mouthFrownLeft": "AU15",
        "mouthFrownRight": "AU15",
        "mouthShrugLower": "AU17",
        "mouthStretchLeft": "AU20",
        "mouthStretchRight": "AU20",
        "mouthPressLeft": "AU24",
        "mouthPressRight": "AU24",
        "jawOpen": "AU26",
        "mouthRollLower": "AU28",
        "eyeBlinkLeft": "AU43",
        "eyeBlinkRight": "AU43",
    }
    for bs, a in follow.items():
        out[:, idx[bs]] = np.clip(0.8 * au[:, AU_COLUMNS.index(a)] + 0.2 * out[:, idx[bs]], 0.0, 1.0)
    out[:, idx["_neutral"]] = np.clip(1.0 - out[:, 1:].max(axis=1), 0.0, 1.0)
    return out


def _emotions(rng: np.random.Generator, au: np.ndarray) -> np.ndarray:
    """Seven probabilities summing to 1 in EMOTION_COLUMNS_MP order (anger .. neutral)."""
    a = {name: au[:, AU_COLUMNS.index(name)] for name in AU_COLUMNS}
    logits = rng.normal(0.0, 0.5, size=(len(au), 7))
    logits[:, 0] += 3 * a["AU04"] * a["AU07"]
    logits[:, 1] += 3 * a["AU09"]
    logits[:, 2] += 2 * a["AU01"] * a["AU20"]
    logits[:, 3] += 4 * a["AU12"]
    logits[:, 4] += 3 * a["AU15"]
    logits[:, 5] += 3 * a["AU05"] * a["AU26"]
    logits[:, 6] += 1.5
    p = np.exp(logits - logits.max(axis=1, keepdims=True))
    return p / p.sum(axis=1, keepdims=True)


def crop_box(mesh: np.ndarray, detector: str) -> np.ndarray:
    """(m, 4) FaceRectX, Y, Width, Height the detector writes for faces ``mesh`` (m, 478, 3) in pixels: its crop box.

    The detector box is the face's 2-D extent padded :data:`_DETECTOR_PAD`; "v2": the centred square of side
    :data:`V2_EXPAND` x its longer side; "mp": the box scaled :data:`MP_EXPAND` about its centre, corners rounded.
    """
    lo, hi = mesh[:, :, :2].min(axis=1), mesh[:, :, :2].max(axis=1)
    pad = _DETECTOR_PAD * (hi - lo)
    lo, hi = lo - pad, hi + pad
    centre, size = (lo + hi) / 2, hi - lo
    if detector == "v2":
        side = V2_EXPAND * size.max(axis=1, keepdims=True)
        return np.column_stack([centre - side / 2, side, side])
    corner_lo, corner_hi = np.round(centre - MP_EXPAND * size / 2), np.round(centre + MP_EXPAND * size / 2)
    return np.column_stack([corner_lo, corner_hi - corner_lo])


def z_to_crop(z: np.ndarray, width: np.ndarray, detector: str) -> np.ndarray:
    """z in frame pixels (m, k) -> the detector's crop units, with FaceRectWidth ``width`` (m,): "v2" z / width,
    "mp" z * 256 / width (NaN where the width is not positive: py-feat's no-face rows)."""
    w = np.where(width > 0, width, np.nan)[:, None]
    return z / w if detector == "v2" else z * MP_CROP / w


def _faces(
    rng: np.random.Generator,
    mesh: np.ndarray,
    au: np.ndarray,
    pose_fex: np.ndarray,
    score: tuple[float, float],
    identity: np.ndarray | None,
    detector: str,
) -> dict[str, np.ndarray]:
    """Every measurement of ``m`` detected faces (meshes in pixels): 2-D blocks keyed by group."""
    m = len(mesh)
    rect = crop_box(mesh, detector)  # X, Y, Width, Height
    iod_px = np.linalg.norm(mesh[:, 33, :2] - mesh[:, 263, :2], axis=1)
    cm_per_px = 9.0 / np.maximum(iod_px, 1e-6)  # outer eye corners ~9 cm apart
    centre = mesh.mean(axis=1)
    position = np.column_stack(
        [
            (centre[:, 0] - FRAME_WIDTH / 2) * cm_per_px,
            (centre[:, 1] - FRAME_HEIGHT / 2) * cm_per_px,
            -FRAME_WIDTH * cm_per_px,
        ]
    )
    gaze = rng.normal(0.0, 0.12, size=(m, 2))
    emotions = _emotions(rng, au)
    out = {
        "rect": rect,
        "score": rng.uniform(*score, size=(m, 1)),
        "pose": np.column_stack([pose_fex, position]),
        "au": np.clip(au, 0.0, 1.0),
        "blend": _blendshapes(rng, au),
        "emotion": emotions,
        "gaze": np.column_stack([gaze, np.hypot(gaze[:, 0], gaze[:, 1])]),
        "affect": np.column_stack(
            [
                emotions[:, 3] - emotions[:, [0, 1, 2, 4]].sum(1),
                np.clip(0.3 + emotions[:, [0, 2, 5]].sum(1) + rng.normal(0, 0.05, m), -1, 1),
            ]
        ),
        "mesh": mesh,
    }
    if identity is not None:
        emb = identity[None, :] + rng.normal(0.0, 0.02, size=(m, len(identity)))
        out["identity"] = (emb / np.linalg.norm(emb, axis=1, keepdims=True)).astype(np.float32)
    return out


def _video_rows(
    spec: synth.SynthSpec,
    video: int,
    n: int,
    gen_args: tuple,
    detector: str,
    no_face_rate: float,
    extra_face_rate: float,
    seed: int,
) -> dict:
    """One video's rows: synth's frames, no-face rows, background faces; plus the clean frames."""
    g = synth.generate_video(spec, video, n, *gen_args)
    plan_rng = np.random.default_rng([seed, spec.seed, video, 1])
    rng = np.random.default_rng([seed, spec.seed, video, 2])
    no_face, extra, extra_first = _plan(plan_rng, n, no_face_rate, extra_face_rate)

    order = [POSE_COLUMNS.index(p) for p in FEX_POSE_COLUMNS]
    v2 = detector == "v2"
    main = _faces(
        rng,
        g["mesh"],
        g["au"],
        g["pose"][:, order],
        (0.9, 1.0),
        _unit(rng.standard_normal(512)) if v2 else None,
        detector,
    )
    # the background person: the main mesh scaled 0.4 about its centre, ~150 px to the side with more room
    ef = np.flatnonzero(extra)
    centre = g["mesh"][ef].mean(axis=1, keepdims=True)
    side = -np.sign(g["mesh"][:, :, 0].mean() - FRAME_WIDTH / 2) or 1.0
    offset = np.array([side * rng.uniform(130, 170), rng.normal(0, 20), 0.0])
    small = centre + 0.4 * (g["mesh"][ef] - centre) + offset + rng.normal(0, 0.3, size=(len(ef), N_VERTICES, 3))
    extra_au = synth._au_intensities(rng, len(ef), rng.uniform(0.3, 1.6, size=5 + len(AU_COLUMNS)))
    extra_pose = np.deg2rad(rng.normal(0, [10, 7, 18]) + rng.normal(0, 2, size=(len(ef), 3)))  # Fex order
    other = _faces(
        rng, small, extra_au, extra_pose, (0.6, 0.9), _unit(rng.standard_normal(512)) if v2 else None, detector
    )

    # rows: one per frame, two where a background face is; it comes first where extra_first
    per_frame = 1 + extra.astype(int)
    row_frame = np.repeat(np.arange(n), per_frame)
    first_row = np.cumsum(per_frame) - per_frame
    pos = np.arange(len(row_frame)) - first_row[row_frame]
    kind = np.where(extra_first[row_frame], 1 - pos, pos)  # 0 main face, 1 background face
    main_rows, extra_rows = kind == 0, kind == 1
    blocks = {}
    for key, values in main.items():
        block = np.empty(
            (len(row_frame),) + values.shape[1:], dtype=values.dtype if key in ("mesh", "identity") else np.float64
        )
        block[main_rows] = values
        block[extra_rows] = other[key]
        blocks[key] = block
    gone = main_rows & no_face[row_frame]
    for key, block in blocks.items():
        block[gone] = np.nan
        if key in ("rect", "score") and not v2:
            block[gone] = 0.0
    identity = np.where(extra_rows, "Person_1", "Person_0").astype(object)
    identity[gone] = np.nan
    vid = f"vid{video:06d}"
    seconds = row_frame // FPS
    keep = ~no_face
    return {
        "blocks": blocks,
        "frame": row_frame,
        "input": np.full(len(row_frame), f"videos/{vid}.mp4", dtype=object),
        "approx_time": np.array([f"{s // 60:02d}:{s % 60:02d}" for s in seconds], dtype=object),
        "Identity": identity,
        "clean": {
            "video_id": np.full(int(keep.sum()), vid, dtype=object),
            "frame": np.flatnonzero(keep),
            "au": g["au"][keep],
            "pose": g["pose"][keep][:, order],
            "mesh": g["mesh"][keep].astype(np.float32),
        },
        "n_frames": n,
        "n_no_face": int(no_face.sum()),
        "n_extra": int(extra.sum()),
    }


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


class _Frame:
    """py-feat's columns for some videos' rows, in order: ``blocks`` of numeric columns, each ``(names, 2-D values)``,
    then the trailing text and frame columns (``tail``). Rendered as the DataFrame py-feat saves (CSV) or straight
    as an Arrow table (parquet: ``pa.Table.from_pandas`` spent most of a parquet write walking ~2,000 columns)."""

    def __init__(self, blocks: list[tuple[list[str], np.ndarray]], tail: dict[str, np.ndarray]):
        self.blocks, self.tail = blocks, tail
        self.n_rows = len(tail["frame"])

    def to_pandas(self) -> pd.DataFrame:
        frames = [pd.DataFrame(values, columns=names) for names, values in self.blocks]
        return pd.concat([*frames, pd.DataFrame(self.tail)], axis=1)

    def key(self) -> tuple:
        """What the DataFrame's Arrow schema (pandas metadata included) depends on: the names, the numeric dtypes,
        and what pandas infers from the values of the text columns (all NaN in a chunk of no-face rows only)."""
        return (
            tuple((tuple(names), values.dtype.str) for names, values in self.blocks),
            tuple(
                (name, v.dtype.str, pd.api.types.infer_dtype(v, skipna=True) if v.dtype == object else None)
                for name, v in self.tail.items()
            ),
        )

    def to_arrow(self, schema: pa.Schema) -> pa.Table:
        """The table ``pa.Table.from_pandas(self.to_pandas(), schema=schema, preserve_index=False)`` gives (NaN as
        null, as ``from_pandas`` reads it), built column by column from the blocks."""
        arrays = []
        for names, values in self.blocks:
            columns = np.asfortranarray(values)  # each column contiguous: no copy per column
            for j, name in enumerate(names):
                arrays.append(pa.array(columns[:, j], type=schema.field(name).type, from_pandas=True))
        for name, v in self.tail.items():
            arrays.append(pa.array(v, type=schema.field(name).type, from_pandas=True))
        return pa.Table.from_arrays(arrays, schema=schema)


# _Frame.key() -> the Arrow schema of the first chunk with that key, for the life of the process
_SCHEMAS: dict[tuple, pa.Schema] = {}


def _frame_schema(frame: _Frame) -> pa.Schema:
    """The schema a parquet file of py-feat's DataFrame gets: pyarrow's inference, text columns as text even when a
    chunk is all NaN, and the pandas metadata ``from_pandas`` writes with it. Inferred once per ``_Frame.key()``."""
    key = frame.key()
    if key not in _SCHEMAS:
        df = frame.to_pandas()
        fields = [pa.field(c, pa.string()) if c in ("input", "approx_time", "Identity") else None for c in df.columns]
        inferred = pa.Schema.from_pandas(df, preserve_index=False)
        schema = pa.schema([f or inferred.field(i) for i, f in enumerate(fields)], metadata=inferred.metadata)
        _SCHEMAS[key] = pa.Table.from_pandas(df, schema=schema, preserve_index=False).schema
    return _SCHEMAS[key]


def _frame(
    parts: list[dict], detector: str, normalized: bool, frame_size: bool, with_mesh: bool, z_pixels: bool = False
) -> _Frame:
    """py-feat's columns for some videos' rows (``with_mesh=False``: without the 478-vertex mesh)."""

    def cat(key):
        return np.concatenate([p["blocks"][key] for p in parts])

    mesh = cat("mesh").astype(np.float64)
    if normalized:
        mesh = mesh / np.array([FRAME_WIDTH, FRAME_HEIGHT, FRAME_WIDTH])
    elif not z_pixels:  # z as the detector writes it: in its crop's units
        mesh[:, :, 2] = z_to_crop(mesh[:, :, 2], cat("rect")[:, 2], detector)
    mesh = mesh.astype(np.float32)
    r = len(mesh)
    blocks: list[tuple[list[str], np.ndarray]] = []

    def add(values, columns):
        blocks.append((list(columns), np.asarray(values).reshape(r, -1)))

    add(cat("rect"), FACE_RECT_COLUMNS)
    add(cat("score"), ["FaceScore"])
    nan_identity = np.full((r, len(IDENTITY_COLUMNS)), np.nan)
    if detector == "mp":
        if with_mesh:
            add(mesh.reshape(r, -1), mesh_columns("mp"))  # interleaved x_0, y_0, z_0, ...
        add(cat("pose"), FEX_POSE_COLUMNS + HEAD_POSITION_COLUMNS)
        add(cat("blend"), BLENDSHAPE_COLUMNS)
        add(cat("au"), AU_COLUMNS)
        add(cat("emotion"), EMOTION_COLUMNS_MP)
        add(nan_identity, IDENTITY_COLUMNS)  # no identity model run
        add(cat("gaze"), GAZE_COLUMNS)
    else:
        add(mesh[:, list(LANDMARK68_VERTICES), :2].transpose(0, 2, 1).reshape(r, -1), landmark68_columns())
        add(cat("pose"), FEX_POSE_COLUMNS + HEAD_POSITION_COLUMNS)
        add(cat("au"), AU_COLUMNS)
        mp_to_v2 = [
            EMOTION_COLUMNS_MP.index(e)
            for e in ("neutral", "happiness", "sadness", "surprise", "fear", "disgust", "anger")
        ]
        add(cat("emotion")[:, mp_to_v2], EMOTION_COLUMNS_V2)
        add(cat("affect"), ["valence", "arousal"])
        add(cat("gaze"), GAZE_COLUMNS)
        add(cat("identity"), IDENTITY_COLUMNS)
        if with_mesh:
            add(mesh.transpose(0, 2, 1).reshape(r, -1), mesh_columns("v2"))  # axis-major
        add(cat("blend"), BLENDSHAPE_COLUMNS)
    if frame_size:
        add(np.tile([FRAME_HEIGHT, FRAME_WIDTH], (r, 1)), FRAME_SIZE_COLUMNS)
    tail = {
        "input": np.concatenate([p["input"] for p in parts]),
        "frame": np.concatenate([p["frame"] for p in parts]).astype(np.int64),
        "approx_time": np.concatenate([p["approx_time"] for p in parts]),
        "Identity": np.concatenate([p["Identity"] for p in parts]),
    }
    return _Frame(blocks, tail)


def _clean_table(parts: list[dict]) -> pa.Table:
    c = {k: np.concatenate([p["clean"][k] for p in parts]) for k in ("video_id", "frame", "au", "pose", "mesh")}
    data = {"video_id": pa.array(c["video_id"], pa.string()), "frame": pa.array(c["frame"].astype(np.int64))}
    for j, name in enumerate(AU_COLUMNS):
        data[name] = pa.array(c["au"][:, j])
    for j, name in enumerate(FEX_POSE_COLUMNS):
        data[name] = pa.array(c["pose"][:, j])
    flat = np.asfortranarray(c["mesh"].reshape(len(c["mesh"]), -1))  # contiguous columns: no copy per column
    for k, name in enumerate(clean_columns()[2 + len(AU_COLUMNS) + 3 :]):
        data[name] = pa.array(flat[:, k])
    return pa.table(data)


class _ParquetSink:
    """A parquet file written chunk by chunk (one schema: text columns stay text when a chunk is all NaN)."""

    def __init__(self, path: Path):
        self.path = path
        self.writer: pq.ParquetWriter | None = None
        self.schema: pa.Schema | None = None
        self._ctx = atomic_path(path, suffix=".parquet")
        self.tmp = self._ctx.__enter__()

    def write(self, table: pa.Table | _Frame) -> None:
        if isinstance(table, _Frame):
            self.schema = self.schema or _frame_schema(table)
            table = table.to_arrow(self.schema)
        if self.writer is None:
            self.schema = self.schema or table.schema
            self.writer = pq.ParquetWriter(self.tmp, table.schema, compression="zstd")
        self.writer.write_table(table, row_group_size=8192)

    def close(self, error: BaseException | None = None) -> None:
        if self.writer is not None:
            self.writer.close()
        if error is None:
            self._ctx.__exit__(None, None, None)
        else:
            self._ctx.__exit__(type(error), error, error.__traceback__)


def write_pyfeat_tables(
    out_dir: str | Path,
    spec: synth.SynthSpec,
    *,
    detector: str = "mp",
    fmt: str = "csv",
    no_face_rate: float = 0.03,
    extra_face_rate: float = 0.05,
    normalized: bool = False,
    frame_size: bool = True,
    z_pixels: bool = False,
    profile_rate: float | None = None,
    clean_dir: str | Path | None = None,
    videos_per_file: int | None = None,
    seed: int = 0,
) -> dict:
    """Write synth's videos as py-feat 2.1.5 exports them (``clip_0000.csv`` ...); optionally the hand-cleaned tables.

    Parameters
    ----------
    detector : "mp" (MPDetector, mp_facemesh_v2; ~2,045 columns) or "v2" (Detectorv2).
    fmt : "csv" (``DataFrame.to_csv(index=False)``, as py-feat's ``save=``), "parquet" (the same DataFrame),
        "split" (parquet without the mesh plus an ``[N, 478, 3]`` float32 ``.npy`` of the same stem; "mp" only).
    no_face_rate : fraction of each video's frames (in runs of 1-10) whose face row is replaced by a no-face row.
    extra_face_rate : fraction of the face frames (in runs) with a second, smaller background face ("Person_1").
    normalized : meshes (and v2's 68 points) as x / FrameWidth, y / FrameHeight, z / FrameWidth.
    frame_size : False drops FrameHeight/FrameWidth (a normalized table then cannot be converted to pixels).
    z_pixels : z in frame pixels, not in the detector's crop units (a table rescaled after py-feat: ingested with
        ``data.mesh_units=pixels``, the independent route of the conversion).
    profile_rate : fraction of each video's frames, in runs, with the head turned toward profile (|yaw| 60-85 deg,
        ``SynthSpec.profile_rate``/``profile_yaw_deg``); None: the spec's. The clean tables hold the same frames.
    clean_dir : also write synth's ``columns`` layout (``clip_0000.parquet``: video_id, frame, AUs, Pitch, Roll, Yaw,
        interleaved pixel mesh as float32) holding the main face of every frame that has one.
    videos_per_file : videos per output file (None: one file for all, as one ``detect`` call over many videos).
    seed : seeds the py-feat extras (no-face runs, background faces, blendshapes, ...); synth's frames follow ``spec``.

    Returns a summary: files, clean_files, n_rows, n_frames, n_face_frames, n_no_face, n_extra_faces, n_videos.
    """
    _check_detector(detector)
    if fmt not in FORMATS:
        raise ValueError(f"fmt={fmt!r}: use one of {', '.join(FORMATS)}")
    if fmt == "split" and detector != "mp":
        raise ValueError("fmt='split' (parquet + mesh .npy) is written for detector='mp' only")
    if not (0.0 <= no_face_rate < 1.0 and 0.0 <= extra_face_rate <= 1.0):
        raise ValueError(
            f"need 0 <= no_face_rate < 1 and 0 <= extra_face_rate <= 1, got {no_face_rate}, {extra_face_rate}"
        )
    if videos_per_file is not None and videos_per_file < 1:
        raise ValueError(f"videos_per_file={videos_per_file}: use None or >= 1")
    if profile_rate is not None:
        spec = replace(spec, profile_rate=profile_rate)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if clean_dir is not None:
        clean_dir = Path(clean_dir)
        clean_dir.mkdir(parents=True, exist_ok=True)
        if clean_dir.resolve() == out_dir.resolve() and fmt != "csv":
            raise ValueError("clean_dir must differ from out_dir for fmt='parquet'/'split' (same file names)")

    counts, gen_args = _synth_setup(spec)
    per_file = videos_per_file or spec.n_videos
    files: list[str] = []
    clean_files: list[str] = []
    summary: dict[str, Any] = {
        "files": files,
        "clean_files": clean_files,
        "n_rows": 0,
        "n_frames": 0,
        "n_face_frames": 0,
        "n_no_face": 0,
        "n_extra_faces": 0,
        "n_videos": spec.n_videos,
    }
    for file_no, first in enumerate(range(0, spec.n_videos, per_file)):
        videos = range(first, min(first + per_file, spec.n_videos))
        ext = ".csv" if fmt == "csv" else ".parquet"
        path = out_dir / f"clip_{file_no:04d}{ext}"
        clean_path = None if clean_dir is None else clean_dir / f"clip_{file_no:04d}.parquet"
        _write_one(
            path,
            clean_path,
            videos,
            counts,
            spec,
            gen_args,
            detector,
            fmt,
            no_face_rate,
            extra_face_rate,
            normalized,
            frame_size,
            z_pixels,
            seed,
            summary,
        )
        summary["files"].append(str(path))
        if clean_path is not None:
            summary["clean_files"].append(str(clean_path))
    return summary


def _write_one(
    path: Path,
    clean_path: Path | None,
    videos: range,
    counts: np.ndarray,
    spec,
    gen_args,
    detector,
    fmt,
    no_face_rate,
    extra_face_rate,
    normalized,
    frame_size,
    z_pixels,
    seed,
    summary,
) -> None:
    """One output file (and its clean twin), built and written a chunk of whole videos at a time."""
    chunks: list[list[int]] = [[]]
    rows = 0
    for v in videos:
        if chunks[-1] and rows + counts[v] > _CHUNK_ROWS:
            chunks.append([])
            rows = 0
        chunks[-1].append(v)
        rows += int(counts[v])

    clean_sink = _ParquetSink(clean_path) if clean_path is not None else None
    sink = _ParquetSink(path) if fmt in ("parquet", "split") else None
    csv_ctx = atomic_path(path, suffix=".csv") if fmt == "csv" else None
    csv_tmp = csv_ctx.__enter__() if csv_ctx is not None else None
    npy_parts: list[Path] = []
    error = None
    try:
        for k, chunk in enumerate(chunks):
            parts = [
                _video_rows(spec, v, int(counts[v]), gen_args, detector, no_face_rate, extra_face_rate, seed)
                for v in chunk
            ]
            frame = _frame(parts, detector, normalized, frame_size, with_mesh=fmt != "split", z_pixels=z_pixels)
            if fmt == "csv":
                frame.to_pandas().to_csv(csv_tmp, index=False, mode="w" if k == 0 else "a", header=k == 0)
            else:
                assert sink is not None  # parquet and split write through a sink
                sink.write(frame)
            if fmt == "split":
                m = np.concatenate([p["blocks"]["mesh"] for p in parts]).astype(np.float64)
                if normalized:
                    m = m / np.array([FRAME_WIDTH, FRAME_HEIGHT, FRAME_WIDTH])
                part = path.with_name(f".{path.stem}.part{k:05d}.npy")
                np.save(part, m.astype(np.float32))
                npy_parts.append(part)
            if clean_sink is not None:
                clean_sink.write(_clean_table(parts))
            summary["n_rows"] += frame.n_rows
            for p in parts:
                summary["n_frames"] += p["n_frames"]
                summary["n_face_frames"] += p["n_frames"] - p["n_no_face"]
                summary["n_no_face"] += p["n_no_face"]
                summary["n_extra_faces"] += p["n_extra"]
            del frame, parts
        if fmt == "split":
            _join_npy(path.with_suffix(".npy"), npy_parts)
    except BaseException as e:
        error = e
        raise
    finally:
        for part in npy_parts:
            part.unlink(missing_ok=True)
        for s in (sink, clean_sink):
            if s is not None:
                s.close(error)
        if csv_ctx is not None:
            csv_ctx.__exit__(*((type(error), error, error.__traceback__) if error is not None else (None, None, None)))


def _join_npy(path: Path, parts: list[Path]) -> None:
    """Concatenate ``[n_k, 478, 3]`` float32 .npy parts into one file, one part in memory at a time."""
    shapes = [np.load(p, mmap_mode="r").shape for p in parts]
    n = sum(s[0] for s in shapes)
    with atomic_path(path, suffix=".npy") as tmp:
        out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=(n, N_VERTICES, 3))
        start = 0
        for p, s in zip(parts, shapes, strict=True):
            out[start : start + s[0]] = np.load(p)
            start += s[0]
        out.flush()
        del out
