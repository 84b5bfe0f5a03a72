"""``resireg-runs rerun RUN [--out DIR] [--allow-drift] [--rtol X] [overrides...]``: a run
again, rebuilt from its record (:mod:`~resireg_train.runs.rerun.plan`), refused or recorded
where it drifted (:mod:`~resireg_train.runs.rerun.drift`), run in a new folder, and one
verdict on the two records (:mod:`~resireg_train.runs.rerun.verdict`).

Imported by ``resireg_train.cli.runs``.
"""

from __future__ import annotations

import datetime as _dt
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

from resireg.secrets import mask_text
from resireg_train.record.run_record import RunRecord, target_problem
from resireg_train.runs.index import Run, find_run
from resireg_train.runs.rerun.plan import RerunRefused, job_command, job_env, plan
from resireg_train.runs.rerun.verdict import Verdict, compare

__all__ = ["default_out", "main", "rerun"]


def default_out(run: Run) -> Path:
    """``outputs/rerun/<run id>_<date>_<time>`` under the working folder."""
    stamp = _dt.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    return Path("outputs") / "rerun" / f"{run.run_id}_{stamp}"


def rerun(
    spec: str,
    roots: Sequence[str],
    out: str | None = None,
    given: Sequence[str] = (),
    allow_drift: bool = False,
    rtol: float | None = None,
    stream: TextIO = sys.stdout,
) -> Verdict | None:
    """Rerun the run ``spec`` (a folder or run id under ``roots``) into ``out`` and print the
    verdict on ``stream`` (module docstring). Returns the verdict, ``None`` when the rerun's
    job failed (its record and log say why). Raises :class:`RerunRefused` (a ``ValueError``)
    before anything is written when the run cannot be rerun as it ran."""
    from resireg_train.record.settings import provenance_settings
    from resireg_train.runs.index import read_run

    run = find_run(spec, roots)
    folder = Path(out) if out else default_out(run)
    if problem := target_problem(folder, folder=True):
        raise RerunRefused(f"--out {folder}: {problem}; give the rerun a new folder")
    tolerance = float(provenance_settings()["rerun_rtol"] if rtol is None else rtol)
    if not tolerance >= 0:
        raise RerunRefused(f"--rtol {rtol}: expected a number >= 0")
    p = plan(run, folder.resolve(), given, allow_drift)
    if p.drift:
        stream.write("rerun despite (--allow-drift):\n" + "".join(f"  {d}\n" for d in p.drift))
    stream.write(f"rerun of {run.run_id} ({run.path}) into {p.out}"
                 f"{f' with {p.threads} torch thread(s)' if p.threads else ''}\n")  # fmt: skip
    stream.flush()
    code = subprocess.run(job_command(p), env=job_env(p), check=False).returncode
    record = RunRecord(p.out)
    if not record.exists(p.out):
        stream.write(f"the rerun did not start (exit status {code}); see above\n")
        return None
    block: dict[str, Any] = {"of": {"run_id": run.run_id, "path": str(run.path)},
                             "drift": p.drift, "allowed_drift": bool(p.drift)}  # fmt: skip
    new = read_run(p.out)
    if code != 0 or new.results.get("status") != "completed":
        record.update(rerun=block)
        error = new.results.get("error") or f"exit status {code}"
        stream.write(f"the rerun failed: {mask_text(str(error))} (its record: {p.out})\n")
        return None
    verdict = compare(run, new, tolerance)
    record.update(rerun={**block, **verdict.record()})
    stream.write("\n".join(verdict.lines()) + "\n")
    return verdict


def main(args: Any) -> int:
    """``resireg-runs rerun``'s parsed arguments run (:func:`rerun`); the exit status: 0 for
    identical or within tolerance, 1 when the rerun differs or failed."""
    verdict = rerun(args.run, args.root, args.out, args.overrides, args.allow_drift, args.rtol)
    return 0 if verdict is not None and verdict.kind != "differs" else 1
