"""Rendering on a Ray cluster (``blender-gen render ... --ray auto|local|ADDRESS``).

One Ray task per scenario: a scenario's cameras share one scene build (load, label, export), the
costly part of a small render, so a task renders all of them, and a dataset of dozens to
thousands of scenes gives the cluster enough units to balance. Each task runs the same worker as
``--workers`` (``python -m blender_tools.worker JOB``) in a fresh bpy process, so memory stays flat,
and declares what it needs (``num_cpus``; ``num_gpus`` with ``--device gpu``).

Files come back two ways:

* no shared filesystem (the default): a task renders into a scratch folder of its node and returns
  its files through Ray's object store; the driver writes them atomically into the dataset (and
  merges scenario.json with what an earlier render recorded);
* ``--shared-out``: every node sees the dataset folder, and tasks write into it directly.

Faults: a task whose process dies is retried by Ray (``max_retries``); a job error (bad input) is
not. The driver, killed and started again, sends every task the files already complete, which the
task skips, so nothing is rendered twice and nothing is lost. Retries are counted by a small Ray
actor each attempt reports to. Test-only: ``BLENDER_TOOLS_FAIL_ONCE=DIR`` makes each scenario's
first attempt exit abruptly (a marker file in DIR remembers it).
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dataset_spec.cli_support import UserError

from .pipeline import Job

MAX_RETRIES = 3
FAIL_ONCE_ENV = "BLENDER_TOOLS_FAIL_ONCE"


class WorkerDied(RuntimeError):
    """The render worker process ended abnormally (retried by Ray)."""


class JobFailed(RuntimeError):
    """The job's input is bad (reported, not retried)."""


def require_ray():
    try:
        import ray
    except ImportError:
        raise UserError("--ray needs Ray: pip install -e '.[cluster]'") from None
    return ray


PROBE_TIMEOUT_S = 10.0


def check_address(address: str) -> None:
    """``--ray HOST:PORT`` checked before any work: a port in 1..65535 (at once) that accepts a TCP
    connection within ``PROBE_TIMEOUT_S`` (Ray itself would retry for many minutes). ``auto``,
    ``local`` and ``ray://`` addresses are left to Ray."""
    if address in ("auto", "local") or "://" in address:
        return
    host, sep, port_text = address.rpartition(":")
    if not sep or not host:
        raise UserError(f"--ray {address}: expected auto, local, HOST:PORT or ray://HOST:PORT")
    try:
        port = int(port_text)
    except ValueError:
        raise UserError(f"--ray {address}: port {port_text!r} is not a number") from None
    if not 1 <= port <= 65535:
        raise UserError(f"--ray {address}: port {port} is outside 1..65535")
    try:
        socket.create_connection((host.strip("[]"), port), timeout=PROBE_TIMEOUT_S).close()
    except OSError as exc:
        raise UserError(f"--ray {address}: cannot reach a Ray cluster there ({exc.strerror or exc})") from None


def connect(address: str):
    """Join (``auto``, ``HOST:PORT``, ``ray://...``) or start (``local``) a Ray cluster."""
    ray = require_ray()
    repo = str(Path(__file__).resolve().parents[1])  # the workers import blender_tools from here (or their install)
    kwargs = {"include_dashboard": False, "log_to_driver": False, "ignore_reinit_error": True,
              "runtime_env": {"env_vars": {"PYTHONPATH": repo}}}
    try:
        ray.init(address=None if address == "local" else address, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise UserError(f"--ray {address}: cannot reach a Ray cluster ({str(exc).splitlines()[0]})") from None
    return ray


def render_unit(job: dict, shared: bool, counter) -> dict:
    """A Ray task: one scenario's job in a fresh worker process; its files (when not shared) and stats."""
    import ray

    t0 = time.perf_counter()
    ray.get(counter.started.remote(job["scenario"]))
    marker_dir = os.environ.get(FAIL_ONCE_ENV)
    if marker_dir:
        marker = Path(marker_dir) / f"{job['scenario']}.failed"
        if not marker.exists():
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.write_text("first attempt")
            os._exit(1)  # the task's process dies, as on a node failure
    scratch = None if shared else tempfile.mkdtemp(prefix="blender_gen_ray_")
    try:
        if scratch:
            job = {**job, "out": scratch}
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(Path(__file__).resolve().parents[1]),
                                                                          os.environ.get("PYTHONPATH")) if p)}
        proc = subprocess.run([sys.executable, "-m", "blender_tools.worker", json.dumps(job)], capture_output=True,
                              text=True, env=env)
        events = [json.loads(line[5:]) for line in proc.stdout.splitlines() if line.startswith("@@BT ")]
        errors = [e["message"] for e in events if e.get("event") == "error"]
        if proc.returncode == 2:
            raise JobFailed(errors[0] if errors else "render job refused")
        if proc.returncode != 0:
            raise WorkerDied(errors[0] if errors else f"render worker exited with status {proc.returncode}")
        files = {}
        if scratch:
            base = Path(scratch)
            for path in sorted((base / "scenarios" / job["scenario"]).rglob("*")):
                if path.is_file() and not path.name.startswith("."):
                    files[str(path.relative_to(base))] = path.read_bytes()
        done = next((e for e in events if e.get("event") == "done"), {"render_s": 0.0})
        return {"scenario": job["scenario"], "files": files, "rendered": sum(e.get("event") == "file" for e in events),
                "render_s": done["render_s"], "task_s": time.perf_counter() - t0, "warnings": [e["message"] for e in events if e.get("event") == "warning"]}
    finally:
        if scratch:
            import shutil

            shutil.rmtree(scratch, ignore_errors=True)


