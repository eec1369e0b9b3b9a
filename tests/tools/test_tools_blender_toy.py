"""Projection tool on the Blender-rendered toy scene: mesh silhouettes agree with Cycles' object ids.

Skips without bpy (the ``blender_toy_dataset`` fixture renders once per session, ~10 s).
"""
from __future__ import annotations

import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.boxes import box_iou
from tools.occlusion import occlusion_statistics
from tools.projection import label_scenario


@pytest.fixture(scope="module")
def toy_labels(blender_toy_dataset):
    ds = Dataset.open(blender_toy_dataset)
    name = ds.scenario_names()[0]
    return ds, name, label_scenario(ds, name, write=False)  # the fixture is read-only


def test_unoccluded_actors_silhouette_equals_rendered_segmentation(toy_labels):
    ds, name, views = toy_labels
    n_checked = 0
    for vl in views:
        inst = ds.read_instance(name, vl.camera)
        for o in vl.objects:
            ys, xs = np.nonzero(inst == o.instance_id)
            assert o.visible_pixels <= o.amodal_pixels + max(2, 0.02 * o.amodal_pixels)
            if xs.size:
                seg = np.array([xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5])
                assert np.all(seg[:2] >= np.array(o.extras["silhouette_box"][:2]) - 1)
                assert np.all(seg[2:] <= np.array(o.extras["silhouette_box"][2:]) + 1)
            if o.visible_fraction >= 0.99 and o.in_frame_fraction == 1.0 and o.amodal_pixels >= 40:
                assert np.allclose(seg, o.extras["silhouette_box"], atol=1.0)  # mesh silhouette = render
                if o.cls == "car":  # box-shaped: segmentation box ~ amodal 3D-box projection
                    assert box_iou(seg, o.box)[0, 0] >= 0.8
                    n_checked += 1
    assert n_checked >= 2


def test_hidden_pedestrian_is_hidden_in_one_view_and_seen_in_another(toy_labels):
    ds, name, views = toy_labels
    scn = ds.scenario(name)
    hidden = [a.id for a in scn.actors if a.name == "ped_hidden"]
    if not hidden:
        pytest.skip("the toy scene has no 'ped_hidden' actor any more")
    fractions = [o.visible_fraction for vl in views for o in vl.objects if o.instance_id == hidden[0]]
    assert min(fractions) < 0.4 and max(fractions) >= 0.4
    stats = occlusion_statistics(views)
    assert stats["hidden_seen_elsewhere"] >= 1
