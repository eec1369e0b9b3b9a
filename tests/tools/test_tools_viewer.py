"""Segmentation viewer: palette separation, output sizes, legend entries, HTML id map, CLI errors."""
from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from dataset_spec import Dataset
from tools.palette import colour_distance, colourise, id_colour
from tools.projection import label_dataset
from tools.viewer import (LEGEND_WIDTH, LINE_HEIGHT, TITLE_HEIGHT, contact_sheet, hover_page, legend_entries,
                          read_hover_page_ids, view_image)


@pytest.fixture(scope="module")
def ds(synthetic_dataset, tmp_path_factory):
    root = shutil.copytree(synthetic_dataset, tmp_path_factory.mktemp("view") / "ds")
    label_dataset(root, progress=False)
    return Dataset.open(root)


def test_neighbouring_ids_get_clearly_different_colours():
    gaps = [colour_distance(id_colour(i), id_colour(i + 1)) for i in range(1, 3000)]
    assert min(gaps) > 150  # of a maximum of ~441
    assert colour_distance(id_colour(13), id_colour(14)) > 150
    assert min(colour_distance(id_colour(i), (0, 0, 0)) for i in range(1, 500)) > 150  # never like background
    assert np.array_equal(id_colour(0), [0, 0, 0]) and np.array_equal(id_colour(37), id_colour(37))


def test_colourise_maps_each_id_to_its_colour():
    ids = np.array([[0, 13], [14, 13]], np.uint16)
    rgb = colourise(ids)
    assert rgb.shape == (2, 2, 3) and rgb.dtype == np.uint8
    assert np.array_equal(rgb[0, 1], id_colour(13)) and np.array_equal(rgb[1, 1], id_colour(13))
    assert np.array_equal(rgb[1, 0], id_colour(14)) and np.array_equal(rgb[0, 0], [0, 0, 0])


def test_legend_lists_exactly_the_ids_in_view(ds):
    inst = ds.read_instance("toy_01", "cam_1")
    entries = legend_entries(ds, "toy_01", inst)
    assert [e["id"] for e in entries] == sorted(set(np.unique(inst).tolist()) - {0})
    scn = ds.scenario("toy_01")
    for e in entries:
        assert (e["name"], e["class"]) == (scn.actor(e["id"]).name, scn.actor(e["id"]).cls)
        assert e["colour"] == id_colour(e["id"]).tolist()


@pytest.mark.parametrize("mode, panels", [("side", 2), ("overlay", 1), ("seg", 1)])
def test_view_image_sizes(ds, mode, panels):
    n_legend = len(legend_entries(ds, "toy_01", ds.read_instance("toy_01", "cam_0")))
    img = view_image(ds, "toy_01", "cam_0", mode=mode, scale=3)
    assert img.shape == (max(48 * 3, LINE_HEIGHT * n_legend + 6), panels * 64 * 3 + LEGEND_WIDTH, 3)
    bare = view_image(ds, "toy_01", "cam_0", mode=mode, scale=2, legend=False, labels=False)
    assert bare.shape == (96, panels * 128, 3)


def test_side_view_shows_the_segmentation_colours(ds):
    inst = ds.read_instance("toy_01", "cam_0")
    img = view_image(ds, "toy_01", "cam_0", mode="side", labels=False, legend=False)
    assert np.array_equal(img[:, 64:], colourise(inst))
    assert np.array_equal(img[:, :64], ds.read_rgb("toy_01", "cam_0", "noon"))


def test_label_boxes_are_drawn_on_the_rgb_panel(ds):
    plain = view_image(ds, "toy_01", "cam_0", labels=False, legend=False, scale=4)
    boxed = view_image(ds, "toy_01", "cam_0", labels=True, legend=False, scale=4)
    changed = np.any(plain != boxed, axis=2)
    assert changed[:, :256].sum() > 50 and changed[:, 256:].sum() == 0
    o = ds.read_labels("toy_01", "cam_0").objects[0]
    x0, y0 = ((o.box[:2] + 0.5) * 4).round().astype(int)
    assert np.array_equal(boxed[y0 + 2, x0], id_colour(o.instance_id))  # left edge in the id's colour


def test_contact_sheet_size(ds):
    sheet = contact_sheet(ds, "toy_01", scale=2)
    n_cams = len(ds.scenario("toy_01").cameras)
    assert sheet.shape == (2 * TITLE_HEIGHT + n_cams * 96, 90 + 4 * 128, 3)


def test_hover_page_embeds_the_id_map_and_legend(ds):
    html = hover_page(ds, "toy_02", "cam_2")
    ids, legend = read_hover_page_ids(html)
    inst = ds.read_instance("toy_02", "cam_2")
    assert np.array_equal(ids, inst)
    assert {e["id"] for e in legend} == set(np.unique(inst).tolist()) - {0}
    assert "mousemove" in html and "data:image/png;base64," in html and "http" not in html.replace("http-equiv", "")


def test_cli_writes_pngs_and_pages(ds, tmp_path, capsys):
    from tools.viewer_cli import main

    assert main([str(ds.root), "--scenario", "toy_03", "--camera", "cam_1", "--out", str(tmp_path), "--scale", "2"]) == 0
    files = sorted(p.name for p in (tmp_path / "toy_03").iterdir())
    assert files == ["cam_1.html", "cam_1_instance_side.png", "contact_sheet.png"]
    img = cv2.imread(str(tmp_path / "toy_03" / "cam_1_instance_side.png"))
    assert img.shape[1] == 2 * 128 + LEGEND_WIDTH


@pytest.mark.parametrize("extra, needle", [([], "not a dataset folder"), (["--scenario", "nope"], "no scenario")])
def test_cli_errors_are_one_line(ds, tmp_path, capsys, extra, needle):
    from tools.viewer_cli import main

    root = str(tmp_path) if not extra else str(ds.root)
    assert main([root, *extra, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1
