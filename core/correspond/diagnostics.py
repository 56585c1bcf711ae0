"""How a correspondence came about (`CorrespondenceDiagnostics`): the optional record beside
a `Correspondence`, for people, the command's summary line and benchmarks. Nothing that
uses the landmarks needs it: a correspondence without it (`diagnostics=None`) models,
samples and saves as one with it.

What it records, each as optional arrays of the correspondence file (files written before
a record lack it and load with it empty):
* `iterations`: each shape's ICP iterations in the last round;
* the start (start.py, starting.py): `start` ("closest" or "spectral", what
  `initialisation="auto"` chose; "" in files written before, which took the start their
  settings name), `start_reason`, and `shape_starts`, the start each shape's registration
  took ("spectral", "closest", or "template" for the template's own shape);
* `pose_notes`: per shape, how posing.py posed it or why not (the poses themselves are
  part of the correspondence: they make its model frame);
* feature matches (features.py, matching.py): `between_shares`, each shape's share of
  `feature_between` (0 when its turning lines disagree with the template's; empty when
  not compared); `feature_fit_worse`, the shapes feature matches fitted worse than closest
  points in the first round (empty when not checked); `plain_shares`, each shape's share of
  template points matched plainly because their regions merge on it (empty when not
  checked);
* `refinement` and `refinement_trace`: files written while groupwise refinement after
  NICP was an option record "population" and its objective trace (E, compactness, spread
  per accepted step); they still load. Files written since hold neither, as files from
  before the option did ("none", an empty trace).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..base.errors import ModelFileError
from ..base.npzfile import ArraySpec, validate_arrays

__all__ = ["CorrespondenceDiagnostics", "DIAGNOSTIC_ARRAYS", "RECORDED_REFINEMENTS"]

#: the refinements a correspondence file may record ("population": written while that
#: refinement was an option)
RECORDED_REFINEMENTS = ("population", "none")


@dataclass
class CorrespondenceDiagnostics:
    """How a correspondence came about (module docstring); every per-shape array has one
    entry per shape of the correspondence, or none (not recorded)."""

    iterations: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (M,) or (0,)
    start: str = ""  # the start registration took ("closest" or "spectral"; "": not recorded)
    start_reason: str = ""  # why ("asked for", or the evidence `initialisation="auto"` read)
    shape_starts: list[str] = field(default_factory=list)  # per shape, its start ([]: not recorded)
    pose_notes: list[str] = field(default_factory=list)  # per shape, how it was posed or why not ([]: not recorded)
    between_shares: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,) or (0,): not compared
    feature_fit_worse: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # (M,) or (0,): not checked
    plain_shares: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,) or (0,): not checked
    refinement: str = "none"  # "population" only in files written while that refinement was an option
    refinement_trace: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (T, 3) E, compactness, spread

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The record as arrays of a correspondence file (the refinement only when one ran)."""
        arrays = {
            "iterations": np.asarray(self.iterations).astype(np.int64).reshape(-1),
            "between_shares": np.asarray(self.between_shares, dtype=np.float64).reshape(-1),
            "feature_fit_worse": np.asarray(self.feature_fit_worse, dtype=bool).reshape(-1),
            "plain_shares": np.asarray(self.plain_shares, dtype=np.float64).reshape(-1),
            "start": np.asarray(self.start, dtype=str),
            "start_reason": np.asarray(self.start_reason, dtype=str),
            "shape_starts": np.asarray(self.shape_starts, dtype=str).reshape(-1),
            "pose_notes": np.asarray(self.pose_notes, dtype=str).reshape(-1),
        }
        if self.refinement != "none" or len(self.refinement_trace):
            arrays["refinement"] = np.asarray(self.refinement, dtype=str)
            arrays["refinement_trace"] = np.asarray(self.refinement_trace, dtype=np.float64).reshape(-1, 3)
        return arrays

    @classmethod
    def from_arrays(cls, a: dict, shapes: int, label: str) -> "CorrespondenceDiagnostics | None":
        """The record of a correspondence file's arrays `a` of `shapes` shapes (None when the
        file holds none of it); a malformed one is a ModelFileError starting with `label`."""
        if not any(key in a for key in DIAGNOSTIC_ARRAYS):
            return None
        iterations = np.asarray(a["iterations"]) if "iterations" in a else np.zeros(0, dtype=np.int64)
        validate_arrays({"iterations": iterations}, {"iterations": ArraySpec("i", ("S",))}, label)
        if len(iterations) not in (0, shapes):
            raise ModelFileError(f"{label}: iterations must be empty or one count per shape ({shapes}), "
                                 f"got {len(iterations)}")
        refinement = str(a["refinement"]) if "refinement" in a else "none"
        trace = np.asarray(a["refinement_trace"]) if "refinement_trace" in a else np.zeros((0, 3))
        validate_arrays({"refinement": np.asarray(refinement), "refinement_trace": trace}, _REFINEMENT_SPEC, label)
        if refinement not in RECORDED_REFINEMENTS:
            raise ModelFileError(f"{label}: unknown refinement {refinement!r} "
                                 f"(expected {' or '.join(RECORDED_REFINEMENTS)})")
        worse = np.asarray(a["feature_fit_worse"]) if "feature_fit_worse" in a else np.zeros(0, dtype=bool)
        validate_arrays({"feature_fit_worse": worse}, {"feature_fit_worse": ArraySpec("b", ("S",))}, label)
        if len(worse) not in (0, shapes):
            raise ModelFileError(f"{label}: feature_fit_worse must be empty or one flag per shape "
                                 f"({shapes}), got {len(worse)}")
        return cls(iterations=iterations, start=_optional_text(a, "start", label),
                   start_reason=_optional_text(a, "start_reason", label),
                   shape_starts=_optional_texts(a, "shape_starts", shapes, label),
                   pose_notes=_optional_texts(a, "pose_notes", shapes, label),
                   between_shares=_optional_shares(a, "between_shares", shapes, label), feature_fit_worse=worse,
                   plain_shares=_optional_shares(a, "plain_shares", shapes, label), refinement=refinement,
                   refinement_trace=trace)


