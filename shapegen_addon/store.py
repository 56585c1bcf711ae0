"""The fitted model inside the .blend: packed into a Text datablock.

Choice: the model file (the core's versioned, pickle-free "shapegen.model" .npz, already
zip-compressed) is stored byte for byte in a custom property (`shapegen_model_npz`, a
bytes ID property) of a Text datablock named "<name>.shapegen", referenced by
`scene.shapegen.model_text`; the Text's body is a short human-readable description.
Why packed rather than a file beside the .blend:

* one file travels: copying, e-mailing, linking or appending the .blend keeps the model;
  a relative path breaks as soon as the .blend moves alone, and an unsaved file has no
  folder to be relative to at the time the fit finishes;
* it is plain, visible data (Text editor, Blender File view), saved with a fake user,
  extractable without the add-on (`open("m.npz", "wb").write(text["shapegen_model_npz"])`),
  never executed;
* cost: the compressed model size in the .blend; storing or reading 15 MB takes < 10 ms
  (measured headless). The first version kept base64 in the Text's body: 4/3 the size and
  ~0.2 s of main-thread work per 20 MB (encode + `Text.from_string`), too slow for the
  "apply the result without stalling the UI" budget.

Decoded models are cached per process, keyed by a uuid stored on the Text
(`shapegen_model_id`), so the cache survives undo (which rebuilds Blender's data) and a
reopened file restores it (handlers.py, at load_post; or lazily in `get_model`). This
module knows only the Text datablock: what follows a new model (the latent sliders) is
the caller's business.
"""

from __future__ import annotations

import tempfile
import uuid
from pathlib import Path

import bpy
import numpy as np

from ..core.base.errors import ModelFileError, ShapeGenError
from ..core.app.shape_model import GenerativeShapeModel
from .keys import (LATENT_DIM_KEY, MATCHING_KEY, MODEL_FILE_KEY, MODEL_ID_KEY, MODEL_NAME_KEY, MODEL_TYPE_KEY,
                   N_LANDMARKS_KEY, N_SHAPES_KEY, OUTLIERS_KEY, RESIDUAL_MEDIAN_KEY, TEMPLATE_KEY)

__all__ = ["NeedsModel", "pack_model", "get_model", "require_model", "model_id", "model_name", "model_bytes",
           "read_model_file", "store_fitted_model", "forget_cache"]


class NeedsModel:
    """Operator mixin: poll() is False, with the reason, while the scene has no model."""

    @classmethod
    def poll(cls, context):
        if context.scene.shapegen.model_text is None:
            cls.poll_message_set("No fitted model in this scene: fit or load one first")
            return False
        return True


_CACHE: dict[str, GenerativeShapeModel] = {}


def model_id(scene: bpy.types.Scene) -> str:
    text = scene.shapegen.model_text
    return "" if text is None else str(text.get(MODEL_ID_KEY, ""))


def model_name(scene: bpy.types.Scene) -> str:
    text = scene.shapegen.model_text
    return "" if text is None else str(text.get(MODEL_NAME_KEY, text.name))


def pack_model(path: str | Path, name: str, model: GenerativeShapeModel | None = None,
               data: bytes | None = None) -> bpy.types.Text:
    """A new Text datablock holding the model file at `path` (bytes unchanged; `data`:
    those bytes, when already read)."""
    if data is None:
        data = Path(path).read_bytes()
    text = bpy.data.texts.new(f"{name}.shapegen")
    lines = [f"ShapeGen model '{name}'"]
    if model is not None:
        lines.append(f"{model.model_type}, {model.latent_dim} latent dimensions, {len(model.names)} training "
                     f"shapes, {model.n_landmarks} landmarks")
    lines += [
        "",
        f"The model file ({len(data) / 1e6:.1f} MB, a 'shapegen.model' .npz: numpy arrays, no pickles)",
        f"is stored in this Text's custom property '{MODEL_FILE_KEY}'. To extract it without",
        "the add-on, in Blender's Python console:",
        f"    open('model.npz', 'wb').write(bpy.data.texts['{text.name}']['{MODEL_FILE_KEY}'])",
        "With the add-on: ShapeGen > Model > Export Model. Editing this text changes nothing.",
    ]
    text.from_string("\n".join(lines) + "\n")
    text.use_fake_user = True
    text[MODEL_FILE_KEY] = bytes(data)
    text[MODEL_ID_KEY] = uuid.uuid4().hex
    text[MODEL_NAME_KEY] = name
    if model is not None:
        _CACHE[text[MODEL_ID_KEY]] = model
        describe(text, model)
    return text


