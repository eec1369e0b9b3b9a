#!/usr/bin/env bash
# YOLOv8n (Ultralytics, from its yaml: no weights can be downloaded) trained on a dataset's YOLO export for
# the same wall time as one of our trained runs, its confidence threshold chosen on validation (best F1@0.2),
# then scored here with pnyolo-eval --results on the test split (OUT/eval_test: at that threshold; AP50 from
# every detection in OUT/eval_test_all).
# Usage: benchmarks/compare_yolov8.sh DATASET RUN_DIR OUT   (RUN_DIR holds the run's bench_timing.json)
# Needs the environment of ../shared/tools/ultralytics-offline/setup.sh in OUT/ultra (built here if missing).
set -euo pipefail
DATASET=$1; RUN=$2; OUT=$3
ROOT=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$OUT"; OUT=$(cd "$OUT" && pwd); DATASET=$(cd "$DATASET" && pwd)
SECONDS_BUDGET=$(python3 -c "import json,sys; print(json.load(open('$RUN/bench_timing.json'))['seconds'])")
echo "[yolov8] wall-time budget: ${SECONDS_BUDGET} s (the run in $RUN)"
"$ROOT/.venv/bin/project-labels" "$DATASET" --no-labelling --export yolo --variant all --out "$OUT/exports" --quiet
[ -f "$OUT/ultra/env.sh" ] || bash "$ROOT/../shared/tools/ultralytics-offline/setup.sh" "$OUT/ultra"
(
  source "$OUT/ultra/env.sh"
  cd "$OUT"
  python - "$OUT" "$SECONDS_BUDGET" <<'PY'
import sys, time
from ultralytics import YOLO
out, budget = sys.argv[1], float(sys.argv[2])
data = f"{out}/exports/yolo/data.yaml"
model = YOLO("yolov8n.yaml")
t0 = time.time()
model.train(data=data, imgsz=320, epochs=1000, time=budget / 3600, pretrained=False, amp=False, device="cpu",
            workers=0, plots=False, project=f"{out}/runs", name="train", exist_ok=True, verbose=False)
print(f"[yolov8] trained {time.time() - t0:.0f} s")
for split in ("val", "test"):
    YOLO(f"{out}/runs/train/weights/best.pt").val(data=data, split=split, save_json=True, imgsz=320, device="cpu",
                                                  plots=False, project=f"{out}/runs", name=split, exist_ok=True,
                                                  conf=0.001, verbose=False)
PY
)
"$ROOT/.venv/bin/python" - "$OUT" "$DATASET" <<'PY'
import json, subprocess, sys
out, dataset = sys.argv[1], sys.argv[2]
def score(split, threshold, name):
    rows = [r for r in json.load(open(f"{out}/runs/{split}/predictions.json")) if r["score"] >= threshold]
    json.dump(rows, open(f"{out}/{name}.json", "w"))
    subprocess.run([f"{sys.prefix}/bin/pnyolo-eval", "--results", f"{out}/{name}.json", dataset, "--split", split,
                    "--variant", "all", "--out", f"{out}/{name}", "--quiet"], check=True, capture_output=True)
    return json.load(open(f"{out}/{name}/metrics.json"))
val = {t: score("val", t, f"eval_val_{t}")["strict"]["0.2"]["f1"] for t in (0.05, 0.1, 0.2, 0.3, 0.45, 0.6)}
best = max(val, key=val.get)
test, every = score("test", best, "eval_test"), score("test", 0.0, "eval_test_all")
hidden = test["recall_by_visibility"]["0.2"].get("hidden here, seen in another view", {}).get("recall")
print(f"[yolov8] confidence {best} (validation F1@0.2 {val[best]:.3f}): test F1@0.2 {test['strict']['0.2']['f1']:.3f}, "
      f"hidden-but-seen recall {hidden}, AP50 {every['ap50']:.3f} (every detection)")
PY
