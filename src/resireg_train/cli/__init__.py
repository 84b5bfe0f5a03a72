"""Console entry points: resireg-train, resireg-eval, resireg-report (Hydra mains share task.py)."""
