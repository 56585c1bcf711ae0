"""Objects left out of training: the names of a user's training collection's objects
that Prepare, Find Correspondences and Fit skip, recorded on that collection
(keys.EXCLUDED_KEY) by Exclude Outliers and cleared by Include Excluded. The objects
themselves are never changed, moved or hidden.

The outliers offered for exclusion are those the scene's model flags (its summary on the
model's Text, "name: reason") and those the last Find Correspondences flagged on the
collection's prepared copies (keys.CORRESPONDENCE_OUTLIER_KEY holds the reason)."""

from __future__ import annotations

import bpy

from .keys import CORRESPONDENCE_OUTLIER_KEY, EXCLUDED_KEY, OUTLIERS_KEY, PREPARED_KEY, SOURCE_COLLECTION_KEY, SOURCE_KEY
from .prepared import prepared_collection_for, prepared_objects

__all__ = ["excluded_names", "training_collection", "training_objects", "without_excluded", "exclude",
           "include_all", "outliers"]


def excluded_names(collection: bpy.types.Collection | None) -> list[str]:
    """Names of the objects of `collection` left out of training."""
    return [] if collection is None else [str(name) for name in collection.get(EXCLUDED_KEY, [])]


def training_collection(collection: bpy.types.Collection | None) -> bpy.types.Collection | None:
    """The user's collection: `collection` itself, or the source of a prepared one."""
    if collection is not None and collection.get(PREPARED_KEY):
        return bpy.data.collections.get(str(collection.get(SOURCE_COLLECTION_KEY, "")))
    return collection


def training_objects(collection: bpy.types.Collection) -> list[bpy.types.Object]:
    """The objects of `collection` (children included) by name, without the excluded ones."""
    excluded = set(excluded_names(collection))
    return sorted((o for o in collection.all_objects if o.name not in excluded), key=lambda o: o.name)


def without_excluded(prepared: bpy.types.Collection, copies) -> list[bpy.types.Object]:
    """The prepared `copies` whose source object is not excluded in its source collection."""
    excluded = set(excluded_names(training_collection(prepared)))
    return [copy for copy in copies if copy.get(SOURCE_KEY, copy.name) not in excluded]


def exclude(collection: bpy.types.Collection, names) -> list[str]:
    """Leave the objects `names` of `collection` out of training; returns those newly left out."""
    present = {o.name for o in collection.all_objects}
    current = excluded_names(collection)
    added = [name for name in dict.fromkeys(names) if name in present and name not in current]
    collection[EXCLUDED_KEY] = current + added
    return added


def include_all(collection: bpy.types.Collection) -> list[str]:
    """Take every excluded object of `collection` back into training; returns their names."""
    names = excluded_names(collection)
    if EXCLUDED_KEY in collection:
        del collection[EXCLUDED_KEY]
    return names


def outliers(scene: bpy.types.Scene, collection: bpy.types.Collection | None) -> list[tuple[str, str]]:
    """(object name, reason) of every flagged object of the user's `collection`: flagged by
    the scene's model or by the last Find Correspondences on its prepared collection (the
    model's reason first)."""
    if collection is None:
        return []
    names = sorted((o.name for o in collection.all_objects), key=len, reverse=True)  # longest name first
    found: dict[str, str] = {}
    text = scene.shapegen.model_text
    for line in (text.get(OUTLIERS_KEY, []) if text is not None else []):
        line = str(line)
        name = next((n for n in names if line == n or line.startswith(f"{n}: ")), None)
        if name is not None:
            found.setdefault(name, line[len(name) + 2:] or "outlier")
    prepared = prepared_collection_for(collection)
    for copy in prepared_objects(prepared) if prepared is not None else []:
        reason, name = copy.get(CORRESPONDENCE_OUTLIER_KEY), str(copy.get(SOURCE_KEY, ""))
        if reason and name in names:
            found.setdefault(name, reason if isinstance(reason, str) else "outlier")
    return sorted(found.items())
