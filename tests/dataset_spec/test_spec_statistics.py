"""dataset-spec info --plots: label histograms and hidden-but-seen counts, as JSON and pictures."""
from __future__ import annotations

import json
import shutil

from dataset_spec import Dataset
from dataset_spec.cli import main
from dataset_spec.statistics import label_statistics


def test_statistics_count_every_label_and_the_hidden_but_seen_ones(synthetic_dataset, tmp_path, capsys):
    from tools.projection import label_dataset

    root = shutil.copytree(synthetic_dataset, tmp_path / "ds")
    assert main(["info", str(root), "--plots", str(tmp_path / "no")]) == 2  # no labels yet: says how to make them
    assert "project-labels" in capsys.readouterr().err
    label_dataset(root, progress=False)
    ds = Dataset.open(root)
    stats = label_statistics(ds)
    for name in ds.scenario_names():
        views = {c.name: ds.read_labels(name, c.name) for c in ds.scenario(name).cameras}
        hidden = seen = 0
        for cam, vl in views.items():
            for o in vl.kept():
                if o.visible_fraction <= 0:
                    hidden += 1
                    seen += any(x.instance_id == o.instance_id and x.visible_pixels > 0
                                for other, ol in views.items() if other != cam for x in ol.objects)
        assert stats["scenarios"][name]["fully_hidden"] == hidden
        assert stats["scenarios"][name]["hidden_but_seen"] == seen
        assert stats["scenarios"][name]["labels"] == sum(len(vl.objects) for vl in views.values())
    for cls, s in stats["classes"].items():
        assert sum(s["visible_fraction"]["counts"]) == sum(s["distance"]["counts"]) == s["n"]
    assert main(["info", str(root), "--plots", str(tmp_path / "stats")]) == 0
    assert json.loads((tmp_path / "stats" / "statistics.json").read_text())["totals"] == stats["totals"]
    for picture in ("label_histograms.png", "hidden_but_seen.png"):
        assert (tmp_path / "stats" / picture).stat().st_size > 1000
    assert stats["totals"]["hidden_but_seen"] > 0
