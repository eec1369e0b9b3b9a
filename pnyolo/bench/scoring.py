"""A trained model's predictions as the bench's analyses read them, each (model, split, condition) predicted once
(``pnyolo.engine.predict``), packaged as evaluation's ``Scoring``: here, above both, so that ``engine`` imports no
analysis::

    scoring = predict_scoring(trained, dataset, own=True)   # .clean, .own (each view alone), .cars (their messages)
"""
from __future__ import annotations

from pnyolo.cooperation.senders import OwnViews
from pnyolo.engine.predict import Condition, Trained, predict
from pnyolo.evaluation.evaluate import Scoring


def predict_scoring(t: Trained, dataset, clean: bool = True, own: bool = False, samples: bool = False,
                    device=None):
    """``t``'s predictions on ``dataset`` at its operating point as an ``evaluation.evaluate.Scoring``: ``clean``
    (with the samples it queried where ``samples``), every view alone where ``own`` (the own-view ablation and,
    for a kind with 3D detections, the cars' messages, ``cooperation.senders.OwnViews``)."""
    ev = t.config.eval
    own_preds = predict(t.model, dataset, ev, Condition(own_view=True), device) if own else None
    return Scoring(t.config, predict(t.model, dataset, ev, Condition(samples=samples), device) if clean else None,
                   own_preds, OwnViews(own_preds, ev) if own and t.decoding.world_outputs else None)
