"""Training loop: one scene (V source views) per step, one backward pass per step.

Each step encodes the V views once, renders every grid ray of every view in checkpointed chunks
(``model.chunk_memory_mb``), computes the YOLO loss for all views and calls backward once
(activation checkpointing recomputes each chunk in the backward pass instead of the original's
backward per chunk).

Outputs in ``out_dir``: ``latest.pt`` (atomic; resume point), ``epoch_XXXX.pt`` (backup every
``train.save_every_epochs`` epochs; the newest ``train.keep_checkpoints`` kept), ``best.pt`` (best
validation F1 at ``eval.select_iou``), ``log.jsonl`` (every step and event), ``epochs.csv``,
``vis/*.png``, ``config.yaml``. With ``train.ema_decay`` > 0 validation and the
checkpoints' ``model`` use the moving average of the weights (``pnyolo.engine.weight_average``); the
trained weights are kept in ``train_model`` to resume from.

Example::

    summary = train("out/dataset", load_config("configs/cpu.yaml"), "runs/cpu")
"""
from __future__ import annotations

import contextlib
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import yaml
from tqdm import tqdm

from dataset_spec.atomic import atomic_write_text
from dataset_spec.cli_support import UserError
from pnyolo.config import Config, to_dict
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.engine.checkpoint import (check_compatible, load_weights, make_payload, read_checkpoint, rng_state,
                                     save_checkpoint, set_rng_state)
from pnyolo.engine.distributed import Dist, init_from_env, shutdown
from pnyolo.engine.loader import epoch_items
from pnyolo.engine.logs import JsonlLog, TensorBoardLog, append_csv, clear_run, truncate_logs
from pnyolo.engine.memory import limit_heap_retention
from pnyolo.engine.preflight import check_run_folder, items_per_step
from pnyolo.engine.predict import predict
from pnyolo.engine.runtime import apply_threads, deterministic_mode, pick_device, seed_everything
from pnyolo.engine.schedule import epoch_order, make_scheduler
from pnyolo.engine.weight_average import WeightAverage
from pnyolo.cooperation.pose_noise import training_poses
from pnyolo.evaluation.evaluate import item_name, score
from pnyolo.evaluation.pictures import panel, write_png
from pnyolo.evaluation.report import headline
from pnyolo.models import build_model, predict_item


VAL_PICTURES = 2  # validation items whose detections go to TensorBoard at every validation


class TrainingStopped(UserError):
    """Training stopped on repeated non-finite values (reported in one line)."""


def first_nonfinite_grad(model) -> str | None:
    for name, p in model.named_parameters():
        if p.grad is not None and not torch.isfinite(p.grad).all():
            return name
    return None


def param_groups(model, params: list, tc) -> list:
    """The optimizer's parameter groups: one, or with ``train.encoder_lr_scale`` != 1 the encoder's
    backbone (``EncoderBase.backbone_parameters``) at that share of ``train.lr`` beside the rest."""
    if tc.encoder_lr_scale == 1.0:
        return params
    if model.encoder is None:
        raise UserError(f"train.encoder_lr_scale: model.kind {model.kind} has no image encoder (leave it at 1)")
    backbone = {id(p) for p in model.encoder.backbone_parameters()}
    return [{"params": [p for p in params if id(p) not in backbone]},
            {"params": [p for p in params if id(p) in backbone], "lr": tc.lr * tc.encoder_lr_scale}]


def train(root: str | Path, cfg: Config, out_dir: str | Path, resume: bool = False, quiet: bool = False,
          scenarios: list[str] | None = None, force: bool = False) -> dict:
    """Train; returns a summary dict (steps, last loss, best F1, paths). ``resume`` continues the
    run in ``out_dir`` exactly; ``force`` deletes an earlier run there first. Under torchrun every
    rank calls this (pnyolo.engine.distributed)."""
    dist = init_from_env(pick_device(cfg.train.device).type)
    try:
        with deterministic_mode(cfg.train.deterministic):
            summary = Trainer(root, cfg, Path(out_dir), resume, quiet, scenarios, force, dist).run()
        dist.barrier()  # every rank done (rank 0 writing its checkpoints) before any tears the group down
        return summary
    finally:
        shutdown(dist)


