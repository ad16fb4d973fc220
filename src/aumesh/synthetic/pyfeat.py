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
* optionally MediaPipe's normalized image units (x / width, y / height, z / width) and no frame-size columns;
* with :class:`synth.SynthSpec`'s ``au_noise_sd`` the AUs as a noisy detector records them, and with
  ``instrument_noise_sd`` a second detector's AUs on the same frames (``AU01_2`` ... ``AU43_2``, after the AUs).

Only column names are taken from py-feat; nothing of its code or data. Files are written one at a time, in chunks of
videos, so ~100k frames in one CSV stay in bounded memory. This module writes the files (CSV, parquet, the split
layout); the column layouts are :mod:`aumesh.synthetic.pyfeat_columns`'s, the faces and their rows
:mod:`aumesh.synthetic.pyfeat_faces`'.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from aumesh.core.families import EMOTION_NAME_MAP
from aumesh.core.io import atomic_path
from aumesh.core.schema import AU_COLUMNS, N_VERTICES
from aumesh.synthetic import tables as synth
from aumesh.synthetic.family_truth import family_truth_fields
from aumesh.synthetic.pyfeat_columns import (
    BLENDSHAPE_COLUMNS,
    EMOTION_COLUMNS_MP,
    EMOTION_COLUMNS_V2,
    FACE_RECT_COLUMNS,
    FEX_POSE_COLUMNS,
    FRAME_SIZE_COLUMNS,
    GAZE_COLUMNS,
    HEAD_POSITION_COLUMNS,
    IDENTITY_COLUMNS,
    LANDMARK68_VERTICES,
    check_detector,
    clean_columns,
    landmark68_columns,
    mesh_columns,
)
from aumesh.synthetic.pyfeat_faces import FRAME_HEIGHT, FRAME_WIDTH, synth_setup, video_rows, z_to_crop

FORMATS = ("csv", "parquet", "split")

_CHUNK_ROWS = 4096  # rows per DataFrame written (whole videos; a longer video is one chunk)


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
        if "au2" in parts[0]["blocks"]:
            add(cat("au2"), synth.INSTRUMENT_COLUMNS)
        add(cat("emotion"), EMOTION_COLUMNS_MP)
        add(nan_identity, IDENTITY_COLUMNS)  # no identity model run
        add(cat("gaze"), GAZE_COLUMNS)
    else:
        add(mesh[:, list(LANDMARK68_VERTICES), :2].transpose(0, 2, 1).reshape(r, -1), landmark68_columns())
        add(cat("pose"), FEX_POSE_COLUMNS + HEAD_POSITION_COLUMNS)
        add(cat("au"), AU_COLUMNS)
        if "au2" in parts[0]["blocks"]:
            add(cat("au2"), synth.INSTRUMENT_COLUMNS)
        # Detectorv2's columns hold the same probabilities, matched by name (never by position)
        mp_to_v2 = [EMOTION_COLUMNS_MP.index(EMOTION_NAME_MAP[e]) for e in EMOTION_COLUMNS_V2]
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
    if "au2" in parts[0]["clean"]:  # the second detector's AUs (SynthSpec.instrument_noise_sd)
        au2 = np.concatenate([p["clean"]["au2"] for p in parts])
        for j, name in enumerate(synth.INSTRUMENT_COLUMNS):
            data[name] = pa.array(au2[:, j])
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
    twin_face: bool = False,
    family_truth: bool = False,
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
    twin_face : a second person of about the main face's size beside it in every face frame (``Identity``
        "Person_2"; :func:`aumesh.synthetic.pyfeat_faces.twin_faces`): the largest-face rule cannot tell them apart.
        Off by default (no extra random draw: the tables are byte-identical without it).
    family_truth : the main face's blendshapes and emotions drawn independently of its AUs and its mesh moved by their
        known fields (:mod:`aumesh.synthetic.family_truth`; the truth: ``family_truth.family_truth_arrays(*tables.true_coefficients(spec)[:2])``),
        the clean tables' meshes too. Off by default (no extra random draw: byte-identical tables without it).

    Returns a summary: files, clean_files, n_rows, n_frames, n_face_frames, n_no_face, n_extra_faces, n_twin_faces
    (frames with a twin), n_videos.
    """
    check_detector(detector)
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

    counts, gen_args = synth_setup(spec)
    fields = family_truth_fields(*synth.true_coefficients(spec)[:2]) if family_truth else None
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
        "n_twin_faces": 0,
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
            twin_face,
            fields,
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
    twin_face=False,
    family_fields=None,
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
                video_rows(
                    spec,
                    v,
                    int(counts[v]),
                    gen_args,
                    detector,
                    no_face_rate,
                    extra_face_rate,
                    seed,
                    twin_face,
                    family_fields,
                )
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
                summary["n_twin_faces"] += p["n_twin"]
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
