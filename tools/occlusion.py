"""Occlusion statistics over labelled views: how hidden are the actors, and does another view help?

Each (actor, camera) pair with a label (the actor reaches into the camera's frustum) falls in one bin
of its visible fraction ``v``:

=================  ===========================  =====================================
bin                rule                         KITTI occlusion level
=================  ===========================  =====================================
``fully_hidden``   v == 0                       2 (largely occluded)
``mostly_hidden``  0 < v < 0.4                  2
``partly_hidden``  0.4 <= v < 0.8               1
``visible``        v >= 0.8                     0
``unmeasured``     no silhouette pixel in image 3 (not in the bins above)
=================  ===========================  =====================================

*Hidden* means fully or mostly hidden (v < 0.4). A hidden pair is *seen elsewhere* when the same
actor of the same scenario has v >= 0.4 (at least partly visible) in at least one other camera:
the cases a multi-view detector can recover and a single-view one cannot.

Usage::

    stats = occlusion_statistics(label_scenario(ds, "toy_01", write=False))
    print(format_statistics(stats))
"""
from __future__ import annotations

from collections import defaultdict

from dataset_spec import Dataset, LabelThresholds, ViewLabels

from .projection import LARGELY_OCCLUDED_BELOW, PARTLY_OCCLUDED_BELOW, label_scenario

BINS = ("fully_hidden", "mostly_hidden", "partly_hidden", "visible")
SEEN_ELSEWHERE_MIN_VISIBLE = LARGELY_OCCLUDED_BELOW


def visibility_bin(visible_fraction: float) -> str:
    """Name of the bin of a visible fraction (see the module table)."""
    if visible_fraction <= 0.0:
        return "fully_hidden"
    if visible_fraction < LARGELY_OCCLUDED_BELOW:
        return "mostly_hidden"
    return "partly_hidden" if visible_fraction < PARTLY_OCCLUDED_BELOW else "visible"


def _empty_counts() -> dict:
    return {"pairs": 0, **{b: 0 for b in BINS}, "unmeasured": 0, "hidden": 0, "hidden_seen_elsewhere": 0}


def occlusion_statistics(labels: list[ViewLabels]) -> dict:
    """Counts per visibility bin over all (actor, camera) pairs in ``labels`` (JSON-serialisable).

    Returns ``{"pairs", "fully_hidden", "mostly_hidden", "partly_hidden", "visible", "unmeasured",
    "hidden", "hidden_seen_elsewhere", "hidden_seen_elsewhere_fraction", "per_class": {cls: counts},
    "bins": {...the rules...}}``. ``pairs`` counts every labelled pair, ``unmeasured`` included.
    """
    # Best visible fraction of each actor per camera, to look up "another camera".
    views: dict[tuple[str, int], dict[str, float]] = defaultdict(dict)
    for vl in labels:
        for o in vl.objects:
            if o.amodal_pixels > 0:
                views[(vl.scenario, o.instance_id)][vl.camera] = o.visible_fraction

    total = _empty_counts()
    per_class: dict[str, dict] = defaultdict(_empty_counts)
    for vl in labels:
        for o in vl.objects:
            for counts in (total, per_class[o.cls]):
                counts["pairs"] += 1
            if o.amodal_pixels <= 0:
                for counts in (total, per_class[o.cls]):
                    counts["unmeasured"] += 1
                continue
            name = visibility_bin(o.visible_fraction)
            hidden = o.visible_fraction < LARGELY_OCCLUDED_BELOW
            elsewhere = hidden and any(cam != vl.camera and v >= SEEN_ELSEWHERE_MIN_VISIBLE
                                       for cam, v in views[(vl.scenario, o.instance_id)].items())
            for counts in (total, per_class[o.cls]):
                counts[name] += 1
                counts["hidden"] += int(hidden)
                counts["hidden_seen_elsewhere"] += int(elsewhere)
    for counts in [total, *per_class.values()]:
        counts["hidden_seen_elsewhere_fraction"] = (counts["hidden_seen_elsewhere"] / counts["hidden"]
                                                    if counts["hidden"] else None)
    total["per_class"] = {k: per_class[k] for k in sorted(per_class)}
    total["bins"] = {"fully_hidden": "visible_fraction == 0",
                     "mostly_hidden": f"0 < visible_fraction < {LARGELY_OCCLUDED_BELOW}",
                     "partly_hidden": f"{LARGELY_OCCLUDED_BELOW} <= visible_fraction < {PARTLY_OCCLUDED_BELOW}",
                     "visible": f"visible_fraction >= {PARTLY_OCCLUDED_BELOW}",
                     "seen_elsewhere": f"visible_fraction >= {SEEN_ELSEWHERE_MIN_VISIBLE} in another camera"}
    return total


def label_and_measure(ds: Dataset, scenario: str, thresholds: LabelThresholds | None = None) -> list[ViewLabels]:
    """The labelling stage of one scenario: every view's labels.json written and the scenario's
    occlusion statistics stored in its extras (``occlusion``), as ``blender-gen render`` and
    ``project-labels`` leave every scenario they touch."""
    labels = label_scenario(ds, scenario, thresholds, write=True)
    scn = ds.scenario(scenario)
    scn.extras["occlusion"] = occlusion_statistics(labels)
    ds.write_scenario(scn)
    return labels


def format_statistics(stats: dict) -> str:
    """A few human-readable lines summarising ``occlusion_statistics`` output."""
    def line(name: str, c: dict) -> str:
        frac = c["hidden_seen_elsewhere_fraction"]
        seen = "n/a" if frac is None else f"{c['hidden_seen_elsewhere']} ({100 * frac:.0f}%)"
        return (f"{name}: {c['pairs']} actor-camera pairs: {c['visible']} visible, {c['partly_hidden']} partly, "
                f"{c['mostly_hidden']} mostly, {c['fully_hidden']} fully hidden, {c['unmeasured']} unmeasured; "
                f"hidden but seen by another camera: {seen}")

    return "\n".join([line("all", stats)] + [line(k, v) for k, v in stats["per_class"].items()])
