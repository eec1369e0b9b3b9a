"""What a training run checks before any work: its folder may take it, and the training split has the items a step
takes (one-line errors). ``pnyolo-train --nproc`` runs ``preflight`` once before its workers start."""
from __future__ import annotations

from pathlib import Path

from dataset_spec.cli_support import UserError, check_output_dir
from pnyolo.config import Config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.engine.logs import RUN_DIRS, run_outputs


def check_run_folder(out: Path, resume: bool, force: bool) -> None:
    """``out`` may take this run: writable, and holding no earlier run unless resumed or forced
    (a new run beside an old one would interleave their logs)."""
    check_output_dir(out)
    if resume and force:
        raise UserError("--resume and --force exclude each other: continue the run, or start it over")
    for name in RUN_DIRS:
        if (out / name).exists() and not (out / name).is_dir():
            raise UserError(f"--out {out}: {out / name} is a file; the run writes a folder there (move the file)")
    earlier = [p for p in run_outputs(out) if p.suffix == ".pt"]  # logs without a checkpoint block nothing
    if resume and not (out / "latest.pt").is_file():
        raise UserError(f"--resume: no checkpoint {out / 'latest.pt'} to resume from")
    if earlier and not resume and not force:
        raise UserError(f"--out {out} already holds a training run ({earlier[0].name}); use --resume to continue "
                        "it, --force to start over (its checkpoints and logs are deleted), or another --out")
    if not force:  # --force deletes them (a link itself, never its target)
        for path in run_outputs(out):
            if path.is_symlink() or (path.is_file() and path.stat().st_nlink > 1):
                raise UserError(f"--out {out}: {path.name} is a {'link' if path.is_symlink() else 'hard link'}; a "
                                "run's files and folders are its own (remove it, or --force to start over)")


def preflight(root: str | Path, cfg: Config, out_dir: str | Path, resume: bool = False, force: bool = False,
              scenarios: list[str] | None = None, processes: int = 1) -> None:
    """The user's mistakes a run would meet first (its folder; the dataset, its labels and 3D boxes; enough items
    for a step of ``processes``), as one-line errors before any work: ``pnyolo-train --nproc`` checks them once
    before its workers."""
    check_run_folder(Path(out_dir), resume, force)
    items_per_step(len(MultiViewDataset(root, "train", cfg, training=True, scenarios=scenarios)), processes,
                   cfg.train.items_per_step)


def items_per_step(items: int, processes: int, per_process: int) -> int:
    """The items one optimizer step takes (``processes x train.items_per_step``); a one-line error where the
    training split has fewer."""
    per_step = processes * per_process
    if items < per_step:
        raise UserError(f"{items} training items, fewer than the {per_step} one step takes "
                        f"({processes} processes x train.items_per_step {per_process})")
    return per_step
