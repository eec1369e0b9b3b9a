"""Late fusion's rule chosen on validation, like every model's operating point (``selection``)::

    choice = choose_late_fusion(preset, cars, cfg)        # a LateChoice; choice.point(cfg.eval): the point with it
    into = choose_late_into(preset, cars, cfg, ego_preds, cfg_ego, ego_name)   # an IntoChoice

``cars`` are the sender model's own-view detections on validation (``cooperation.senders.OwnViews``), ``ego_preds``
the ego model's validation predictions: nothing here runs a model.

Three rules compete on the validation split, each at its own thresholds of the preset's confidence grid:
the best car's detection of each road user kept from one threshold on (the rule as first reported);
agreement (``pnyolo.cooperation.agreement``): cars send from one threshold on, the reports of a road user
are scored together by noisy-OR and kept from a second, higher one; and calibrated agreement, the same
with each report's score first replaced by its chance of being a road user given its score and its
distance from the sender (``pnyolo.cooperation.calibration``, fitted on the validation reports sent from
the lowest threshold). For each send threshold the keep threshold is chosen by the one-standard-error
rule (``select_threshold``); the candidate with the best validation F1 wins (ties: the simpler rule, then
the lower send threshold).

Late fusion into an ego model (the preset's baseline, the single view): each target view's car keeps its
own detector's detections from one threshold on (at least the one chosen for it alone) and adds the other
cars' reports sent from another; both thresholds are those with the best validation F1.
"""
from __future__ import annotations

import numpy as np

from pnyolo.bench.presets import BenchPreset
from pnyolo.bench.record import AGREEMENT, BEST_CAR, CALIBRATED, INTO_EGO, IntoChoice, LateChoice
from pnyolo.bench.selection import select_threshold, sweep_views, _without_layout_counts
from pnyolo.bench.stages import log
from pnyolo.decoding.world import project_into_views
from pnyolo.evaluation.bootstrap import spread_text
from pnyolo.cooperation.calibration import calibrated, fit_calibration, report_labels, sender_distances
from pnyolo.cooperation.late_fusion import Ego, LateRule, car_id, late_fusion, pool_cars


def choose_late_fusion(preset: BenchPreset, own, cfg) -> LateChoice:
    """The late-fusion rule and thresholds with the best validation F1@``preset.iou`` for the model whose own-view
    validation detections ``own`` holds (``OwnViews``, the model at its chosen operating point, ``cfg``): a
    ``LateChoice``, whose ``point(cfg.eval)`` is the operating point with the rule (nothing is written)."""
    grid, ev = tuple(sorted(preset.conf_grid)), cfg.eval
    cars = [(p.item, [m.detections for m in own.messages(p.item, grid[0])], [car_id(p.item, b) for b in
                                                                             range(len(p.item.views))])
            for p in own.preds.items]  # per item: its views' world detections at the lowest threshold, their senders
    n = len(cars[0][0].class_names) if cars else 0
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
                      pick["val_f1"], _without_layout_counts(best_car), val_layouts=pick["val_layouts"])
    log(f"late fusion, best car: validation F1@{preset.iou} {pick['val_f1']:.3f} from {pick['threshold']:.2f}")
    for rule, calibration in ((AGREEMENT, None), (CALIBRATED, coef)):
        for send in grid:
            swept = rows(send, grid if calibration else tuple(t for t in grid if t >= send), calibration)
            pick = select_threshold(swept, seed=0)
            log(f"late fusion, {rule}: cars send from {send:.2f}, kept from {pick['threshold']:.2f}: validation "
                f"F1@{preset.iou} {pick['val_f1']:.3f} (standard error {spread_text(pick['val_f1_se'], pick['val_layouts'])})")
            if pick["val_f1"] > best.val_f1:
                best = LateChoice(rule, send, pick["threshold"], pick["val_f1"], pick["val_f1_se"],
                                  best.best_car_val_f1, _without_layout_counts(swept), calibration,
                                  pick["val_layouts"])
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


def choose_late_into(preset: BenchPreset, cars, cfg, ego_preds, ego_cfg, ego_name: str) -> IntoChoice:
    """The send threshold of the sender cars (their own-view validation detections ``cars``, decoded by ``cfg``)
    and the threshold of the ego car's own detections (``ego_preds``, the ego model's validation predictions
    decoded by ``ego_cfg``; from its chosen threshold up, on the preset's grid) with the best validation
    F1@``preset.iou`` of late fusion into the ego (``late_fusion.Ego``); ties: lower thresholds."""
    items = [(p.item, ego_preds.detections_at(k, ego_cfg.eval)) for k, p in enumerate(ego_preds.items)]
    n = len(items[0][0].class_names) if items else 0
    alone = sweep_views(items, (0.0,), preset.iou, n)[0]
    best, rows = None, []
    for ego_t in (t for t in sorted(preset.conf_grid) if t >= ego_cfg.eval.conf_threshold):
        for send in sorted(preset.conf_grid):
            rule = LateRule.of(cfg.eval, send)
            decoded = [(item, late_fusion(cars.messages(item, send), item, rule,
                                          ego=Ego(own, ego_t, ego_cfg.eval.nms_iou))) for item, own in items]
            row = sweep_views(decoded, (0.0,), preset.iou, n)[0]
            rows.append({"send": send, "ego_threshold": ego_t,
                         **{k: row[k] for k in ("f1", "precision", "recall", "hidden_seen_recall")}})
            if best is None or row["f1"] > best["f1"]:
                best = rows[-1]
    log(f"late fusion into {ego_name}: validation F1@{preset.iou} {best['f1']:.3f} with the other cars sending from "
        f"{best['send']:.2f} and its own detections from {best['ego_threshold']:.2f} ({ego_name} alone {alone['f1']:.3f})")
    return IntoChoice(INTO_EGO, ego_name, best["send"], best["ego_threshold"], best["f1"], alone["f1"], rows)