class Trainer:
    """One training run: each optimizer step takes the next ``world x train.items_per_step`` items of
    the epoch's order; every rank trains on its ``items_per_step`` of them (accumulating their
    gradients), DistributedDataParallel averages the ranks' gradients, rank 0 logs, validates and
    writes checkpoints. One process with items_per_step k is the same run as k processes with 1."""

    def __init__(self, root, cfg: Config, out: Path, resume: bool, quiet: bool, scenarios, force: bool, dist: Dist):
        if dist.main:
            check_run_folder(out, resume, force)
        dist.barrier()
        self.cfg, self.out, self.dist, self.quiet = cfg, out, dist, quiet
        tc = self.tc = cfg.train
        self.threads, notes = apply_threads(tc.threads, dist.world)
        notes = [notes]
        device = pick_device(tc.device)
        self.device = torch.device("cuda", dist.local_rank) if device.type == "cuda" and dist.active else device
        seed_everything(tc.seed + dist.rank)  # augmentation and sampling differ between ranks
        self.train_ds = MultiViewDataset(root, "train", cfg, training=True, scenarios=scenarios)
        self.per_step = items_per_step(len(self.train_ds), dist.world, tc.items_per_step)
        self.val_ds = None
        self.validates = tc.val_every > 0 and scenarios is None and bool(self.train_ds.ds.split("val"))
        if dist.main and self.validates:
            self.val_ds = MultiViewDataset(root, "val", cfg, training=False, views=cfg.eval.views)
        else:
            why = ("train.val_every is 0" if tc.val_every <= 0 else "--scenario chose the scenarios"
                   if scenarios is not None else "the dataset has no val split")
            notes.append(f"no validation ({why}): best.pt will be the last checkpoint")
        self.class_names = self.train_ds.class_names
        self.model = build_model(cfg, len(self.class_names)).to(self.device)
        self.model.check_data(self.train_ds)
        if tc.compile and self.model.encoder is not None:  # in place: the state dict keeps its names
            self.model.encoder.compile()
        g = self.train_ds.grid(self.train_ds.scenarios[0])
        limit_heap_retention(self.model, cfg.data.num_views, cfg.data.num_views * g.grid_h * g.grid_w)
        self.params = [p for p in self.model.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(param_groups(self.model, self.params, tc), lr=tc.lr)
        self.steps_per_epoch = len(self.train_ds) // self.per_step
        self.total = tc.epochs * self.steps_per_epoch
        if tc.max_steps:
            self.total = min(self.total, tc.max_steps)
        self.scheduler = make_scheduler(self.optimizer, tc, tc.lr_schedule_steps or self.total)
        # "seconds": the training's wall time up to the last checkpoint over every sitting, pauses between them not
        # counted (a resumed run goes on from its checkpoint's figure): the time a run reports
        self.state = {"epoch": 0, "step": 0, "order": None, "pos": 0, "best_f1": -1.0, "bad_steps": 0, "seconds": 0.0}
        self.latest = out / "latest.pt"
        ckpt = self._resume() if resume else None
        self.average = None
        if tc.ema_decay > 0:
            self.average = WeightAverage(self.model, tc.ema_decay, updates=self.state["step"])
            if ckpt is not None and "train_model" in ckpt:
                load_weights(self.average.model, ckpt["model"], self.latest)
        self.used = self.average.model if self.average else self.model  # what validation and "model" hold
        self.ddp = self.model
        if dist.active:
            from torch.nn.parallel import DistributedDataParallel

            self.ddp = DistributedDataParallel(self.model, device_ids=[self.device.index] if self.device.type == "cuda"
                                               else None)
        self.log = self.board = None
        if dist.main:
            if force or not resume:  # a new run: what an earlier one left before its first checkpoint goes too
                clear_run(out)
            if resume:  # the logs continue from the checkpoint: later records were redone, so they go
                truncate_logs(out, self.state["step"], self.state["epoch"])
            atomic_write_text(out / "config.yaml", yaml.safe_dump(to_dict(cfg), sort_keys=False))
            self.log = JsonlLog(out / "log.jsonl")
            self.log.write({"event": "resume" if resume else "start", "step": self.state["step"],  # what it ran on
                            "epoch": self.state["epoch"], "processes": dist.world, "threads": self.threads})
            (out / "vis").mkdir(exist_ok=True)
            if tc.tensorboard:
                self.board = TensorBoardLog(out / "tensorboard", self.state["step"] + 1 if resume else None)
            said = notes if not quiet else notes[1:]  # --quiet keeps what changes the run (no validation)
            if said:  # the run's first line, once every check has passed
                print("pnyolo-train: " + "; ".join(said), file=sys.stderr)

    def _resume(self) -> dict:
        ckpt = read_checkpoint(self.latest)
        check_compatible(ckpt, self.cfg, self.class_names, self.latest)
        load_weights(self.model, ckpt.get("train_model") or ckpt["model"], self.latest)
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.scheduler.load_state_dict(ckpt["scheduler"])
        self.state.update(ckpt["train_state"])
        ranks = ckpt.get("rng_ranks", [ckpt["rng"]])
        if len(ranks) != self.dist.world:
            raise UserError(f"--resume: {self.latest} was written by {len(ranks)} process(es); resume it with as many "
                            f"(here {self.dist.world})")
        set_rng_state(ranks[self.dist.rank])
        return ckpt

    def save(self, path: Path) -> None:
        """Every rank's random state is gathered; rank 0 writes (atomically), with the training's seconds so far."""
        now = time.perf_counter()
        self.state["seconds"] = float(self.state.get("seconds", 0.0)) + now - self.sitting
        self.sitting = now
        ranks = self.dist.gather(rng_state())
        if self.dist.main:
            extra = {"train_model": self.model.state_dict()} if self.average else {}
            save_checkpoint(path, **make_payload(self.used, self.optimizer, self.scheduler, self.cfg, self.class_names,
                                                 train_state=dict(self.state), rng_ranks=ranks, **extra))

    def run(self) -> dict:
        tc, state = self.tc, self.state
        self.sitting = time.perf_counter()  # this sitting's clock, added to state["seconds"] at each checkpoint
        bar = tqdm(total=self.total, initial=min(state["step"], self.total), disable=self.quiet or not self.dist.main,
                   dynamic_ncols=True, desc="train")
        self.model.train()
        self.last_loss, stop = float("nan"), False
        while state["epoch"] < tc.epochs and not stop:
            if state["order"] is None:
                state["order"], state["pos"] = epoch_order(len(self.train_ds), tc.seed, state["epoch"]), 0
            self.items = epoch_items(self.train_ds, state["order"], (state["epoch"], state["pos"]), self.dist,
                                     tc.items_per_step, tc.workers, tc.seed, pin=self.device.type == "cuda")
            epoch_losses, t_epoch = [], time.time()
            while state["pos"] + self.per_step <= len(state["order"]):
                if tc.max_steps and state["step"] >= tc.max_steps:
                    stop = True
                    break
                if self._step(epoch_losses):
                    bar.update(1)
                    bar.set_postfix(loss=f"{self.last_loss:.4f}", epoch=state["epoch"])
            if not stop:
                self._end_epoch(epoch_losses, t_epoch)
        if stop:
            self.save(self.latest)
        if not self.validates:  # nothing to choose by: the last weights are the best there is
            self.save(self.out / "best.pt")
        bar.close()
        if self.board:
            self.board.close()
        return {"steps": state["step"], "epoch": state["epoch"],  # no step taken (a finished run resumed): no loss
                "last_loss": self.last_loss if math.isfinite(self.last_loss) else None,
                "best_f1": state["best_f1"], "latest": str(self.latest), "device": str(self.device),
                "processes": self.dist.world, "items_per_step": self.per_step, "threads": self.threads,
                "seconds": float(state.get("seconds", 0.0))}

    def autocast(self):
        """``train.amp``: bf16 autocast for forward and loss, or nothing."""
        if self.tc.amp == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _step(self, epoch_losses: list[float]) -> bool:
        """One optimizer step on this rank's items; False when it was skipped (non-finite values)."""
        tc, state, model = self.tc, self.state, self.model
        t_step = time.perf_counter()
        k = tc.items_per_step
        state["pos"] += self.per_step
        self.optimizer.zero_grad(set_to_none=True)
        total, terms, where, item, options = 0.0, {}, None, None, {}
        for j in range(k):
            item = training_poses(next(self.items), tc.pose_noise, state["step"], self.dist.rank)
            options, targets = model.training_options(item, model.targets(item), tc)  # the kind's own choices
            sync = self.ddp.no_sync() if self.dist.active and j < k - 1 else contextlib.nullcontext()
            with sync, self.autocast():
                out_v = predict_item(model, item, self.device, runner=self.ddp, **options)
                loss, item_terms = model.loss(out_v, item, targets, self.device)
                finite = self.dist.all_true(bool(torch.isfinite(loss)))  # every rank skips together
                if not finite:
                    where = "loss " + ",".join(n for n, v in item_terms.items() if not math.isfinite(v))
                    break
                (loss / k).backward()
            total += float(loss.detach()) / k
            terms = {n: terms.get(n, 0.0) + v / k for n, v in item_terms.items()}
        if where is None:  # gradients are averaged over the ranks by now: every rank sees the same
            bad = first_nonfinite_grad(model)
            where = f"gradient of {bad}" if bad else None
        if where:
            state["bad_steps"] += 1
            self.optimizer.zero_grad(set_to_none=True)
            if self.log:
                self.log.write({"event": "nonfinite", "where": where, "step": state["step"], "epoch": state["epoch"],
                                "scenario": item.scenario, "variant": item.variant, "views": item.views})
            if state["bad_steps"] >= tc.max_bad_steps:
                self.save(self.latest)
                raise TrainingStopped(f"stopped after {state['bad_steps']} consecutive non-finite steps "
                                      f"(last: {where}); see {self.out / 'log.jsonl'}")
            return False
        state["bad_steps"] = 0
        if tc.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.params, tc.grad_clip)
        self.optimizer.step()
        if self.average:
            self.average.update(model)
        if tc.lr_schedule == "cosine":
            self.scheduler.step()
        state["step"] += 1
        self.last_loss = self.dist.mean(total)
        epoch_losses.append(self.last_loss)
        lr = self.optimizer.param_groups[0]["lr"]
        if self.dist.main and state["step"] % max(1, tc.log_every) == 0:
            ray_mask, drop_own = options.get("ray_mask"), options.get("drop_own_view")
            self.log.write({"event": "step", "step": state["step"], "epoch": state["epoch"], "loss": self.last_loss,
                            **terms, "lr": lr, "seconds": round(time.perf_counter() - t_step, 4),
                            "rays": 1.0 if ray_mask is None else round(float(ray_mask.float().mean()), 4),
                            "own_view_dropped": 0.0 if drop_own is None else round(float(drop_own.float().mean()), 4),
                            "scenario": item.scenario, "variant": item.variant, "views": item.views})
            if self.board:
                self.board.step(state["step"], self.last_loss, terms, lr, time.perf_counter() - t_step)
        if self.dist.main and tc.vis_every and state["step"] % tc.vis_every == 0:
            visualise(model, item, self.cfg, self.class_names, self.out / "vis" / f"step_{state['step']:07d}.png")
        if tc.checkpoint_every and state["step"] % tc.checkpoint_every == 0:
            self.save(self.latest)
        self.last_item = item
        return True

    def _end_epoch(self, epoch_losses: list[float], t_epoch: float) -> None:
        tc, state = self.tc, self.state
        if tc.lr_schedule == "exponential":
            self.scheduler.step()
        state["epoch"] += 1
        state["order"], state["pos"] = None, 0
        row = {"epoch": state["epoch"], "step": state["step"],
               "train_loss": float(np.mean(epoch_losses)) if epoch_losses else float("nan"),
               "lr": self.optimizer.param_groups[0]["lr"], "seconds": round(time.time() - t_epoch, 2), "val_f1": ""}
        per_epoch_outputs = state["epoch"] % max(1, tc.save_every_epochs) == 0 or state["epoch"] >= tc.epochs
        improved = False
        if self.dist.main:
            if not tc.vis_every and per_epoch_outputs and hasattr(self, "last_item"):
                visualise(self.model, self.last_item, self.cfg, self.class_names,
                          self.out / "vis" / f"epoch_{state['epoch']:04d}.png")
            if self.val_ds is not None and state["epoch"] % tc.val_every == 0:
                improved = self._validate(row)
            append_csv(self.out / "epochs.csv", row)
        state["best_f1"] = self.dist.gather(state["best_f1"])[0]  # rank 0 validates; every rank keeps its figure
        improved = self.dist.gather(improved)[0]
        if per_epoch_outputs:
            self.save(self.latest)
            self.save(self.out / f"epoch_{state['epoch']:04d}.pt")
            if self.dist.main and tc.keep_checkpoints:
                for old in sorted(self.out.glob("epoch_*.pt"))[:-tc.keep_checkpoints]:
                    old.unlink()
        if improved:
            self.save(self.out / "best.pt")

    def _validate(self, row: dict) -> bool:
        """Rank 0: validation metrics logged; True when F1 at eval.select_iou is the best so far."""
        state, cfg = self.state, self.cfg
        preds = predict(self.used, self.val_ds, cfg.eval, device=self.device)
        summary = score(preds, cfg.eval).summary()
        f1 = headline(summary, cfg.eval.select_iou)
        row["val_f1"] = f1
        self.log.write({"event": "validation", "epoch": state["epoch"], "step": state["step"], "f1": f1,
                        "ap50": summary["ap50"]})
        if self.board:
            self.board.validation(state["step"], summary, cfg.eval.select_iou)
            for k in range(min(VAL_PICTURES, len(self.val_ds))):  # from the predictions just scored
                val_item = self.val_ds[k]
                self.board.picture(state["step"], f"val/{item_name(val_item)}",
                                   panel(val_item, preds.detections_at(k, cfg.eval), self.class_names,
                                         self.used.targets(val_item)))
        if f1 > state["best_f1"]:
            state["best_f1"] = f1
            return True
        return False


@torch.no_grad()
def visualise(model, item, cfg: Config, class_names, path: Path | None = None):
    """An item's panel of detections (H, W, 3) uint8 by the model as it is now, in evaluation mode (not the
    training step's outputs, taken in training mode before the step), written to ``path`` if given."""
    was = model.training
    model.eval()
    out_v = predict_item(model, item, next(model.parameters()).device, cfg.eval)
    dets = model.decode(out_v, item, cfg.eval)
    picture = panel(item, dets, class_names, model.targets(item))
    if path is not None:
        write_png(path, picture)
    model.train(was)
    return picture
