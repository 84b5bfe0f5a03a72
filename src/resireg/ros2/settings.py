"""The live node's parameters: names and defaults read from the project's YAML files at start,
checked with the project's rules (no rclpy, no torch: a bad value is reported in a second).

One source per default. ``resireg-ros2`` takes the names and defaults of ``resireg-map``
(``conf/map.yaml``) for what the two share, and adds its own in ``conf/ros2.yaml``:

- the map's keys (``variant``, ``window``, ``voxel_size``, ``points``, ``lattice``,
  ``sum_dtype``, ``storage`` and the ``compact.*`` block, ``max_voxels``, ``short_side``,
  ``model_path``, ``device``, ``seed``, ``save_every``, ``resume``) and ``encoder`` (a
  ``conf/encoder/<name>.yaml`` file, the ``encoder`` entry of map.yaml's defaults list):
  ``conf/map.yaml``, checked by the map's rules (:data:`resireg.specs.mapping.MAP_RULES`, which
  ``resireg-map`` checks too);
- the ReSiReg variants' parameters (``full.n_prototypes``, ``lite.alpha``, ...):
  ``conf/resireg/default.yaml``, checked by the variant table's rules
  (:data:`resireg.specs.variants.VARIANT_SPECS`);
- the live source's keys (``conf/source/ros2.yaml``, composed with its defaults,
  ``rosbag.yaml`` and ``_common.yaml``, as ``resireg-map source=ros2`` has them): those that
  apply to the node's topics (``source.tolerance``, ``source.max_pose_gap``,
  ``source.max_depth``, the topics, ``source.world_frame``, ``source.camera_frame``,
  ``source.depth_scale``) and, under their own names, the pairing's (``max_wait``,
  ``buffer_size``, ``camera_offset``, ``qos``), checked by the source table's rules
  (:data:`resireg.specs.sources.LIVE_RULES`);
- ``viewer.save``, ``viewer.spawn``, ``viewer.query``, ``viewer.map_every``: ``conf/map.yaml``'s
  ``viewer`` block (``viewer.serve``, ``viewer.connect``: ``conf/ros2.yaml``'s);
- the node's own (queue, keyframes, rates, the live Rerun stream): ``conf/ros2.yaml``.

As ROS parameters they keep their dotted YAML paths (``-p source.tolerance:=0.05``,
``-p full.n_prototypes:=24``). The folder is ``conf/`` beside ``src/`` (a checkout or an
editable install) unless ``$RESIREG_CONFIG_DIR`` names another.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from resireg.errors import ConfigError
from resireg.specs.encoders import ENCODER_REPORT_KEYS
from resireg.specs.mapping import MAP_RULES
from resireg.specs.rules import DEVICE, Rule, integer, is_int, is_num, number
from resireg.specs.sources import LIVE_RULES
from resireg.specs.table import compose_conf, conf_dir
from resireg.specs.tree import flatten
from resireg.specs.variants import PARAM_VARIANTS, VARIANT_SPECS

__all__ = [
    "LIVE_KEYS",
    "MAP_BLOCKS",
    "MAP_KEYS",
    "NODE_FILE",
    "RENAMED_PARAMETERS",
    "SOURCE_FILE",
    "SOURCE_KEYS",
    "Parameter",
    "SettingsError",
    "check",
    "compact_settings",
    "config_dir",
    "current_arguments",
    "encoder_entry",
    "parameter_table",
    "parameters",
]

#: The node's own parameters (the file is read at start).
NODE_FILE = "ros2.yaml"
#: The map keys of ``conf/map.yaml`` the node takes (with ``encoder``, the defaults list's).
MAP_KEYS = ("variant", "window", "voxel_size", "points", "lattice", "sum_dtype",
            "storage", "max_voxels", "short_side", "model_path", "device", "seed", "save_every",
            "resume")  # fmt: skip
#: The block of ``conf/map.yaml`` the node takes key by key (``-p compact.dim:=64``).
MAP_BLOCKS = ("compact",)
#: The source keys that apply to live topics (a bag's path, limit, frame_skip and its tf topic
#: names do not: tf2_ros subscribes to /tf and /tf_static, remapped with ``-r``).
SOURCE_KEYS = ("tolerance", "max_pose_gap", "max_depth", "colour_topic", "depth_topic",
               "camera_info_topic", "pose_topic", "world_frame", "camera_frame",
               "depth_scale")  # fmt: skip
#: The live source's keys the node takes under their own names (``-p max_wait:=1.0``).
LIVE_KEYS = ("max_wait", "buffer_size", "camera_offset", "qos")
#: The file (under ``conf/``) of the source keys and :data:`LIVE_KEYS`: the live source's.
SOURCE_FILE = "source/ros2.yaml"
#: The Rerun viewer's keys of ``conf/map.yaml`` the node takes (``-p viewer.save:=map.rrd``).
VIEWER_KEYS = ("save", "spawn", "query", "map_every")

#: The node's renamed parameters by their old name (issue 52: one word per meaning), a dotted
#: name's first part (``rerun`` is every ``rerun.<key>``): the new name, the release that renamed
#: it and the one that removes the old name, which until then is read with one warning line
#: (:func:`current_arguments`). The same renames of ``resireg-map``'s keys for the Hydra commands
#: are ``resireg_train.config.moves.RENAMED_KEYS`` (``resireg`` does not import
#: ``resireg_train``: a test checks that the two tables agree).
RENAMED_PARAMETERS: dict[str, tuple[str, str, str]] = {
    "configuration": ("variant", "0.2.0", "0.3.0"),
    "rerun": ("viewer", "0.2.0", "0.3.0"),
}


class SettingsError(ConfigError):
    """A bad parameter value or file: the message is one line naming the parameter."""


#: The project's ``conf/`` folder (``$RESIREG_CONFIG_DIR`` overrides it): the spec tables'.
config_dir = conf_dir


def _yaml(path: Path) -> dict[str, Any]:
    import yaml

    if not path.is_file():
        raise SettingsError(f"{path}: no such file (the node reads its defaults from conf/; set "
                            "RESIREG_CONFIG_DIR to the project's conf folder)")  # fmt: skip
    with open(path) as f:
        return yaml.safe_load(f) or {}


def _defaults_entry(cfg: Mapping[str, Any], group: str) -> Any:
    """The option of config group ``group`` in a Hydra defaults list (``- encoder: x``)."""
    for item in cfg.get("defaults", []):
        if isinstance(item, dict) and group in item:
            return item[group]
    return None


@dataclass(frozen=True)
class Parameter:
    """One node parameter: its ROS name (the YAML path), default, where the default is read
    (``file:key``) and its rule (``None``: any value)."""

    name: str
    default: Any
    origin: str
    rule: Rule | None = None


def _text(v: Any) -> bool:
    return isinstance(v, str) and bool(v)


def _optional_text(v: Any) -> bool:
    return v is None or isinstance(v, str)


def _variant_ok(v: Any) -> bool:
    from resireg.specs.variants import parse_variant, takes_prior, variant_layer

    if not isinstance(v, str) or takes_prior(v):
        return False
    try:
        base, overrides = parse_variant(v)
        if variant_layer(v) is not None:
            return False
    except ValueError:
        return False
    if base not in VARIANT_SPECS:
        return False
    try:
        from resireg.specs.variants import check_variant_kwargs

        check_variant_kwargs(base, overrides)
    except (ValueError, KeyError):
        return False
    return set(overrides) <= set(VARIANT_SPECS[base].params)


_MAP_RULES: dict[str, Rule] = {
    "variant": (
        _variant_ok,
        f"one of {list(VARIANT_SPECS)}, optionally with parameter overrides "
        "(full@n_prototypes:24); +prior and @layer: are not run by the live node",
    ),
    **MAP_RULES,  # window, voxel_size, points, lattice, sum_dtype, storage, compact.*, ...
    "model_path": (_optional_text, "null or an export folder / Hugging Face repo id"),
    "device": DEVICE,
    "seed": (is_int, "an integer"),
    "resume": (lambda v: isinstance(v, bool), "true or false"),
    "encoder": (_text, "a conf/encoder/<name>.yaml name"),
}
_SOURCE_RULES: dict[str, Rule] = {
    "tolerance": number(0, strict=True, finite=True),
    "max_pose_gap": number(0, strict=True, finite=True),
    "max_depth": (
        lambda v: v is None or (is_num(v) and 0 < v < math.inf),
        "null or a number of metres > 0 (finite)",
    ),
    "colour_topic": (_text, "a topic name"),
    "depth_topic": (_text, "a topic name"),
    "camera_info_topic": (_text, "a topic name"),
    "pose_topic": (_optional_text, "null (the camera pose from tf) or a topic name"),
    "world_frame": (_text, "a frame name"),
    "camera_frame": (_optional_text, "null (the depth image's frame) or a frame name"),
    "depth_scale": number(0, strict=True, finite=True),
}
_VIEWER_RULES: dict[str, Rule] = {
    "save": (_optional_text, "null or a .rrd file"),
    "spawn": (lambda v: isinstance(v, bool), "true or false"),
    "query": (_optional_text, "null or a text"),
    "map_every": integer(1),
    "serve": (lambda v: isinstance(v, bool), "true or false"),
    "connect": (_optional_text, "null or a viewer's gRPC URL (rerun+http://host:port/proxy)"),
}
_NODE_RULES: dict[str, Rule] = {
    "output_dir": (_text, "a folder"),
    "queue_size": integer(1),
    "window_timeout": number(0, strict=True, finite=True),
    "keyframe.translation": number(0, finite=True),
    "keyframe.rotation": number(0, finite=True),
    "publish_rate": number(0, strict=True, finite=True),
    "status_rate": number(0, strict=True, finite=True),
    "top_k": integer(1),
    "max_points": integer(1),
}


def _source_defaults(conf: Path) -> dict[str, tuple[Any, str]]:
    """The live source's keys and the file each default is in: ``conf/source/ros2.yaml``
    composed with its defaults, as ``resireg-map source=ros2`` has them."""
    folder, _, name = SOURCE_FILE.rpartition("/")
    try:
        return compose_conf(conf / folder, name.removesuffix(".yaml"), _yaml)
    except FileNotFoundError as err:  # a parent of the file (its own is checked by _yaml)
        raise SettingsError(
            f"{err} (the node reads its defaults from conf/; set "
            "RESIREG_CONFIG_DIR to the project's conf folder)"
        ) from err


def parameters(conf: Path | None = None) -> dict[str, Parameter]:
    """Every node parameter, its default read from the YAML files (module docstring)."""
    conf = config_dir() if conf is None else Path(conf)
    out: dict[str, Parameter] = {}
    map_cfg = _yaml(conf / "map.yaml")
    for key in MAP_KEYS:
        if key not in map_cfg:
            raise SettingsError(f"{conf / 'map.yaml'}: no {key!r} key")
        out[key] = Parameter(key, map_cfg[key], f"map.yaml:{key}", _MAP_RULES[key])
    for block in MAP_BLOCKS:
        for key, value in (map_cfg.get(block) or {}).items():
            name = f"{block}.{key}"
            if name not in _MAP_RULES:
                raise SettingsError(f"{conf / 'map.yaml'}: {name!r} is no map setting")
            out[name] = Parameter(name, value, f"map.yaml:{name}", _MAP_RULES[name])
    out["encoder"] = Parameter("encoder", _defaults_entry(map_cfg, "encoder"),
                               "map.yaml:defaults.encoder", _MAP_RULES["encoder"])  # fmt: skip
    variants = _yaml(conf / "resireg" / "default.yaml")
    for name in PARAM_VARIANTS:
        for key, value in (variants.get(name) or {}).items():
            rule = VARIANT_SPECS[name].params.get(key)
            out[f"{name}.{key}"] = Parameter(f"{name}.{key}", value,
                                             f"resireg/default.yaml:{name}.{key}", rule)  # fmt: skip
    source = _source_defaults(conf)
    for key in (*SOURCE_KEYS, *LIVE_KEYS):
        if key not in source:
            raise SettingsError(f"{conf / SOURCE_FILE}: no source key {key!r}")
    for key in SOURCE_KEYS:
        value, file = source[key]
        out[f"source.{key}"] = Parameter(f"source.{key}", value, f"{file}:{key}",
                                         _SOURCE_RULES[key])  # fmt: skip
    for key in LIVE_KEYS:
        value, file = source[key]
        out[key] = Parameter(key, value, f"{file}:{key}", LIVE_RULES[key])
    viewer = map_cfg.get("viewer") or {}
    for key in VIEWER_KEYS:
        out[f"viewer.{key}"] = Parameter(f"viewer.{key}", viewer.get(key), f"map.yaml:viewer.{key}",
                                        _VIEWER_RULES[key])  # fmt: skip
    for name, value in flatten(_yaml(conf / NODE_FILE)).items():
        rule = _VIEWER_RULES[name.split(".", 1)[1]] if name.startswith("viewer.") else None
        rule = _NODE_RULES.get(name, rule)
        if rule is None:
            raise SettingsError(f"{conf / NODE_FILE}: {name!r} is no node parameter")
        out[name] = Parameter(name, value, f"{NODE_FILE}:{name}", rule)
    return out


def _nearest(name: str, known: list[str]) -> str:
    close = difflib.get_close_matches(name, known, n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def check(values: Mapping[str, Any], table: Mapping[str, Parameter],
          unknown: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:  # fmt: skip
    """``values`` (every parameter of ``table``) if each passes its rule, else a
    :class:`SettingsError` of one line naming every bad ``name=value`` and what is expected, and
    each ``unknown`` name given on the command line with the nearest known one."""
    errors = [f"{n}: no such parameter{_nearest(n, list(table))}" for n in unknown]
    for name, p in table.items():
        value = values.get(name, p.default)
        if p.rule is not None and not p.rule[0](value):
            errors.append(f"{name}={value!r}: expected {p.rule[1]}")
    if errors:
        raise SettingsError("; ".join(errors))
    return {name: values.get(name, p.default) for name, p in table.items()}


def variant_params(values: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """``{"full": {...}, "lite": {...}, "calib": {...}}`` of checked values (SemanticMap's
    ``params``, as ``resireg_train.jobs.map.make_map`` passes them)."""
    out: dict[str, dict[str, Any]] = {name: {} for name in PARAM_VARIANTS}
    for key, value in values.items():
        name, _, rest = key.partition(".")
        if name in out and rest:
            out[name][rest] = list(value) if isinstance(value, tuple) else value
    return out


def compact_settings(values: Mapping[str, Any]) -> dict[str, Any] | None:
    """The ``compact`` block of checked values (SemanticMap's ``compact``) for
    ``storage=compact``, else ``None``; a ``compact.basis`` path expanded and resolved."""
    if values["storage"] != "compact":
        return None
    out = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith("compact.")}
    basis = out.get("basis")
    if isinstance(basis, str) and Path(basis).expanduser().exists():
        out["basis"] = str(Path(basis).expanduser().resolve())
    return out


def encoder_entry(values: Mapping[str, Any], conf: Path | None = None) -> dict[str, Any]:
    """The encoder entry of ``conf/encoder/<encoder>.yaml`` with ``${model_path}`` resolved:
    ``build_encoder``'s keywords (``kind`` and the builder's keys)."""
    conf = config_dir() if conf is None else Path(conf)
    name = values["encoder"]
    path = conf / "encoder" / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in (conf / "encoder").glob("*.yaml"))
        raise SettingsError(f"encoder={name!r}: expected one of {known} (conf/encoder/)")
    entry = _yaml(path)
    out = {}
    for key, value in entry.items():
        if key in ENCODER_REPORT_KEYS:
            continue
        if value == "${model_path}":
            value = values["model_path"]
            if value is None:
                raise SettingsError(f"model_path=None: encoder={name!r} loads an export: set "
                                    "-p model_path:=<export folder or Hugging Face repo id>")  # fmt: skip
        elif isinstance(value, str) and "${" in value:
            raise SettingsError(f"encoder={name!r}: {key}={value!r} refers to another config "
                                "key, which the live node does not resolve")  # fmt: skip
        out[key] = value
    return out


def parameter_table(conf: Path | None = None) -> str:
    """The parameters as a Markdown table (docs/robot.md holds it; a test compares)."""
    rows = ["| parameter | default | from |", "| --- | --- | --- |"]
    for p in parameters(conf).values():
        default = "null" if p.default is None else p.default
        if isinstance(default, bool):
            default = str(default).lower()
        rows.append(f"| `{p.name}` | `{default}` | `conf/{p.origin}` |")
    return "\n".join(rows)


def _renamed(name: str) -> tuple[str, str | None]:
    """``name`` (a parameter's, or a params file's top-level key) in today's spelling, and the
    old name it was given in (``None``: not renamed)."""
    head, dot, rest = name.partition(".")
    if head not in RENAMED_PARAMETERS:
        return name, None
    return f"{RENAMED_PARAMETERS[head][0]}{dot}{rest}", head


def _warning(old: str, read: list[str]) -> str:
    new, since, removed = RENAMED_PARAMETERS[old]
    return (f"{old!r} is now {new!r} (renamed in {since}; the old name goes in {removed}): "
            f"read {', '.join(read)}")  # fmt: skip


def _both(old: str, given: list[str], where: str = "") -> SettingsError:
    new = RENAMED_PARAMETERS[old][0]
    return SettingsError(
        f"{where}{' '.join(given)}: {old!r} and {new!r} name one parameter "
        f"({old!r} is the old name of {new!r}): give it once, as {new!r}"
    )


def _current_file(path: Path, folder: Path, warn: Callable[[str], None]) -> Path:
    """A ``--params-file`` in today's names: ``path`` itself when it uses no old name, else a
    copy with the old names renamed, written to ``folder`` (one warning line per old name; a
    node's parameters holding an old name and its new one: :class:`SettingsError`)."""
    import yaml

    try:
        tree = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):  # rcl reports it in its own words
        return path
    if not isinstance(tree, dict):
        return path
    read: dict[str, list[str]] = {}
    for node in tree.values():
        params = node.get("ros__parameters") if isinstance(node, dict) else None
        if not isinstance(params, dict):
            continue
        heads = {k.partition(".")[0] for k in params if isinstance(k, str)}
        renamed = {}
        for key, value in params.items():
            new, old = _renamed(key) if isinstance(key, str) else (key, None)
            if old is not None:
                if RENAMED_PARAMETERS[old][0] in heads:
                    given = sorted(
                        k
                        for k in params
                        if isinstance(k, str)
                        and k.partition(".")[0] in (old, RENAMED_PARAMETERS[old][0])
                    )
                    raise _both(old, given, f"{path}: ")
                read.setdefault(old, []).append(f"{key} -> {new} in {path}")
            renamed[new] = value
        params.clear()
        params.update(renamed)
    if not read:
        return path
    for old, words in read.items():
        warn(_warning(old, words))
    out = folder / f"{len(list(folder.iterdir()))}-{path.name}"
    out.write_text(yaml.safe_dump(tree, sort_keys=False))
    return out


