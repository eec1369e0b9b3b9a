"""What a render run does around the renders, on this machine: worker processes and their events, the
progress bar, the labelling stage and its occlusion statistics, the splits as scenarios appear,
leftovers of killed runs, and the summary lines."""
from __future__ import annotations

import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from dataset_spec.cli_support import UserError


def print_summary(out: Path, summary: list) -> None:
    for name, wall, stats, occ in summary:
        cyc = stats["render_s"]
        ratio = f"{wall / cyc:.2f}" if cyc > 0 else "n/a"
        print(f"{name}: {stats['files']} files rendered in {wall:.1f} s (Cycles {cyc:.1f} s, wall/Cycles {ratio}) "
              f"-> {out}")
        if occ:
            print("  occlusion: " + occlusion_line(occ))


class Progress:
    def __init__(self, disable: bool):
        from tqdm import tqdm

        self.bar = tqdm(total=0, unit="render", disable=disable, dynamic_ncols=True, file=sys.stderr)

    def plan(self, scenario: str, views):
        self.bar.total += sum(n for _, n in views)
        self.bar.refresh()

    def step(self, scenario: str, event: dict):
        self.bar.set_description(f"{scenario} {event['camera']} {event['kind']}", refresh=False)
        self.bar.update(1)

    def plan_units(self, n: int):
        self.bar.unit = "scenario"
        self.bar.total = n
        self.bar.refresh()

    def unit_done(self, scenario: str):
        self.bar.set_description(scenario, refresh=False)
        self.bar.update(1)

    def write(self, msg: str):
        self.bar.write(msg, file=sys.stderr)

    def close(self):
        self.bar.close()


def handle(event: dict, scenario: str, progress: Progress, stats: dict) -> None:
    kind = event.get("event")
    if kind == "plan":
        progress.plan(scenario, event["views"])
    elif kind == "file":
        progress.step(scenario, event)
        stats["files"] += 1
        stats.setdefault("renders", []).append({k: event[k] for k in ("camera", "kind", "render_s")})
    elif kind == "warning":
        progress.write(f"blender-gen: warning: {scenario}: {event['message']}")
    elif kind == "done":
        stats["render_s"] += event["render_s"]


def run_in_process(job, progress: Progress) -> dict:
    from ._bpy import BlenderMissing
    from .pipeline import JobError, run_job

    stats = {"files": 0, "render_s": 0.0}
    try:
        run_job(job, lambda e: handle(e, job.scenario, progress, stats))
    except (JobError, BlenderMissing) as exc:
        raise UserError(str(exc)) from None
    return stats


def worker_env() -> dict:
    """The render workers' environment: this checkout importable, and a temporary folder of their own,
    named for this process (``pipeline.TEMP_PREFIX``), so the ``blender_*`` folders Blender makes there
    go when this run ends, or with the next run's ``remove_stale_temp_dirs`` when it was killed."""
    from .pipeline import TEMP_PREFIX

    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["TMPDIR"] = tempfile.mkdtemp(prefix=f"{TEMP_PREFIX}{os.getpid()}_workers_")
    return env


def run_workers(jobs, progress: Progress) -> dict:
    """Run one worker process per job; collect their events; one-line error if one fails."""
    from .worker import EVENT_PREFIX

    stats = {"files": 0, "render_s": 0.0}
    events: queue.Queue = queue.Queue()
    procs = []
    logs = []
    env = worker_env()
    try:
        for job in jobs:
            log = tempfile.TemporaryFile(mode="w+")
            proc = subprocess.Popen([sys.executable, "-m", "blender_tools.worker", json.dumps(job.to_dict())],
                                    stdout=subprocess.PIPE, stderr=log, text=True, env=env)
            procs.append(proc)
            logs.append(log)

            def pump(p=proc, i=len(procs) - 1):
                for line in p.stdout:
                    if line.startswith(EVENT_PREFIX):
                        events.put((i, json.loads(line[len(EVENT_PREFIX):])))
                events.put((i, None))

            threading.Thread(target=pump, daemon=True).start()
        running, errors = len(procs), []
        while running:
            i, event = events.get()
            if event is None:
                running -= 1
            elif event.get("event") == "error":
                errors.append(event["message"])
            else:
                handle(event, jobs[i].scenario, progress, stats)
        for i, proc in enumerate(procs):
            rc = proc.wait()
            if rc != 0 and not errors:
                logs[i].seek(0)
                tail = [ln for ln in logs[i].read().splitlines() if ln.strip()]
                errors.append(f"render worker exited with status {rc}" + (f": {tail[-1]}" if tail else ""))
        if errors:
            raise UserError(errors[0])
        return stats
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
        for log in logs:
            log.close()
        shutil.rmtree(env["TMPDIR"], ignore_errors=True)