def describe(text: bpy.types.Text, model: GenerativeShapeModel) -> None:
    """Summary custom properties on the Text, so panels can draw without decoding."""
    corr = model.correspondence
    text[MODEL_TYPE_KEY] = model.model_type
    text[LATENT_DIM_KEY] = int(model.latent_dim)
    text[N_SHAPES_KEY] = len(model.names)
    text[N_LANDMARKS_KEY] = int(model.n_landmarks)
    text[TEMPLATE_KEY] = str(corr.template_name)
    text[RESIDUAL_MEDIAN_KEY] = float(np.median(corr.residuals))
    text[MATCHING_KEY] = corr.matching_summary()
    text[OUTLIERS_KEY] = [f"{n}: {r}" if r else n for n, r, bad in
                                 zip(corr.names, corr.outlier_reasons, corr.outliers) if bad]


def model_bytes(text: bpy.types.Text) -> bytes:
    """The model file's bytes packed in `text`."""
    data = text.get(MODEL_FILE_KEY)
    if not isinstance(data, bytes) or not data:
        raise ModelFileError(f"Text '{text.name}' holds no packed ShapeGen model (property '{MODEL_FILE_KEY}')")
    return data


def _unpack(text: bpy.types.Text) -> GenerativeShapeModel:
    with tempfile.TemporaryDirectory(prefix="shapegen-model-") as folder:
        path = Path(folder) / f"{bpy.path.clean_name(text.name)}.npz"
        path.write_bytes(model_bytes(text))
        try:
            return GenerativeShapeModel.load(path)
        except ModelFileError as exc:
            raise ModelFileError(str(exc).replace(str(path), f"Text '{text.name}'")) from None


def get_model(scene: bpy.types.Scene) -> GenerativeShapeModel | None:
    """The scene's fitted model (decoded once per process), or None when there is none.
    Raises ModelFileError when the packed model is damaged."""
    text = scene.shapegen.model_text
    if text is None:
        return None
    key = str(text.get(MODEL_ID_KEY, ""))
    if not key:
        key = text[MODEL_ID_KEY] = uuid.uuid4().hex
    model = _CACHE.get(key)
    if model is None:
        model = _CACHE[key] = _unpack(text)
    return model


def require_model(scene: bpy.types.Scene) -> GenerativeShapeModel:
    """get_model, but a clear ShapeGenError when the scene has no model."""
    model = get_model(scene)
    if model is None:
        raise ShapeGenError("No fitted model in this scene: fit one (ShapeGen > Model > Fit) or load a model file")
    return model


def read_model_file(path: str | Path) -> tuple[GenerativeShapeModel, bytes]:
    """Load (and so validate) a model file and read its bytes: no bpy, so the fit's result
    hand-off runs it on a helper thread, off Blender's main thread."""
    return GenerativeShapeModel.load(path), Path(path).read_bytes()


def store_fitted_model(scene: bpy.types.Scene, path: str | Path, name: str,
                       loaded: tuple[GenerativeShapeModel, bytes] | None = None) -> GenerativeShapeModel:
    """Make the model file at `path` the scene's model: load (validates), pack, point the
    scene at it. `loaded`: `read_model_file(path)`, when done already. The previous model's Text is removed unless another scene still uses it.
    Nothing changes when loading fails."""
    model, data = loaded if loaded is not None else read_model_file(path)
    model.metadata.setdefault("name", name)
    old = scene.shapegen.model_text
    text = pack_model(path, name, model, data)
    scene.shapegen.model_text = text
    if old is not None and old != text and not any(s.shapegen.model_text == old for s in bpy.data.scenes):
        _CACHE.pop(str(old.get(MODEL_ID_KEY, "")), None)
        bpy.data.texts.remove(old)
    return model


def forget_cache() -> None:
    _CACHE.clear()
