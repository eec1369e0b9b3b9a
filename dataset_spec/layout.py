"""Where each file of a dataset lives (the only place that builds dataset paths; every one through
``dataset_spec.names.below``, so no name from data leads out of the dataset).

::

    ROOT/
      dataset.json                              DatasetInfo: version, classes, splits
      scenarios/<scenario>/
        scenario.json                           Scenario: actors, cameras, lighting variants (at frame 0)
        frames.json                             Sequence: every frame's time and poses (sequences only)
        meshes/<actor id>.ply                   world-space actor meshes at frame 0 (optional)
        views/<camera>/                         frame 0:
          depth.exr                             planar depth, float32, channel Z
          instance.png                          uint16 instance ids
          rgb/<lighting variant>.png            8-bit RGB, one per lighting variant
          labels.json                           ViewLabels (projection tool)
          frames/<frame, 4 digits>/             frame 1, 2, ...: the same four kinds of files

Frame 0 of every scenario lies where a one-frame scenario's files lie, so a dataset of one frame is
laid out exactly as before sequences existed, and a reader that knows no frames reads frame 0.
"""
from __future__ import annotations

from pathlib import Path

from .names import below

DATASET_FILE = "dataset.json"
SCENARIO_FILE = "scenario.json"
FRAMES_FILE = "frames.json"
MAX_FRAMES = 10000  # frame folders are named by 4 digits


class Layout:
    def __init__(self, root: str | Path):
        self.root = Path(root)

    @property
    def dataset_json(self) -> Path:
        return self.root / DATASET_FILE

    @property
    def scenarios_dir(self) -> Path:
        return self.root / "scenarios"

    def scenario_dir(self, scenario: str) -> Path:
        return below(self.root, "scenarios", scenario)

    def scenario_json(self, scenario: str) -> Path:
        return self.scenario_dir(scenario) / SCENARIO_FILE

    def frames_json(self, scenario: str) -> Path:
        return self.scenario_dir(scenario) / FRAMES_FILE

    def mesh(self, scenario: str, actor_id: int) -> Path:
        return self.mesh_file(scenario, self.mesh_relpath(actor_id))

    def mesh_file(self, scenario: str, relpath: str) -> Path:
        """An actor's ``mesh`` (a path relative to its scenario folder), kept below that folder."""
        return below(self.scenario_dir(scenario), *relpath.split("/"))

    @staticmethod
    def mesh_relpath(actor_id: int) -> str:
        return f"meshes/{actor_id:05d}.ply"

    def view_dir(self, scenario: str, camera: str, frame: int = 0) -> Path:
        """A view's folder at ``frame``: the camera's folder for frame 0, ``frames/<frame>`` below it after."""
        root = below(self.scenario_dir(scenario), "views", camera)
        return root if frame == 0 else below(root, "frames", frame_name(frame))

    def depth(self, scenario: str, camera: str, frame: int = 0) -> Path:
        return self.view_dir(scenario, camera, frame) / "depth.exr"

    def instance(self, scenario: str, camera: str, frame: int = 0) -> Path:
        return self.view_dir(scenario, camera, frame) / "instance.png"

    def rgb(self, scenario: str, camera: str, variant: str, frame: int = 0) -> Path:
        return below(self.view_dir(scenario, camera, frame), "rgb", f"{variant}.png")

    def labels(self, scenario: str, camera: str, frame: int = 0) -> Path:
        return self.view_dir(scenario, camera, frame) / "labels.json"


def frame_name(frame: int) -> str:
    """A frame's folder name: its index, 4 digits."""
    if not isinstance(frame, int) or isinstance(frame, bool) or not 0 <= frame < MAX_FRAMES:
        raise ValueError(f"a frame index is a whole number 0..{MAX_FRAMES - 1}, got {frame!r}")
    return f"{frame:04d}"