def occlusion_line(occ: dict) -> str:
    keys = ("pairs", "visible", "partly_hidden", "mostly_hidden", "fully_hidden", "hidden", "hidden_seen_elsewhere")
    if not all(k in occ for k in keys):
        return json.dumps(occ, sort_keys=True)
    frac = occ["hidden_seen_elsewhere"] / occ["hidden"] if occ["hidden"] else 0.0
    return (f"{occ['pairs']} actor-camera pairs in frustum: {occ['visible']} visible, {occ['partly_hidden']} partly, "
            f"{occ['mostly_hidden']} mostly, {occ['fully_hidden']} fully hidden; {occ['hidden_seen_elsewhere']} of "
            f"{occ['hidden']} hidden ones visible from another camera ({100 * frac:.0f}%)")


def remove_leftovers(out: Path, scenario: str) -> None:
    """Delete temporary files an interrupted run left in this scenario (before workers start)."""
    from dataset_spec.atomic import is_temporary
    from dataset_spec.layout import Layout

    d = Layout(out).scenario_dir(scenario)
    if d.is_dir():
        for p in d.rglob(".*.tmp-*"):
            if is_temporary(p):
                p.unlink(missing_ok=True)


def plan_splits(out: Path, names: list[str], seed: int, split: str | None = None) -> dict[str, list[str]]:
    """The splits once this run's scenarios exist: the dataset's assignment kept, the new ones placed by
    ``dataset_spec.splits.extend_splits``'s rule, or (``split``, ``--split``) this run's scenarios in that split;
    says so in one line."""
    from dataset_spec import Dataset
    from dataset_spec.splits import extend_splits, placement_line

    existing, have = {}, []
    if (out / "dataset.json").is_file():
        ds = Dataset.open(out)
        existing, have = ds.info.splits, ds.scenario_names()
    if split is not None:
        where = {n: s for s, members in existing.items() for n in members}
        placed = {n: (split, "--split") for n in names if where.get(n) != split}
        existing = {s: [n for n in members if n not in placed] for s, members in existing.items()}
        existing = {**existing, split: sorted(set(existing.get(split, [])) | set(names))}
    planned, more = extend_splits(existing, have + names, seed)
    placed = {**placed, **more} if split is not None else more
    print("blender-gen: " + placement_line(placed, len(set(have + names)) - len(placed)))
    return planned


def update_splits(out: Path, planned: dict[str, list[str]]) -> None:
    """Write the planned splits of the scenarios that exist so far (nothing when they are already there)."""
    from dataset_spec import Dataset

    ds = Dataset.open(out)
    have = set(ds.scenario_names())
    splits = {s: [n for n in names if n in have] for s, names in planned.items()}
    if splits != {s: sorted(ds.info.splits.get(s, [])) for s in splits}:
        ds.set_splits(splits)


def occlusion(out: Path, scenario: str, progress: Progress) -> dict | None:
    """The labelling stage: ``project-labels`` (the tools half, run as its own process) writes the
    scenario's per-view labels and stores its occlusion statistics in its extras, returned here."""
    from dataset_spec import Dataset

    exe = Path(sys.executable).parent / "project-labels"
    exe = str(exe) if exe.exists() else shutil.which("project-labels")
    if exe is None:
        progress.write("blender-gen: note: project-labels is not installed; skipping labels and occlusion statistics")
        return None
    proc = subprocess.run([exe, str(out), "--scenario", scenario, "--quiet"], capture_output=True, text=True)
    if proc.returncode != 0:
        raise UserError(f"labelling {scenario} failed: {(proc.stderr.strip().splitlines() or ['?'])[-1]}")
    return Dataset.open(out).scenario(scenario).extras.get("occlusion")
