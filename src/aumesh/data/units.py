"""py-feat's mesh units -> frame pixels, and the measurements that guard them (docs/conventions.md, "py-feat's mesh
units"): the ingest's step 3 (:mod:`aumesh.data.ingest`), reused as it is by the clip reader (:mod:`aumesh.data.clip`).

* MediaPipe's raw landmarks are normalized image coordinates (x / width, y / height, z on x's scale). Judged from
  the mesh's whole 2-D extent (:func:`normalized_rows`: a face in pixels, even in profile, is tens of pixels tall;
  one in normalized units spans less than :data:`NORMALIZED_MAX_EXTENT`, and a small fraction of its FaceRect),
  converted with ``FrameWidth``/``FrameHeight`` or refused when the table lacks them;
* py-feat writes x, y in frame pixels but z in its detector's crop units (:data:`Z_CROP`, :func:`z_scale`):
  Detectorv2's z is in 0-1 of its square chip (``z_px = z * FaceRectWidth``), MPDetector's in pixels of its
  256-px crop (``z_px = z * FaceRectWidth / 256``). ``data.mesh_units=pixels`` takes every z as pixels;
* the face's proportions are measured per source (:func:`depth_height`: face depth over face height, z- over
  y-extent, stable under yaw; :func:`growth_sums`: how z grows with the face's size) in mergeable summaries
  (:class:`RatioHist`, :class:`UnitStats`) for the ingest stage's guard (:data:`DEPTH_HEIGHT_RANGE`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from aumesh.core.errors import TableError
from aumesh.core.schema import N_VERTICES
from aumesh.data import pyfeat
from aumesh.data.readers import Block
from aumesh.geometry.landmarks import FACE_OVAL

#: Vertices whose extents judge the units and measure the face's proportions: the face oval (its top 10 and chin 152
#: span the face's height at any yaw, its sides 234/454 lie at the back of the face) and the nose tip 1 (the front).
SHAPE_VERTICES: tuple[int, ...] = (*FACE_OVAL, 1)
#: A mesh whose 2-D extent (the larger of its x and y spans) is below this is in normalized image units: a face in
#: pixels is tens of pixels tall even in profile (py-feat's smallest detected face, a ~20 px box), a face in 0-1
#: units spans at most the frame (1) and a little beyond it.
NORMALIZED_MAX_EXTENT = 1.5
#: ... and below this fraction of its FaceRect's longer side, where py-feat wrote one (FaceRect is in pixels in
#: either detector's export; a mesh in pixels spans ~0.6-0.9 of its crop box, one in 0-1 units ~1/frame size).
NORMALIZED_MAX_RECT_FRACTION = 0.1
#: The detectors' z units: name and divisor, z_px = z * FaceRectWidth / divisor (docs/conventions.md).
#: Detectorv2: ``_mesh_to_original_frame`` (feat/detector_v2.py) maps x, y from 0-1 over the square chip
#: (``extract_face_square_pad_torch``, feat/utils/image_operations.py: the detector box squared to its longer side x
#: EXPAND_BBOX 1.2) to frame pixels and returns z unchanged; ``forward`` writes that square (``_crop_affine_to_box``)
#: divided by the loader's rescale as FaceRect, so FaceRectWidth is the chip's side in frame pixels.
#: MPDetector: ``detect_faces`` crops ``extract_face_from_bbox_torch(face_size=256, expand_bbox=1.25)`` (the box
#: expanded 1.25x, resized to 256 x 256), FaceRect is that expanded box in frame pixels, and ``forward`` rescales
#: only x, y ("leave Z in original scale"): z is in the 256-px crop's pixels, on x's scale (MediaPipe's z).
Z_CROP: dict[str, tuple[str, float]] = {"Detectorv2": ("chip", 1.0), "MPDetector": ("crop256", 256.0)}
#: The median over a source's faces of face depth over face height (z- over y-extent of :data:`SHAPE_VERTICES`)
#: must lie in this range. MediaPipe's canonical face (py-feat's canonical_face_model.pt) has depth/width ~0.65,
#: width/height ~0.85: depth/height ~0.55; py-feat's v4 release ~0.7 (depth/width 0.81); aumesh's template 0.34;
#: a profile face (yaw 90) shows its width as depth, ~1.2. A flat face (z left in Detectorv2's chip units) is
#: ~0.001. The range is a factor of ~3 beyond the faces: it refuses units, not people.
DEPTH_HEIGHT_RANGE = (0.1, 3.0)
#: z's growth with the face (:func:`growth_slope`) is judged on at least this many near-frontal faces whose heights
#: spread at least this much (SD of log face height: ~8 %); with a frontal face's depth varying ~10 % (expression,
#: the pose left) the slope's standard error is then below ~0.2, a fifth of the gap between py-feat's crop units (0)
#: and pixels (1); the verdict is at 0.5. (Synthetic faces: 1.06 in pixels, 0.07-0.10 in either crop's units.)
GROWTH_MIN_ROWS = 50
GROWTH_MIN_SPREAD = 0.08
#: ... among near-frontal faces (|pitch| and |yaw| below this, radians: ~11 deg), whose depth/height is the face's.
GROWTH_MAX_POSE = 0.2
#: log10 bin width of the depth/height histograms (:class:`RatioHist`: ~2.3 %), and their range (beyond: the end bins).
RATIO_BIN = 0.01
RATIO_LOG_RANGE = (-6.0, 4.0)


@dataclass(frozen=True)
class RatioHist:
    """A histogram of positive ratios in log10 bins of :data:`RATIO_BIN`, sparse (only the bins with counts: a source's
    faces fill a few dozen), so a source's measurement costs a few hundred bytes and merges over blocks and tasks.

    ``bins`` (k,) int32 sorted bin numbers (bin b holds log10 values in ``[b, b + 1) * RATIO_BIN``), ``counts`` (k,).
    """

    bins: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __add__(self, other: RatioHist) -> RatioHist:
        if not len(other.bins):
            return self
        if not len(self.bins):
            return other
        bins, inverse = np.unique(np.r_[self.bins, other.bins], return_inverse=True)
        return RatioHist(bins.astype(np.int32), np.bincount(inverse, np.r_[self.counts, other.counts]).astype(np.int64))

    def median(self) -> float | None:
        """The median ratio (its bin's geometric centre: within ~1.2 %); None when empty."""
        total = int(self.counts.sum())
        if not total:
            return None
        k = int(np.searchsorted(np.cumsum(self.counts), (total + 1) / 2))
        return float(10 ** ((int(self.bins[k]) + 0.5) * RATIO_BIN))


@dataclass
class UnitStats:
    """One source's mesh units, summed over its blocks: what was converted and the face's proportions.

    ``xy``: "pixels" | "normalized" (| "mixed" when blocks of one source differ: refused by the ingest stage);
    ``z``: "pixels" | "chip" | "crop256" | "normalized"; the histograms count each face row's depth/height
    (:func:`depth_height`) in :class:`RatioHist` bins, as written (``before``), as ingested (``after``) and with z
    converted by the detector's crop (``crop``; empty unless the table is a detector's export with FaceRect).
    """

    detector: str = ""
    xy: str = ""
    z: str = ""
    rows: int = 0  # face rows kept
    rows_converted: int = 0  # rows whose mesh was rescaled (normalized, or z from a detector's crop units)
    rows_normalized: int = 0
    rows_z_converted: int = 0  # rows whose z was converted from the detector's crop units
    before: RatioHist = field(default_factory=lambda: RatioHist())
    after: RatioHist = field(default_factory=lambda: RatioHist())
    crop: RatioHist = field(default_factory=lambda: RatioHist())
    growth: np.ndarray = field(default_factory=lambda: np.zeros(5))  # :func:`growth_sums` of the rows

    def __add__(self, other: UnitStats) -> UnitStats:
        def unit(a: str, b: str) -> str:
            return a or b if not (a and b) or a == b else "mixed"

        return UnitStats(
            self.detector or other.detector,
            unit(self.xy, other.xy),
            unit(self.z, other.z),
            self.rows + other.rows,
            self.rows_converted + other.rows_converted,
            self.rows_normalized + other.rows_normalized,
            self.rows_z_converted + other.rows_z_converted,
            self.before + other.before,
            self.after + other.after,
            self.crop + other.crop,
            self.growth + other.growth,
        )

    def z_growth(self) -> float | None:
        """How z as written grows with the face's size (:func:`growth_slope`); None when the faces' sizes vary too
        little to tell."""
        return growth_slope(self.growth)

    def depth_height(self) -> tuple[float | None, float | None, float | None]:
        """Median face depth/height as written, as ingested and with z converted by the detector's crop; None
        where nothing was measured."""
        return self.before.median(), self.after.median(), self.crop.median()


def shape_extents(mesh: np.ndarray, axes: Sequence[int] = (0, 1, 2)) -> np.ndarray:
    """(n, len(axes)) spans along ``axes`` (0 x, 1 y, 2 z) of :data:`SHAPE_VERTICES` of axis-major meshes (n, 1434)
    (NaN where a vertex is)."""
    idx = np.add.outer(np.asarray(axes) * N_VERTICES, SHAPE_VERTICES)  # (a, k)
    part = np.sort(mesh[:, idx].astype(np.float64), axis=2)  # (n, a, k), NaN last
    # second-largest minus second-smallest: one wild vertex (a corrupt export, dropped later by prepare's
    # max_vertex_iod) neither judges the units nor flattens the face; the oval's vertices are ~5 % of it apart
    return part[:, :, -2] - part[:, :, 1]


def depth_height(extents: np.ndarray) -> np.ndarray:
    """(n,) face depth over face height, z- over y-extent (:func:`shape_extents`): yaw turns x into z, not y."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return extents[:, 2] / extents[:, 1]


def frontal(values: dict[str, np.ndarray]) -> np.ndarray:
    """(n,) bool: faces within :data:`GROWTH_MAX_POSE` radians of frontal in pitch and yaw (py-feat's pose columns)."""
    return (np.abs(values["Pitch"]) < GROWTH_MAX_POSE) & (np.abs(values["Yaw"]) < GROWTH_MAX_POSE)


def growth_sums(z_extent: np.ndarray, height: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(5,) n, sum x, sum y, sum x^2, sum x y of x = log face height (y-extent, pixels), y = log z-extent as written,
    over ``rows`` (near-frontal faces, :func:`frontal`: pitch turns height into depth, yaw width) where both are
    finite and positive: the sums of a least-squares slope, mergeable over blocks."""
    ok = rows & np.isfinite(z_extent) & np.isfinite(height) & (z_extent > 0) & (height > 0)
    x, y = np.log(height[ok]), np.log(z_extent[ok])
    return np.array([len(x), x.sum(), y.sum(), (x * x).sum(), (x * y).sum()])


def growth_slope(sums: np.ndarray) -> float | None:
    """The slope of log z-extent on log face height over a source's faces (:func:`growth_sums`), None below
    :data:`GROWTH_MIN_ROWS` faces or :data:`GROWTH_MIN_SPREAD`. In frame pixels a face's depth grows with its size
    (slope ~1); in py-feat's crop units it does not (~0: each face's crop is rescaled to the same chip, 0-1 or 256
    px). The height, not FaceRectWidth: MPDetector's crop width shrinks as the head turns while the depth grows. This
    tells the units apart where the depth/height ratio cannot (an MPDetector face ~256 px wide looks the same in
    either)."""
    n, sx, sy, sxx, sxy = (float(v) for v in sums)
    if n < GROWTH_MIN_ROWS:
        return None
    var = sxx / n - (sx / n) ** 2
    if var < GROWTH_MIN_SPREAD**2:
        return None
    return (sxy / n - sx * sy / n**2) / var


def ratio_hist(ratio: np.ndarray) -> RatioHist:
    """The finite values of ``ratio`` (n,) counted in :class:`RatioHist` bins."""
    r = np.abs(ratio[np.isfinite(ratio)])
    with np.errstate(divide="ignore"):
        logs = np.clip(np.log10(r), *RATIO_LOG_RANGE)
    bins, counts = np.unique(np.floor(logs / RATIO_BIN).astype(np.int32), return_counts=True)
    return RatioHist(bins, counts.astype(np.int64))


def normalized_rows(
    mesh: np.ndarray, rect_side: np.ndarray | None = None, extents: np.ndarray | None = None
) -> np.ndarray:
    """(n,) bool: rows whose mesh (n, 1434) is in normalized image units.

    The mesh's 2-D extent (the larger of its x and y spans over :data:`SHAPE_VERTICES`) is below
    :data:`NORMALIZED_MAX_EXTENT`, and, where the row has a FaceRect (``rect_side``: its longer side in pixels,
    (n,); NaN or 0 where py-feat wrote none), below :data:`NORMALIZED_MAX_RECT_FRACTION` of it. A face turned to
    profile keeps its height: its inter-ocular distance can fall below a pixel, its extent does not. ``extents``:
    its x, y spans (n, 2) when already measured (:func:`shape_extents`).
    """
    extent = (shape_extents(mesh, (0, 1)) if extents is None else extents).max(axis=1)
    normalized = extent < NORMALIZED_MAX_EXTENT
    if rect_side is not None:
        has_rect = np.isfinite(rect_side) & (rect_side > 0)
        normalized &= ~has_rect | (extent < NORMALIZED_MAX_RECT_FRACTION * np.where(has_rect, rect_side, 0.0))
    return normalized


def rect_side(block: Block, layout: pyfeat.Layout) -> np.ndarray | None:
    """(n,) the longer side of each row's FaceRect (None: the table has no FaceRect columns)."""
    if layout.box_size is None:
        return None
    w, h = (block.values[c] for c in layout.box_size)
    return np.fmax(w, h)


def to_pixels(block: Block, layout: pyfeat.Layout, normalized: np.ndarray, where: str) -> None:
    """Convert the ``normalized`` rows' meshes in place: x by FrameWidth, y by FrameHeight, z by FrameWidth
    (MediaPipe's z is on x's scale)."""
    if not normalized.any():
        return
    extent = float(np.median(shape_extents(block.mesh[normalized], (0, 1)).max(axis=1)))
    if layout.frame_size is None:
        raise TableError(
            f"{where}: the mesh is in normalized image units (0-1; median face extent {extent:.3g}), and the "
            f"table has no FrameWidth/FrameHeight to convert it. Fix: keep py-feat's FrameWidth and FrameHeight "
            f"columns, or multiply x and z by the frame width and y by its height before `dvc add data`."
        )
    width, height = (block.values[c][normalized] for c in layout.frame_size)
    bad = ~(np.isfinite(width) & np.isfinite(height) & (width > 0) & (height > 0))
    if bad.any():
        raise TableError(
            f"{where}: FrameWidth/FrameHeight are missing or not positive on {int(bad.sum())} rows whose "
            f"mesh is in normalized units. Fix: fill them with the video's frame size in pixels."
        )
    scale = np.column_stack([width, height, width]).astype(np.float32)  # (m, 3)
    m = block.mesh[normalized].reshape(-1, 3, N_VERTICES) * scale[:, :, None]
    block.mesh[normalized] = m.reshape(len(m), -1)


def z_scale(block: Block, layout: pyfeat.Layout, mesh_units: str, where: str) -> tuple[str, np.ndarray | None]:
    """The unit z is written in and the factor (n,) that takes it to frame pixels (None: z is pixels already).

    ``mesh_units="detector"``: Detectorv2's chip units (``z * FaceRectWidth``) and MPDetector's 256-px crop units
    (``z * FaceRectWidth / 256``), :data:`Z_CROP`; a ``table`` or ``split`` source, and ``mesh_units="pixels"``,
    are pixels.

    Raises
    ------
    TableError
        The conversion needs FaceRectWidth and a row has none (or not > 0): naming the file, the row's video and
        frame, and the fix.
    """
    if mesh_units == "pixels" or layout.detector not in Z_CROP:
        return "pixels", None
    unit, divisor = Z_CROP[layout.detector]
    width_col = pyfeat.FACE_BOX_SIZE[0]
    if layout.box_size is None:
        raise TableError(
            f"{where}: column {width_col!r} is missing: {layout.detector}'s z is in its crop's units "
            f"and FaceRectWidth (the crop in pixels) converts it. Fix: keep py-feat's FaceRect columns, or set "
            f"data.mesh_units=pixels if z is already in pixels."
        )
    width = block.values[width_col]
    bad = ~(np.isfinite(width) & (width > 0))
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise TableError(
            f"{where}: column {width_col!r} is {width[row]} on a face row (frame {int(block.frame[row])} of video "
            f"{str(block.video[row])!r}; {int(bad.sum())} such rows): {layout.detector}'s z is in its crop's units "
            f"and FaceRectWidth converts it. Fix: keep py-feat's FaceRect values as detect wrote them, or set "
            f"data.mesh_units=pixels if z is already in pixels."
        )
    return unit, width / divisor


def convert_units(block: Block, layout: pyfeat.Layout, mesh_units: str, where: str) -> UnitStats:
    """The kept rows' meshes to frame pixels, in place (module docstring, step 3); what was done, measured.

    The face's depth/height is measured as written and, after a conversion, again on the mesh as it leaves. For a
    detector's export the ratio with z converted by its crop (the written ratio x the row's factor: z scales, y does
    not) is kept whether or not the conversion was made (``UnitStats.crop``: the guard's "with the conversion").
    """
    extents = shape_extents(block.mesh)  # (n, 3): the units' judgement and the face's proportions
    normalized = normalized_rows(block.mesh, rect_side(block, layout), extents[:, :2])
    if normalized.any() and not normalized.all():
        row = int(np.flatnonzero(normalized != normalized[0])[0])
        raise TableError(
            f"{where}: mixes meshes in pixels and in normalized image units (frame {int(block.frame[row])} of "
            f"video {str(block.video[row])!r} differs from the first). Fix: export every video the same way."
        )
    ratio = depth_height(extents)
    n = len(block)
    stats = UnitStats(detector=layout.detector, rows=n, before=ratio_hist(ratio))
    stats.after = stats.before
    if n and normalized[0]:
        to_pixels(block, layout, normalized, where)
        stats.after = ratio_hist(depth_height(shape_extents(block.mesh)))  # measured on the mesh as it leaves
        stats.xy = stats.z = "normalized"
        stats.rows_converted = stats.rows_normalized = n
        return stats
    if layout.detector in Z_CROP and layout.box_size is not None:
        width = block.values[pyfeat.FACE_BOX_SIZE[0]]
        stats.crop = ratio_hist(ratio * width / Z_CROP[layout.detector][1])
        stats.growth = growth_sums(extents[:, 2], extents[:, 1], frontal(block.values))
    if n:
        unit, factor = z_scale(block, layout, mesh_units, where)
        stats.xy, stats.z = "pixels", unit
        if factor is not None:
            block.mesh[:, 2 * N_VERTICES :] *= factor.astype(np.float32)[:, None]
            extents[:, 2:] = shape_extents(block.mesh, (2,))  # measured on the mesh as it leaves (its z)
            stats.after = ratio_hist(depth_height(extents))
            stats.rows_converted = stats.rows_z_converted = n
    return stats
