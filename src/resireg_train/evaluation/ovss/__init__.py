"""OVSS evaluation: the engine, the ReSiRegEval training callback, segmentation datasets."""
