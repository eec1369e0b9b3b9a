"""The field's ground-plane evaluation (Wildtrack, MultiviewX, MVDet and its successors): rows of
``frame grid_x grid_y`` for the ground truth (``gt.txt``) and for the detections, matched per frame
one to one (Hungarian, on the distance between grid positions) within 0.5 m, as their evaluators do::

    grid = GRIDS["wildtrack"]                                  # dataset_spec.ground_grid: 2.5 cm cells
    scores = clear_mod(read_rows("gt.txt"), read_rows("test.txt"), grid.cells(0.5))
    scores["moda"], scores["modp"], scores["precision"], scores["recall"]

MODA = 1 - (FP + FN) / N_gt; MODP = mean over matches of 1 - d / threshold; precision TP / (TP + FP);
recall TP / N_gt. A pair at exactly the threshold matches (the published ports mask distances
above it). The grids (``dataset_spec.ground_grid``) turn positions and grid cells into world metres.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dataset_spec.atomic import atomic_write_text
from dataset_spec.cli_support import UserError
from dataset_spec.ground_grid import GroundGrid
from dataset_spec.names import excerpt
from dataset_spec.rig_import import read_source
from pnyolo.evaluation.metrics_3d import matches_within


def frame_ranges(frames) -> str:
    """Frame numbers as runs: ``{0, 1, 2, 5}`` -> ``"0..2, 5"`` (at most six runs, then an ellipsis)."""
    runs: list[list[int]] = []
    for f in sorted(frames):
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    text = [f"{a}" if a == b else f"{a}..{b}" for a, b in runs[:6]]
    return ", ".join(text) + (", ..." if len(runs) > 6 else "")


def read_rows(path: str | Path, grid: GroundGrid | None = None, frames=None) -> np.ndarray:
    """A ``frame grid_x grid_y`` file (whitespace or commas; later columns ignored) -> (N, 3) float;
    one-line errors naming the file and the line: not text, not numbers, not finite, a frame that is
    not a whole number or (``frames``: the frame numbers a dataset has) not one of them, a position
    outside ``grid``."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path} does not exist")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file (expected 'frame grid_x grid_y' rows)") from None
    known = None if frames is None else {int(f) for f in frames}
    rows = []
    for k, line in enumerate(text.splitlines(), 1):
        parts = line.replace(",", " ").split()
        if not parts:
            continue
        where = f"{path}:{k}"
        try:
            row = [float(v) for v in parts[:3]]
        except ValueError:
            raise UserError(f"{where}: expected 'frame grid_x grid_y' numbers, got {excerpt(line.strip())}") from None
        if len(row) < 3:
            raise UserError(f"{where}: expected 'frame grid_x grid_y', got {excerpt(line.strip())}")
        if not all(np.isfinite(row)):
            raise UserError(f"{where}: numbers must be finite, got {excerpt(line.strip())}")
        if row[0] % 1:
            raise UserError(f"{where}: frame {row[0]:g} is not a whole number")
        if known is not None and int(row[0]) not in known:
            raise UserError(f"{where}: frame {int(row[0])} is not a frame of the dataset (its frames: "
                            f"{frame_ranges(known)})")
        if grid is not None and not (0 <= row[1] < grid.nx and 0 <= row[2] < grid.ny):
            raise UserError(f"{where}: position ({row[1]:g}, {row[2]:g}) is outside the dataset's {grid.nx} x {grid.ny} "
                            "ground grid (rows of another dataset?)")
        rows.append(row)
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def write_rows(path: str | Path, rows) -> None:
    """(N, 3) ``frame grid_x grid_y`` rows as the field's evaluators read them (integers, atomic)."""
    rows = np.asarray(rows).reshape(-1, 3)
    atomic_write_text(Path(path), "".join(f"{int(f)} {int(round(x))} {int(round(y))}\n" for f, x, y in rows))


def clear_mod(gt: np.ndarray, pred: np.ndarray, threshold: float) -> dict:
    """MODA, MODP, precision and recall of ``pred`` against ``gt`` ((N, 3) rows, distances and
    ``threshold`` in the rows' units: grid cells), every frame of either counted."""
    gt, pred = np.asarray(gt, dtype=np.float64).reshape(-1, 3), np.asarray(pred, dtype=np.float64).reshape(-1, 3)
    tp = fp = fn = 0
    closeness = []
    for frame in np.unique(np.concatenate([gt[:, 0], pred[:, 0]])):
        g, p = gt[gt[:, 0] == frame, 1:], pred[pred[:, 0] == frame, 1:]
        d = np.hypot(p[:, None, 0] - g[None, :, 0], p[:, None, 1] - g[None, :, 1])
        found = matches_within(d, threshold)
        tp, fp, fn = tp + len(found), fp + len(p) - len(found), fn + len(g) - len(found)
        closeness += [1 - dist / threshold for _, _, dist in found]
    n_gt = len(gt)
    return {"moda": 1 - (fp + fn) / n_gt if n_gt else None, "modp": float(np.mean(closeness)) if closeness else None,
            "precision": tp / (tp + fp) if tp + fp else None, "recall": tp / n_gt if n_gt else None,
            "tp": tp, "fp": fp, "fn": fn, "n_gt": n_gt}


