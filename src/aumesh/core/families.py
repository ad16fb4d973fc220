"""The input families beside the AUs: MediaPipe's 52 blendshapes and py-feat's 7 emotions (issue 46).

One place for each family's names and order, and for the names py-feat's two detectors write them under. The lists
are py-feat 2.1.5's (names and order only, no code; docs/families.md says how they were read and checked):

* blendshapes: ``feat/utils/__init__.py`` ``MP_BLENDSHAPE_NAMES``; both detectors write them under these names, in
  this order (``MPDetector.forward``: ``pd.DataFrame(bs_array, columns=MP_BLENDSHAPE_NAMES)``;
  ``Detectorv2.forward``: ``pd.DataFrame(out.blendshapes, columns=MP_BLENDSHAPE_NAMES)``, values in [0, 1]), and
  ``PLSFeatMeshModel`` (``feat/plotting.py``, ``_FEAT_MESH_SPECS["blendshape"]``) requires an NPZ's
  ``feature_columns`` to equal them;
* emotions: ``feat/utils/__init__.py`` ``FEAT_EMOTION_COLUMNS`` (anger .. neutral), the order
  ``_FEAT_MESH_SPECS["emotion"]`` requires of an NPZ's ``feature_columns`` and the names ``MPDetector.forward``
  writes (softmax probabilities of its 7 classes). ``Detectorv2.forward`` writes ``out.emotion_names``: the
  checkpoint's class order ``feat/multitask/__init__.py`` ``EMOTION_NAMES_V24`` (Neutral, Happy, Sad, Surprise, Fear,
  Disgust, Anger; a softmax), or ``EMOTION_NAMES`` with an eighth ``Contempt`` for a v2.3 checkpoint, which has no
  place in the family and is left out. The two orders differ: ``emotion_to_mesh_pls_v5`` shipped with Detectorv2's
  columns under ``FEAT_EMOTION_COLUMNS`` labels (the note above ``_FEAT_MESH_SPECS``), so columns are always mapped
  by name (:func:`family_columns`), never by position.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from aumesh.core.errors import TableError
from aumesh.core.schema import AU_COLUMNS, feature_columns

# feat/utils/__init__.py MP_BLENDSHAPE_NAMES (py-feat 2.1.5): MediaPipe's ARKit-style names, its output order.
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

# feat/utils/__init__.py FEAT_EMOTION_COLUMNS (py-feat 2.1.5): the family's order, MPDetector's column names.
EMOTION_COLUMNS: tuple[str, ...] = ("anger", "disgust", "fear", "happiness", "sadness", "surprise", "neutral")

# feat/multitask/__init__.py EMOTION_NAMES_V24: what Detectorv2 writes (its checkpoint's order, capitalised).
EMOTION_COLUMNS_V2: tuple[str, ...] = ("Neutral", "Happy", "Sad", "Surprise", "Fear", "Disgust", "Anger")

#: Each detector's emotion column -> the family's name (by meaning; MPDetector's names are the family's own).
EMOTION_NAME_MAP: dict[str, str] = {
    **{name: name for name in EMOTION_COLUMNS},
    "Neutral": "neutral",
    "Happy": "happiness",
    "Sad": "sadness",
    "Surprise": "surprise",
    "Fear": "fear",
    "Disgust": "disgust",
    "Anger": "anger",
}

#: The families: name -> the model's input columns, in the order of py-feat's ``feature_columns``.
FAMILIES: dict[str, tuple[str, ...]] = {
    "au": AU_COLUMNS,
    "blendshapes": BLENDSHAPE_COLUMNS,
    "emotions": EMOTION_COLUMNS,
}

#: Each detector's header name -> the family's name, per family (the AU and blendshape names are written as is).
NAME_MAPS: dict[str, Mapping[str, str]] = {
    "au": {name: name for name in AU_COLUMNS},
    "blendshapes": {name: name for name in BLENDSHAPE_COLUMNS},
    "emotions": EMOTION_NAME_MAP,
}

#: py-feat's ``feature`` key and NPZ stem for the non-AU families (``feat/plotting.py`` ``_FEAT_MESH_SPECS``:
#: ``load_blendshape_face_mesh_model`` reads ``bs_to_mesh_pls_<version>.npz``, the emotion loader
#: ``emotion_to_mesh_pls_<version>.npz``).
PYFEAT_FEATURE: dict[str, tuple[str, str]] = {
    "blendshapes": ("blendshape", "bs_to_mesh_pls"),
    "emotions": ("emotion", "emotion_to_mesh_pls"),
}


#: The feature sets (the ``features`` config group, ``conf/features/<name>.yaml``): name -> (family, pose covariates,
#: pose x input interactions). One name per design, so no combination of switches can contradict another; the AU
#: names are the card's (``au_pose_interactions`` is its v2 design), each family has the same three designs
#: (py-feat's blendshape and emotion models are ``<family>_pose_interactions``: ``PLSFeatMeshModel``'s docstring,
#: "the absorbed feature x pose interaction terms").
FEATURE_SETS: dict[str, tuple[str, bool, bool]] = {
    f"{family}{suffix}": (family, pose, interactions)
    for family in ("au", "blendshapes", "emotions")
    for suffix, pose, interactions in (("", False, False), ("_pose", True, False), ("_pose_interactions", True, True))
}


def feature_set_columns(name: str) -> list[str]:
    """Design-matrix column names of a feature set: ``[inputs | pose | pose x input]`` (e.g. 211 columns for
    ``blendshapes_pose_interactions``: 52 + 3 + 156)."""
    if name not in FEATURE_SETS:
        raise ValueError(f"features={name!r}: use one of {', '.join(FEATURE_SETS)}")
    family, pose, interactions = FEATURE_SETS[name]
    return feature_columns(pose, interactions, FAMILIES[family])


def check_family(family: str) -> tuple[str, ...]:
    """The columns of ``family`` (``au``, ``blendshapes``, ``emotions``); a one-line error for any other name."""
    if family not in FAMILIES:
        raise ValueError(f"family={family!r}: use one of {', '.join(FAMILIES)}")
    return FAMILIES[family]


def family_columns(header: Iterable[str], family: str, source: str = "the table") -> dict[str, str]:
    """Which header column holds each of ``family``'s inputs, matched by name (never by position).

    Parameters
    ----------
    header : iterable of str
        A table's column names, in any order; columns outside the family (e.g. Detectorv2's ``Contempt``) are
        ignored.
    family : {"au", "blendshapes", "emotions"}
    source : str
        The file the header comes from, for the error message.

    Returns
    -------
    dict
        Family name -> header column, in the family's order (``FAMILIES[family]``), e.g. for a Detectorv2 table
        ``{"anger": "Anger", ..., "happiness": "Happy", ..., "neutral": "Neutral"}``.

    Raises
    ------
    TableError
        One line naming ``source`` and the first family input the header lacks (under either detector's name), or
        two header columns that name the same input (e.g. ``happiness`` and ``Happy``).
    """
    columns = check_family(family)
    names = NAME_MAPS[family]
    found: dict[str, str] = {}
    for col in header:
        key = names.get(str(col))
        if key is None:
            continue
        if key in found:
            raise TableError(
                f"{source}: columns {found[key]!r} and {col!r} both hold {family} input {key!r}. "
                f"Fix: keep one of them (MPDetector writes {key!r}, Detectorv2 its capitalised name)"
            )
        found[key] = str(col)
    for key in columns:
        if key not in found:
            aliases = sorted(h for h, k in names.items() if k == key)
            raise TableError(
                f"{source}: no column for {family} input {key!r} (expected one of {', '.join(map(repr, aliases))}). "
                f"Fix: export the table with py-feat's MPDetector or Detectorv2, which write all "
                f"{len(columns)} {family} columns"
            )
    return {key: found[key] for key in columns}


#: The families ingest and prepare carry beside the AUs when the tables hold them (the AUs are always required).
CARRIED_FAMILIES: tuple[str, ...] = ("blendshapes", "emotions")


def header_families(header: Iterable[str], source: str = "the table") -> dict[str, dict[str, str]]:
    """The carried families (:data:`CARRIED_FAMILIES`) a table's header holds whole, each mapped by name.

    A family none of whose names (under either detector's spelling) is in the header is absent: left out, nothing
    filled in. A family some but not all of whose inputs are there is a half-written export, refused.

    Parameters
    ----------
    header : iterable of str
        The table's column names, any order (Detectorv2's ``Contempt`` and every other column ignored).
    source : str
        The file, for the error message.

    Returns
    -------
    dict
        ``{family: {family name: header column}}`` (:func:`family_columns`) for the families held whole, in
        :data:`CARRIED_FAMILIES` order.

    Raises
    ------
    TableError
        One line naming ``source``, the family, the first input it lacks and the fix (as :func:`family_columns`:
        also two columns holding one input).
    """
    names = [str(c) for c in header]
    out: dict[str, dict[str, str]] = {}
    for family in CARRIED_FAMILIES:
        held = [c for c in names if c in NAME_MAPS[family]]
        if not held:
            continue
        columns = FAMILIES[family]
        mapped = {NAME_MAPS[family][c] for c in held}
        missing = [key for key in columns if key not in mapped]
        if missing:
            aliases = sorted(h for h, k in NAME_MAPS[family].items() if k == missing[0])
            raise TableError(
                f"{source}: holds {len(mapped)} of the {len(columns)} {family} columns but not {missing[0]!r} "
                f"(expected one of {', '.join(map(repr, aliases))}"
                + (f"; {len(missing) - 1} more missing" if len(missing) > 1 else "")
                + f"). Fix: export the table again with py-feat's MPDetector or Detectorv2 (they write all "
                f"{len(columns)}), or drop every {family} column to train without them"
            )
        out[family] = family_columns(names, family, source)
    return out
