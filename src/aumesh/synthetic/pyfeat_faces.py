"""The faces of the synthetic py-feat tables (:mod:`aumesh.synthetic.pyfeat`): one video's detected faces and rows,
with what a real ``detect`` export measures around :mod:`aumesh.synthetic.tables`'s frames (the same videos, seeds and
meshes in frame pixels):

* ``FaceRectX/Y/Width/Height`` (:func:`crop_box`): the crop box the detector cut the face from, in frame pixels,
  around a detector box (the face's 2-D extent padded 8 %): Detectorv2's square of side 1.2 x the box's longer side,
  centred, and MPDetector's box expanded 1.25x about its centre, corners rounded to whole pixels;
* z in the detector's crop units (:func:`z_to_crop`): Detectorv2's 0-1 of its chip, MPDetector's pixels of its
  256-px crop;
* frames without a face (occlusion, in runs), kept as one row whose measurements are NaN (``FaceScore`` and
  ``FaceRect*`` 0 for "mp", NaN for "v2");
* a second, smaller face in the background in some runs of frames (``Identity`` "Person_1"), before or after the
  main face's row, as the detector found them;
* opt-in (``twin``): a second person of about the main face's size beside it in every face frame (``Identity``
  "Person_2", its own AUs, pose and face shape; box area 0.90-1.10 x the main's, so the largest face flips between
  the two), its row before or after the main face's (:func:`twin_faces`);
* blendshapes, emotions, gaze, head position and identity embeddings that loosely follow the AUs.
"""

from __future__ import annotations

import numpy as np

from aumesh.core.schema import ANCHOR_INDICES, AU_COLUMNS, N_VERTICES, POSE_COLUMNS, flatten_axis_major
from aumesh.synthetic import tables as synth
from aumesh.synthetic.family_truth import BLENDSHAPE_AU, draw_family_values
from aumesh.synthetic.pyfeat_columns import BLENDSHAPE_COLUMNS, FEX_POSE_COLUMNS

FRAME_WIDTH = 640.0
FRAME_HEIGHT = 480.0
FPS = 25

#: The detectors' crops (docs/conventions.md "py-feat's mesh units"): Detectorv2's square side over the detector
#: box's longer side (EXPAND_BBOX, feat/multitask/inference.py), MPDetector's expansion and crop size
#: (``MPDetector.detect_faces``).
V2_EXPAND = 1.2
MP_EXPAND = 1.25
MP_CROP = 256.0
_DETECTOR_PAD = 0.08  # the detector box: the face's 2-D extent padded 8 % each side

_NO_FACE_RUN = (1, 10)  # occlusions: 1-10 consecutive frames
_EXTRA_FACE_RUN = (5, 40)  # a person in the background for a while