def current_arguments(argv: list[str], warn: Callable[[str], None], folder: Path) -> list[str]:
    """``resireg-ros2``'s command line (before ``rclpy.init``) with every parameter given by an
    old name (:data:`RENAMED_PARAMETERS`) renamed: ``-p configuration:=full`` / ``--param
    rerun.save:=m.rrd`` (also ``-p node:name:=value``) and a ``--params-file``'s keys (the
    file's copy in today's names is written to ``folder``, which must outlive ``rclpy.init``);
    ``warn`` gets one line per old name, naming the new one.

    Raises :class:`SettingsError` (one line naming both) when an old name and its new one are
    given together on the command line, or in one node's parameters of one file."""
    out = list(argv)
    rules: list[tuple[int, str, str | None]] = []  # argv index, name, old name
    ros = False
    for i, word in enumerate(argv):
        if word == "--ros-args":
            ros = True
        elif word == "--":
            ros = False
        elif ros and i > 0 and argv[i - 1] in ("-p", "--param") and ":=" in word:
            target, _, value = word.partition(":=")
            prefix, _, name = target.rpartition(":")
            new, old = _renamed(name)
            rules.append((i, name, old))
            out[i] = f"{prefix}:{new}:={value}" if prefix else f"{new}:={value}"
        elif ros and i > 0 and argv[i - 1] == "--params-file":
            out[i] = str(_current_file(Path(word), folder, warn))
    heads = {name.partition(".")[0] for _, name, _ in rules}
    read: dict[str, list[str]] = {}
    for i, _, old in rules:
        if old is None:
            continue
        new = RENAMED_PARAMETERS[old][0]
        if new in heads:
            given = [argv[j] for j, n, _ in rules if n.partition(".")[0] in (old, new)]
            raise _both(old, given)
        read.setdefault(old, []).append(f"{argv[i]} -> {out[i]}")
    for old, words in read.items():
        warn(_warning(old, words))
    return out
