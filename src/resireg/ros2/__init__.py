"""ReSiReg on a live robot: a ROS 2 node over :class:`resireg.mapping.SemanticMap` (torch, numpy,
rclpy; no Lightning, no Hydra). ``resireg-ros2`` runs it (:mod:`.cli`); docs/robot.md.

- :mod:`.settings`: the node's parameters, their defaults read from ``conf/`` (map.yaml,
  resireg/default.yaml, source/ros2.yaml, ros2.yaml) and checked by the project's rules (no
  rclpy, no torch);
- :mod:`.pipeline`: pairing, keyframes and the mapping thread (no rclpy);
- :mod:`.clouds`: ``PointCloud2`` of voxel maps, written and read with numpy;
- :mod:`.poses`: the camera pose from a pose topic or from tf;
- :mod:`.topics`: the input types, the QoS profiles, subscribing once a publisher appears;
- :mod:`.session`: the node's map: encoder, opened or resumed map, mapping thread, saves;
- :mod:`.node`: the rclpy node (needs the ``robot`` extra or a ROS 2 Jazzy install);
- :mod:`.bag_player`: recorded frames published as a camera driver would (the tests' and the
  benchmarks' robot);
- :mod:`.source`: live topics as a map source, ``resireg-map source=ros2`` (the node's pairing,
  its own rclpy context; rclpy imported when a source is made).

Importing this package imports none of them.

Nothing else in ``resireg`` imports it. May be imported by ``resireg_train`` only through the
source table's name (``resireg.ros2.source:LiveSource``, ``resireg-map source=ros2``), by the
console script ``resireg-ros2`` and by tests.
"""
