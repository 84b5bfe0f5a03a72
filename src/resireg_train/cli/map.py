"""``resireg-map``: a language-queryable voxel map from a posed RGB-D recording (Hydra main;
``conf/map.yaml``, docs/maps.md#robot-maps-semanticmap). The job's steps:
:mod:`resireg_train.jobs.map`.

    resireg-map source=rosbag source.path=run.bag model_path=<export> source.world_frame=odom
    resireg-map source=tum source.path=rgbd_dataset_freiburg1_desk source.camera=fr1
    resireg-map source=scannet source.path=/datasets/scannet/scene0011_00 rerun.save=map.rrd
    resireg-map source=nerfstudio source.path=data/scene
    resireg-map source=ros2 source.world_frame=odom     # live topics, until idle or Ctrl-C

The map is saved to ``<output dir>/map`` every ``save_every`` windows and at the end, with
``map.ply`` and ``results.json``; ``resume=true`` continues it from the last frame it holds, or
is refused naming the keys that differ.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from resireg_train.cli.job import hydra_entry_point, run_task
from resireg_train.jobs.map import map_job

__all__ = ["main", "run_map"]


def run_map(cfg: DictConfig) -> dict[str, Any]:
    """Map from a composed ``map.yaml`` config; returns the ``results.json`` content."""
    return run_task(cfg, map_job, resume_hint="resume=true with the same run folder "
                    "continues from the last save")  # fmt: skip


main = hydra_entry_point("map", run_map)

if __name__ == "__main__":
    main()
