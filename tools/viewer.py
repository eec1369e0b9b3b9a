"""Segmentation viewer: colourised id maps, overlays, legends, label boxes, contact sheets, HTML.

All images are (H, W, 3) uint8 RGB. Ids are coloured by ``tools.palette`` (neighbouring ids far
apart); instance maps use hue offset 0, semantic (class) maps ``SEMANTIC_OFFSET``.

Usage::

    img = view_image(ds, "toy_01", "cam_0", mode="side", labels=True)    # RGB | ids | legend
    write_png("out/toy_01_cam_0.png", img)
    sheet = contact_sheet(ds, "toy_01")     # cameras x [RGB | depth | segmentation | labels]
    html = hover_page(ds, "toy_01", "cam_0")   # self-contained page: id/name/class under the cursor
"""
from __future__ import annotations

import base64
import html
import json

import cv2
import numpy as np

from dataset_spec import Dataset, Label2D
from dataset_spec.atomic import atomic_path
from dataset_spec.errors import SpecError

from .palette import colourise, id_colour

SEMANTIC_OFFSET = 0.31
FONT = cv2.FONT_HERSHEY_SIMPLEX
TEXT_SCALE = 0.4
LINE_HEIGHT = 16
SWATCH = 12
LEGEND_WIDTH = 220
TITLE_HEIGHT = 18
MODES = ("side", "overlay", "seg")


