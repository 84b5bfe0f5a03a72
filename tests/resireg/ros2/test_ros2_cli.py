"""resireg-ros2's command line and parameters: one line and exit 2 without rclpy or for a bad
value; the parameter table read from conf/ (one source per default) and the one docs/robot.md
shows; the pairing, keyframe and cloud code of resireg.ros2 against independent references."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from helpers.paths import ROOT
from helpers.ros2 import ros_env
from resireg.ros2 import settings
from resireg.ros2.clouds import pack_rgb, unpack_rgb


def test_without_rclpy_the_command_names_the_robot_extra(monkeypatch, capsys):
    import importlib.util

    from resireg.ros2 import cli

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "rclpy" else real(name, *a))  # fmt: skip
    assert cli.main(["--ros-args", "-p", "window:=2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs the 'robot' extra (rclpy not installed)" in err[0]
    assert 'pip install "resireg[robot]"' in err[0]


def test_defaults_are_the_yaml_files_values():
    """Every parameter's default is the value at its origin in conf/ (read here with PyYAML
    independently), and the map keys are resireg-map's own names."""
    table = settings.parameters()
    for p in table.values():
        file, _, key = p.origin.partition(":")
        node = yaml.safe_load((ROOT / "conf" / file).read_text())
        if key == "defaults.encoder":
            value = next(d["encoder"] for d in node["defaults"] if "encoder" in d)
        else:
            value = node
            for part in key.split("."):
                value = value[part]
        assert p.default == value, p
    assert {n for n in table if "." not in n} >= set(settings.MAP_KEYS) | {"encoder"}
    from resireg.specs.sources import SOURCE_SPECS

    assert {f"source.{k}" for k in settings.SOURCE_KEYS} <= set(table)
    assert set(settings.SOURCE_KEYS) <= set(SOURCE_SPECS["rosbag"].rules)  # resireg-map's names


def test_docs_list_every_parameter_with_its_default():
    text = (ROOT / "docs" / "robot.md").read_text()
    assert settings.parameter_table() in text


def test_bad_values_are_one_line_naming_them():
    table = settings.parameters()
    values = {n: p.default for n, p in table.items()}
    with pytest.raises(settings.SettingsError) as err:
        settings.check({**values, "window": 0, "full.alpha": -1.0, "qos": "fast"}, table,
                       ["voxel_sise"])  # fmt: skip
    text = str(err.value)
    assert "\n" not in text
    for part in ("voxel_sise: no such parameter (did you mean voxel_size?)",
                 "window=0: expected an integer >= 1",
                 "full.alpha=-1.0: expected a number > 0 (finite)",
                 "qos='fast': expected one of ['sensor_data', 'reliable']"):  # fmt: skip
        assert part in text
    settings.check({**values, "variant": "lite@alpha:5.0"}, table)
    for bad in ("full+prior", "lite@layer:3", "nope", "full@n_prototypes:0"):
        with pytest.raises(settings.SettingsError, match="variant="):
            settings.check({**values, "variant": bad}, table)


@pytest.mark.slow
def test_a_bad_parameter_exits_2_with_one_line(tmp_path):
    """The real command (a fresh process, Fast DDS on shared memory): exit 2, one stderr line."""
    proc = subprocess.run([sys.executable, "-m", "resireg.ros2.cli", "--ros-args", "-p",
                           "window:=0", "-p", "source.tolerance:=-1.0", "-p",
                           f"output_dir:={tmp_path}"], capture_output=True, text=True,
                          env=ros_env(), timeout=300)  # fmt: skip
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0] == ("resireg-ros2: error: window=0: expected an integer >= 1; "
                        "source.tolerance=-1.0: expected a number > 0 (finite)")  # fmt: skip


def test_keyframes_follow_the_motion_thresholds():
    from resireg.ros2.pipeline import KeyframeFilter

    rng = np.random.default_rng(0)
    poses = []
    for i in range(40):
        m = np.eye(4)
        m[:3, :3] = Rotation.from_euler("z", 0.02 * i + rng.normal(0, 0.01)).as_matrix()
        m[:3, 3] = [0.01 * i, rng.normal(0, 0.005), 0]
        poses.append(m)
    keep = KeyframeFilter(0.05, 0.1)
    got = [keep(p) for p in poses]
    expected, last = [], None  # by hand: distance and the angle of the relative rotation
    for p in poses:
        ok = last is None or (np.linalg.norm(p[:3, 3] - last[:3, 3]) >= 0.05
                              or Rotation.from_matrix(last[:3, :3].T @ p[:3, :3]).magnitude()
                              >= 0.1)  # fmt: skip
        expected.append(ok)
        last = p if ok else last
    assert got == expected and 3 < sum(got) < 40
    assert all(KeyframeFilter(0, 0)(p) for p in poses)


