"""The check of a resume (``resireg-train ... ckpt_path=last``): the command's config must be
the run's own (``.hydra/config.yaml``, read through today's moves:
:func:`resireg_train.config.moves.current_targets`, :func:`~resireg_train.config.moves.current_keys`),
and a new run never takes a folder that holds one. Also the command that resumes a run, which
an interrupted run prints and a refused resume names."""

from __future__ import annotations

import re
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError
from resireg.secrets import mask_text
from resireg.specs.tree import differences
from resireg_train.config.moves import (
    check_stored_targets,
    current_keys,
    current_overrides,
    current_spelling,
    current_targets,
)
from resireg_train.record.masking import masked_tree
from resireg_train.record.run_record import RunRecord

__all__ = ["check_resume", "hydra_quoted", "refuse_occupied", "resume_command"]


def hydra_quoted(folder: Path | str) -> str:
    """A folder as a Hydra override's value: double-quoted where it holds what Hydra parses
    (a sweep job's folder holds ``=`` and ``,``)."""
    folder = str(folder)
    if re.fullmatch(r"[\w/.\-:~+@%]+", folder):
        return folder
    return '"' + folder.replace("\\", "\\\\").replace('"', '\\"') + '"'


#: Keys a resume may change: the resume itself, and what is recorded of the run without
#: changing what it computes (its trackers, what provenance keeps of the code, the system
#: metrics' interval).
_RESUME_FREE = ("ckpt_path", "tracker", "provenance", "system_metrics")
#: Overrides a resume command sets itself (or must not repeat: the sweep's own folders).
_RESUME_SET = ("ckpt_path", "hydra.run.dir", "hydra.sweep.dir", "hydra.sweep.subdir",
               "hydra.mode", "hydra.output_subdir", "hydra.job.name")  # fmt: skip


def resume_command(
    task: Sequence[str], hydra: Sequence[str], out: Path, multirun: bool = False
) -> str:
    """The command that resumes the run in ``out``: ``resireg-train`` with the run's own
    overrides (``task``: the command line's, a sweep job's swept values included; ``hydra``:
    Hydra's), ``ckpt_path=last hydra.run.dir=<out>``, and for a sweep job ``hydra.mode=RUN``
    (it resumes that job alone), shell-quoted, URL passwords masked (a tracking URI's password
    is given again, or through the tracker's own environment variables)."""

    def kept(items: Sequence[str]) -> list[str]:
        return [o for o in items if o.split("=", 1)[0].lstrip("+~") not in _RESUME_SET]

    folder = hydra_quoted(out)  # a sweep job's folder: "=" and ","
    words = [
        "resireg-train",
        *kept(task),
        *kept(hydra),
        "ckpt_path=last",
        f"hydra.run.dir={folder}",
    ]
    if multirun:
        words.append("hydra.mode=RUN")
    return mask_text(" ".join(shlex.quote(str(w)) for w in words))


def _differences(run: dict[str, Any], this: dict[str, Any]) -> list[str]:
    """``key=<this value> (the run: <its value>)`` of every leaf that differs, the shallowest
    keys first (``trainer.max_epochs`` before a dataset's ``split``)."""
    return [
        f"{key}={now!r} (the run: {then!r})"
        for key, then, now in differences(run, this, skip=_RESUME_FREE)
    ]


def check_resume(out: Path, composed: DictConfig) -> None:
    """Refuse a resume of the run in ``out`` whose config (``composed``, without its
    ``hydra`` node) differs from the run's ``.hydra/config.yaml`` (read in today's class paths
    and key spellings, :mod:`resireg_train.config.moves`; one naming a class of ours that is
    gone is refused naming it and the release): ``ConfigError`` naming the
    differing keys (up to 8, and how many more), the run's overrides and this command's, the
    command that resumes the run with its own overrides, and the way to train on with other
    settings. A folder without a stored config (a run started from Python) is not checked."""
    stored = out / ".hydra" / "config.yaml"
    if not stored.is_file():
        return
    # a run written before a class moved names its old path, one written before a key
    # existed lacks it, and one written before a key was renamed spells it the old way: compare
    # with today's (a class of ours that is gone and in no moves table: refused, naming it);
    # the saved config has its URL passwords masked (RunRecord.start): compare masked values
    run = current_targets(OmegaConf.to_container(OmegaConf.load(stored), resolve=False))
    written_by = ((RunRecord.read(out) or {}).get("provenance") or {}).get("code") or {}
    check_stored_targets(run, str(stored), written_by.get("version"))
    run = current_keys(current_spelling(run, "train"))
    this = OmegaConf.to_container(composed, resolve=False)
    this.pop("hydra", None)
    run, this = masked_tree(run), masked_tree(this)
    differences = _differences(run, this)
    if not differences:
        return
    shown = "; ".join(differences[:8])
    if len(differences) > 8:
        shown += f"; and {len(differences) - 8} more"
    hydra_file = out / ".hydra" / "hydra.yaml"
    recorded = yaml.safe_load(hydra_file.read_text())["hydra"] if hydra_file.is_file() else {}
    overrides = recorded.get("overrides") or {}
    task = current_overrides(
        "train", yaml.safe_load((out / ".hydra" / "overrides.yaml").read_text()) or []
    )
    command = resume_command(task, overrides.get("hydra") or [], out,
                             recorded.get("mode") == "MULTIRUN")  # fmt: skip
    given = list(composed.hydra.overrides.task) if "hydra" in composed else []
    raise ConfigError(
        f"ckpt_path={composed.get('ckpt_path')}: this command's config differs from the run's "
        f"({stored}) in {len(differences)} key(s): {shown}. The run's overrides: "
        f"{' '.join(task) or 'none'}; this command's: {' '.join(given) or 'none'}. Nothing under "
        f"{out} was changed. Resume with the run's own overrides: {command}; to train on with "
        f"other settings, start a new run from its weights: "
        f"model.init_from={out / 'checkpoints' / 'last.ckpt'}"
    )



def refuse_occupied(out: Path, multirun: bool | None = None) -> None:
    """A new run never shares a folder with another (their metrics.csv, checkpoints and
    results.json would interleave): a folder already holding a run record is refused unless
    the run resumes it. Default folders are unique (time + run id, for sweeps too); this
    guards a folder given by hand."""
    previous = RunRecord.read(out)
    if not previous:
        return
    if multirun is None:
        multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    if multirun:
        where, unset = f"the sweep job's folder {out} (hydra.sweep.dir/subdir)", "hydra.sweep.dir"
    else:
        where, unset = f"hydra.run.dir={out}", "hydra.run.dir"
    raise FileExistsError(
        f"{where} already holds a run ({previous.get('name')!r}, status "
        f"{previous.get('status')!r}): resume it with ckpt_path=last, or give this run its "
        f"own folder (leave {unset} unset for a new, unique one)"
    )
