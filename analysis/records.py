"""The record a correction stage leaves: what it did, after which formula, with which values.

Every correction in :mod:`cdpr.analysis.corrections`, :mod:`cdpr.analysis.windage` and
:mod:`cdpr.analysis.flow` returns one :class:`CorrectionRecord` beside its arrays, so the reduction
core can list, per point, every correction applied, its source and its size.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class CorrectionRecord:
    """What one correction stage did.

    name: short stage name (``"zero_drift"``, ``"solid_blockage"``, ...).
    source: the formula's source (book, section, equation name).
    values: the parameters used and summary sizes (JSON-friendly: numbers, strings, lists).
    flags: named conditions the stage met (``"closing_zero_missing"``, ...), empty when none.
    """

    name: str
    source: str
    values: Mapping[str, Any] = field(default_factory=dict)
    flags: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """A JSON-friendly copy."""
        return {
            "name": self.name,
            "source": self.source,
            "values": dict(self.values),
            "flags": list(self.flags),
        }
