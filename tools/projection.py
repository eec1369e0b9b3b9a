"""2D labels from 3D actors: amodal boxes, in-frame and visible fractions, occlusion, distance.

For each camera, every actor of a detectable class whose 3D box is partly in front of the camera
(and nearer than ``far``) and whose silhouette covers at least one pixel centre of the image gets
a ``Label2D``, fully occluded ones included (the camera's own car, ``mounted_on``, is skipped). Actors of other
classes (ground, walls, buildings) get no label but still occlude, because the visible pixels
come from the rendered instance segmentation.

Measures (see ``dataset_spec.labels2d.Label2D``):

* ``box``: the 3D box clipped at the near plane, projected, clipped to the image.
* ``in_frame_fraction``: the share of the actor's 3D box inside the camera's view frustum
  (``dataset_spec.boxes.frustum_fraction``): how much of the road user is in frame. Unlike a share
  of the image-plane silhouette it stays meaningful for a road user beside the camera whose box
  crosses the near plane (its silhouette there grows without bound).
* ``visible_fraction``: instance pixels / in-image silhouette pixels, clipped to [0, 1].
* ``occlusion_level`` (KITTI): 0 if visible >= 0.8, 1 if >= 0.4, 2 below (3, unknown, is
  never written: an actor without silhouette pixels in the image gets no label).
* ``distance``: camera centre to box centre, metres.

Usage::

    from tools.projection import label_dataset, label_view
    n_views = label_dataset("out/dataset")                  # writes labels.json for every view
    labels = label_view(ds, "toy_01", "cam_0")              # one view, not written
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dataset_spec import Actor, CameraInfo, Dataset, Label2D, LabelThresholds, Scenario, ViewLabels
from dataset_spec.boxes import box_in_view, frustum_fraction
from dataset_spec.camera import points_to_camera, project_camera_points
from dataset_spec.synthetic import BOX_FACES

from .silhouette import clip_triangles_near, measure_silhouettes, rasterise_mask

# Visible-fraction bounds of the KITTI occlusion levels (also used by tools.occlusion).
PARTLY_OCCLUDED_BELOW = 0.8
LARGELY_OCCLUDED_BELOW = 0.4
UNKNOWN_OCCLUSION = 3

Mesh = tuple[np.ndarray, np.ndarray]  # world vertices (N, 3), triangle faces (M, 3)


def kitti_occlusion_level(visible_fraction: float, measurable: bool = True) -> int:
    """KITTI occlusion level from a visible fraction: 0 fully visible, 1 partly, 2 largely, 3 unknown."""
    if not measurable:
        return UNKNOWN_OCCLUSION
    if visible_fraction >= PARTLY_OCCLUDED_BELOW:
        return 0
    return 1 if visible_fraction >= LARGELY_OCCLUDED_BELOW else 2


def actor_mesh(ds: Dataset, scenario: str, actor: Actor) -> Mesh:
    """The actor's world-space mesh, or its 3D box as 12 triangles when it has no mesh."""
    if actor.mesh is not None:
        return ds.read_mesh(scenario, actor.id)
    return actor.box.corners, BOX_FACES


def scenario_meshes(ds: Dataset, scenario: Scenario, actor_ids=None) -> dict[int, Mesh]:
    """Meshes of the detectable actors of a scenario (or of ``actor_ids``), keyed by actor id."""
    detectable = set(ds.info.detectable_classes)
    return {a.id: actor_mesh(ds, scenario.name, a) for a in scenario.actors
            if (a.id in actor_ids if actor_ids is not None else a.cls in detectable)}


def amodal_mask(camera: CameraInfo, mesh: Mesh) -> np.ndarray:
    """(H, W) bool: the image pixels the actor's whole silhouette covers, hidden parts included (the
    pixels ``Label2D.amodal_pixels`` counts)."""
    vertices, faces = mesh
    tris = points_to_camera(camera.camera_to_world, np.asarray(vertices, dtype=np.float64))[np.asarray(faces)]
    tris, _ = clip_triangles_near(tris, max(camera.near, 1e-4))
    return rasterise_mask(project_camera_points(camera.K, tris), camera.width, camera.height)


def _candidates(camera: CameraInfo, actors: list[Actor], detectable: set[str]):
    """Detectable actors whose 3D box reaches into the frustum: (actor, (clipped 2D box, distance)) by
    the one rule of ``dataset_spec.boxes.box_in_view``."""
    out = []
    for actor in actors:
        if actor.cls not in detectable or actor.id == camera.mounted_on:
            continue
        seen = box_in_view(camera.K, camera.camera_to_world, camera.width, camera.height, camera.near, camera.far,
                           actor.box.center, actor.box.size, actor.box.yaw)
        if seen is not None:
            out.append((actor, seen))
    return out