def synth_setup(spec: synth.SynthSpec) -> tuple[np.ndarray, tuple]:
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
    for bs, a in BLENDSHAPE_AU.items():  # the shapes' meanings, the family truth's table
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
    au2: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Every measurement of ``m`` detected faces (meshes in pixels): 2-D blocks keyed by group (``au2``: a second
    detector's AUs, ``SynthSpec.instrument_noise_sd``)."""
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
    if au2 is not None:
        out["au2"] = np.clip(au2, 0.0, 1.0)
    if identity is not None:
        emb = identity[None, :] + rng.normal(0.0, 0.02, size=(m, len(identity)))
        out["identity"] = (emb / np.linalg.norm(emb, axis=1, keepdims=True)).astype(np.float32)
    return out


def video_rows(
    spec: synth.SynthSpec,
    video: int,
    n: int,
    gen_args: tuple,
    detector: str,
    no_face_rate: float,
    extra_face_rate: float,
    seed: int,
    twin: bool = False,
    family_fields: dict[str, np.ndarray] | None = None,
) -> dict:
    """One video's rows: synth's frames, no-face rows, background faces (and ``twin``: :func:`twin_faces`); plus the
    clean frames. With ``family_fields`` (:func:`aumesh.synthetic.family_truth.family_fields`, pixels) the main face's
    blendshapes and emotions are drawn from their own stream (``[seed, spec.seed, video, 6]``) and its mesh moves by
    their fields (:mod:`aumesh.synthetic.family_truth`); the clean frames hold that mesh too."""
    family, moved = None, None
    if family_fields is not None:  # its own stream: without it nothing more is drawn (tables stay byte-identical)
        family = draw_family_values(np.random.default_rng([seed, spec.seed, video, 6]), n)
        moved = synth.family_displacement(family, family_fields)
    coef, intercept, identity_basis, latent_basis, resemblance = gen_args
    g = synth.generate_video(spec, video, n, coef, intercept, identity_basis, latent_basis, resemblance, extra=moved)
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
        g.get("au2"),
    )
    if family is not None:
        main["blend"], main["emotion"] = family
    # the background person: the main mesh scaled 0.4 about its centre, ~150 px to the side with more room
    ef = np.flatnonzero(extra)
    centre = g["mesh"][ef].mean(axis=1, keepdims=True)
    side = -np.sign(g["mesh"][:, :, 0].mean() - FRAME_WIDTH / 2) or 1.0
    offset = np.array([side * rng.uniform(130, 170), rng.normal(0, 20), 0.0])
    small = centre + 0.4 * (g["mesh"][ef] - centre) + offset + rng.normal(0, 0.3, size=(len(ef), N_VERTICES, 3))
    extra_au = synth._au_intensities(rng, len(ef), rng.uniform(0.3, 1.6, size=5 + len(AU_COLUMNS)))
    extra_pose = np.deg2rad(rng.normal(0, [10, 7, 18]) + rng.normal(0, 2, size=(len(ef), 3)))  # Fex order
    extra_au2 = None
    if "au2" in g:  # the second detector reads the background face too: its own stream, no draw from rng
        noise2 = np.random.default_rng([seed, spec.seed, video, 3]).normal(
            0.0, spec.instrument_noise_sd, extra_au.shape
        )
        extra_au2 = extra_au + noise2
    other = _faces(
        rng,
        small,
        extra_au,
        extra_pose,
        (0.6, 0.9),
        _unit(rng.standard_normal(512)) if v2 else None,
        detector,
        extra_au2,
    )

    # rows: one per frame, two where a background face is; it comes first where extra_first
    per_frame = 1 + extra.astype(int)
    row_frame = np.repeat(np.arange(n), per_frame)
    first_row = np.cumsum(per_frame) - per_frame
    pos = np.arange(len(row_frame)) - first_row[row_frame]
    kind = np.where(extra_first[row_frame], 1 - pos, pos)  # 0 main face, 1 background face
    twin_rows, n_twin = np.zeros(len(kind), bool), 0
    if twin:  # its own streams: a table without twins draws nothing more (stays byte-identical)
        faces2, twin_first = twin_faces(spec, video, n, g, ~no_face, detector, seed)
        row_frame, kind = _with_twins(row_frame, kind, ~no_face, twin_first)
        twin_rows, n_twin = kind == 2, int((~no_face).sum())
    main_rows, extra_rows = kind == 0, kind == 1
    blocks = {}
    for key, values in main.items():
        block = np.empty(
            (len(row_frame),) + values.shape[1:], dtype=values.dtype if key in ("mesh", "identity") else np.float64
        )
        block[main_rows] = values
        block[extra_rows] = other[key]
        if twin:
            block[twin_rows] = faces2[key]
        blocks[key] = block
    gone = main_rows & no_face[row_frame]
    for key, block in blocks.items():
        block[gone] = np.nan
        if key in ("rect", "score") and not v2:
            block[gone] = 0.0
    identity = np.where(extra_rows, "Person_1", "Person_0").astype(object)
    identity[twin_rows] = "Person_2"
    identity[gone] = np.nan
    path = f"videos/vid{video:06d}.mp4"  # py-feat's input: the video's identity, in the clean tables too
    seconds = row_frame // FPS
    keep = ~no_face
    return {
        "blocks": blocks,
        "frame": row_frame,
        "input": np.full(len(row_frame), path, dtype=object),
        "approx_time": np.array([f"{s // 60:02d}:{s % 60:02d}" for s in seconds], dtype=object),
        "Identity": identity,
        "clean": {
            "video_id": np.full(int(keep.sum()), path, dtype=object),
            "frame": np.flatnonzero(keep),
            "au": g["au"][keep],
            **({"au2": g["au2"][keep]} if "au2" in g else {}),
            "pose": g["pose"][keep][:, order],
            "mesh": g["mesh"][keep].astype(np.float32),
        },
        "n_frames": n,
        "n_no_face": int(no_face.sum()),
        "n_extra": int(extra.sum()),
        "n_twin": n_twin,
    }


