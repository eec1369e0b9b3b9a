"""Late fusion's rule chosen on validation, like every model's operating point (``selection``)::

    choice = choose_late_fusion(preset, model, cfg, val_dataset)   # a LateChoice; cfg.eval set to it
    into = choose_late_into(preset, (sender, cfg), (ego, cfg_ego), ego_name, val_dataset)  # an IntoChoice

Three rules compete on the validation split, each at its own thresholds of the preset's confidence grid:
the best car's detection of each road user kept from one threshold on (the rule as first reported);
agreement (``pnyolo.evaluation.agreement``): cars send from one threshold on, the reports of a road user
are scored together by noisy-OR and kept from a second, higher one; and calibrated agreement, the same
with each report's score first replaced by its chance of being a road user given its score and its
distance from the sender (``pnyolo.evaluation.calibration``, fitted on the validation reports sent from
the lowest threshold). For each send threshold the keep threshold is chosen by the one-standard-error
rule (``select_threshold``); the candidate with the best validation F1 wins (ties: the simpler rule, then
the lower send threshold). Each car's own-view pass is run once per validation item; the rest is decoding.

Late fusion into an ego model (the preset's baseline, the single view): each target view's car keeps its
own detector's detections from one threshold on (at least the one chosen for it alone) and adds the other
cars' reports sent from another; both thresholds are those with the best validation F1.
"""
from __future__ import annotations

import numpy as np
import torch

from pnyolo.bench.presets import BenchPreset
from pnyolo.bench.record import AGREEMENT, BEST_CAR, CALIBRATED, INTO_EGO, IntoChoice, LateChoice
from pnyolo.bench.selection import select_threshold, sweep_views, _without_scenario_counts
from pnyolo.bench.stages import log
from pnyolo.decoding.world import project_into_views
from pnyolo.evaluation.calibration import calibrated, fit_calibration, report_labels, sender_distances
from pnyolo.evaluation.late_fusion import Ego, car_id, late_fusion, pool_cars
from pnyolo.models import predict_item


@torch.no_grad()
def choose_late_fusion(preset: BenchPreset, model, cfg, dataset) -> LateChoice:
    """The late-fusion rule and thresholds with the best validation F1@``preset.iou`` for ``model`` (set to its
    chosen operating point), written into ``cfg.eval`` (late_send, late_keep, late_calibration; the best-car
    rule leaves late_keep None and sets conf_threshold's stand-in late_send to its threshold)."""
    was = model.training
    model.eval()
    grid, ev = tuple(sorted(preset.conf_grid)), cfg.eval
    cars = []  # per item: (item, its views' world detections at the lowest threshold, their senders)
    for k in range(len(dataset)):
        item = dataset[k]
        out = predict_item(model, item, None, ev, own_view_only=True)
        dets = model.world_detections(out, ev, grid[0])
        cars.append((item, dets, [car_id(item, b) for b in range(len(dets))]))
    model.train(was)
    n = len(dataset.class_names)
    coef = list(fit_reports(cars, ev.centre_nms_m))
    log(f"late fusion, sender calibration on {sum(len(d) for _, ds, _ in cars for d in ds)} validation reports: "
        f"sigmoid({coef[0]:.2f} logit(s) {coef[1]:+.2f} d/10m {coef[2]:+.2f})")

    def rows(send: float | None, keep_grid: tuple[float, ...], calibration=None) -> list[dict]:
        return sweep_views([(item, project_into_views(pool_cars(calibrated([d.above(send or grid[0]) for d in dets], item,
                                                                           calibration), owners, ev.centre_nms_m,
                                                                None if send is None else 0.0), item, item.scored))
                            for item, dets, owners in cars], keep_grid, preset.iou, n)

    best_car = rows(None, grid)  # a threshold on the best car's score equals sending from it
    pick = select_threshold(best_car, seed=0)
    best = LateChoice(BEST_CAR, pick["threshold"], pick["threshold"], pick["val_f1"], pick["val_f1_se"],
                      pick["val_f1"], _without_scenario_counts(best_car), val_scenarios=pick["val_scenarios"])
    log(f"late fusion, best car: validation F1@{preset.iou} {pick['val_f1']:.3f} from {pick['threshold']:.2f}")
    for rule, calibration in ((AGREEMENT, None), (CALIBRATED, coef)):
        for send in grid:
            swept = rows(send, grid if calibration else tuple(t for t in grid if t >= send), calibration)
            pick = select_threshold(swept, seed=0)
            log(f"late fusion, {rule}: cars send from {send:.2f}, kept from {pick['threshold']:.2f}: validation "
                f"F1@{preset.iou} {pick['val_f1']:.3f} (standard error {pick['val_f1_se']:.3f})")
            if pick["val_f1"] > best.val_f1:
                best = LateChoice(rule, send, pick["threshold"], pick["val_f1"], pick["val_f1_se"],
                                  best.best_car_val_f1, _without_scenario_counts(swept), calibration,
                                  pick["val_scenarios"])
    ev.late_send, ev.late_keep = best.send, (None if best.rule == BEST_CAR else best.keep)
    ev.late_calibration = best.calibration
    return best


