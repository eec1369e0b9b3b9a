"""Where each model with 3D detections places what it finds (issue 87, the placement probe in every report): its
test results file (the one the devkit's DetectionEval scored) matched as the devkit matches for its true-positive
errors, each match's ground-plane error split along the nearest camera's line of sight and across it
(``pnyolo.evaluation.placement``)."""
from __future__ import annotations

import json

from pnyolo.bench.analyses import Analysis, register_analysis
from pnyolo.evaluation.bootstrap import UNIT


@register_analysis
class Placement(Analysis):
    name, title, order = "placement", "Where the 3D detections are placed: along the line of sight and across it", 20

    def measure(self, run) -> dict | None:
        from pnyolo.evaluation.devkit_eval import available
        from pnyolo.evaluation.placement import placement_of

        if not available():
            return None
        out = {}
        for kind in (k for k in run.preset.late_fusion if k in run.results):
            path = run.report / kind / "results_nusc_test.json"  # kept by the devkit's DetectionEval
            if path.is_file():
                figures = placement_of(run.data, "test", json.loads(path.read_text()))
                out[kind] = {c: {k: v for k, v in f.items() if k != "points"} for c, f in figures.items()}
        return out or None

    def lines(self, doc: dict, run) -> list[str]:
        lines = ["Each detection of the test results file the devkit scored, matched as its DetectionEval matches for "
                 "the true-positive errors (2 m, by score; buses and trucks as cars); its error split along the line of "
                 "sight from the nearest camera (radial: > 0 placed farther than it is) and across it. A radial share "
                 "near 1 that grows with distance says the depth along the ray is what limits placement. Standard "
                 f"errors: {UNIT}.", "",
                 "| model, class | distance | matches | median error (m) | RMS radial (m) | RMS lateral (m) | mean radial (m) "
                 "| radial share |", "|---|---|---:|---:|---:|---:|---:|---:|"]
        for kind, classes in doc.items():
            for cls, f in classes.items():
                lines += [f"| {kind}, {cls} | {r['bin']} | {r['n']} | {_f(r['median_error_m'])} | {_f(r['rms_radial_m'])} "
                          f"| {_f(r['rms_lateral_m'])} | {_f(r['mean_radial_m'])} | {_share(r)} |" for r in f["rows"]]
        dups = [f"{kind}, {cls}: {f['duplicates']} of {f['predictions']}" for kind, c in doc.items() for cls, f in c.items()]
        return lines + ["", "Detections within 1 m of a higher-scoring one of their class (what a suppression by centre "
                            "distance would remove): " + "; ".join(dups) + "."]


def _f(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def _share(r: dict) -> str:
    if r["radial_share"] is None:
        return "-"
    se = r["radial_share_se"]
    return f"{r['radial_share']:.2f}" + (f" ± {se:.2f}" if se is not None else "")
