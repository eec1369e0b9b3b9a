"""The viewer's hover pages in a real browser: headless Chromium names the actor under the pointer."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from dataset_spec import Dataset
from tools.viewer import hover_page

CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
selenium = pytest.importorskip("selenium", reason="selenium is not installed (it comes with the test extra)")
pytestmark = pytest.mark.skipif(not (CHROMIUM and DRIVER),
                                reason="no headless Chromium here: install Debian's chromium and chromium-driver "
                                       "(.ci/run does)")


@pytest.fixture(scope="module")
def browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=900,700"):
        opts.add_argument(flag)
    driver = webdriver.Chrome(service=Service(DRIVER), options=opts)
    yield driver
    driver.quit()


def test_pointer_over_two_actors_shows_their_id_name_and_class(browser, synthetic_dataset, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    ds = Dataset.open(synthetic_dataset)
    scn = ds.scenario("toy_01")
    cam = scn.cameras[0]
    page = tmp_path / "view.html"
    page.write_text(hover_page(ds, "toy_01", cam.name, scale=4))
    browser.get(page.as_uri())
    img = browser.find_element(By.ID, "view")
    info = browser.find_element(By.ID, "info")
    inst = ds.read_instance("toy_01", cam.name)
    by_id = {a.id: a for a in scn.actors}
    ids = [i for i, n in zip(*np.unique(inst, return_counts=True)) if i and n >= 6 and by_id[i].cls in ("car", "pedestrian")]
    assert len(ids) >= 2
    w, h = img.size["width"], img.size["height"]
    for actor_id in ids[:2]:
        v, u = np.argwhere(inst == actor_id)[len(np.argwhere(inst == actor_id)) // 2]
        x = (u + 0.5) * w / inst.shape[1] - w / 2  # offsets from the element's centre (Selenium 4)
        y = (v + 0.5) * h / inst.shape[0] - h / 2
        ActionChains(browser).move_to_element_with_offset(img, int(round(x)), int(round(y))).perform()
        actor = by_id[int(actor_id)]
        assert info.text == f"pixel ({u}, {v}): id {actor_id} {actor.name} ({actor.cls})"  # (spaces collapsed)
    v, u = np.argwhere(inst == 0)[0]
    ActionChains(browser).move_to_element_with_offset(
        img, int(round((u + 0.5) * w / inst.shape[1] - w / 2)), int(round((v + 0.5) * h / inst.shape[0] - h / 2))).perform()
    assert info.text.endswith("nothing (id 0)")


def test_hostile_names_reach_the_page_as_text_and_no_script_runs(browser, synthetic_dataset, tmp_path, monkeypatch):
    """Names the readers refuse can still reach a page through the API (a Scenario built in memory):
    the page shows them as text and runs none of them."""
    from dataclasses import replace

    from selenium.webdriver.common.by import By

    ds = Dataset.open(synthetic_dataset)
    scn = ds.scenario("toy_01")
    cam = scn.cameras[0]
    inst, rgb = ds.read_instance("toy_01", cam.name), ds.read_rgb("toy_01", cam.name, scn.lighting[0].name)
    hostile_actor = '<img src=x onerror="window.pwned=1">'
    hostile_camera = "<svg onload=window.pwned=2></svg>"
    ds._scenarios["toy_01"] = replace(scn, actors=[replace(a, name=hostile_actor) for a in scn.actors])
    monkeypatch.setattr(ds, "read_instance", lambda *a: inst)
    monkeypatch.setattr(ds, "read_rgb", lambda *a: rgb)
    page = tmp_path / "hostile.html"
    page.write_text(hover_page(ds, "toy_01", hostile_camera, scale=2))
    browser.get(page.as_uri())
    assert browser.execute_script("return window.pwned") is None
    assert hostile_camera in browser.title and hostile_camera in browser.find_element(By.TAG_NAME, "h3").text
    legend = browser.find_element(By.ID, "legend").text
    assert hostile_actor in legend
    assert not browser.find_elements(By.CSS_SELECTOR, "#legend img, h3 svg")
