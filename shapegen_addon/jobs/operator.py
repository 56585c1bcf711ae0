"""`JobOperator`: what the operators that run core work in a worker (Prepare, Find
Correspondences, Fit) share — the collection they work on, Extra Settings as JSON over
the panel's settings (run options such as `jobs` among them, handed to the job beside its
settings, never recorded), `wait`, and one background job at a time."""

from __future__ import annotations

import json
from typing import Callable

import bpy
from bpy.props import BoolProperty, StringProperty

from ...core.app.fit_settings import split_run_options
from .runtime import no_job_running, run_worker_job

__all__ = ["JobOperator", "merge_settings"]


def merge_settings(base: dict, extra: dict) -> dict:
    """`base` updated by `extra`; nested objects are merged key by key."""
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_settings(out[key], value)
        else:
            out[key] = value
    return out


def _parse_extra_settings(text: str) -> dict:
    """The "Extra Settings" JSON: an object, or empty. ValueError otherwise."""
    extra = json.loads(text) if text.strip() else {}
    if not isinstance(extra, dict):
        raise ValueError("Extra Settings are not a JSON object")
    return extra


class JobOperator:
    """Operator mixin of the operators that run a background job. Subclasses set
    `job_name` (names the job in messages and its temporary folder)."""

    job_name = "job"

    collection_name: StringProperty(
        name="Collection", default="",
        description="Collection to work on (empty: the panel's chosen collection)",
    )
    extra_settings: StringProperty(
        name="Extra Settings", default="",
        description='More settings as JSON over the panel\'s: Prepare options, CorrespondenceSettings fields '
                    '(Find Correspondences) or FitSettings fields, nested as FitSettings nests them (Fit), and '
                    'how the job runs ("jobs": worker processes, "scheduler": a Dask cluster), '
                    'e.g. {"jobs": 1, "prepare": {"seed": 2}}',
    )
    wait: BoolProperty(name="Wait", default=False, options={"SKIP_SAVE"},
                       description="Block until the job ends (scripts and background mode)")

    @classmethod
    def poll(cls, context):
        if not no_job_running(cls):
            return False
        if context.scene.shapegen.source_collection is None:
            cls.poll_message_set("Choose a training collection first (Data panel)")
            return False
        return True

    def chosen_collection(self, context) -> bpy.types.Collection | None:
        """The collection named by `collection_name`, else the panel's chosen training
        collection. None (reported) when there is none."""
        name = self.collection_name
        collection = bpy.data.collections.get(name) if name else context.scene.shapegen.source_collection
        if collection is None:
            self.report({"ERROR"}, f"No collection named '{name}'" if name else "Choose a training collection first")
        return collection

    def job_options(self, base: dict, check: Callable[[dict], object]) -> tuple[dict, dict] | None:
        """(options, run): `base` (from the panel) merged with Extra Settings, checked by
        `check(options)` (which raises TypeError or ValueError) before any worker starts,
        and the run options Extra Settings name (core.app.fit_settings.RunOptions: `jobs`,
        `scheduler`), for the job's arguments. None (reported) when either is invalid."""
        try:
            run, options = split_run_options(merge_settings(base, _parse_extra_settings(self.extra_settings)))
            check(options)
        except (TypeError, ValueError) as exc:
            self.report({"ERROR"}, f"Invalid {self.job_name} settings: {exc}")
            return None
        return options, {name: value for name, value in run.as_dict().items() if value is not None}

    def run_job(self, context, start: Callable, started: str) -> set[str]:
        """Start the job (`start(folder)`, see runtime.run_worker_job), then wait for it
        (`wait`) or leave it to the UI timer."""
        return run_worker_job(self, context.scene.shapegen, f"shapegen-{self.job_name}-", start, wait=self.wait,
                              started=started)