def measure_view(camera: CameraInfo, actors: list[Actor], meshes: dict[int, Mesh], instance: np.ndarray,
                 detectable: set[str]) -> list[Label2D]:
    """Labels of one view from its camera, actors, actor meshes and instance ids (H, W).

    ``meshes`` maps actor id -> (vertices (N, 3) world, faces (M, 3)); missing actors use their box.
    """
    if instance.shape != (camera.height, camera.width):
        raise ValueError(f"instance map is {instance.shape}, camera {camera.name} is {camera.height}x{camera.width}")
    cands = _candidates(camera, actors, detectable)
    if not cands:
        return []
    verts, tris_idx, groups, base = [], [], [], 0
    for g, (actor, _) in enumerate(cands):
        v, f = meshes.get(actor.id) or (actor.box.corners, BOX_FACES)
        verts.append(np.asarray(v, dtype=np.float64))
        tris_idx.append(np.asarray(f, dtype=np.int64) + base)
        groups.append(np.full(len(f), g))
        base += len(v)
    cam_pts = points_to_camera(camera.camera_to_world, np.concatenate(verts))
    tris_cam = cam_pts[np.concatenate(tris_idx)]  # (T, 3, 3)
    sil = measure_silhouettes(tris_cam, np.concatenate(groups), len(cands), camera.K, camera.width, camera.height,
                              near=max(camera.near, 1e-4))

    ids = np.array([a.id for a, _ in cands])
    counts = np.bincount(instance.ravel(), minlength=int(ids.max()) + 1)
    visible_pixels = counts[ids]
    labels = []
    for g, (actor, (box, distance)) in enumerate(cands):
        amodal = int(sil.image_pixels[g])
        if amodal == 0:  # the silhouette covers no pixel centre of the image: not in view
            continue
        visible = float(np.clip(visible_pixels[g] / amodal, 0.0, 1.0))
        bounds = sil.image_bounds[g]
        extras = {"silhouette_box": None if np.isnan(bounds[0]) else [float(x) for x in bounds],
                  "silhouette_source": "mesh" if actor.mesh is not None and actor.id in meshes else "box"}
        labels.append(Label2D(
            instance_id=actor.id, cls=actor.cls, box=box,
            in_frame_fraction=frustum_fraction(camera.K, camera.camera_to_world, actor.box.center, actor.box.size,
                                               actor.box.yaw, camera.width, camera.height, max(camera.near, 1e-4)),
            visible_fraction=visible, distance=distance,
            visible_pixels=int(visible_pixels[g]), amodal_pixels=amodal,
            occlusion_level=kitti_occlusion_level(visible, amodal > 0), extras=extras))
    return labels


def _scenario(ds: Dataset, scenario: str | Scenario) -> Scenario:
    return ds.scenario(scenario) if isinstance(scenario, str) else scenario


def label_view(ds: Dataset, scenario: str | Scenario, camera: str | CameraInfo,
               thresholds: LabelThresholds | None = None, meshes: dict[int, Mesh] | None = None,
               frame: int = 0) -> ViewLabels:
    """Labels of one camera of one scenario at ``frame`` (not written; see ``label_scenario``).

    ``scenario`` as a Scenario is taken as it stands at ``frame``; ``meshes`` (actor id -> mesh at
    ``frame``) lets callers labelling several cameras read meshes once.
    """
    scn = ds.scenario_at(scenario, frame) if isinstance(scenario, str) else scenario
    cam = scn.camera(camera) if isinstance(camera, str) else camera
    if meshes is None:
        meshes = moved_meshes(ds, scn.name, scenario_meshes(ds, scn), frame)
    instance = ds.read_instance(scn.name, cam.name, frame)
    objects = measure_view(cam, scn.actors, meshes, instance, set(ds.info.detectable_classes))
    return ViewLabels(scn.name, cam.name, cam.width, cam.height, thresholds or LabelThresholds(), objects, frame)


def moved_meshes(ds: Dataset, scenario: str, meshes: dict[int, Mesh], frame: int) -> dict[int, Mesh]:
    """Frame-0 ``meshes`` where their actors are at ``frame`` (read once, moved for every frame)."""
    if frame == 0:
        return meshes
    seq = ds.sequence(scenario)
    return {aid: (seq.move(aid, frame, v), f) for aid, (v, f) in meshes.items()}


def label_scenario(ds: Dataset, scenario: str | Scenario, thresholds: LabelThresholds | None = None,
                   write: bool = True) -> list[ViewLabels]:
    """Label every camera of a scenario at every frame (frame-major); with ``write`` each view's labels.json
    is written (atomically)."""
    name = scenario if isinstance(scenario, str) else scenario.name
    first = _scenario(ds, scenario)
    meshes = scenario_meshes(ds, first)
    out = []
    for frame in range(first.frames):
        scn = ds.scenario_at(name, frame) if frame else first
        now = moved_meshes(ds, name, meshes, frame)
        for cam in scn.cameras:
            labels = label_view(ds, scn, cam, thresholds, meshes=now, frame=frame)
            if write:
                ds.write_labels(labels)
            out.append(labels)
    return out


def label_dataset(ds_or_root: Dataset | str | Path, thresholds: LabelThresholds | None = None,
                  progress: bool = True, scenarios: list[str] | None = None) -> int:
    """Label and write every view of every scenario (or of ``scenarios``); returns the number of views."""
    from tqdm import tqdm

    ds = ds_or_root if isinstance(ds_or_root, Dataset) else Dataset.open(ds_or_root)
    names = ds.scenario_names() if scenarios is None else list(scenarios)
    n_views = 0
    for name in tqdm(names, desc="labelling scenarios", unit="scenario", disable=not progress):
        n_views += len(label_scenario(ds, name, thresholds, write=True))
    return n_views
