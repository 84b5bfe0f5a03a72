"""The 3D semantic-mapping task on ScanNet v2 (``task=scannet3d``; paper Table 2, Fig. 4b): its
task class (:mod:`.task`, ``ScanNet3DTask``), engine (:mod:`.engine`, ``MappingEngine``: frames
fused into voxel maps) and result (:mod:`.result`, ``MappingResult``: scored by the metric
table's voxel scorer). The dataset readers are
:mod:`resireg_train.data.scannet`, :mod:`~resireg_train.data.replica` and
:mod:`~resireg_train.data.tartanair` (``sweep=replica3d``, ``sweep=tartanair3d``), the geometry :mod:`resireg.mapping`; the protocol:
docs/protocol.md section 4. May be imported by the task table (by name) and the CLIs.
"""
