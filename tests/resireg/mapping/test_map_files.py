"""Saved maps under hostile input (issue 51, Maps): a map file whose sizes would make a load
allocate gigabytes, a map.json field of the wrong type, the multi-session recipe of
resireg-map (compact.basis=<the first run>) and resireg-map-merge, an --out that holds another
run, a map merged with itself. Every refusal is one line naming the file and the field (no
traceback), and every file of the inputs and of the other runs keeps its bytes (SHA-256 before
and after)."""

import hashlib
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from test_compact_map import _rewrite, frames, unit

from resireg.integrity import IntegrityError
from resireg.mapping import SemanticMap, map_folder
from resireg.mapping.basis import load_basis
from resireg.mapping.map_file import remove_partial_saves
from resireg.mapping.tensor_file import write_tensors

COMPACT = {"dim": 8, "basis_rows": 10}


def digests(*folders):
    """SHA-256 of every file under the folders (hidden ones included), by path."""
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest()
            for folder in folders for p in sorted(Path(folder).rglob("*")) if p.is_file()}  # fmt: skip


def one_line_refusal(proc, *parts):
    """A command that exited 1 without a traceback, its error in one stderr line holding
    every one of ``parts`` (Hydra's lines around a job's error aside)."""
    assert proc.returncode == 1, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    lines = [x for x in proc.stderr.splitlines() if str(parts[0]) in x]
    assert len(lines) == 1, proc.stderr[-3000:]
    for part in parts:
        assert str(part) in lines[0], (part, lines[0])
    return lines[0]


def saved(folder, seed=0, windows=1, **settings):
    """A small map of random features (``frames``) saved to ``folder``."""
    smap = SemanticMap(None, "bb", 0.1, **settings)
    for f in frames(windows, seed):
        smap.fuse(*f)
    return smap.save(folder)


# ---------------------------------------------------------------- item 1: load
def hostile_map(folder):
    """The map of the issue: a tensor file of 0 voxels, ``features.unit`` of shape
    ``[0, 2**20]`` and 512 hot rows, ``map.json`` saying ``dim = stored_dim = 2**20``, every
    digest recomputed (a load that sized the hot blocks first allocated 2 GiB)."""
    saved(folder, storage="compact", compact={"dim": None})
    name = json.loads((folder / "map.json").read_text())["tensors"]
    d, h = 2**20, 512

    def zeros(*shape, dtype=torch.float32):
        return [torch.zeros(*shape, dtype=dtype)]

    write_tensors(folder / name, {
        "features.keys": zeros(0, dtype=torch.int64),
        "features.slots": [torch.full((16,), -1, dtype=torch.int32)],
        "features.unit": zeros(0, d, dtype=torch.float16), "features.norm": zeros(0),
        "features.counts": zeros(0, dtype=torch.int32),
        "features.colour": zeros(0, 3, dtype=torch.uint8),
        "features.colour_counts": zeros(0, dtype=torch.int32),
        "features.hot_rows": [torch.arange(h)], "features.hot_sums": zeros(h, 0),
        "features.hot_counts": zeros(h, dtype=torch.int64), "features.hot_colour": zeros(h, 0),
        "features.hot_colour_counts": zeros(h, dtype=torch.int64),
    })  # fmt: skip

    def edit(record):
        record.update(dim=d, stored_dim=d, voxels=0, basis_sha256=None)
        record["settings"]["compact"]["dim"] = None

    _rewrite(folder, edit)
    return folder


PEAK = textwrap.dedent(
    """
    import json, resource, sys
    from resireg.mapping import SemanticMap  # the modules the load needs, imported first
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    try:
        SemanticMap.load(sys.argv[1])
        error = None
    except Exception as err:
        error = f"{type(err).__name__}: {err}"
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"error": error, "kib": peak - before}))
    """
)