def test_pose_buffer_equals_the_whole_stream_track():
    """A live pose buffer (samples arriving one by one) answers at each time as PoseTrack
    over the whole stream does, times the camera offset; final once a later sample came."""
    from resireg.ros2.poses import PoseBuffer
    from resireg.sources.pairing import PoseTrack

    rng = np.random.default_rng(1)
    stamps = np.cumsum(rng.uniform(0.02, 0.2, 30))
    poses = np.stack([np.eye(4)] * 30)
    poses[:, :3, :3] = Rotation.random(30, random_state=2).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(30, 3))
    offset = np.eye(4)
    offset[:3, 3] = (0.1, 0.2, 0.3)
    whole = PoseTrack(stamps, poses, 0.02, 0.15)
    live = PoseBuffer("/odom", offset, 0.02, 0.15)
    for i, (s, p) in enumerate(zip(stamps, poses, strict=True)):
        live.add(s, p)
        for t in (stamps[max(i - 1, 0)] + 0.01, s, s + 0.01):
            got, _, final = live.lookup(t)
            ref = whole.at(t)
            assert final == (t <= s)
            if final:
                assert (got is None) == (ref is None)
                if ref is not None:
                    np.testing.assert_allclose(got, ref @ offset, atol=1e-12)


def test_rgb_packing_is_rviz_bits():
    c = np.array([[255, 0, 0], [1, 2, 3], [0, 0, 255]], dtype=np.uint8)
    bits = pack_rgb(c).view(np.uint32)
    assert bits.tolist() == [0xFF0000, 0x010203, 0x0000FF]
    np.testing.assert_array_equal(unpack_rgb(pack_rgb(c)), c)


# the node's parameters renamed with resireg-map's keys in 0.2.0 (issue 52): the old names run
# as the new ones, with one warning line, until 0.3.0
WARNING = "{old!r} is now {new!r} (renamed in 0.2.0; the old name goes in 0.3.0): read {read}"


@pytest.mark.parametrize(("flag", "old", "new"), [
    ("-p", "configuration:=lite@alpha:5.0", "variant:=lite@alpha:5.0"),
    ("--param", "configuration:=bb", "variant:=bb"),
    *[("-p", f"rerun.{k}:=1", f"viewer.{k}:=1")
      for k in ("save", "spawn", "query", "map_every", "serve", "connect")],
    ("--param", "resireg_map:rerun.save:=m.rrd", "resireg_map:viewer.save:=m.rrd"),
])  # fmt: skip
def test_an_old_parameter_name_runs_as_the_new_one(flag, old, new, tmp_path):
    lines = []
    argv = ["resireg-ros2", "--ros-args", "-p", "window:=2", flag, old, "-r", "__node:=x"]
    out = settings.current_arguments(argv, lines.append, tmp_path)
    assert out == ["resireg-ros2", "--ros-args", "-p", "window:=2", flag, new, "-r", "__node:=x"]
    head = old.rpartition(":=")[0].rpartition(":")[2].partition(".")[0]
    assert lines == [WARNING.format(old=head, new={"configuration": "variant",
                                                   "rerun": "viewer"}[head],
                                    read=f"{old} -> {new}")]  # fmt: skip
    # words outside --ros-args (the program's own) and today's names are left alone
    plain = ["resireg-ros2", "-p", "configuration:=bb", "--ros-args", "-p", "variant:=bb"]
    assert settings.current_arguments(plain, lines.append, tmp_path) == plain
    assert len(lines) == 1


def test_old_and_new_name_together_exit_2_before_anything_starts(monkeypatch, capsys):
    from resireg.ros2 import cli

    def started(*args):
        raise AssertionError("the node was started")

    monkeypatch.setattr(cli, "_run", started)
    for given in (["configuration:=lite", "variant:=full"],
                  ["viewer.spawn:=true", "rerun.save:=m.rrd"]):  # fmt: skip
        argv = ["--ros-args", "-p", given[0], "--param", given[1]]
        assert cli.main(argv) == 2
        captured = capsys.readouterr()
        old, new = ("configuration", "variant") if "variant" in given[1] else ("rerun", "viewer")
        assert captured.err == (
            f"resireg-ros2: error: {given[0]} {given[1]}: {old!r} and {new!r} name one "
            f"parameter ({old!r} is the old name of {new!r}): give it once, as {new!r}\n"
        )
        assert captured.out == ""


def _params_file(path, params):
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
    return path