def _optional_shares(a: dict, key: str, shapes: int, label: str) -> np.ndarray:
    """An optional per-shape share array (`between_shares`, `plain_shares`): empty when
    absent; else one share in [0, 1] per shape."""
    shares = np.asarray(a[key]) if key in a else np.zeros(0)
    validate_arrays({key: shares}, {key: ArraySpec("f", ("S",))}, label)
    if len(shares) not in (0, shapes) or not np.all((shares >= 0) & (shares <= 1)):
        raise ModelFileError(f"{label}: {key} must be empty or one share in [0, 1] per shape "
                             f"({shapes}), got {len(shares)} values")
    return shares


def _optional_text(a: dict, key: str, label: str) -> str:
    """An optional text ("" when absent: files written before it)."""
    if key not in a:
        return ""
    validate_arrays({key: np.asarray(a[key])}, {key: ArraySpec("U", ())}, label)
    return str(a[key])


def _optional_texts(a: dict, key: str, shapes: int, label: str) -> list[str]:
    """An optional text per shape (`shape_starts`, `pose_notes`): none when absent."""
    texts = np.asarray(a[key]) if key in a else np.zeros(0, dtype=str)
    validate_arrays({key: texts}, {key: ArraySpec("U", ("S",))}, label)
    if len(texts) not in (0, shapes):
        raise ModelFileError(f"{label}: {key} must be empty or one text per shape ({shapes}), got {len(texts)}")
    return texts.tolist()


#: the optional refinement record (files written while refinement was an option)
_REFINEMENT_SPEC = {"refinement": ArraySpec("U", ()), "refinement_trace": ArraySpec("f", ("T", 3))}
#: every array of the record (a file holding none of them has no record)
DIAGNOSTIC_ARRAYS = ("iterations", "start", "start_reason", "shape_starts", "pose_notes", "between_shares",
                     "feature_fit_worse", "plain_shares", "refinement", "refinement_trace")
