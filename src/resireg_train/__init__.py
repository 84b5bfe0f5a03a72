"""Training, evaluation and sweeps for ReSiReg (Lightning + Hydra). Imports `resireg`, never the reverse."""