def test_a_params_file_with_old_names_is_read_in_the_new_ones(tmp_path):
    import hashlib

    src = _params_file(tmp_path / "robot.yaml", {"configuration": "lite", "window": 2,
                                                 "rerun": {"save": "m.rrd", "map_every": 3},
                                                 "rerun.serve": True})  # fmt: skip
    digest = hashlib.sha256(src.read_bytes()).hexdigest()
    copies = tmp_path / "copies"
    copies.mkdir()
    lines = []
    out = settings.current_arguments(["resireg-ros2", "--ros-args", "--params-file", str(src)],
                                     lines.append, copies)  # fmt: skip
    assert out[:3] == ["resireg-ros2", "--ros-args", "--params-file"]
    assert Path(out[3]).parent == copies
    assert yaml.safe_load(Path(out[3]).read_text()) == {"/**": {"ros__parameters": {
        "variant": "lite", "window": 2, "viewer": {"save": "m.rrd", "map_every": 3},
        "viewer.serve": True}}}  # fmt: skip
    assert lines == [
        WARNING.format(old="configuration", new="variant", read=f"configuration -> variant in {src}"),
        WARNING.format(old="rerun", new="viewer",
                       read=f"rerun -> viewer in {src}, rerun.serve -> viewer.serve in {src}"),
    ]  # fmt: skip
    assert hashlib.sha256(src.read_bytes()).hexdigest() == digest  # the user's file: as it was
    # a file in today's names is passed as it is, without a word
    new = _params_file(tmp_path / "new.yaml", {"variant": "bb"})
    argv = ["resireg-ros2", "--ros-args", "--params-file", str(new)]
    assert settings.current_arguments(argv, lines.append, copies) == argv and len(lines) == 2
    both = _params_file(tmp_path / "both.yaml", {"rerun": {"save": "a.rrd"}, "viewer.spawn": True})
    with pytest.raises(settings.SettingsError) as err:
        settings.current_arguments(["x", "--ros-args", "--params-file", str(both)], print, copies)
    assert str(err.value) == (f"{both}: rerun viewer.spawn: 'rerun' and 'viewer' name one "
                              "parameter ('rerun' is the old name of 'viewer'): give it once, "
                              "as 'viewer'")  # fmt: skip


@pytest.mark.slow
def test_the_real_command_reads_old_names_as_the_new_ones(tmp_path):
    """A fresh process (rclpy's parameters): ``-p configuration:=`` and a params file's
    ``rerun.map_every`` reach the node as ``variant`` and ``viewer.map_every`` (their bad values
    are refused under the new names), after one warning line each; the file is unchanged."""
    params = _params_file(tmp_path / "robot.yaml", {"rerun": {"map_every": 0}})
    text = params.read_text()
    proc = subprocess.run([sys.executable, "-m", "resireg.ros2.cli", "--ros-args", "-p",
                           "configuration:=nope", "--params-file", str(params), "-p",
                           f"output_dir:={tmp_path}"], capture_output=True, text=True,
                          env=ros_env(), timeout=300)  # fmt: skip
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert proc.returncode == 2, proc.stderr
    assert lines[:2] == [
        "resireg-ros2: warning: " + WARNING.format(
            old="rerun", new="viewer", read=f"rerun -> viewer in {params}"),
        "resireg-ros2: warning: " + WARNING.format(
            old="configuration", new="variant", read="configuration:=nope -> variant:=nope"),
    ], proc.stderr  # fmt: skip
    assert len(lines) == 3 and lines[2].startswith("resireg-ros2: error: variant='nope': "
                                                   "expected one of "), proc.stderr  # fmt: skip
    assert lines[2].endswith("; viewer.map_every=0: expected an integer >= 1"), proc.stderr
    assert params.read_text() == text


def test_the_parameter_list_has_the_new_names(capsys):
    from resireg.ros2 import cli

    assert cli.main(["--parameters"]) == 0
    names = [row.split("`")[1] for row in capsys.readouterr().out.splitlines()[2:]]
    assert "variant" in names and "configuration" not in names
    assert sorted(n for n in names if n.partition(".")[0] in ("viewer", "rerun")) == [
        f"viewer.{k}" for k in sorted(("save", "spawn", "query", "map_every", "serve", "connect"))
    ]


def test_the_node_renames_agree_with_the_hydra_commands():
    """The node's table (resireg cannot import resireg_train) and resireg-map's renamed keys
    name the same renames of the keys they share."""
    from resireg_train.config.moves import RENAMED_KEYS

    assert set(settings.RENAMED_PARAMETERS) == {"configuration", "rerun"}
    for old, (new, since, removed) in settings.RENAMED_PARAMETERS.items():
        r = RENAMED_KEYS[old]
        assert "map" in r.configs and (r.new, r.since, r.removed) == (new, since, removed)


@pytest.mark.parametrize("kind", ["missing", "truncated"])
def test_a_params_file_rcl_cannot_read_ends_in_one_line_naming_it(tmp_path, kind):
    """A ``--params-file`` that does not exist, or whose YAML is cut mid-flow, is refused with
    exit 2 and one line of ours naming the file (rcl's own log line may precede it), never
    rclpy's traceback; the node starts nothing and writes nothing."""
    params = tmp_path / "robot.yaml"
    if kind == "truncated":
        params.write_text("resireg_map:\n  ros__parameters:\n    window: [4,\n")
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "resireg.ros2.cli", "--ros-args",
                           "--params-file", str(params), "-p", f"output_dir:={out}"],
                          capture_output=True, text=True, env=ros_env(), timeout=300)  # fmt: skip
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert lines[-1].startswith(f"resireg-ros2: error: Couldn't parse params file: "
                                f"'--params-file {params}'"), proc.stderr  # fmt: skip
    assert ", at /" not in lines[-1] and not out.exists()