BAD_FIELDS = {  # field edited -> what the one line says
    "frames": (lambda r: r.update(frames="many"), "frames='many': expected an integer >= 0"),
    "meta": (lambda r: r.update(meta=[1, 2]), "meta=[1, 2]: expected null or a mapping"),
    "dim": (lambda r: r.update(dim="x"), "dim='x': expected null or an integer >= 1"),
    "voxels": (lambda r: r.update(voxels=-1), "voxels=-1: expected an integer >= 0"),
    "settings": (lambda r: r.update(settings=[1]), "settings=[1]: expected a mapping"),
    "voxel_size": (lambda r: r["settings"].update(voxel_size="big"),
                   "settings.voxel_size='big': expected a number > 0"),
    "unknown": (lambda r: r["settings"].update(bogus=1), "settings.bogus: no such setting"),
    "compact.dim": (lambda r: r["settings"]["compact"].update(dim=4),
                    "basis of shape [16, 8]: expected [dim=16, settings.compact.dim=4]"),
    "stored_dim": (lambda r: r.update(stored_dim=2**20),
                   "stored_dim=1048576: the map's settings and basis store 8-d features"),
}  # fmt: skip


@pytest.mark.slow
def test_a_hostile_map_is_refused_in_one_line_before_it_allocates(tmp_path):
    """SemanticMap.load of the issue's 13 KB map: refused naming its tensor file and the hot
    blocks, its peak memory (ru_maxrss, in a process that imported resireg.mapping first)
    under 256 MiB more than before the call (2 GiB before the fix). map.json fields of the
    wrong type or size, digests recomputed: an IntegrityError of one line naming map.json and
    the field; through resireg-map-merge, one line on stderr and no traceback. No file of a
    map changes."""
    from helpers.run import run

    hostile = hostile_map(tmp_path / "hostile")
    kept = digests(hostile)
    proc = subprocess.run([sys.executable, "-c", PEAK, str(hostile)], capture_output=True,
                          text=True, timeout=300, check=True)  # fmt: skip
    got = json.loads(proc.stdout.splitlines()[-1])
    assert got["kib"] <= 256 * 1024, got
    assert got["error"].startswith("IntegrityError: ") and "\n" not in got["error"]
    assert str(hostile) in got["error"] and "hot_sums of shape [512, 0]" in got["error"]
    assert digests(hostile) == kept
    good = saved(tmp_path / "good", storage="compact", compact=COMPACT)
    for field, (edit, says) in BAD_FIELDS.items():
        folder = tmp_path / field
        shutil.copytree(good, folder)
        _rewrite(folder, edit)
        with pytest.raises(IntegrityError) as info:
            SemanticMap.load(folder)
        text = str(info.value)
        assert "\n" not in text and str(folder / "map.json") in text and says in text, text
    before = digests(tmp_path)
    proc = run("resireg-map-merge", tmp_path / "meta", good, "--out", tmp_path / "out",
               check=False)  # fmt: skip
    one_line_refusal(proc, tmp_path / "meta" / "map.json", "meta=[1, 2]")
    assert {k: v for k, v in digests(tmp_path).items() if "/out/" not in k} == before


# ---------------------------------------------------------------- item 2: the recipe
@pytest.fixture(scope="module")
def export_512(tmp_path_factory):
    """A tiny ResiregVLM export whose dense features are 512-d (random init): a compact map
    (compact.dim 128) fits a basis for it."""
    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.models import ResiregVLM

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("export512") / "export"
    ResiregVLM.build(TINY_BACKBONE, {**TINY_HEAD, "out_dim": 512}, TINY_TEXT).save_pretrained(path)
    return path


def test_a_basis_argument_is_a_map_folder_or_a_run_folder(tmp_path):
    """compact.basis follows the rule of every map argument (map_folder): a map folder and a
    run folder holding it in map/ give the same basis; a folder holding neither is refused
    naming it; a compact map built with it (SemanticMap(compact={'basis': ...})) carries the
    first map's basis digest and merges with it."""
    first = saved(tmp_path / "run1" / "map", storage="compact", compact=COMPACT)
    assert map_folder(tmp_path / "run1") == map_folder(first) == first
    a, b = load_basis(first), load_basis(tmp_path / "run1")
    assert torch.equal(a, b) and a.shape == (16, 8)
    (tmp_path / "nothing").mkdir()
    with pytest.raises(ValueError, match=r"^compact\.basis='.*nothing' is neither a saved map"):
        load_basis(tmp_path / "nothing")
    second = SemanticMap(None, "bb", 0.1, storage="compact",
                         compact={**COMPACT, "basis": str(tmp_path / "run1")})  # fmt: skip
    for f in frames(1, 1):
        second.fuse(*f)
    one = SemanticMap.load(tmp_path / "run1")
    assert second.basis_sha256 == one.basis_sha256
    assert one.merge(second).frames == 4