# ----------------------------------------------------------------------------- building blocks
def write_png(path, rgb: np.ndarray) -> None:
    """Write an RGB uint8 image as PNG, atomically."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        buf.tofile(tmp)


def write_gif(path, frames: list[np.ndarray], fps: float | None) -> None:
    """Write RGB uint8 frames as an animated GIF (looping, ``fps`` frames a second), atomically."""
    from PIL import Image

    images = [Image.fromarray(np.ascontiguousarray(f)) for f in frames]
    with atomic_path(path) as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], loop=0,
                       duration=int(round(1000 / (fps or 1.0))))


def upscale(img: np.ndarray, scale: int) -> np.ndarray:
    """Nearest-neighbour enlargement (ids stay crisp)."""
    return img if scale == 1 else np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)


def depth_to_rgb(depth: np.ndarray) -> np.ndarray:
    """Planar depth (H, W) -> colour map, near bright; 0 (no surface) black."""
    valid = depth > 0
    out = np.zeros(depth.shape + (3,), np.uint8)
    if valid.any():
        inv = np.zeros_like(depth, dtype=np.float64)
        inv[valid] = 1.0 / depth[valid]
        lo, hi = inv[valid].min(), inv[valid].max()
        norm = np.where(valid, (inv - lo) / max(hi - lo, 1e-12), 0.0)
        coloured = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
        out[valid] = cv2.cvtColor(coloured, cv2.COLOR_BGR2RGB)[valid]
    return out


def overlay(rgb: np.ndarray, ids: np.ndarray, alpha: float = 0.55, offset: float = 0.0) -> np.ndarray:
    """Blend id colours over an RGB image where ids > 0."""
    seg = colourise(ids, offset).astype(np.float64)
    out = rgb.astype(np.float64)
    mask = ids > 0
    out[mask] = (1 - alpha) * out[mask] + alpha * seg[mask]
    return np.round(out).astype(np.uint8)


def draw_labels(img: np.ndarray, labels: list[Label2D], scale: int = 1) -> np.ndarray:
    """Draw 2D label boxes (in the image's original pixel units times ``scale``) with id and visible fraction."""
    out = np.ascontiguousarray(img.copy())
    for o in labels:
        colour = tuple(int(c) for c in id_colour(o.instance_id))
        x0, y0, x1, y1 = ((np.asarray(o.box) + 0.5) * scale).round().astype(int)
        cv2.rectangle(out, (x0, y0), (x1 - 1, y1 - 1), colour, 1)
        text = f"{o.instance_id} v" + ("?" if o.visible_fraction is None else f"{o.visible_fraction:.2f}")
        cv2.putText(out, text, (x0 + 1, max(y0 - 2, 9)), FONT, TEXT_SCALE * 0.8, colour, 1, cv2.LINE_AA)
    return out


def titled(img: np.ndarray, title: str) -> np.ndarray:
    """Put a title bar above an image."""
    bar = np.full((TITLE_HEIGHT, img.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, title, (3, TITLE_HEIGHT - 5), FONT, TEXT_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, img])


def legend_entries(ds: Dataset, scenario: str, ids: np.ndarray) -> list[dict]:
    """Legend rows for the instance ids present in ``ids``: ``{"id", "name", "class", "colour"}``.

    Ids with no actor in the scenario table are listed as ``unknown``.
    """
    scn = ds.scenario(scenario)
    known = {a.id: a for a in scn.actors}
    rows = []
    for i in np.unique(ids):
        i = int(i)
        if i == 0:
            continue
        actor = known.get(i)
        rows.append({"id": i, "name": actor.name if actor else "unknown", "class": actor.cls if actor else "unknown",
                     "colour": [int(c) for c in id_colour(i)]})
    return rows


def semantic_legend_entries(ds: Dataset, class_ids: np.ndarray) -> list[dict]:
    present = {int(i) for i in np.unique(class_ids)} - {0}
    return [{"id": c.id, "name": c.name, "class": c.name, "colour": [int(v) for v in id_colour(c.id, SEMANTIC_OFFSET)]}
            for c in ds.info.classes if c.id in present]


def legend_image(entries: list[dict], height: int, width: int = LEGEND_WIDTH) -> np.ndarray:
    """A white panel with one swatch + ``id name (class)`` line per entry; at least ``height`` tall."""
    h = max(height, LINE_HEIGHT * len(entries) + 6)
    panel = np.full((h, width, 3), 255, np.uint8)
    for k, e in enumerate(entries):
        y = 4 + k * LINE_HEIGHT
        cv2.rectangle(panel, (4, y), (4 + SWATCH, y + SWATCH), tuple(e["colour"]), -1)
        cv2.putText(panel, f"{e['id']} {e['name']} ({e['class']})", (8 + SWATCH, y + SWATCH - 2), FONT, TEXT_SCALE,
                    (0, 0, 0), 1, cv2.LINE_AA)
    return panel


def _pad_to_height(img: np.ndarray, height: int) -> np.ndarray:
    if img.shape[0] >= height:
        return img
    return np.vstack([img, np.full((height - img.shape[0],) + img.shape[1:], 255, np.uint8)])


# ----------------------------------------------------------------------------- views
def _variant(ds: Dataset, scenario: str, variant: str | None) -> str:
    names = [v.name for v in ds.scenario(scenario).lighting]
    if variant is None:
        if not names:
            raise SpecError(ds.layout.scenario_json(scenario), "scenario has no lighting variants")
        return names[0]
    if variant not in names:
        raise SpecError(ds.layout.scenario_json(scenario), f"no lighting variant {variant!r} (has: {names})")
    return variant


def _view_labels(ds: Dataset, scenario: str, camera: str, frame: int = 0) -> list[Label2D] | None:
    path = ds.layout.labels(scenario, camera, frame)
    return ds.read_labels(scenario, camera, frame).objects if path.is_file() else None


def view_image(ds: Dataset, scenario: str, camera: str, variant: str | None = None, mode: str = "side",
               semantic: bool = False, labels: bool = True, scale: int = 1, legend: bool = True,
               frame: int = 0) -> np.ndarray:
    """One view (at ``frame`` of a sequence) as a picture.

    ``mode``: ``"side"`` = RGB | colourised ids, ``"overlay"`` = ids blended over RGB, ``"seg"`` = ids only.
    ``semantic`` colours classes instead of instances. ``labels`` draws stored 2D boxes (when labels.json
    exists) on the RGB panel. Width = panels * W * scale (+ ``LEGEND_WIDTH`` with ``legend``);
    height = max(H * scale, legend rows).
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    ids = ds.read_semantic(scenario, camera, frame) if semantic else ds.read_instance(scenario, camera, frame)
    offset = SEMANTIC_OFFSET if semantic else 0.0
    seg = colourise(ids, offset)
    if mode == "seg":
        panels = [seg]
    else:
        rgb = ds.read_rgb(scenario, camera, _variant(ds, scenario, variant), frame)
        panels = [rgb, seg] if mode == "side" else [overlay(rgb, ids, offset=offset)]
    panels = [upscale(p, scale) for p in panels]
    stored = _view_labels(ds, scenario, camera, frame) if labels else None
    if stored:
        panels[0] = draw_labels(panels[0], stored, scale)
    image = np.hstack(panels)
    if legend:
        entries = semantic_legend_entries(ds, ids) if semantic else legend_entries(ds, scenario, ids)
        panel = legend_image(entries, image.shape[0])
        image = np.hstack([_pad_to_height(image, panel.shape[0]), panel])
    return image


def picture_pixels(ds: Dataset, scenario: str, cameras: list, scale: int, mode: str, sheet: bool) -> int:
    """Pixels of the pictures of ``scenario`` as ``contact_sheet`` (``sheet``: one, every camera's row at the first
    camera's size, as it resizes them) or ``view_image`` makes them (one per camera of ``cameras``, each at its own
    size, the legend at its width), from the cameras' sizes alone: what a command will write."""
    first = ds.scenario(scenario).cameras[0]
    if sheet:
        w, h = first.width * scale, first.height * scale
        return (90 + 4 * w) * (2 * TITLE_HEIGHT + h * len(ds.scenario(scenario).cameras))
    return sum(((2 if mode == "side" else 1) * c.width * scale + LEGEND_WIDTH) * c.height * scale for c in cameras)


def contact_sheet(ds: Dataset, scenario: str, variant: str | None = None, scale: int = 1, frame: int = 0) -> np.ndarray:
    """All cameras of a scenario (at ``frame``), one row each: RGB | depth | segmentation | labels (titled columns).

    Each cell is W * scale x H * scale (cameras of other sizes are resized to the first camera's),
    plus a title bar on top of the sheet and the camera name left of each row.
    """
    scn = ds.scenario(scenario)
    variant = _variant(ds, scenario, variant)
    w0, h0 = scn.cameras[0].width * scale, scn.cameras[0].height * scale
    rows = []
    for cam in scn.cameras:
        rgb = ds.read_rgb(scenario, cam.name, variant, frame)
        inst = ds.read_instance(scenario, cam.name, frame)
        cells = [rgb, depth_to_rgb(ds.read_depth(scenario, cam.name, frame)), colourise(inst), overlay(rgb, inst, 0.35)]
        cells = [cv2.resize(upscale(c, scale), (w0, h0), interpolation=cv2.INTER_NEAREST) for c in cells]
        stored = _view_labels(ds, scenario, cam.name, frame)
        if stored:
            sx, sy = w0 / cam.width, h0 / cam.height
            cells[3] = draw_labels(cells[3], stored, scale) if (sx, sy) == (scale, scale) else cells[3]
        name = np.full((h0, 90, 3), 255, np.uint8)
        cv2.putText(name, cam.name, (3, h0 // 2), FONT, TEXT_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
        rows.append(np.hstack([name] + cells))
    header = np.hstack([np.full((TITLE_HEIGHT, 90, 3), 255, np.uint8)] +
                       [titled(np.zeros((0, w0, 3), np.uint8), t) for t in ("RGB", "depth", "segmentation", "labels")])
    when = f", frame {frame}" if scn.frames > 1 else ""
    return titled(np.vstack([header] + rows), f"{scenario} ({variant}{when})")


STRIP_FRAMES = 50  # a strip and its animation show at most this many frames, spread over the sequence
STRIP_WIDTH = 480  # pixels: wider frames are shrunk in a strip (memory bounded whatever the input declares)


def strip_frames(count: int, most: int = STRIP_FRAMES) -> list[int]:
    """The frames a strip shows: every one up to ``most``, else ``most`` spread evenly (first and last kept)."""
    if count <= most:
        return list(range(count))
    return sorted({int(round(k * (count - 1) / (most - 1))) for k in range(most)})


def time_strip(ds: Dataset, scenario: str, camera: str, variant: str | None = None, scale: int = 1,
               columns: int = 5) -> tuple[np.ndarray, list[np.ndarray]]:
    """One camera over a sequence: a contact sheet of its frames' RGB with their labels (``columns`` a row,
    each titled with its frame and time) and those frames (for an animation): at most ``STRIP_FRAMES`` of
    them, each at most ``STRIP_WIDTH`` wide, so memory stays bounded for any sequence (the title says so)."""
    scn = ds.scenario(scenario)
    variant = _variant(ds, scenario, variant)
    seq = ds.sequence(scenario)
    shown = strip_frames(scn.frames)
    frames = []
    for f in shown:
        img = upscale(ds.read_rgb(scenario, camera, variant, f), scale)
        stored = _view_labels(ds, scenario, camera, f)
        img = draw_labels(img, stored, scale) if stored else img
        if img.shape[1] > STRIP_WIDTH:
            img = cv2.resize(img, (STRIP_WIDTH, max(1, img.shape[0] * STRIP_WIDTH // img.shape[1])),
                             interpolation=cv2.INTER_AREA)
        frames.append(titled(img, f"frame {f}  t = {seq.frames[f].time_s:.2f} s"))
    blank = np.full_like(frames[0], 255)
    rows = [np.hstack((frames[k:k + columns] + [blank] * columns)[:columns]) for k in range(0, len(frames), columns)]
    which = "" if len(shown) == scn.frames else f" ({len(shown)} shown, spread evenly)"
    return titled(np.vstack(rows), f"{scenario} / {camera} ({variant}), {scn.frames} frames at {scn.fps or 1:g} fps"
                  + which), frames


# ----------------------------------------------------------------------------- HTML
_HTML = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{title}</title>
<style>body{{font-family:sans-serif;margin:12px}} #wrap{{position:relative;display:inline-block}}
img{{image-rendering:pixelated;width:{css_w}px;height:{css_h}px;display:block}}
#info{{margin-top:6px;font-size:15px;min-height:1.3em}} td{{padding:0 6px}}</style></head>
<body><h3>{title}</h3>
<div id="wrap"><img id="view" src="data:image/png;base64,{png}" alt="view"></div>
<div id="info">move the mouse over the image</div>
<table id="legend"></table>
<script type="application/json" id="idmap">{idmap}</script>
<script>
const meta = JSON.parse(document.getElementById("idmap").textContent);
const raw = atob(meta.ids_base64);
const ids = new Uint16Array(meta.width * meta.height);
for (let i = 0; i < ids.length; i++) ids[i] = raw.charCodeAt(2 * i) | (raw.charCodeAt(2 * i + 1) << 8);
const table = {{}};
for (const e of meta.legend) table[e.id] = e;
const img = document.getElementById("view"), info = document.getElementById("info");
img.addEventListener("mousemove", ev => {{
  const r = img.getBoundingClientRect();
  const u = Math.floor((ev.clientX - r.left) / r.width * meta.width);
  const v = Math.floor((ev.clientY - r.top) / r.height * meta.height);
  if (u < 0 || v < 0 || u >= meta.width || v >= meta.height) return;
  const id = ids[v * meta.width + u], e = table[id];
  info.textContent = `pixel (${{u}}, ${{v}}): ` + (id === 0 ? "nothing (id 0)" :
      `id ${{id}}  ${{e ? e.name : "unknown"}}  (${{e ? e["class"] : "unknown"}})`);
}});
const leg = document.getElementById("legend");
for (const e of meta.legend) {{  // dataset strings enter the page as text, never as markup
  const row = leg.insertRow(), swatch = row.insertCell();
  swatch.style.background = `rgb(${{e.colour.map(Number).join(",")}})`;
  swatch.style.width = "14px";
  for (const value of [e.id, e.name, e["class"]]) row.insertCell().textContent = String(value);
}}
</script></body></html>
"""


def hover_page(ds: Dataset, scenario: str, camera: str, variant: str | None = None, scale: int = 4,
               frame: int = 0) -> str:
    """A self-contained HTML page: the view (ids over RGB) and the id/name/class under the mouse.

    The instance map is embedded as base64 of little-endian uint16 values (row-major) in a JSON
    block ``<script id="idmap">`` with ``width``, ``height``, ``ids_base64`` and ``legend``.
    """
    inst = ds.read_instance(scenario, camera, frame)
    rgb = ds.read_rgb(scenario, camera, _variant(ds, scenario, variant), frame)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(overlay(rgb, inst, 0.45), cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError("PNG encoding failed")
    meta = {"scenario": scenario, "camera": camera, "frame": frame, "width": int(inst.shape[1]), "height": int(inst.shape[0]),
            "ids_base64": base64.b64encode(inst.astype("<u2").tobytes()).decode("ascii"),
            "legend": legend_entries(ds, scenario, inst)}
    return _HTML.format(title=html.escape(f"{scenario} / {camera}"), png=base64.b64encode(buf.tobytes()).decode("ascii"),
                        css_w=inst.shape[1] * scale, css_h=inst.shape[0] * scale,
                        idmap=json.dumps(meta).replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026"))


def read_hover_page_ids(html: str) -> tuple[np.ndarray, list[dict]]:
    """Parse the embedded id map and legend back out of a ``hover_page`` (for tests and tools)."""
    start = html.index('<script type="application/json" id="idmap">') + len('<script type="application/json" id="idmap">')
    meta = json.loads(html[start:html.index("</script>", start)])
    ids = np.frombuffer(base64.b64decode(meta["ids_base64"]), dtype="<u2").reshape(meta["height"], meta["width"])
    return ids, meta["legend"]
