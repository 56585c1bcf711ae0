"""Background jobs: the bpy-free manager (`manager`), the runtime in Blender (`runtime`:
polling, the shared operator tail, reporting the outcome) and the operator mixin
(`operator`)."""

from .manager import MANAGER, JobManager
from .operator import JobOperator
from .runtime import (job_scene, job_settings, no_job_running, poll_job, report_outcome, start_polling,
                      unregister_timer)

__all__ = ["MANAGER", "JobManager", "JobOperator", "job_scene", "job_settings", "no_job_running", "poll_job",
           "report_outcome", "start_polling", "unregister_timer"]
