"""Where each file of a dataset lives (the only place that builds dataset paths; every one through
``dataset_spec.names.below``, so no name from data leads out of the dataset).

::

    ROOT/
      dataset.json                              DatasetInfo: version, classes, splits
      scenarios/<scenario>/
        scenario.json                           Scenario: actors, cameras, lighting variants
        meshes/<actor id>.ply                   world-space actor meshes (optional)
        views/<camera>/
          depth.exr                             planar depth, float32, channel Z
          instance.png                          uint16 instance ids
          rgb/<lighting variant>.png            8-bit RGB, one per lighting variant
          labels.json                           ViewLabels (projection tool)
"""
from __future__ import annotations

from pathlib import Path

from .names import below

DATASET_FILE = "dataset.json"
SCENARIO_FILE = "scenario.json"


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

    def mesh(self, scenario: str, actor_id: int) -> Path:
        return self.mesh_file(scenario, self.mesh_relpath(actor_id))

    def mesh_file(self, scenario: str, relpath: str) -> Path:
        """An actor's ``mesh`` (a path relative to its scenario folder), kept below that folder."""
        return below(self.scenario_dir(scenario), *relpath.split("/"))

    @staticmethod
    def mesh_relpath(actor_id: int) -> str:
        return f"meshes/{actor_id:05d}.ply"

    def view_dir(self, scenario: str, camera: str) -> Path:
        return below(self.scenario_dir(scenario), "views", camera)

    def depth(self, scenario: str, camera: str) -> Path:
        return self.view_dir(scenario, camera) / "depth.exr"

    def instance(self, scenario: str, camera: str) -> Path:
        return self.view_dir(scenario, camera) / "instance.png"

    def rgb(self, scenario: str, camera: str, variant: str) -> Path:
        return below(self.view_dir(scenario, camera), "rgb", f"{variant}.png")

    def labels(self, scenario: str, camera: str) -> Path:
        return self.view_dir(scenario, camera) / "labels.json"