def complete_files(out: Path, scenario: str, variants: list[str]) -> list[str]:
    """The files of a scenario already complete in the dataset (relative paths): what a task skips."""
    from dataset_spec import Dataset
    from dataset_spec.dataset import missing_view_files

    if not (out / "dataset.json").is_file():
        return []
    ds = Dataset.open(out)
    try:
        scn = ds.scenario(scenario)
    except Exception:  # noqa: BLE001 - no (readable) scenario.json yet: nothing to skip
        return []
    lay, done = ds.layout, []
    for frame in range(scn.frames):
        for cam in scn.cameras:
            missing = set(missing_view_files(lay, scenario, cam, variants, frame=frame))
            if "data" not in missing:
                done += [lay.depth(scenario, cam.name, frame), lay.instance(scenario, cam.name, frame)]
            done += [lay.rgb(scenario, cam.name, v, frame) for v in variants if v not in missing]
    return [str(p.relative_to(out)) for p in done]


def write_result(out: Path, result: dict) -> None:
    """A task's files into the dataset, atomically; scenario.json merged with the one already there."""
    from dataset_spec import Dataset, DatasetInfo
    from dataset_spec.atomic import atomic_write_bytes
    from dataset_spec.schema import Scenario

    from .pipeline import merge_scenario

    ds = Dataset.create(out, DatasetInfo(name=out.name))
    for rel, data in result["files"].items():
        if rel.endswith("scenario.json"):
            new = Scenario.from_dict(json.loads(data), rel)
            old = ds.scenario(new.name) if ds.layout.scenario_json(new.name).is_file() else None
            ds.write_scenario(merge_scenario(old, new))
        else:
            atomic_write_bytes(out / rel, data)


def render_on_ray(jobs: list[Job], address: str, shared: bool, cpus: int, gpu: bool, progress, after_scenario
                  ) -> dict:
    """Every scenario's job as a Ray task; ``after_scenario(name)`` runs on the driver once a
    scenario's files are in (labels, statistics). Returns {units, retries, files, render_s, wall_s}."""
    ray = connect(address)
    t0 = time.perf_counter()

    @ray.remote
    class Attempts:
        def __init__(self):
            self.n = 0

        def started(self, scenario: str) -> None:
            self.n += 1

        def count(self) -> int:
            return self.n

    counter = Attempts.remote()
    task = ray.remote(render_unit).options(num_cpus=cpus, num_gpus=1 if gpu else 0, max_retries=MAX_RETRIES,
                                           retry_exceptions=[WorkerDied])
    out = Path(jobs[0].out)
    pending = {}
    for job in jobs:
        job.skip = complete_files(out, job.scenario, [v["name"] for v in job.variants]) if not job.force else []
        pending[task.remote(job.to_dict(), shared, counter)] = job.scenario
    progress.plan_units(len(pending))
    stats = {"units": len(pending), "files": 0, "render_s": 0.0}
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            scenario = pending.pop(ready[0])
            try:
                result = ray.get(ready[0])
            except ray.exceptions.RayError as exc:
                cause = getattr(exc, "cause", None)
                raise UserError(f"{scenario}: {cause if cause is not None else str(exc).splitlines()[0]}") from None
            if not shared:
                write_result(out, result)
            for message in result["warnings"]:
                progress.write(f"blender-gen: warning: {scenario}: {message}")
            stats["files"] += result["rendered"]
            stats["render_s"] += result["render_s"]
            after_scenario(scenario, result)
            progress.unit_done(scenario)
        stats["retries"] = ray.get(counter.count.remote()) - stats["units"]
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        ray.shutdown()
    stats["wall_s"] = time.perf_counter() - t0
    return stats
