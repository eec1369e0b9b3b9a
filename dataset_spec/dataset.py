"""Reading and writing a dataset through one object.

Example::

    ds = Dataset.open("out/dataset")             # SpecError if it is not a dataset
    scn = ds.scenario("intersection_07")
    cam = scn.cameras[0]
    rgb = ds.read_rgb(scn.name, cam.name, scn.lighting[0].name)   # (H, W, 3) uint8
    inst = ds.read_instance(scn.name, cam.name)                   # (H, W) uint16
    labels = ds.read_labels(scn.name, cam.name).kept()            # list[Label2D]

    # a sequence: every per-view reader and writer takes a frame (0: the first)
    ds.frames("intersection_07")                                  # [0, 1, ..., N - 1]
    at3 = ds.scenario_at("intersection_07", 3)                    # road users and cameras at frame 3
    rgb3 = ds.read_rgb(scn.name, cam.name, "noon", frame=3)
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from . import images, meshes
from .atomic import atomic_write_json, output_root
from .errors import SpecError
from .layout import Layout
from .names import check_name, excerpt
from .labels2d import ViewLabels
from .schema import SPLIT_NAMES, DatasetInfo, Scenario
from .sequence import Sequence, still_sequence


def read_json(path: str | Path, what: str = ""):
    """A JSON file, which may come from someone else, as Python values: one ``SpecError`` naming the file (and
    ``what`` it should be) for a missing or unreadable file, bad JSON (a number Python will not read, such as an integer
    of more than 4300 digits, included), or nesting deeper than the parser follows. The one JSON reader for files
    from others."""
    path = Path(path)
    prefix = f"{what}: " if what else ""
    if not path.is_file():
        raise SpecError(path, f"{prefix}file is missing")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, and int()'s digit limit
        raise SpecError(path, f"{prefix}invalid JSON ({str(exc)[:200]})") from None
    except RecursionError:
        raise SpecError(path, f"{prefix}invalid JSON (nested deeper than {sys.getrecursionlimit()} levels)") from None
    except OSError as exc:
        raise SpecError(path, f"{prefix}not readable ({exc.__class__.__name__})") from None


def readable_view_file(read, path: Path, expected_hw) -> bool:
    """True when the file at ``path`` decodes with ``read`` at ``expected_hw`` (H, W)."""
    try:
        images.check_resolution(path, images.image_size(path), expected_hw)  # header first: no bomb decoded
        images.check_resolution(path, read(path).shape[:2], expected_hw)
    except SpecError:
        return False
    return True


def missing_view_files(layout: Layout, scenario: str, camera, variants: list[str], absent=(), frame: int = 0) -> list[str]:
    """What a view still needs at ``frame``: ``"data"`` (depth and instance, but for the maps the dataset
    declares ``absent``) and the names of the RGB variants that are missing or do not read back at
    ``camera``'s resolution. A new data pass makes every variant missing, so a view's RGB and
    segmentation come from the same render settings."""
    shape, name = (camera.height, camera.width), camera.name
    data_ok = (("depth" in absent or readable_view_file(images.read_depth, layout.depth(scenario, name, frame), shape))
               and ("instance" in absent
                    or readable_view_file(images.read_instance, layout.instance(scenario, name, frame), shape)))
    if not data_ok:
        return ["data", *variants]
    return [v for v in variants
            if not readable_view_file(images.read_rgb, layout.rgb(scenario, name, v, frame), shape)]


class Dataset:
    def __init__(self, root: str | Path, info: DatasetInfo):
        self.layout = Layout(root)
        self.info = info
        output_root(root, allow_link=True)  # what this dataset writes goes through real folders below its root
        self._scenarios: dict[str, Scenario] = {}
        self._sequences: dict[str, Sequence] = {}

    @property
    def root(self) -> Path:
        return self.layout.root

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, root: str | Path) -> "Dataset":
        root = Path(root)
        if root.is_file():
            raise SpecError(root, "is a file; expected a dataset folder (the one holding dataset.json)")
        if not root.is_dir():
            raise SpecError(root, "dataset folder does not exist")
        layout = Layout(root)
        if not layout.dataset_json.is_file():
            raise SpecError(root, f"not a dataset folder (no {layout.dataset_json.name})")
        return cls(root, DatasetInfo.from_dict(read_json(layout.dataset_json), layout.dataset_json))

    @classmethod
    def create(cls, root: str | Path, info: DatasetInfo) -> "Dataset":
        """Open an existing dataset (keeping its info) or start a new one with ``info``."""
        if Layout(root).dataset_json.is_file():
            return cls.open(root)
        ds = cls(root, info)
        ds.write_info()
        return ds

    def write_info(self) -> None:
        atomic_write_json(self.layout.dataset_json, self.info.to_dict())

    # ------------------------------------------------------------------ scenarios
    def scenario_names(self) -> list[str]:
        d = self.layout.scenarios_dir
        if not d.is_dir():
            return []
        return sorted(p.name for p in d.iterdir() if (p / "scenario.json").is_file())

    def scenario(self, name: str) -> Scenario:
        if name not in self._scenarios:
            path = self.layout.scenario_json(name)
            if not path.is_file():
                raise SpecError(path, f"no scenario {name!r} in this dataset (have: {self.scenario_names()})")
            self._scenarios[name] = Scenario.from_dict(read_json(path), path)
        return self._scenarios[name]

    def sequence(self, name: str) -> Sequence:
        """The scenario's frames (``frames.json``; a scenario of one frame: its road users at rest)."""
        if name not in self._sequences:
            scn = self.scenario(name)
            path = self.layout.frames_json(name)
            if scn.frames == 1 and not path.is_file():
                seq = still_sequence(scn, {c.name for c in self.info.classes if c.detectable})
            else:
                seq = Sequence.from_dict(read_json(path), path)
                if len(seq.frames) != scn.frames:
                    raise SpecError(path, f"holds {len(seq.frames)} frames, scenario.json says {scn.frames}")
            self._sequences[name] = seq
        return self._sequences[name]

    def frames(self, name: str) -> list[int]:
        """The frame indices of a scenario (``[0]`` for one instant)."""
        return list(range(self.scenario(name).frames))

    def scenario_at(self, name: str, frame: int = 0) -> Scenario:
        """The scenario at ``frame``: its road users' boxes and cameras' poses then (frame 0: as written)."""
        scn = self.scenario(name)
        if frame == 0 and scn.frames == 1:
            return scn
        if not 0 <= frame < scn.frames:
            raise SpecError(self.layout.scenario_json(name), f"no frame {frame} (frames 0..{scn.frames - 1})")
        return scn.at(self.sequence(name).frames[frame])

    def write_sequence(self, name: str, sequence: Sequence) -> None:
        atomic_write_json(self.layout.frames_json(name), sequence.to_dict())
        self._sequences[name] = sequence

    def select_scenarios(self, requested: list[str] | None = None) -> list[str]:
        """``requested`` scenario names checked against the dataset (all scenarios when None)."""
        names = self.scenario_names()
        if not names:
            raise SpecError(self.root, "the dataset has no scenarios")
        if not requested:
            return names
        missing = [s for s in requested if s not in names]
        if missing:
            raise SpecError(self.root, f"no scenario {', '.join(missing)} in this dataset (have: {', '.join(names)})")
        return list(requested)

    def split(self, split: str) -> list[str]:
        """The scenarios of ``split``; a SpecError where the splits are broken (``split_problems``): a reader of
        splits (training, evaluation, every export) never works on a split that leaks or names nothing."""
        if split not in SPLIT_NAMES:
            raise SpecError(self.layout.dataset_json, f"unknown split {split!r} (allowed: {SPLIT_NAMES})")
        problems = self.split_problems()
        if problems:
            raise SpecError(self.layout.dataset_json, f"{problems[0]} (dataset-spec validate lists every problem; "
                                                      "dataset-spec split sets new splits)")
        return list(self.info.splits.get(split, []))

    def split_problems(self) -> list[str]:
        """What makes the splits unusable, as the validator reports it: a scenario in two splits (leaks between
        them), a split naming a scenario the dataset does not have."""
        names, seen, out = set(self.scenario_names()), {}, []
        for split in SPLIT_NAMES:
            for scn in self.info.splits.get(split, []):
                if scn in seen:
                    out.append(f"scenario {scn!r} is in both '{seen[scn]}' and '{split}' splits (leaks between splits)")
                seen[scn] = split
                if scn not in names:
                    out.append(f"split '{split}' names scenario {scn!r}, which does not exist")
        return out

    def write_scenario(self, scenario: Scenario) -> None:
        """Write ``scenario.json`` (its names checked first: a writer never writes what readers refuse)."""
        named = (("scenario", [scenario.name]), ("camera", [c.name for c in scenario.cameras]),
                 ("lighting variant", [v.name for v in scenario.lighting]), ("actor", [a.name for a in scenario.actors]))
        for what, names in named:
            for name in names:
                if (why := check_name(name)) is not None:
                    raise SpecError(self.layout.scenarios_dir, f"{what} name {excerpt(name)} {why}")
        atomic_write_json(self.layout.scenario_json(scenario.name), scenario.to_dict())
        self._scenarios[scenario.name] = scenario

    def set_splits(self, splits: dict[str, list[str]]) -> None:
        self.info.splits = {k: sorted(v) for k, v in splits.items()}
        self.write_info()

    # ------------------------------------------------------------------ per-view files
    # Readers check each image against its camera's resolution, with the validator's message; the size is
    # checked from the file's header before it is decoded. Every one takes the frame (0: the first).
    def _read_view_image(self, read, path: Path, scenario: str, camera: str) -> np.ndarray:
        cam = self.scenario(scenario).camera(camera)
        images.check_resolution(path, images.image_size(path), (cam.height, cam.width))
        img = read(path)
        images.check_resolution(path, img.shape[:2], (cam.height, cam.width))
        return img

    def read_rgb(self, scenario: str, camera: str, variant: str, frame: int = 0) -> np.ndarray:
        return self._read_view_image(images.read_rgb, self.layout.rgb(scenario, camera, variant, frame), scenario, camera)

    def require(self, view_map: str, purpose: str) -> None:
        """SpecError naming dataset.json when the dataset declares ``view_map`` absent (imported
        camera data has no depth or instance maps): a tool that needs them says so before it starts."""
        if not self.info.has(view_map):
            raise SpecError(self.layout.dataset_json, f"this dataset has no {view_map} maps ('absent' lists them: "
                                                      f"imported camera data), which {purpose} needs")

    def read_depth(self, scenario: str, camera: str, frame: int = 0) -> np.ndarray:
        self.require("depth", "reading depth")
        return self._read_view_image(images.read_depth, self.layout.depth(scenario, camera, frame), scenario, camera)

    def read_instance(self, scenario: str, camera: str, frame: int = 0) -> np.ndarray:
        self.require("instance", "reading instance ids")
        return self._read_view_image(images.read_instance, self.layout.instance(scenario, camera, frame), scenario,
                                     camera)

    def check_segmentation_sizes(self, scenarios: list[str]) -> None:
        """SpecError for the first view of ``scenarios`` (every frame) whose instance.png is missing or not its
        camera's size, read from the PNG headers only: a tool checks before it starts writing."""
        self.require("instance", "this tool")
        for name in scenarios:
            for frame in self.frames(name):
                for cam in self.scenario(name).cameras:
                    path = self.layout.instance(name, cam.name, frame)
                    images.check_resolution(path, images.png_size(path), (cam.height, cam.width))

    def read_semantic(self, scenario: str, camera: str, frame: int = 0) -> np.ndarray:
        table = self.scenario(scenario).class_of_instance(self.info)
        return images.semantic_from_instance(self.read_instance(scenario, camera, frame), table)

    def read_labels(self, scenario: str, camera: str, frame: int = 0) -> ViewLabels:
        path = self.layout.labels(scenario, camera, frame)
        if not path.is_file():
            raise SpecError(path, "no 2D labels for this view (run the projection tool: project-labels DATASET)")
        return ViewLabels.from_dict(read_json(path), path)

    def read_mesh(self, scenario: str, actor_id: int, frame: int = 0):
        """An actor's world-space mesh (vertices, faces) at ``frame``: frame 0's moved rigidly with it."""
        actor = self.scenario(scenario).actor(actor_id)
        if actor.mesh is None:
            raise SpecError(self.layout.scenario_json(scenario), f"actor {actor_id} has no mesh")
        vertices, faces = meshes.read_mesh(self.layout.mesh_file(scenario, actor.mesh))
        return (self.sequence(scenario).move(actor_id, frame, vertices) if frame else vertices), faces

    def write_rgb(self, scenario: str, camera: str, variant: str, rgb: np.ndarray, frame: int = 0) -> None:
        images.write_rgb(self.layout.rgb(scenario, camera, variant, frame), rgb)

    def write_depth(self, scenario: str, camera: str, depth: np.ndarray, frame: int = 0) -> None:
        images.write_depth(self.layout.depth(scenario, camera, frame), depth)

    def write_instance(self, scenario: str, camera: str, instance: np.ndarray, frame: int = 0) -> None:
        images.write_instance(self.layout.instance(scenario, camera, frame), instance)

    def write_labels(self, labels: ViewLabels) -> None:
        atomic_write_json(self.layout.labels(labels.scenario, labels.camera, labels.frame), labels.to_dict())

    def write_mesh(self, scenario: str, actor_id: int, vertices: np.ndarray, faces: np.ndarray) -> str:
        """Write an actor's world-space mesh; returns the path to store in ``Actor.mesh``."""
        meshes.write_mesh(self.layout.mesh(scenario, actor_id), vertices, faces)
        return Layout.mesh_relpath(actor_id)

    def view_is_complete(self, scenario: str, camera: str, variants: list[str], frame: int = 0) -> bool:
        """True when depth, instance and every requested RGB variant of a view at ``frame`` exist and read
        back at the camera's resolution (a truncated or garbage file is not complete)."""
        cam = self.scenario(scenario).camera(camera)
        return not missing_view_files(self.layout, scenario, cam, variants, self.info.absent, frame)

