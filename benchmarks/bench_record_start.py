"""What a run's record costs at its start and on every write, before and after a change.

Two measurements, each in a fresh process per code tree, median of ``--repeats``:

- **start**: the provenance block and the first write of ``results.json`` from a dirty git
  checkout (one tracked edit, ``--untracked`` untracked text files of 16 KiB, an untracked
  ``.env``), as a job's start does it (``start_provenance`` and the record's first write; with
  ``RunRecord``, also the masking of the saved ``.hydra`` configs). The command line holds a
  tracking URI with a password. This is where the secret checks (untracked files hashed,
  secret-looking names, binary files, the cap) and the URL masking cost; by default this tree
  inlines no untracked content, so the second column opts every untracked file in
  (``provenance.untracked_content=[*]``: what the code before did with every file under
  1 MiB), the like-for-like comparison;
- **update**: one merge into a record holding a 100-epoch history (what the training writes
  every epoch), where the masking of every string costs.

Each tree is copied into its own temporary git checkout (provenance reads the checkout its
code runs from):

    python benchmarks/bench_record_start.py --before /path/to/older/src [--repeats 7]

``--before`` is the ``src`` folder of the other version (e.g. ``git archive <commit> src conf
| tar -x -C /tmp/before``); its ``conf`` beside it. Without it only this tree is measured.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_PROBE = r"""
import json, statistics, sys, tempfile, time
from pathlib import Path
from omegaconf import OmegaConf
try:  # the settings read once from the config (RecordSettings), then the block
    from resireg_train.record.provenance.block import start_provenance
    from resireg_train.record.settings import RecordSettings
    def begin(cfg, out):
        return start_provenance(RecordSettings.from_config(cfg), out)
except ImportError:  # before the record's package (issue 52): start_provenance read the config
    from resireg_train.runs.provenance import start_provenance as begin
try:
    from resireg_train.record.masking import mask_saved_configs
    from resireg_train.record.run_record import RunRecord
except ImportError:  # before the record's package (issue 52)
    try:
        from resireg_train.record.run_record import RunRecord, mask_saved_configs
    except ImportError:  # the code before RunRecord
        RunRecord = None
if RunRecord is not None:
    def write(out, **fields):
        return RunRecord(out).update(**fields)
    def saved(out):
        mask_saved_configs(out)
else:
    from resireg_train.record.run_record import update_results as write
    def saved(out):
        pass
repeats = int(sys.argv[1])
sys.argv = ["resireg-eval", "tracker=mlflow",
            "tracker.mlflow.tracking_uri=http://user:pw@127.0.0.1:5000", "dataset=synthetic"]
cfg = OmegaConf.create({"name": "bench", "seed": 0, "dataset": {"path": "synthetic", "size": 8},
                        "tracker": {"mlflow": {"tracking_uri": "http://user:pw@127.0.0.1:5000"}}})
try:  # this tree: every provenance key (the opt-in one changed)
    try:
        from resireg_train.record.settings import provenance_settings
    except ImportError:  # before the record's package (issue 52)
        from resireg_train.runs.provenance import provenance_settings
    opted = OmegaConf.merge(cfg, {"provenance": {**provenance_settings(),
                                                 "untracked_content": ["*"]}})
except ImportError:  # before: untracked text under 1 MiB was always inlined
    opted = cfg
starts, inlined, updates = [], [], []
history = [{"epoch": e, "step": e * 10, **{f"train/m{k}": 0.5 for k in range(12)}}
           for e in range(100)]
for _ in range(repeats):
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        (out / ".hydra").mkdir()
        (out / ".hydra" / "overrides.yaml").write_text(
            "- tracker.mlflow.tracking_uri=http://user:pw@127.0.0.1:5000\n" * 3)
        t0 = time.perf_counter()
        write(out, name="bench", status="running", provenance=begin(cfg, out))
        saved(out)
        starts.append(time.perf_counter() - t0)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        t0 = time.perf_counter()
        write(out, name="bench", status="running", provenance=begin(opted, out))
        inlined.append(time.perf_counter() - t0)
        write(out, history=history, final=history[-1])
        t0 = time.perf_counter()
        write(out, epoch=100, history=history, final=history[-1])
        updates.append(time.perf_counter() - t0)
print(json.dumps({"start": statistics.median(starts), "inlined": statistics.median(inlined),
                  "update": statistics.median(updates)}))
"""


def _checkout(src: Path, dest: Path, untracked: int) -> Path:
    """A git checkout of ``src`` and its ``conf`` in ``dest``, made dirty."""
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    shutil.copytree(src, dest / "src", ignore=ignore)
    shutil.copytree(src.parent / "conf", dest / "conf", ignore=ignore)

    def git(*args: str) -> None:
        subprocess.run(["git", "-C", str(dest), "-c", "user.name=b", "-c", "user.email=b@b",
                        *args], check=True, capture_output=True)  # fmt: skip

    git("init", "-q", "-b", "main")
    git("add", "-A")
    git("commit", "-qm", "bench")
    edited = dest / "src" / "resireg" / "errors.py"
    edited.write_text(edited.read_text() + "# a local edit\n")
    (dest / ".env").write_text("AWS_SECRET_ACCESS_KEY=not-a-real-key\n")
    (dest / "notes").mkdir()
    for i in range(untracked):
        (dest / "notes" / f"n{i:03d}.txt").write_text(("x" * 63 + "\n") * 256)  # 16 KiB
    return dest


def measure(src: Path, repeats: int, untracked: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        repo = _checkout(src, Path(tmp) / "repo", untracked)
        env = {k: v for k, v in os.environ.items() if k != "RESIREG_CONFIG_DIR"}
        env["PYTHONPATH"] = str(repo / "src")
        proc = subprocess.run([sys.executable, "-c", _PROBE, str(repeats)], env=env, check=True,
                              capture_output=True, text=True)  # fmt: skip
        return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--before", type=Path, help="the other version's src folder")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--untracked", type=int, default=64)
    args = parser.parse_args(argv)
    trees = {"this tree": ROOT / "src"}
    if args.before is not None:
        trees = {"before": args.before.resolve(), **trees}
    results = {name: measure(src, args.repeats, args.untracked) for name, src in trees.items()}
    print("| code | start (s) | start, untracked text inlined (s) | update (ms) |\n"
          "|---|---:|---:|---:|")  # fmt: skip
    for name, r in results.items():
        print(f"| {name} | {r['start']:.3f} | {r['inlined']:.3f} | {r['update'] * 1000:.2f} |")
    if "before" in results:
        b, a = results["before"], results["this tree"]
        print(f"\nratio this tree / before: start {a['start'] / b['start']:.2f}, inlined "
              f"{a['inlined'] / b['inlined']:.2f}, update {a['update'] / b['update']:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