@pytest.mark.slow
def test_the_multi_session_recipe_through_the_commands(tmp_path, export_512):
    """resireg-map storage=compact on a bag (a 512-d encoder: a 128-d basis fitted), a second
    resireg-map with compact.basis=<the first run's folder>, then resireg-map-merge of the two
    run folders: the merged map holds the union of both maps' voxels with their counts summed
    and the count-weighted mean of their features (numpy, from the two maps' own files), the
    first run's basis (by SHA-256) and every frame; the runs' files keep their bytes."""
    pytest.importorskip("rosbags")
    from helpers.run import run
    from resireg_train.data.room_bag import TOPICS, room_frames, write_bag

    bag = write_bag(tmp_path / "room", room_frames(6))
    common = [f"model_path={export_512}", "device=cpu", "source=rosbag", f"source.path={bag}",
              f"source.colour_topic={TOPICS['colour']}", f"source.depth_topic={TOPICS['depth']}",
              f"source.camera_info_topic={TOPICS['info']}", "variant=bb", "window=2",
              "voxel_size=0.2", "storage=compact", "ply.colour_by=rgb"]  # fmt: skip
    run1, run2, out = tmp_path / "run1", tmp_path / "run2", tmp_path / "merged"
    run("resireg-map", *common, "source.limit=3", f"hydra.run.dir={run1}", threads=1)
    run("resireg-map", *common, f"compact.basis={run1}", f"hydra.run.dir={run2}", threads=1)
    a, b = SemanticMap.load(run1), SemanticMap.load(run2)
    assert a.basis.shape == (512, 128) and a.basis_sha256 == b.basis_sha256
    before = digests(run1, run2)
    proc = run("resireg-map-merge", run1, run2, "--out", out)
    assert "Traceback" not in proc.stderr
    merged = SemanticMap.load(out)
    record = json.loads((out / "results.json").read_text())
    assert record["status"] == "completed" and record["map"]["frames"] == 3 + 6
    assert merged.frames == a.frames + b.frames == 9
    assert merged.basis_sha256 == a.basis_sha256
    want = {}
    for m in (a, b):
        for key, n, mean in zip(map(tuple, m.indices.tolist()), m.voxels.counts.tolist(),
                                m.voxels.means().numpy(), strict=True):  # fmt: skip
            held = want.get(key, (0, 0.0))
            want[key] = (held[0] + n, held[1] + n * mean)
    assert sorted(want) == list(map(tuple, merged.indices.tolist()))
    assert merged.voxels.counts.tolist() == [want[k][0] for k in sorted(want)]
    expected = unit(np.stack([want[k][1] / want[k][0] for k in sorted(want)]))
    cos = np.sum(unit(merged.features()[1].numpy()) * expected, 1)
    assert cos.min() >= 0.999
    assert digests(run1, run2) == before
    # The merge is made of both runs' parts: run1 merged with it again is refused, naming
    # both and run1's part, also after run1 was resumed (its tensor file rewritten, its id kept).
    assert len(a.parts) == len(b.parts) == 1 and merged.parts == [*a.parts, *b.parts]
    for resumed in (False, True):
        if resumed:
            run("resireg-map", *common, f"hydra.run.dir={run1}", "resume=true", threads=1)
            assert SemanticMap.load(run1).frames == 6 and SemanticMap.load(run1).parts == a.parts
        before = digests(run1, out)
        again = tmp_path / f"again-{resumed}"
        proc = run("resireg-map-merge", run1, out, "--out", again, check=False)
        one_line_refusal(proc, f"maps: {out / 'map'} and {run1 / 'map'} share the part "
                         f"{a.parts[0]}", "count twice")  # fmt: skip
        assert not (again / "map").exists() and digests(run1, out) == before


