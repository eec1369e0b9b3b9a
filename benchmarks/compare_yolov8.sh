#!/usr/bin/env bash
# YOLOv8n (Ultralytics, from its yaml: no weights can be downloaded) trained on a dataset's YOLO export for
# the same wall time as one of our trained runs, then scored here with pnyolo-eval --results on the test split.
# Usage: benchmarks/compare_yolov8.sh DATASET RUN_DIR OUT   (RUN_DIR holds bench_timing.json or log.jsonl)
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
  python - "$OUT/exports/yolo/data.yaml" "$SECONDS_BUDGET" <<'PY'
import sys, time
from ultralytics import YOLO
data, budget = sys.argv[1], float(sys.argv[2])
model = YOLO("yolov8n.yaml")
t0 = time.time()
model.train(data=data, imgsz=320, epochs=1000, time=budget / 3600, pretrained=False, amp=False, device="cpu",
            workers=0, plots=False, project="runs", name="train", exist_ok=True, verbose=False)
print(f"[yolov8] trained {time.time() - t0:.0f} s")
model.val(data=data, split="test", save_json=True, imgsz=320, device="cpu", plots=False, project="runs",
          name="test", exist_ok=True, conf=0.001)
PY
)
"$ROOT/.venv/bin/pnyolo-eval" --results "$OUT/runs/test/predictions.json" "$DATASET" --split test --variant all \
  --out "$OUT/eval"
