"""The 3D semantic-mapping task on ScanNet v2 (paper Table 2, Fig. 4b): the dataset reader
(:mod:`.scannet`), the task engine (:mod:`.engine`), its metric (:mod:`.metric`) and a synthetic
ScanNet-format scene (:mod:`.synthetic`). The protocol: docs/protocol.md section 4. The
method-level geometry lives in :mod:`resireg.mapping`."""