def twin_faces(
    spec: synth.SynthSpec, video: int, n: int, g: dict, face: np.ndarray, detector: str, seed: int
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """A second person beside the main face in each face frame (``face``: (n,) bool), and whether its row comes first.

    Its mesh is the main face's expression on another face shape (x x 0.94, y x 1.05 about the face's centre: a
    narrower, longer face), scaled by 0.95-1.05 per frame (box area 0.90-1.10 x the main's: the largest-face rule
    cannot tell them apart, :data:`aumesh.data.face_track.AMBIGUOUS_AREA_RATIO`) and ~1.3 face widths to the side
    with more room, moving with the main face; its AUs and pose its own. Drawn from its own random streams
    (``[seed, spec.seed, video, 4]``, ``..5``)."""
    rng = np.random.default_rng([seed, spec.seed, video, 4])
    rows = np.flatnonzero(face)
    mesh = g["mesh"][rows]
    centre = mesh.mean(axis=1, keepdims=True)
    width = np.ptp(mesh[:, :, 0], axis=1).mean()
    side = -np.sign(g["mesh"][:, :, 0].mean() - FRAME_WIDTH / 2) or 1.0
    scale = rng.uniform(0.95, 1.05, size=(len(rows), 1, 1))
    shape = np.array([0.94, 1.05, 1.0])
    offset = np.array([side * 1.3 * width, rng.normal(0, 10), 0.0])
    other = centre + scale * shape * (mesh - centre) + offset
    au = synth._au_intensities(rng, len(rows), rng.uniform(0.3, 1.6, size=5 + len(AU_COLUMNS)))
    pose = np.deg2rad(rng.normal(0, [8, 6, 15]) + rng.normal(0, 2, size=(len(rows), 3)))  # Fex order
    au2 = None
    if "au2" in g:
        au2 = au + np.random.default_rng([seed, spec.seed, video, 5]).normal(0.0, spec.instrument_noise_sd, au.shape)
    v2 = detector == "v2"
    faces = _faces(rng, other, au, pose, (0.9, 1.0), _unit(rng.standard_normal(512)) if v2 else None, detector, au2)
    return faces, rng.random(n) < 0.5


def _with_twins(
    row_frame: np.ndarray, kind: np.ndarray, face: np.ndarray, twin_first: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(row_frame, kind)`` with a twin row (kind 2) in each face frame: before the frame's rows where
    ``twin_first``, else after them."""
    frames, kinds = [], []
    starts = np.r_[0, np.flatnonzero(np.diff(row_frame)) + 1, len(row_frame)]
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        t = int(row_frame[a])
        mine = kind[a:b].tolist()
        if face[t]:
            mine = [2, *mine] if twin_first[t] else [*mine, 2]
        frames += [t] * len(mine)
        kinds += mine
    return np.array(frames, dtype=row_frame.dtype), np.array(kinds, dtype=kind.dtype)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)
