"""Model cards for exports: every export ``resireg-train`` writes gets a ``README.md`` in
Hugging Face's model-card format (:func:`resireg.models.vlm.card.model_card`'s front matter and
body), with the training data as ``datasets``, the run's validation scores as ``model-index``
results, and a provenance section (run id, commit, checkpoint digest, data identity);
``resireg-runs card <export> --add <eval run>`` adds an evaluation's results
(:func:`add_evaluation`): under a lock on the export's card (two at once both land, one after
the other), written atomically. ``huggingface_hub.ModelCard.load`` reads both, and
``ResiregVLM.push_to_hub`` publishes the card's results with the model.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from resireg.integrity import atomic_write
from resireg_train.record.run_record import RecordError, RunRecord

try:  # POSIX; where it is missing (Windows) cards are not locked
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

__all__ = [
    "CARD_FILE",
    "CARD_LOCK",
    "TRAINING_VALIDATION",
    "add_evaluation",
    "eval_results",
    "write_export_card",
]

CARD_FILE = "README.md"
#: The lock file beside an export's card, held (``flock``) while an evaluation is added.
CARD_LOCK = ".card.lock"
#: How long :func:`add_evaluation` waits for another one adding to the same card.
CARD_LOCK_WAIT_S = 60.0
_TASK = "image-segmentation"


#: The ``dataset_config`` of the scores the training run's ReSiReg callback logged at its last
#: validation: model-index groups results by task and dataset (config, split, revision), so
#: they stay apart from (and keep their own source beside) a later ``resireg-eval``'s.
TRAINING_VALIDATION = "validation during training"


def eval_results(
    record: Mapping[str, Any], source: str, folder: Path, training: bool = False
) -> list[Any]:
    """One ``huggingface_hub.EvalResult`` per mIoU / f-mIoU a run record's ``final`` holds
    (``val/<task>/<dataset>/<metric>_<variant>``), named ``<metric> (<variant>)``, its source
    ``source`` at the run ``folder`` (a ``file://`` URL); ``training``: a training run's
    validation scores (:data:`TRAINING_VALIDATION`)."""
    from huggingface_hub import EvalResult

    dataset_spec = ((record.get("params") or {}).get("dataset")) or {}
    out = []
    for key, value in sorted((record.get("final") or {}).items()):
        parts = key.split("/")
        if len(parts) != 4 or parts[0] != "val" or value is None:
            continue
        _, task, dataset, score = parts
        metric, _, variant = score.partition("_")
        if metric not in ("miou", "fmiou") or "@" in variant:
            continue
        out.append(EvalResult(
            task_type=_TASK, task_name=f"open-vocabulary {task}", dataset_type=dataset,
            dataset_name=dataset, dataset_split=dataset_spec.get("split"),
            dataset_config=TRAINING_VALIDATION if training else dataset_spec.get("config"),
            dataset_revision=dataset_spec.get("revision"),
            metric_type="mean_iou" if metric == "miou" else "frequency_weighted_iou",
            metric_name=f"{metric} ({variant})", metric_value=float(value), source_name=source,
            source_url=Path(folder).resolve().as_uri(),
        ))  # fmt: skip
    return out


def _provenance_section(record: Mapping[str, Any], export: Path) -> str:
    prov = record.get("provenance") or {}
    git = (prov.get("code") or {}).get("git") or {}
    made = {}
    made_file = export / "provenance.json"
    if made_file.is_file():
        made = json.loads(made_file.read_text())
    lines = ["", "## Provenance", "",
             f"- training run: `{prov.get('run_id')}` ({prov.get('cli') or 'resireg-train'}), "
             f"folder `{record.get('output_dir')}`",
             f"- code: resireg {(prov.get('code') or {}).get('version')}"
             + (f", commit `{git.get('commit')}`{' (uncommitted changes: code.diff)' if git.get('dirty') else ''}"
                if git else ""),
             f"- last checkpoint SHA-256: `{((made.get('checkpoint') or {}).get('sha256'))}`"]  # fmt: skip
    for key, data in (prov.get("data") or {}).items():
        lines.append(f"- data `{key}`: " + ", ".join(f"{k}={v}" for k, v in data.items()
                                                      if k != "settings"))  # fmt: skip
    return "\n".join(lines) + "\n"


def write_export_card(export: Path, run: RunRecord) -> Path:
    """``<export>/README.md`` for the export the training run of ``run`` (its record) wrote:
    the card of :func:`resireg.models.vlm.card.model_card` named after the run, its training
    data as ``datasets``, its final validation scores as ``model-index`` results, and a
    provenance section."""
    from huggingface_hub import ModelCard

    from resireg.models.vlm.card import model_card
    from resireg.models.vlm.model import read_config

    record, out = run.fields(), run.folder
    cfg = read_config(export)
    name = f"{record.get('name', 'resireg')}-{(record.get('provenance') or {}).get('run_id')}"
    data = (record.get("provenance") or {}).get("data") or {}
    datasets = sorted({str(d.get("repo") or d.get("path") or key) for key, d in data.items()
                       if d.get("kind") in ("hub", "local")})  # fmt: skip
    results = eval_results(record, "resireg-train validation", out, training=True)
    fields: dict[str, Any] = {"model_name": name}
    if datasets:
        fields["datasets"] = datasets
    if results:
        fields["eval_results"] = results
    card = model_card(cfg, name, dict(cfg.get("digests") or {}), fields)
    text = str(ModelCard(str(card) + _provenance_section(record, export)))
    return atomic_write(export / CARD_FILE, text, what="model card")


@contextlib.contextmanager
def _card_lock(export: Path, wait: float = CARD_LOCK_WAIT_S) -> Iterator[None]:
    """Hold the export's card lock (:data:`CARD_LOCK`, ``flock``): another process adding to
    the same card waits up to ``wait`` seconds, then is refused naming the lock (the OS drops
    a lock with its process, so a crashed holder never blocks)."""
    if fcntl is None:  # pragma: no cover
        yield
        return
    path = export / CARD_LOCK
    handle = open(path, "a+")
    try:
        deadline = time.monotonic() + wait
        while True:
            try:
                fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    handle.seek(0)
                    holder = handle.read().strip() or "unknown"
                    raise ValueError(
                        f"{export / CARD_FILE}: another resireg-runs card --add (PID {holder}) "
                        f"has held it for over {wait:g} s ({path}); try again when it ends"
                    ) from None
                time.sleep(0.05)
        handle.truncate(0)
        handle.write(f"{os.getpid()}\n")
        handle.flush()
        yield
    finally:
        handle.close()  # drops the lock


def add_evaluation(export: str | Path, run: str | Path) -> list[Any]:
    """Add the evaluation in run folder ``run`` (``resireg-eval`` of this export) to the
    export's card: its mIoU / f-mIoU per variant as ``model-index`` results beside the
    training's validation scores (an earlier evaluation of the same dataset, split and metric
    is replaced) and a line in the card's evaluations section. Returns the card's results."""
    export, run = Path(export), Path(run)
    path = export / CARD_FILE
    if not path.is_file():
        raise ValueError(f"{export}: no {CARD_FILE} (not an export resireg-train wrote a card for)")
    try:
        record = RunRecord.read(run)
    except (OSError, RecordError) as err:
        raise ValueError(str(err)) from None
    if record.get("status") != "completed":
        raise ValueError(f"{run}: status {record.get('status')!r}, not a completed evaluation")
    new = eval_results(
        record, f"resireg-eval {(record.get('provenance') or {}).get('run_id')}", run
    )
    if not new:
        raise ValueError(f"{run}: its results.json holds no mIoU / f-mIoU to add")
    with _card_lock(export):  # read, add, write: one process at a time
        return _add_to_card(path, export, run, new)


def _add_to_card(path: Path, export: Path, run: Path, new: list[Any]) -> list[Any]:
    from huggingface_hub import ModelCard

    card = ModelCard.load(path)

    def key(result: Any) -> tuple:  # an evaluation replaces an earlier one of the same cell
        return (str(result.source_name).split()[0], result.dataset_name, result.dataset_split,
                result.metric_name)  # fmt: skip

    replaced = {key(r) for r in new}
    kept = [r for r in card.data.eval_results or [] if key(r) not in replaced]
    card.data.eval_results = kept + new
    if not card.data.model_name:
        card.data.model_name = export.parent.name
    line = (f"- `{run}`: " + ", ".join(f"{r.dataset_name} {r.metric_name} = {r.metric_value:.4f}"
                                       for r in new))  # fmt: skip
    header = "\n## Evaluations\n"
    text = card.text.rstrip("\n")
    card.text = text + ("\n" if header in card.text else "\n" + header + "\n") + line + "\n"
    atomic_write(path, str(card), what="model card")
    return card.data.eval_results
