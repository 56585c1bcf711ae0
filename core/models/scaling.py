"""How the shape models' cost grows with the number of training shapes N, and the note a
fit gives when it will be slow.

PPCA: one SVD of the N × D landmark matrix, O(N D min(N, D)). Bayesian GP-LVM: M
inducing points (default 20), O(N M² Q + N² M) per iteration (bgplvm.py): it stays usable
for thousands of shapes. GP-LVM: the exact N × N kernel is factorised at every iteration,
O(N³) (gplvm.py), and encoding searches a latent per shape; above `CUBIC_NOTE_SHAPES`
shapes a fit says so and points to the Bayesian GP-LVM (the default model), which is the
sparse approximation this package offers instead of limiting N.

The training shapes' latents (saved with a model) are, for the GP-LVMs, a search per
shape like any new shape's (`encode`: about 0.1 s per shape, each scoring every training
point as a start: 107 s for 1000 shapes against a 31 s Bayesian GP-LVM fit); above
`ENCODE_SEARCH_SHAPES` shapes they are the fit's own latents instead (the GP-LVM's X, the
Bayesian GP-LVM's means of q(X)), which the searches start near and which cost nothing
(`LatentVariableModel.training_latents`).
"""

from __future__ import annotations

__all__ = ["CUBIC_NOTE_SHAPES", "ENCODE_SEARCH_SHAPES", "ScaleWarning", "size_note"]

#: GP-LVM fits of more shapes than this get a note (at 200 shapes a fit takes about a minute).
CUBIC_NOTE_SHAPES = 200
#: up to this many training shapes a GP-LVM's training latents are searched (`encode`),
#: above it they are the fit's own (module docstring)
ENCODE_SEARCH_SHAPES = 200


class ScaleWarning(UserWarning):
    """A fit whose cost grows steeply with the number of shapes was asked for many."""


def size_note(model_type: str, n_shapes: int) -> str | None:
    """A one-line note when fitting `model_type` to `n_shapes` shapes will be slow because its
    cost grows as N³, else None."""
    if model_type == "gplvm" and n_shapes > CUBIC_NOTE_SHAPES:
        return (f"gplvm on {n_shapes} shapes: the exact GP-LVM's cost grows as N³ (an N × N kernel factorised "
                f"at every iteration), so this fit may take long; the Bayesian GP-LVM (model bgplvm, the default, "
                f"with inducing points) grows linearly with N")
    return None