class GroundRows:
    """A ground-plane detector's pedestrians on a dataset imported from Wildtrack / MultiviewX
    (``dataset-spec import``, whose ``extras.source`` gives the grid and the frames): per frame
    (an item showing every camera of the rig) the ground truth and the detections as grid rows,
    scored by ``clear_mod`` at ``threshold_m`` and written as ``gt.txt`` / ``detections.txt``."""

    def __init__(self, source: dict, class_index: int, threshold_m: float = 0.5):
        g = source["grid"]
        self.grid = GroundGrid(int(g["nx"]), int(g["ny"]), float(g["cell_m"]), tuple(g["origin_m"]))
        self.source_from_world = np.linalg.inv(np.asarray(source["world_from_source"], dtype=np.float64))
        self.frames, self.class_index, self.threshold_m = source["frames"], class_index, threshold_m
        self.gt: list[np.ndarray] = []
        self.det: list[np.ndarray] = []
        self.skipped = 0

    @classmethod
    def for_dataset(cls, dataset, model) -> "GroundRows | None":
        """For a model with world detections on an imported dataset (a MultiViewDataset); else None."""
        source = read_source(dataset.ds.info.extras, str(dataset.ds.layout.dataset_json))
        if not (source and model.world_outputs and "pedestrian" in dataset.class_names):
            return None
        return cls(source, dataset.class_names.index("pedestrian"))

    def _rows(self, frame: int, centres: np.ndarray) -> np.ndarray:
        src = (self.source_from_world[:3, :3] @ centres.reshape(-1, 3).T).T + self.source_from_world[:3, 3]
        xy = self.grid.xy_of_world(src[:, :2])
        return np.concatenate([np.full((len(xy), 1), frame), xy], axis=1)

    def add(self, item, detections, num_cameras: int) -> None:
        """One item's ground truth (its pedestrians' boxes) and world ``detections``; an item that
        does not show all ``num_cameras`` cameras of its frame is not a frame of the benchmark."""
        if len(item.views) != num_cameras or item.scenario not in self.frames:
            self.skipped += 1
            return
        frame = int(self.frames[item.scenario])
        boxes = item.boxes_3d.numpy().astype(np.float64).reshape(-1, 7)
        people = boxes[item.box_classes.numpy() == self.class_index, :3]
        self.gt.append(self._rows(frame, people))
        self.det.append(self._rows(frame, detections.boxes[detections.classes == self.class_index, :3]))

    def add_ground_truth(self, ds, scenarios: list[str]) -> None:
        """The pedestrians of ``scenarios`` (a dataset_spec Dataset's), one frame each, as ground-truth rows."""
        for name in scenarios:
            people = [a.box.center for a in ds.scenario(name).actors if a.cls == "pedestrian"]
            self.gt.append(self._rows(int(self.frames[name]), np.asarray(people, dtype=np.float64).reshape(-1, 3)))

    def finish(self, folder: str | Path) -> dict:
        """The scores (and the rows written to ``folder``), or why there are none."""
        if not self.gt:
            return {"skipped": f"no item showed every camera of its frame ({self.skipped} items): "
                               "set data.num_views to the rig's camera count"}
        gt, det = np.concatenate(self.gt), np.concatenate(self.det)
        write_rows(Path(folder) / "gt.txt", gt)
        write_rows(Path(folder) / "detections.txt", det)
        return {**clear_mod(gt, det, self.grid.cells(self.threshold_m)), "threshold_m": self.threshold_m,
                "frames": len(self.gt), "grid": [self.grid.nx, self.grid.ny, self.grid.cell_m]}


def score_ground_file(dataset_root: str | Path, predictions: str | Path, split: str, out: str | Path) -> int:
    """``pnyolo-eval --results PRED.txt DATASET``: another tool's ``frame grid_x grid_y`` rows scored
    against the ground truth of ``split`` of an imported dataset, on its grid (rows of other frames
    are not counted); writes ``metrics.json`` and the ground truth's ``gt.txt`` to ``out``."""
    import json

    from dataset_spec import Dataset
    from dataset_spec.atomic import atomic_write_json

    ds = Dataset.open(dataset_root)
    source = read_source(ds.info.extras, str(ds.layout.dataset_json))
    if not source:
        raise UserError(f"{dataset_root} has no ground grid (not imported with dataset-spec import): "
                        "score 'frame grid_x grid_y' rows on Wildtrack / MultiviewX imports")
    rows = GroundRows(source, 0)
    rows.add_ground_truth(ds, ds.split(split))
    if not rows.gt:
        raise UserError(f"split {split!r} of {dataset_root} has no frames")
    gt = np.concatenate(rows.gt)
    pred = read_rows(predictions, rows.grid, rows.frames.values())
    pred = pred[np.isin(pred[:, 0], np.unique(gt[:, 0]))]  # frames of the dataset's other splits are not counted
    scores = {**clear_mod(gt, pred, rows.grid.cells(rows.threshold_m)), "threshold_m": rows.threshold_m,
              "frames": len(rows.gt), "results": str(predictions), "split": split}
    write_rows(Path(out) / "gt.txt", gt)
    atomic_write_json(Path(out) / "metrics.json", {"ground_plane": scores})
    print(json.dumps({k: scores[k] for k in ("moda", "modp", "precision", "recall", "frames")})
          + f"; report in {out}")
    return 0
