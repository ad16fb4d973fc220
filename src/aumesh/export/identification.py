"""Which AU fields a release says are unidentified under detector noise: read once from its NPZ, said the same way by
the viewer, the glb and the card's figures (issue 43).

The evaluate stage's identification screen (:func:`aumesh.model.eiv.identification_screen`, docs/method.md eq. 6)
writes four keys into the release NPZ (:meth:`aumesh.model.eiv.IdentificationScreen.release_arrays`):

* ``au_identification_sigma_star`` (20,) float64, ``AU_COLUMNS`` order: the critical isotropic noise sd at which the
  floored corrected fit turns the AU's field by more than 60 degrees; NaN when it does not turn within the grid;
* ``au_identification_flagged`` (20,) bool: ``sigma_star < flag_below``;
* ``au_identification_partner`` (20,) str: each AU's dominant partner (``argmax_j |r_kj| ||B_j|| / ||B_k||``);
* ``au_identification_flag_below`` () float64: the threshold (``model.identification.flag_below``, 0.10 by default).

A flagged AU ``k`` with partner ``j`` cannot be separated from ``j`` by the data; their *partner group* (both AUs moved
by the same amount: the field ``B_k + B_j``) is identified when its members are not. :func:`release_identification`
reads the keys (None for a release without them: old releases show no flags), :class:`AuIdentification` says what a
flagged AU's slider, panel or morph target shows. The screen is a screen, not a proof (card, "AU identification under
detector noise").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from aumesh.core.schema import AU_COLUMNS
from aumesh.model.eiv import partner_group

KEYS = (
    "au_identification_sigma_star",
    "au_identification_flagged",
    "au_identification_partner",
    "au_identification_flag_below",
)
SCREEN_NOTE = (
    "AU identification screen (docs/method.md eq. 6): sigma_star is the isotropic detector-noise sd at which the "
    "floored corrected fit turns the AU's field by more than 60 degrees (null: not within the screen's grid); an AU "
    "is flagged when sigma_star < flag_below: the data cannot separate it from its partner, whose group (both AUs "
    "moved by the same amount) is identified. A screen, not a proof."
)


@dataclass(frozen=True)
class AuIdentification:
    """The screen's result as a release records it, ``AU_COLUMNS`` order.

    Attributes
    ----------
    sigma_star : dict of str -> float or None
        AU -> sigma* (None: the field did not turn within the screen's grid).
    flagged : tuple of str
        The flagged AUs, ``AU_COLUMNS`` order.
    partner : dict of str -> str
        AU -> its dominant partner AU.
    flag_below : float
        The threshold: an AU is flagged when ``sigma_star < flag_below``.
    """

    sigma_star: dict[str, float | None]
    flagged: tuple[str, ...]
    partner: dict[str, str]
    flag_below: float

    def group(self, au: str) -> tuple[str, str]:
        """``au`` and its partner, sorted (``("AU09", "AU10")``): the partner group's members."""
        return tuple(sorted((au, self.partner[au])))  # type: ignore[return-value]

    def group_name(self, au: str) -> str:
        """``"AU09+AU10"``: the name the card's ``au_identification`` gives the group
        (:func:`aumesh.model.eiv.partner_group`)."""
        return partner_group(au, self.partner[au])

    def groups(self) -> dict[str, tuple[str, str]]:
        """The flagged AUs' partner groups, each once (two AUs flagged with each other share one): name -> members."""
        return {self.group_name(au): self.group(au) for au in self.flagged}

    def sigma_text(self, au: str) -> str:
        value = self.sigma_star[au]
        return "beyond the screen's grid" if value is None else f"{value:.3f}"

    def reason(self, au: str) -> str:
        """The one-line reason a flagged AU's slider is greyed, e.g. ``"AU10: not identified under detector noise
        (sigma* = 0.060 < 0.10); its partner AU09 moves with it: use AU09+AU10"``."""
        return (
            f"{au}: not identified under detector noise (sigma* = {self.sigma_text(au)} < {self.flag_below:g}); "
            f"its partner {self.partner[au]} moves with it: use {self.group_name(au)}"
        )

    def short_reason(self, au: str) -> str:
        """The reason in the width of the viewer's panel, shown under the greyed slider with the group's slider below
        it: ``"not identified under detector noise (σ* 0.060 < 0.1)"``."""
        return f"not identified under detector noise (\u03c3* {self.sigma_text(au)} < {self.flag_below:g})"

    def label(self, au: str) -> str:
        """The short mark on a flagged AU's figure panel: ``"unidentified (σ* 0.060): use AU09+AU10"``."""
        return f"unidentified (\u03c3* {self.sigma_text(au)}): use {self.group_name(au)}"

    def to_json(self) -> dict[str, Any]:
        """Plain JSON (no NaN): ``{"flag_below", "aus": {AU: {"sigma_star", "flagged", "partner", "group"}},
        "flagged": [...], "groups": {name: [AU, AU]}, "note"}``: the glb's ``asset.extras["au_identification"]``."""
        return {
            "flag_below": self.flag_below,
            "aus": {
                au: {
                    "sigma_star": self.sigma_star[au],
                    "flagged": au in self.flagged,
                    "partner": self.partner[au],
                    "group": self.group_name(au),
                }
                for au in AU_COLUMNS
            },
            "flagged": list(self.flagged),
            "groups": {name: list(members) for name, members in self.groups().items()},
            "note": SCREEN_NOTE,
        }


def release_identification(npz: Mapping[str, Any], where: str = "release") -> AuIdentification | None:
    """The identification a release records (module docstring), None when it records none (a release from before
    issue 43: nothing is flagged).

    Parameters
    ----------
    npz : mapping
        Release arrays.
    where : str
        The file's name, for the error.

    Raises
    ------
    aumesh.model.release_check.ReleaseError
        Some of the four keys but not all, or one of the wrong shape, dtype or value: naming the key and the fix.
    """
    from aumesh.model.release_check import ReleaseError

    present = [k for k in KEYS if k in npz]
    if not present:
        return None
    fix = "Fix: rebuild the release (`dvc repro`), which writes all four au_identification_* keys."
    if len(present) < len(KEYS):
        missing = [k for k in KEYS if k not in npz]
        raise ReleaseError(f"{where}: has {present} but not {missing}. {fix}")
    n = len(AU_COLUMNS)
    sigma = np.asarray(npz["au_identification_sigma_star"])
    flagged = np.asarray(npz["au_identification_flagged"])
    partner = np.asarray(npz["au_identification_partner"])
    flag_below = np.asarray(npz["au_identification_flag_below"])
    for key, arr, kind, shape in (
        ("au_identification_sigma_star", sigma, "f", (n,)),
        ("au_identification_flagged", flagged, "b", (n,)),
        ("au_identification_partner", partner, "U", (n,)),
        ("au_identification_flag_below", flag_below, "f", ()),
    ):
        if arr.shape != shape or arr.dtype.kind != kind:
            raise ReleaseError(
                f"{where}: '{key}' is {arr.dtype} {arr.shape}, expected dtype kind '{kind}' of shape {shape} "
                f"(AU_COLUMNS order). {fix}"
            )
    names = [str(p) for p in partner.tolist()]
    unknown = sorted({p for p in names if p not in AU_COLUMNS})
    if unknown:
        raise ReleaseError(
            f"{where}: 'au_identification_partner' names {unknown}, not AUs of {list(AU_COLUMNS)}. {fix}"
        )
    return AuIdentification(
        sigma_star={au: None if np.isnan(s) else float(s) for au, s in zip(AU_COLUMNS, sigma.tolist(), strict=True)},
        flagged=tuple(au for au, f in zip(AU_COLUMNS, flagged.tolist(), strict=True) if f),
        partner=dict(zip(AU_COLUMNS, names, strict=True)),
        flag_below=float(flag_below),
    )


__all__ = ["KEYS", "SCREEN_NOTE", "AuIdentification", "release_identification"]
