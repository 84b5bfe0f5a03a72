"""The 3D semantic-mapping task on ScanNet v2 (paper Table 2, Fig. 4b): the dataset reader
(:mod:`.scannet`), the task engine (:mod:`.engine`) and a synthetic ScanNet-format scene
(:mod:`.synthetic`). The method-level geometry lives in :mod:`resireg.mapping`."""