def strip_parts(folder):
    """A map as saved before maps recorded their parts (no ``parts`` in map.json)."""
    _rewrite(folder, lambda r: r.pop("parts"))
    return folder


def tensor_sha256(folder):
    name = json.loads((folder / "map.json").read_text())["tensors"]
    return hashlib.sha256((folder / name).read_bytes()).hexdigest()


def test_a_map_records_its_parts_and_a_merge_refuses_a_shared_one(tmp_path):
    """A new map is one part, a uuid4 kept through save and load (and a save after more
    frames: a resumed map); a merge is made of both maps' parts, in order; merging a map into
    a merge that holds it is refused naming the part, the merge unchanged. A map saved before
    maps recorded their parts is one part, its tensor file's SHA-256 (hashlib, from the file).
    A parts field of the wrong kind is refused on load in one line naming it."""
    import uuid

    from resireg.errors import MapError

    a, b = saved(tmp_path / "a", seed=1), saved(tmp_path / "b", seed=2)
    pa = json.loads((a / "map.json").read_text())["parts"]
    assert len(pa) == 1 and uuid.UUID(pa[0]).version == 4 and SemanticMap.load(a).parts == pa
    grown = SemanticMap.load(a)
    grown.fuse(*frames(1, 3)[0])
    assert SemanticMap.load(grown.save(tmp_path / "grown")).parts == pa
    pb = SemanticMap.load(b).parts
    assert pb != pa
    merged = SemanticMap.load(a).merge(SemanticMap.load(b))
    assert merged.parts == [*pa, *pb] and merged.frames == 4
    m = SemanticMap.load(merged.save(tmp_path / "m"))
    for first, second, part in ((m, SemanticMap.load(a), pa[0]), (SemanticMap.load(b), m, pb[0])):
        with pytest.raises(MapError, match=f"^merge: the maps share the part {part} "):
            first.merge(second)
    assert m.frames == 4 and m.parts == [*pa, *pb]
    old = strip_parts(saved(tmp_path / "old", seed=4))
    assert SemanticMap.load(old).parts == [tensor_sha256(old)]
    assert SemanticMap.load(a).merge(SemanticMap.load(old)).parts == [*pa, tensor_sha256(old)]
    bad = {  # parts -> what the one line says
        "str": "ab" * 16, "empty": [], "short": ["abc"], "upper": ["AB" * 16],
        "twice": [pa[0], pa[0]], "many": [f"{i:032x}" for i in range(4097)],
    }  # fmt: skip
    for label, value in bad.items():
        folder = tmp_path / f"bad-{label}"
        shutil.copytree(a, folder)
        _rewrite(folder, lambda r, v=value: r.update(parts=v))
        with pytest.raises(IntegrityError) as info:
            SemanticMap.load(folder)
        text = str(info.value)
        assert "\n" not in text and f"{folder / 'map.json'}: parts=" in text, text
        assert "expected a list of 1 to 4096 distinct ids" in text and len(text) < 400, text


