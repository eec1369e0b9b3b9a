"""A render worker process: ``python -m blender_tools.worker '<job JSON>'``.

Runs one ``pipeline.Job`` in a fresh bpy process (so memory stays flat over long runs) and
prints events as lines ``@@BT {json}`` on stdout; Blender's own output is silenced around
renders. Exit status 0 on success, 2 for a job error (bad input), 1 for anything else.
"""
from __future__ import annotations

import json
import sys
import traceback

EVENT_PREFIX = "@@BT "


def emit(event: dict) -> None:
    sys.stdout.write(EVENT_PREFIX + json.dumps(event) + "\n")
    sys.stdout.flush()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    from ._bpy import BlenderMissing
    from .pipeline import Job, JobError, run_job

    try:
        job = Job(**json.loads(argv[0]))
        run_job(job, emit)
        return 0
    except (JobError, BlenderMissing) as exc:
        emit({"event": "error", "message": str(exc)})
        return 2
    except Exception as exc:  # a bug: keep the traceback on stderr, one line for the parent
        traceback.print_exc()
        emit({"event": "error", "message": f"worker failed: {type(exc).__name__}: {exc}"})
        return 1


if __name__ == "__main__":
    sys.exit(main())
