"""The frame from above: road users coloured by what the target camera sees of them, the hidden-but-seen
ones marked found or missed by the first model, as a picture."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_pnyolo_common import make_dataset, small_config

from pnyolo.data.dataset import MultiViewDataset
from pnyolo.decoding.detections import ViewDetections
from pnyolo.evaluation.top_down import HIDDEN_SEEN, SEEN, ground_status, hidden_seen_found, top_down


def _perfect(gt) -> ViewDetections:
    return ViewDetections(gt.boxes.copy(), np.ones(len(gt.boxes)), gt.classes.copy(), None, gt.centres)


def test_hidden_but_seen_road_users_are_found_by_a_perfect_detector_and_missed_by_none(tmp_path):
    root = make_dataset(tmp_path / "ds", n_scenarios=2)
    ds = MultiViewDataset(root, "train", small_config(), training=False, views=[0, 1, 2])
    marked = 0
    for k in range(len(ds)):
        item = ds[k]
        for v in item.scored:
            gt, status = item.gt[v], ground_status(item, v)
            hidden_seen = {int(r) for j, r in enumerate(gt.object_rows)
                           if gt.visible_fraction[j] <= 1e-6 and gt.seen_elsewhere[j]}
            assert {r for r, c in status.items() if c == HIDDEN_SEEN} == hidden_seen
            assert {r for r, c in status.items() if c == SEEN} == {int(r) for j, r in enumerate(gt.object_rows)
                                                                   if gt.visible_fraction[j] > 1e-6}
            assert sorted(hidden_seen_found(item, _perfect(gt), v, 0.2)) == [(r, True) for r in sorted(hidden_seen)]
            empty = ViewDetections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=np.int64))
            assert all(not ok for _, ok in hidden_seen_found(item, empty, v, 0.2))
            marked += len(hidden_seen)
    assert marked > 0  # the toy scenes hold such road users
    item = ds[0]
    rgb = top_down(item, {"oracle": [_perfect(g) for g in item.gt]}, item.scored[0], 0.2)
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.shape[0] > 300
    green = np.array([44, 160, 44])  # tab:green, the seen road users' fill
    assert (np.abs(rgb.astype(int) - green).sum(axis=-1) < 30).sum() > 20


def test_a_sequence_from_above_is_one_gif_frame_per_frame(tmp_path):
    from PIL import Image

    from dataset_spec.synthetic import write_synthetic_dataset
    from pnyolo.evaluation.top_down import SequenceMovie
    from tools.projection import label_dataset

    root = write_synthetic_dataset(tmp_path / "seq", n_scenarios=1, frames=3, fps=2.0)
    label_dataset(root, progress=False)
    ds = MultiViewDataset(root, "train", small_config(), training=False, views=[0, 1, 2])
    movie = SequenceMovie(0.2)
    for k in reversed(range(len(ds))):  # in any order
        item = ds[k]
        placed = [replace(_perfect(g), world_boxes=item.boxes_3d.numpy().astype(float)[g.object_rows]) for g in item.gt]
        movie.add(item, {"oracle": placed}, 2.0)
    trails = movie.tracks()  # the oracle's road users tracked over the frames: one trail each, growing
    moving = [a for a in trails[2].values() if np.linalg.norm(a[-1] - a[0]) > 0.5]
    assert sorted(trails) == [0, 1, 2] and len(trails[2]) == len(ds[0].gt[ds[0].scored[0]].boxes)
    assert all(len(a) == 3 for a in trails[2].values()) and moving  # the synthetic sequence's movers
    movie.write(tmp_path / "out")
    gifs = list((tmp_path / "out").glob("*_top_down.gif"))
    assert len(gifs) == 1 and gifs[0].name == f"{ds[0].scenario}_top_down.gif"
    with Image.open(gifs[0]) as gif:
        assert gif.n_frames == 3 and gif.info["duration"] == 500
    single = SequenceMovie(0.2)
    single.add(ds[0], {"oracle": [_perfect(g) for g in ds[0].gt]}, None)  # one instant: no movie
    single.write(tmp_path / "none")
    assert not (tmp_path / "none").exists()