def fit_reports(cars: list, radius: float) -> tuple:
    """The sender calibration fitted on every car's reports of every item (``cars`` as above), each labelled by
    the item's 3D ground truth (``calibration.report_labels``)."""
    scores, distances, labels = [], [], []
    for item, dets, _ in cars:
        for b, d in enumerate(dets):
            scores.append(d.scores)
            distances.append(sender_distances(item, b, d))
            labels.append(report_labels(d, item, radius))
    if not scores:
        return fit_calibration(np.zeros(0), np.zeros(0), np.zeros(0))
    return fit_calibration(np.concatenate(scores), np.concatenate(distances), np.concatenate(labels))


@torch.no_grad()
def choose_late_into(preset: BenchPreset, sender: tuple, ego: tuple, ego_name: str, dataset) -> IntoChoice:
    """The send threshold of the ``sender`` (model, config) cars and the threshold of the ``ego`` (model,
    config) car's own detections (from its chosen threshold up, on the preset's grid) with the best
    validation F1@``preset.iou`` of late fusion into the ego (``late_fusion.Ego``); ties: lower thresholds."""
    (model, cfg), (ego_model, ego_cfg) = sender, ego
    was = model.training, ego_model.training
    model.eval()
    ego_model.eval()
    items = []
    for k in range(len(dataset)):
        item = dataset[k]
        own = ego_model.decode(predict_item(ego_model, item, None, ego_cfg.eval), item, ego_cfg.eval)
        items.append((item, own, predict_item(model, item, None, cfg.eval, own_view_only=True)))
    model.train(was[0])
    ego_model.train(was[1])
    n = len(dataset.class_names)
    alone = sweep_views([(item, own) for item, own, _ in items], (0.0,), preset.iou, n)[0]
    best, rows = None, []
    for ego_t in (t for t in sorted(preset.conf_grid) if t >= ego_cfg.eval.conf_threshold):
        for send in sorted(preset.conf_grid):
            decoded = [(item, late_fusion(model, item, None, cfg.eval, send, out,
                                          ego=Ego(own, ego_t, ego_cfg.eval.nms_iou))[0]) for item, own, out in items]
            row = sweep_views(decoded, (0.0,), preset.iou, n)[0]
            rows.append({"send": send, "ego_threshold": ego_t,
                         **{k: row[k] for k in ("f1", "precision", "recall", "hidden_seen_recall")}})
            if best is None or row["f1"] > best["f1"]:
                best = rows[-1]
    log(f"late fusion into {ego_name}: validation F1@{preset.iou} {best['f1']:.3f} with the other cars sending from "
        f"{best['send']:.2f} and its own detections from {best['ego_threshold']:.2f} ({ego_name} alone {alone['f1']:.3f})")
    return IntoChoice(INTO_EGO, ego_name, best["send"], best["ego_threshold"], best["f1"], alone["f1"], rows)
