"""Training loop: one scene (V source views) per step, one backward pass per step.

Each step encodes the V views once, renders every grid ray of every view in checkpointed chunks
(``model.chunk_memory_mb``), computes the YOLO loss for all views and calls backward once
(activation checkpointing recomputes each chunk in the backward pass instead of the original's
backward per chunk).

Outputs in ``out_dir``: ``latest.pt`` (atomic; resume point), ``epoch_XXXX.pt`` (backup every ``train.save_every_epochs`` epochs),
``best.pt`` (best validation F1 at ``eval.select_iou``), ``log.jsonl`` (every step and event),
``epochs.csv``, ``vis/*.png``, ``config.yaml``. With ``train.ema_decay`` > 0 validation and the
checkpoints' ``model`` use the moving average of the weights (``pnyolo.engine.weight_average``); the
trained weights are kept in ``train_model`` to resume from.

Example::

    summary = train("out/dataset", load_config("configs/cpu.yaml"), "runs/cpu")
"""
from __future__ import annotations

import math
import random
import time
from pathlib import Path

import numpy as np
import torch
import yaml
from tqdm import tqdm

from dataset_spec.atomic import atomic_write_text
from dataset_spec.cli_support import UserError, check_output_dir
from pnyolo.components.losses import YoloLoss, surface_depth_loss
from pnyolo.components.occupancy import OccupancyLoss
from pnyolo.config import Config, to_dict
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.engine.checkpoint import (check_compatible, load_weights, make_payload, read_checkpoint, save_checkpoint,
                                     set_rng_state)
from pnyolo.engine.logs import JsonlLog, TensorBoardLog, append_csv, clear_run, run_outputs, truncate_logs
from pnyolo.engine.ray_selection import ignore_unrendered, own_view_dropout_mask, training_ray_mask
from pnyolo.engine.weight_average import WeightAverage
from pnyolo.evaluation.evaluate import evaluate_dataset, item_name
from pnyolo.evaluation.pictures import panel, write_png
from pnyolo.evaluation.postprocess import decode_with
from pnyolo.evaluation.report import headline
from pnyolo.models import build_model
from pnyolo.models import predict_item


VAL_PICTURES = 2  # validation items whose detections go to TensorBoard at every validation


class TrainingStopped(UserError):
    """Training stopped on repeated non-finite values (reported in one line)."""


def pick_device(name: str) -> torch.device:
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        if getattr(torch.backends, "mps", None) and torch.backends.mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise UserError(f"unknown device {name!r}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("device cuda requested but CUDA is not available")
    return dev


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def first_nonfinite_grad(model) -> str | None:
    for name, p in model.named_parameters():
        if p.grad is not None and not torch.isfinite(p.grad).all():
            return name
    return None


def training_rays(model, item, background_rays: float, own_view_dropout: float = 0.0):
    """(ray mask or None, targets, own-view drop mask or None) for one step of a model that renders
    rays: with ``train.background_rays`` < 1 it renders the target cells, their neighbours and that
    share of the background, the other cells are ignored by the loss; with ``train.own_view_dropout``
    > 0 that share of the rendered rays goes without its own view's features (pnyolo.engine.ray_selection)."""
    if not model.renders_rays:
        return None, item["targets"], None
    mask, targets = None, item["targets"]
    if background_rays < 1:
        mask = training_ray_mask(item["targets"], background_rays)
        targets = ignore_unrendered(item["targets"], mask)
    return mask, targets, own_view_dropout_mask(item["unseen_elsewhere_cells"], own_view_dropout, mask)


def loss_for(model, out, targets, loss_fn, device, item: dict | None = None):
    """The YOLO loss of ``out``; for a model with a depth head (``out.surface_depth``) the
    surface-depth term against ``item["surface_depth"]``; with ``loss.occupancy`` the per-sample 3D
    terms of the rendered samples (``out.samples``, pnyolo.components.occupancy)."""
    loss, terms = loss_fn(out.ray_confidence, out.box, out.class_logits, targets.to(device), model.anchors, out.depth)
    if out.samples is not None and loss_fn.cfg.occupancy > 0:
        extra, more = OccupancyLoss(loss_fn.cfg)(out.samples, targets, item["boxes_3d"], model.anchors)
        loss, terms = loss + extra, {**terms, **more}
    if out.surface_depth is not None:  # (config validation: model.surface_depth needs loss.surface_depth > 0)
        extra = loss_fn.cfg.surface_depth * surface_depth_loss(out.surface_depth, item["surface_depth"].to(device),
                                                               model.surface_stride)
        loss, terms = loss + extra, {**terms, "surface_depth": float(extra.detach())}
    return loss, terms


LR_SCHEDULES = ("exponential", "cosine")


def make_scheduler(optimizer, tc, total_steps: int):
    """``exponential``: lr * lr_decay ** epoch (stepped per epoch). ``cosine``: half a cosine from
    lr to ``lr_min_ratio * lr`` over ``total_steps`` optimizer steps (stepped per step)."""
    if tc.lr_schedule == "exponential":
        return torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=tc.lr_decay)
    if tc.lr_schedule == "cosine":
        span, floor = max(1, total_steps), tc.lr_min_ratio

        def factor(step: int) -> float:
            return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(step, span) / span))
        return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
    raise UserError(f"unknown train.lr_schedule {tc.lr_schedule!r}; known: {', '.join(LR_SCHEDULES)}")