@pytest.mark.slow
def test_a_merge_refuses_a_map_it_is_made_of(tmp_path):
    """resireg-map-merge A B --out M, then A M and M B (M holds A and B) refused in one
    line naming both maps and the shared part, nothing written, every input keeping its
    bytes. A map saved before maps recorded their parts (no parts field) merges; merged again
    with what holds it, it is refused naming its tensor file's SHA-256."""
    from helpers.run import run_side_by_side

    a, b = saved(tmp_path / "a", seed=1), saved(tmp_path / "b", seed=2)
    old = strip_parts(saved(tmp_path / "old", seed=3))
    pa, pb = SemanticMap.load(a).parts, SemanticMap.load(b).parts
    m = tmp_path / "m"
    run_side_by_side(("resireg-map-merge", a, b, "--out", m),
                     ("resireg-map-merge", old, a, "--out", tmp_path / "o"))  # fmt: skip
    assert SemanticMap.load(m).parts == [*pa, *pb] and SemanticMap.load(m).frames == 4
    o = SemanticMap.load(tmp_path / "o")
    assert o.parts == [tensor_sha256(old), *pa] and o.frames == 4
    before = digests(tmp_path)
    procs = run_side_by_side(
        ("resireg-map-merge", a, m, "--out", tmp_path / "x1"),
        ("resireg-map-merge", m, b, "--out", tmp_path / "x2"),
        ("resireg-map-merge", b, tmp_path / "o", old, "--out", tmp_path / "x3"),
        check=(False, False, False),
    )  # fmt: skip
    one_line_refusal(procs[0], f"maps: {m / 'map'} and {a} share the part {pa[0]}")
    one_line_refusal(procs[1], f"maps: {b} and {m / 'map'} share the part {pb[0]}")
    one_line_refusal(procs[2], f"maps: {old} and {tmp_path / 'o' / 'map'} share the part "
                     f"{tensor_sha256(old)}")  # fmt: skip
    after = digests(tmp_path)
    assert {k: v for k, v in after.items() if "/x" not in k} == before
    assert not any((tmp_path / f"x{i}" / "map").exists() for i in (1, 2, 3))


# ---------------------------------------------------------------- items 3 and 4: --out, twice
def other_runs(tmp_path):
    """Two other runs' folders as their commands leave them: an evaluation (its record,
    .hydra files, log) and a resireg-map run (the same, and its map)."""
    from resireg_train.record.run_record import RunRecord

    runs = {}
    for name in ("eval", "map"):
        folder = tmp_path / f"{name}-run"
        (folder / ".hydra").mkdir(parents=True)
        for part in ("config", "hydra", "overrides"):
            (folder / ".hydra" / f"{part}.yaml").write_text(f"# {name}'s {part}\n")
        (folder / f"{name}.log").write_text(f"{name}'s log\n")
        RunRecord(folder).update(name=name, status="completed", final={"miou": 0.5})
        runs[name] = folder
    saved(runs["map"] / "map", seed=3)
    return runs


@pytest.mark.slow
def test_merge_out_onto_another_run_is_refused_before_anything_is_written(tmp_path):
    """resireg-map-merge A B --out <an evaluation's run folder>, --out <a resireg-map run
    folder>, --out <a map folder> and --out <a file>: each refused in one line naming it, every
    file of those folders (their .hydra files, results.json, log, map) and of the inputs
    keeps its bytes and no file is added (not even the lock file). A merge of A B that did
    not complete (killed: its record 'running') is taken again in its own folder."""
    from helpers.run import run_side_by_side
    from resireg_train.record.run_record import RunRecord

    a, b = saved(tmp_path / "a", seed=1), saved(tmp_path / "b", seed=2)
    runs = other_runs(tmp_path)
    own = tmp_path / "own"
    RunRecord(own).update(name="map_merge", status="running", params={"maps": [str(a), str(b)]})
    afile = tmp_path / "afile"
    afile.write_text("not a folder\n")
    before = digests(tmp_path)
    procs = run_side_by_side(
        ("resireg-map-merge", a, b, "--out", runs["eval"]),
        ("resireg-map-merge", a, b, "--out", runs["map"]),
        ("resireg-map-merge", a, b, "--out", b),
        ("resireg-map-merge", a, b, "--out", afile),
        ("resireg-map-merge", a, b, "--out", own),
        check=(False, False, False, False, True),
    )  # fmt: skip
    one_line_refusal(procs[0], f"--out {runs['eval']} holds the record of another run",
                     "'eval', status 'completed'")  # fmt: skip
    one_line_refusal(procs[1], f"--out {runs['map']} holds a map")
    one_line_refusal(procs[2], f"--out {b} holds a map")
    one_line_refusal(procs[3], f"--out {afile}: not a folder")
    after = digests(tmp_path)
    assert {k: v for k, v in after.items() if not k.startswith(str(own))} == {
        k: v for k, v in before.items() if not k.startswith(str(own))}  # fmt: skip
    record = json.loads((own / "results.json").read_text())
    assert record["status"] == "completed" and record["map"]["frames"] == 4
    assert json.loads((own / "results.previous-1.json").read_text())["status"] == "running"


