"""Exception types of the ShapeGen core.

Every error names the object or file it is about, so a user reading one line knows
which input to fix.
"""


class ShapeGenError(Exception):
    """Base class for every error the core raises on purpose."""


class SettingsError(ShapeGenError, ValueError):
    """A setting outside its allowed values. `option` names it (a field name, or a dotted
    path into nested settings); the message is "<prefix><option> <problem>"."""

    def __init__(self, option: str, problem: str, prefix: str = ""):
        super().__init__(f"{prefix}{option} {problem}")
        self.option = option
        self.problem = problem
        self.prefix = prefix


class MeshError(ShapeGenError, ValueError):
    """A mesh is unusable (empty, NaN coordinates, bad indices, ...)."""


class MeshFileError(ShapeGenError, ValueError):
    """A mesh file could not be read; the message starts with the file's path."""


class CollectionError(ShapeGenError, ValueError):
    """A collection of shapes is unusable as a whole (too few shapes, mixed sizes, ...)."""


class ModelFileError(ShapeGenError, ValueError):
    """A model / data file is corrupt, foreign, of another version or pickle-bearing."""


class Cancelled(ShapeGenError):
    """Raised inside long computations when the caller asked to cancel."""


class WorkerDied(ShapeGenError):
    """A worker process ended without a result (killed by a signal, e.g. the out-of-memory
    killer, or crashed); the message names the shape it was working on and what to try."""
