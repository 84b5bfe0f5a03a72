"""A sweep job's folder as Hydra and run_task leave it, for report tests (shared)."""

import json

import yaml


def make_job(sweep, number, overrides, results=None):
    """``<sweep>/<number>_<k=v,...>`` with ``.hydra/overrides.yaml`` (+ ``results.json``)."""
    folder = sweep / f"{number}_{','.join(f'{k}={v}' for k, v in overrides.items())}"
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text(
        yaml.safe_dump([f"{k}={v}" for k, v in overrides.items()])
    )
    if results is not None:
        (folder / "results.json").write_text(json.dumps(results))
    return folder