@pytest.mark.slow
def test_merge_out_inside_another_run_or_map_is_refused(tmp_path):
    """resireg-map-merge A B --out <a folder inside an evaluation's run folder> (its .hydra/,
    where a merge once wrote a whole run of its own) and --out <a new folder inside a map
    folder>: each refused in one line naming the folder it lies in; every file of those runs
    keeps its bytes and nothing is added. A results.json above --out that is no run record
    (another tool's file) does not stop a merge."""
    from helpers.run import run_side_by_side

    a, b = saved(tmp_path / "a", seed=1), saved(tmp_path / "b", seed=2)
    runs = other_runs(tmp_path)
    other_tool = tmp_path / "notes"
    other_tool.mkdir()
    (other_tool / "results.json").write_text("[1, 2]\n")
    before = digests(tmp_path)
    procs = run_side_by_side(
        ("resireg-map-merge", a, b, "--out", runs["eval"] / ".hydra"),
        ("resireg-map-merge", a, b, "--out", runs["map"] / "map" / "merged"),
        ("resireg-map-merge", a, b, "--out", other_tool / "merged"),
        check=(False, False, True),
    )  # fmt: skip
    one_line_refusal(procs[0], f"--out {runs['eval'] / '.hydra'} is inside the folder of "
                     f"another run or map ({runs['eval']})")  # fmt: skip
    one_line_refusal(procs[1], f"--out {runs['map'] / 'map' / 'merged'} is inside the folder of "
                     f"another run or map ({runs['map'] / 'map'})")  # fmt: skip
    after = digests(tmp_path)
    assert {k: v for k, v in after.items() if "/notes/merged/" not in k} == before
    assert SemanticMap.load(other_tool / "merged").frames == 4


@pytest.mark.slow
def test_a_map_merged_with_itself_is_refused_and_a_killed_save_is_cleaned(tmp_path):
    """resireg-map-merge A A (the same path; here once as the run folder, once as its map
    folder) and A C (C a copy of A: the same tensor file SHA-256) are refused in one line
    naming A (and C), A and C keep their bytes and no map is written. A temporary file a
    killed save left in --out/map (its process gone) is removed by the next merge into that
    folder, which completes; SemanticMap.save removes one too, and leaves a running
    process's."""
    from helpers.run import run_side_by_side

    run_a = tmp_path / "run-a"
    a = saved(run_a / "map", seed=1)
    c = tmp_path / "copy"
    shutil.copytree(a, c)
    b = saved(tmp_path / "b", seed=2)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "out"
    (out / "map").mkdir(parents=True)
    left = out / "map" / f".map-0123456789ab.safetensors.{dead.pid}.deadbeef.tmp"
    left.write_bytes(b"half a tensor file")
    before = digests(run_a, c, b)
    same, copy, good = run_side_by_side(
        ("resireg-map-merge", run_a, a, "--out", tmp_path / "same"),
        ("resireg-map-merge", a, c, "--out", tmp_path / "copy-out"),
        ("resireg-map-merge", a, b, "--out", out),
        check=(False, False, True),
    )  # fmt: skip
    one_line_refusal(same, f"maps: {a} is given twice", "counts every point twice")
    one_line_refusal(copy, f"maps: {c} holds the same map as {a}")
    assert not (tmp_path / "same" / "map").exists() and not (tmp_path / "copy-out" / "map").exists()
    assert digests(run_a, c, b) == before
    assert not left.exists() and SemanticMap.load(out).frames == 4
    mine = out / "map" / f".map.json.{os.getpid()}.cafe.tmp"
    theirs = out / "map" / f".map.json.{dead.pid}.cafe.tmp"
    mine.write_text("a save of a running process")
    theirs.write_text("a killed save")
    SemanticMap.load(out).save(out / "map")
    assert mine.exists() and not theirs.exists()
    assert remove_partial_saves(out / "map") == [] and mine.exists()
