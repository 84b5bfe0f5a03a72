"""What a search explores and what it optimises: the Optuna distributions of the search space
(read from Hydra's sweep syntax: ``choice``, ``interval``, ``range``, ``tag(log, ...)``), a
parameter value as an override again, and the check of ``optimized_metric`` against what the
job will log (with the ``first_key`` resolver that lets ``conf/hparams_search/`` name the
first validation dataset's metric)."""

from __future__ import annotations

import math
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.specs.metrics import METRIC_SPECS

__all__ = ["check_metric", "distributions", "format_value", "register_search_resolvers"]


def _interval(low: Any, high: Any, log_scale: bool) -> Any:
    from optuna.distributions import FloatDistribution, IntDistribution

    if isinstance(low, int) and isinstance(high, int):
        return IntDistribution(low, high, log=log_scale)
    return FloatDistribution(float(low), float(high), log=log_scale)


def distributions(params: dict[str, str]) -> dict[str, Any]:
    """Optuna distributions of Hydra sweep expressions: ``choice(a, b)`` (categorical),
    ``interval(lo, hi)`` (float, or int if both ends are), ``range(start, stop, step)``
    (Python's range: ``stop`` excluded, so the highest value is the last one the range
    reaches: no range is ever "not divisible by its step"), ``tag(log, ...)`` log scale."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, RangeSweep
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    from resireg.errors import ConfigError

    parser = OverridesParser.create()
    out = {}
    for key, expr in params.items():
        try:
            (override,) = parser.parse_overrides([f"{key}={expr}"])
        except Exception as err:
            raise ConfigError(f"hydra.sweeper.params.{key}={expr!r}: {err}") from None
        value = override.value()
        log_scale = "log" in getattr(value, "tags", set())
        if isinstance(value, ChoiceSweep):
            out[key] = CategoricalDistribution(list(value.list))
        elif isinstance(value, IntervalSweep):
            out[key] = _interval(value.start, value.end, log_scale)
        elif isinstance(value, RangeSweep):
            start, stop, step = value.start, value.stop, value.step or 1
            count = math.ceil((stop - start) / step)
            if count < 1:
                raise ConfigError(f"hydra.sweeper.params.{key}={expr!r} is an empty range")
            last = start + (count - 1) * step
            if all(isinstance(v, int) for v in (start, stop, step)):
                out[key] = IntDistribution(start, last, step=step)
            else:
                out[key] = FloatDistribution(float(start), float(last), step=float(step))
        else:
            raise ConfigError(
                f"hydra.sweeper.params.{key}={expr!r} is not choice(...), interval(...) or "
                "range(...)"
            )
    return out


def format_value(value: Any) -> str:
    """A parameter value as a Hydra override value."""
    if isinstance(value, float):
        return repr(value)
    return str(value)


def check_metric(cfg: DictConfig) -> None:
    """``optimized_metric`` must be one the job logs: ``val/ovss/<dataset>/(f)miou_<variant>``
    with a configured validation dataset (``resireg-train``: ``val_data=``; ``resireg-eval``:
    ``dataset=``) and variant. Checked before the first trial (a search that would train every
    trial and then find nothing to optimise is refused at once)."""
    from resireg.errors import ConfigError

    metric = cfg.get("optimized_metric")
    if not metric:
        raise ConfigError(
            "optimized_metric is not set: an Optuna search needs the metric to optimise"
        )
    parts = str(metric).split("/")
    if len(parts) != 4 or parts[:2] != ["val", "ovss"]:
        return  # another metric (train/loss...): the job checks it when it ends
    callback = OmegaConf.select(cfg, "callbacks.resireg_eval")
    if callback is not None:  # resireg-train: the ReSiRegEval callback's datasets
        datasets = {str(d.get("name", k)) for k, d in (callback.get("datasets") or {}).items()}
        variants = callback.get("variants") or []
        where = "val_data"
    else:  # resireg-eval
        datasets = {str(OmegaConf.select(cfg, "dataset.name"))}
        variants = cfg.get("variants") or []
        where = "dataset"
    variants = [str(v) for v in variants]
    names = sorted(
        f"val/ovss/{d}/{kind}_{v}"
        for d in datasets
        for v in variants
        for kind in METRIC_SPECS["pixels"].logged  # the OVSS engine logs these
    )
    if metric not in names:
        raise ConfigError(
            f"optimized_metric={metric!r} is never logged with the configured validation data "
            f"({where}: {sorted(datasets)}, variants {variants}); it logs: {names}"
        )


def _first_key(node: Any) -> str:
    """``${first_key:${callbacks.resireg_eval.datasets}}``: the name of the first configured
    validation dataset (the metric a training search optimises follows ``val_data=``)."""
    if not node:
        return "<no validation dataset: val_data= is empty>"
    key = next(iter(node))
    return str(node[key].get("name", key)) if hasattr(node[key], "get") else str(key)


def register_search_resolvers() -> None:
    """``first_key`` for ``conf/hparams_search/``."""
    if not OmegaConf.has_resolver("first_key"):
        OmegaConf.register_new_resolver("first_key", _first_key)