def check_run_folder(out: Path, resume: bool, force: bool) -> None:
    """``out`` may take this run: writable, and holding no earlier run unless resumed or forced
    (a new run beside an old one would interleave their logs)."""
    check_output_dir(out)
    if resume and force:
        raise UserError("--resume and --force exclude each other: continue the run, or start it over")
    earlier = run_outputs(out)
    if resume and not (out / "latest.pt").is_file():
        raise UserError(f"--resume: no checkpoint {out / 'latest.pt'} to resume from")
    if earlier and not resume and not force:
        raise UserError(f"--out {out} already holds a training run ({earlier[0].name}); use --resume to continue "
                        "it, --force to start over (its checkpoints and logs are deleted), or another --out")


def train(root: str | Path, cfg: Config, out_dir: str | Path, resume: bool = False, quiet: bool = False,
          scenarios: list[str] | None = None, force: bool = False) -> dict:
    """Train; returns a summary dict (steps, last loss, best F1, paths). ``resume`` continues the
    run in ``out_dir`` exactly; ``force`` deletes an earlier run there first."""
    out = Path(out_dir)
    check_run_folder(out, resume, force)
    tc = cfg.train
    if tc.threads > 0:
        torch.set_num_threads(tc.threads)
    device = pick_device(tc.device)
    seed_everything(tc.seed)
    train_ds = MultiViewDataset(root, "train", cfg, training=True, scenarios=scenarios)
    val_ds = None
    if tc.val_every > 0 and scenarios is None and train_ds.ds.split("val"):
        val_ds = MultiViewDataset(root, "val", cfg, training=False, views=cfg.eval.views)
    class_names = train_ds.class_names
    model = build_model(cfg, len(class_names)).to(device)
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=tc.lr)
    steps_per_epoch = len(train_ds)
    total = tc.epochs * steps_per_epoch
    if tc.max_steps:
        total = min(total, tc.max_steps)
    scheduler = make_scheduler(optimizer, tc, tc.lr_schedule_steps or total)
    loss_fn = YoloLoss(cfg.loss)
    state = {"epoch": 0, "step": 0, "order": None, "pos": 0, "best_f1": -1.0, "bad_steps": 0}
    latest = out / "latest.pt"
    if resume:
        ckpt = read_checkpoint(latest)
        check_compatible(ckpt, cfg, class_names, latest)
        load_weights(model, ckpt.get("train_model") or ckpt["model"], latest)
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        state.update(ckpt["train_state"])
        set_rng_state(ckpt["rng"])
    average = None
    if tc.ema_decay > 0:
        average = WeightAverage(model, tc.ema_decay, updates=state["step"])  # one update per optimizer step
        if resume and "train_model" in ckpt:
            load_weights(average.model, ckpt["model"], latest)
    used = average.model if average else model  # what validation and the checkpoints' "model" hold
    if force:
        clear_run(out)
    if resume:  # the logs continue from the checkpoint: later records were redone, so they go
        truncate_logs(out, state["step"], state["epoch"])
    atomic_write_text(out / "config.yaml", yaml.safe_dump(to_dict(cfg), sort_keys=False))
    log = JsonlLog(out / "log.jsonl")
    if resume:
        log.write({"event": "resume", "step": state["step"], "epoch": state["epoch"]})
    (out / "vis").mkdir(exist_ok=True)
    board = TensorBoardLog(out / "tensorboard", state["step"] + 1 if resume else None) if tc.tensorboard else None

    def save(path: Path) -> None:
        extra = {"train_model": model.state_dict()} if average else {}
        save_checkpoint(path, **make_payload(used, optimizer, scheduler, cfg, class_names,
                                             train_state=dict(state), **extra))

    bar = tqdm(total=total, initial=min(state["step"], total), disable=quiet, dynamic_ncols=True, desc="train")
    last_loss = float("nan")
    model.train()
    stop = False
    while state["epoch"] < tc.epochs and not stop:
        if state["order"] is None:
            state["order"], state["pos"] = torch.randperm(len(train_ds)).tolist(), 0
        epoch_losses = []
        t_epoch = time.time()
        while state["pos"] < len(state["order"]):
            if tc.max_steps and state["step"] >= tc.max_steps:
                stop = True
                break
            t_step = time.perf_counter()
            item = train_ds[state["order"][state["pos"]]]
            state["pos"] += 1
            optimizer.zero_grad(set_to_none=True)
            ray_mask, targets, drop_own = training_rays(model, item, tc.background_rays, tc.own_view_dropout)
            out_v = predict_item(model, item, device, ray_mask, drop_own_view=drop_own,
                                 return_samples=model.renders_rays and cfg.loss.occupancy > 0)
            loss, terms = loss_for(model, out_v, targets, loss_fn, device, item)
            where = None
            if not torch.isfinite(loss):
                where = "loss " + ",".join(k for k, v in terms.items() if not math.isfinite(v))
            else:
                loss.backward()
                bad = first_nonfinite_grad(model)
                if bad:
                    where = f"gradient of {bad}"
            if where:
                state["bad_steps"] += 1
                optimizer.zero_grad(set_to_none=True)
                log.write({"event": "nonfinite", "where": where, "step": state["step"], "epoch": state["epoch"],
                           "scenario": item["scenario"], "variant": item["variant"], "views": item["views"]})
                if state["bad_steps"] >= tc.max_bad_steps:
                    save(out / "latest.pt")
                    raise TrainingStopped(f"stopped after {state['bad_steps']} consecutive non-finite steps "
                                          f"(last: {where}); see {out / 'log.jsonl'}")
                continue
            state["bad_steps"] = 0
            if tc.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(params, tc.grad_clip)
            optimizer.step()
            if average:
                average.update(model)
            if tc.lr_schedule == "cosine":
                scheduler.step()
            state["step"] += 1
            last_loss = float(loss.detach())
            epoch_losses.append(last_loss)
            if state["step"] % max(1, tc.log_every) == 0:
                log.write({"event": "step", "step": state["step"], "epoch": state["epoch"], "loss": last_loss,
                           **terms, "lr": optimizer.param_groups[0]["lr"],
                           "rays": 1.0 if ray_mask is None else round(float(ray_mask.float().mean()), 4),
                           "own_view_dropped": 0.0 if drop_own is None else round(float(drop_own.float().mean()), 4),
                           "scenario": item["scenario"],
                           "variant": item["variant"], "views": item["views"]})
            if board and state["step"] % max(1, tc.log_every) == 0:
                board.step(state["step"], last_loss, terms, optimizer.param_groups[0]["lr"], time.perf_counter() - t_step)
            bar.update(1)
            bar.set_postfix(loss=f"{last_loss:.4f}", epoch=state["epoch"])
            if tc.vis_every and state["step"] % tc.vis_every == 0:
                visualise(model, item, out_v, cfg, class_names, out / "vis" / f"step_{state['step']:07d}.png")
            if tc.checkpoint_every and state["step"] % tc.checkpoint_every == 0:
                save(latest)
        if stop:
            break
        # ---- end of epoch
        if tc.lr_schedule == "exponential":
            scheduler.step()
        state["epoch"] += 1
        state["order"], state["pos"] = None, 0
        row = {"epoch": state["epoch"], "step": state["step"], "train_loss": float(np.mean(epoch_losses)) if epoch_losses else float("nan"),
               "lr": optimizer.param_groups[0]["lr"], "seconds": round(time.time() - t_epoch, 2), "val_f1": ""}
        per_epoch_outputs = state["epoch"] % max(1, tc.save_every_epochs) == 0 or state["epoch"] >= tc.epochs
        if not tc.vis_every and per_epoch_outputs:
            visualise(model, item, None, cfg, class_names, out / "vis" / f"epoch_{state['epoch']:04d}.png")
        improved = False
        if val_ds is not None and state["epoch"] % tc.val_every == 0:
            summary = evaluate_dataset(used, val_ds, cfg, device).summary()
            f1 = headline(summary, cfg.eval.select_iou)
            row["val_f1"] = f1
            log.write({"event": "validation", "epoch": state["epoch"], "step": state["step"], "f1": f1,
                       "ap50": summary["ap50"]})
            if board:
                board.validation(state["step"], summary, cfg.eval.select_iou)
                for k in range(min(VAL_PICTURES, len(val_ds))):
                    val_item = val_ds[k]
                    board.picture(state["step"], f"val/{item_name(val_item)}",
                                  visualise(used, val_item, None, cfg, class_names))
            if f1 > state["best_f1"]:
                state["best_f1"], improved = f1, True
        append_csv(out / "epochs.csv", row)
        if per_epoch_outputs:
            save(latest)
            save(out / f"epoch_{state['epoch']:04d}.pt")
        if improved:
            save(out / "best.pt")
    if stop:
        save(latest)
    bar.close()
    if board:
        board.close()
    return {"steps": state["step"], "epoch": state["epoch"], "last_loss": last_loss, "best_f1": state["best_f1"],
            "latest": str(latest), "device": str(device)}


@torch.no_grad()
def visualise(model, item, out_v, cfg: Config, class_names, path: Path | None = None):
    """An item's panel of detections (H, W, 3) uint8, written to ``path`` if given."""
    was = model.training
    model.eval()
    out_v = predict_item(model, item, next(model.parameters()).device)
    dets = decode_with(out_v, model.anchors, item["grid"], cfg.eval)
    picture = panel(item, dets, class_names)
    if path is not None:
        write_png(path, picture)
    model.train(was)
    return picture
