"""Safe, versioned `.npz` files: the only on-disk format of ShapeGen's data and models.

* Never pickled: written from plain numeric / string arrays, read with
  ``allow_pickle=False`` (an object array in a file is refused, not executed).
* Tagged: every file holds ``format`` (e.g. "shapegen.prepared") and ``format_version``;
  a foreign file or another version is refused with a message naming the file.
* Validated: the reader checks the keys it needs, their dtypes kinds and shapes.
* Atomic: written to a temporary file in the same folder, then renamed, so a crash never
  leaves a half-written file where a good one was.
* Large arrays cheaply: a `Concatenation` (e.g. the vertices of every mesh of
  a model) is streamed into the file part by part, never built in memory, and arrays
  named in `stored` are written without compression (deflating a million-vertex mesh
  costs seconds and saves a third of its size). `np.load` reads both as usual.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path
from typing import Mapping

import numpy as np

from .errors import ModelFileError

__all__ = ["save_npz", "load_npz", "read_format", "validate_arrays", "ArraySpec", "Concatenation"]


class Concatenation:
    """The array `np.concatenate(parts)` (in `dtype`, default the parts' common type) as
    `save_npz` writes it: streamed part by part, never built in memory. A part is an array
    or an object with `shape`, `dtype` and `__array__` (e.g. an array kept on disk,
    core/meshes/spill.py), made an array only when it is written."""

    def __init__(self, parts, dtype=None):
        self.parts = [part if all(hasattr(part, key) for key in ("shape", "dtype", "__array__")) else np.asarray(part)
                      for part in parts]
        if not self.parts:
            raise ValueError("a Concatenation needs at least one part")
        self.dtype = np.result_type(*[part.dtype for part in self.parts]) if dtype is None else np.dtype(dtype)
        tails = {tuple(part.shape[1:]) for part in self.parts}
        if len(tails) != 1:
            raise ValueError(f"parts of different shapes {sorted(tails)} cannot be concatenated")
        self.shape = (sum(part.shape[0] for part in self.parts), *tails.pop())

    def __array__(self, dtype=None, copy=None):
        whole = np.concatenate([np.asarray(part) for part in self.parts]).astype(self.dtype, copy=False)
        return whole if dtype is None else whole.astype(dtype, copy=False)

    def write(self, handle) -> None:
        """The array as a .npy stream (header, then each part's bytes)."""
        header = {"descr": np.lib.format.dtype_to_descr(self.dtype), "fortran_order": False, "shape": self.shape}
        np.lib.format.write_array_header_1_0(handle, header)
        for part in self.parts:
            handle.write(np.ascontiguousarray(np.asarray(part), dtype=self.dtype).data)


class ArraySpec:
    """Expected dtype kind (numpy 'f', 'i', 'U', 'b', ... ; several allowed) and shape.

    Shape entries are ints, None (any length) or a name: equal names must be equal sizes
    across all arrays of one file (e.g. 'M' shapes, 'L' landmarks).
    """

    def __init__(self, kinds: str, shape: tuple, finite: bool = True):
        self.kinds = kinds
        self.shape = shape
        self.finite = finite  # refuse NaN / inf (False for e.g. partial shapes with NaN gaps)


def save_npz(path: str | os.PathLike, file_format: str, version: int, arrays: Mapping[str, np.ndarray],
             compress: bool = True, stored: tuple[str, ...] = ()) -> Path:
    """Write a tagged .npz atomically (see module docstring). `compress=False` for
    throwaway hand-offs where speed matters more than size; `stored`: keys written
    without compression even then. Values are arrays or `Concatenation`s."""
    path = Path(path)
    payload = {}
    for key, value in arrays.items():
        array = value if isinstance(value, Concatenation) else np.asarray(value)
        if array.dtype.kind == "O":
            raise TypeError(f"{path}: array {key!r} has dtype object; refusing to write a pickle")
        payload[key] = array
    payload["format"] = np.asarray(file_format)
    payload["format_version"] = np.asarray(version, dtype=np.int64)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as handle, zipfile.ZipFile(handle, mode="w", allowZip64=True) as archive:
            for key, array in payload.items():
                member = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                member.compress_type = zipfile.ZIP_DEFLATED if compress and key not in stored else zipfile.ZIP_STORED
                with archive.open(member, "w", force_zip64=True) as out:
                    if isinstance(array, Concatenation):
                        array.write(out)
                    else:
                        np.lib.format.write_array(out, array, allow_pickle=False)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _read_arrays(path: Path, keys: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an .npz file (only `keys`, where present, if given), read without
    pickle and with the file closed again; ModelFileError starting with the path."""
    label = str(path)
    if not path.is_file():
        raise ModelFileError(f"{label}: no such file")
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            # a bare .npy array: np.load returns the array itself
            raise ModelFileError(f"{label}: is a single .npy array, not a ShapeGen .npz file")
        with data:
            arrays = {}
            for key in data.files if keys is None else [k for k in keys if k in data.files]:
                try:
                    arrays[key] = data[key]
                except ValueError as exc:
                    if "pickle" in str(exc).lower():
                        raise ModelFileError(
                            f"{label}: array {key!r} needs pickle to load; refused (ShapeGen files never contain pickles)"
                        ) from None
                    raise
    except ModelFileError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, zlib.error) as exc:
        raise ModelFileError(f"{label}: not a readable .npz file ({type(exc).__name__}: {exc})") from None
    return arrays


def read_format(path: str | os.PathLike) -> str:
    """The format tag of a ShapeGen .npz (e.g. "shapegen.prepared"), read without loading
    the other arrays, so a caller can tell which kind of file it was given."""
    path = Path(path)
    tag = _read_arrays(path, ("format",)).get("format")
    if tag is None or tag.shape != () or tag.dtype.kind != "U":
        raise ModelFileError(f"{path}: not a ShapeGen file (no format tag)")
    return str(tag)


def load_npz(
    path: str | os.PathLike,
    file_format: str,
    version: int | tuple[int, ...],
    spec: Mapping[str, ArraySpec],
) -> dict[str, np.ndarray]:
    """Read and validate a file written by `save_npz` (`version`: the one version read, or
    every version read, newest last). Raises ModelFileError on anything unexpected; the
    message starts with the path."""
    path = Path(path)
    label = str(path)
    arrays = _read_arrays(path)
    if "format" not in arrays or "format_version" not in arrays:
        raise ModelFileError(f"{label}: not a ShapeGen file (no format tag); expected {file_format!r}")
    tag, tag_version = arrays.pop("format"), arrays.pop("format_version")
    found = str(tag)
    if tag.shape != () or tag.dtype.kind != "U" or found != file_format:
        raise ModelFileError(f"{label}: is a {found!r} file, expected {file_format!r}")
    if tag_version.shape != () or tag_version.dtype.kind not in "iu":
        raise ModelFileError(f"{label}: format_version {str(tag_version)!r} is not an integer version")
    found_version = int(tag_version)
    versions = (version,) if isinstance(version, int) else tuple(version)
    if found_version not in versions:
        raise ModelFileError(
            f"{label}: {file_format} version {found_version} is not supported (this ShapeGen reads version "
            f"{' or '.join(map(str, versions))})"
        )
    validate_arrays(arrays, spec, label)
    return arrays


def validate_arrays(arrays: Mapping[str, np.ndarray], spec: Mapping[str, ArraySpec], label: str) -> None:
    """Check that `arrays` holds every key of `spec` with the right dtype kind, shape and
    (where asked) finite values; raise ModelFileError starting with `label` otherwise."""
    sizes: dict[str, int] = {}
    defined_by: dict[str, str] = {}
    for key, expected in spec.items():
        if key not in arrays:
            raise ModelFileError(f"{label}: missing array {key!r}")
        array = np.asarray(arrays[key])
        if array.dtype.kind == "O":
            raise ModelFileError(f"{label}: array {key!r} holds Python objects; refused")
        if array.dtype.kind not in expected.kinds:
            raise ModelFileError(
                f"{label}: array {key!r} has dtype {array.dtype}, expected kind {expected.kinds!r}"
            )
        if len(array.shape) != len(expected.shape):
            raise ModelFileError(
                f"{label}: array {key!r} has shape {array.shape}, expected {len(expected.shape)} dimensions"
            )
        for axis, (got, want) in enumerate(zip(array.shape, expected.shape)):
            if want is None:
                continue
            if isinstance(want, int):
                if got != want:
                    raise ModelFileError(f"{label}: array {key!r} has shape {array.shape}, axis {axis} must be {want}")
            else:
                defined_by.setdefault(want, key)
                if sizes.setdefault(want, got) != got:
                    raise ModelFileError(
                        f"{label}: array {key!r} has shape {array.shape}: its {want} = {got} disagrees "
                        f"with {want} = {sizes[want]} of array {defined_by[want]!r}"
                    )
        if expected.finite and array.dtype.kind == "f" and not np.isfinite(array).all():
            raise ModelFileError(f"{label}: array {key!r} contains NaN or infinite values")
