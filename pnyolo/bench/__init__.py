"""The occlusion benchmark (``pnyolo-bench``): ``presets`` (preset files in configs/bench, validated),
``stages`` (render, label, train), ``selection`` (operating points chosen on validation, then test),
``report`` (report.md, report.json), ``cli`` (the command)."""
