"""``resireg-playground``: an interactive page comparing BB, ReSiReg Lite and ReSiReg Full
(and Full with a SAM 2 prior) on an uploaded or example image (needs the ``playground``
extra: ``pip install -e ".[playground]"``).

    resireg-playground --model-path outputs/smoke/<run>/export          # our VLM, an export
    resireg-playground --encoder clip_vit_b16                           # a conf/encoder/ entry
    resireg-playground --encoder tests/conf/encoder/tiny_vlm.yaml --model-path <export>
    resireg-playground --model-path <export> --prior sam2 --prior-model facebook/sam2.1-hiera-tiny

Gradio, torch and the models load after the arguments parse (``--help`` answers at once).
"""

from __future__ import annotations

import argparse
import os

__all__ = ["main"]

DESCRIPTION = (
    "Interactive playground: similarity maps of BB, ReSiReg Lite and ReSiReg Full side by side "
    "for an uploaded or example image and comma-separated text queries."
)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="resireg-playground", description=DESCRIPTION)
    p.add_argument("--model-path", help="an export folder (resireg-train's <run>/export) or a "
                   "Hugging Face repo id; the encoder when --encoder is not given")  # fmt: skip
    p.add_argument("--encoder", help="a conf/encoder/ name (clip_vit_b16, radio_v3b_siglip2, ...) "
                   "or the path of an encoder YAML file (default: resireg_vlm, i.e. "
                   "--model-path)")  # fmt: skip
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default: the first free one from 7860)")
    p.add_argument("--device", default="auto", help="auto (cuda if available), cpu, cuda, cuda:N")
    p.add_argument("--short-side", type=int, help="default shorter image side in pixels "
                   "(default: the evaluation protocol's, conf/dataset/ade20k.yaml)")  # fmt: skip
    p.add_argument("--prior", choices=("none", "sam2"), default="none",
                   help="add ReSiReg Full with a segmentation prior (sam2: SAM 2.1 automatic "
                   "masks, settings of conf/prior/sam2.yaml; needs transformers)")  # fmt: skip
    p.add_argument("--prior-model", help="with --prior sam2: a Hugging Face id or a local "
                   "folder of a transformers SAM 2 model (default: conf/prior/sam2.yaml's "
                   "model, facebook/sam2.1-hiera-tiny)")  # fmt: skip
    return p


def _prior(kind: str, model: str | None, device: str):
    """The prior provider ``images -> LongTensor [B, H, W]`` of ``conf/prior/<kind>.yaml``
    (``model`` replaces its ``model``), or ``None``."""
    if kind == "none":
        return None
    from omegaconf import OmegaConf

    from resireg.priors import build_prior
    from resireg_train.config.errors import config_path
    from resireg_train.config.paths import CONFIG_DIR

    spec = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "prior" / f"{kind}.yaml"))
    if model:
        spec["model"] = model
    from resireg.models import WeightsUnavailableError

    try:
        with config_path("prior", {"spec": "prior"}):
            return build_prior(spec, device=device)
    except ImportError as err:  # transformers missing: the page works without the prior
        raise ValueError(f"--prior {kind} is not available here: {err}") from err
    except WeightsUnavailableError as err:  # offline: say which option takes a local folder
        raise ValueError(f"--prior-model (prior.model={spec['model']!r}): {err}") from err


def _uncached_repo(source: str) -> str | None:
    """Why ``source``, not a local folder and so a Hugging Face repo id, cannot load here: not
    in the local cache while offline (``HF_HUB_OFFLINE``) or, online, no such repo; ``None``
    when it may load. Checked with huggingface_hub alone, before torch and Gradio load (the
    model loader would find the same after seconds of imports, naming its own config key)."""
    from resireg.specs.exports import registry_model

    if os.path.isdir(source) or registry_model(source) is not None:  # models:/: MLflow's
        return None
    from huggingface_hub import constants, snapshot_download
    from huggingface_hub.errors import LocalEntryNotFoundError, RepositoryNotFoundError

    try:
        snapshot_download(source, local_files_only=True)
        return None
    except LocalEntryNotFoundError:
        pass
    hint = "give an export folder (resireg-train's <run>/export) or a cached repo id"
    if constants.HF_HUB_OFFLINE:
        return (f"{source!r} is no local folder and, as a Hugging Face repo id, not cached "
                f"(HF_HUB_OFFLINE is set); {hint}")  # fmt: skip
    from huggingface_hub import HfApi

    try:
        HfApi().model_info(source, timeout=5)
    except RepositoryNotFoundError:
        return (f"{source!r} is no local folder and no Hugging Face model repo (or none this "
                f"machine's token may read); {hint}")  # fmt: skip
    except Exception as err:  # no network, a proxy, a server error: the model cannot load
        return (f"{source!r} is no local folder and, as a Hugging Face repo id, not cached; "
                f"huggingface.co could not be asked ({type(err).__name__}); {hint}")  # fmt: skip
    return None


def main(argv: list[str] | None = None) -> None:
    """Console entry point (see the module docstring)."""
    parser = _parser()
    args = parser.parse_args(argv)
    if args.model_path is None and args.encoder is None:
        parser.error("give --model-path (an export) or --encoder (a conf/encoder/ name or YAML)")
    if args.prior == "none" and args.prior_model:
        parser.error("--prior-model is given without --prior sam2")
    if args.port is not None and not 0 < args.port < 65536:
        parser.error(f"--port={args.port}: expected 1..65535")
    if args.short_side is not None and args.short_side < 1:
        parser.error(f"--short-side={args.short_side}: expected a number of pixels >= 1")
    # The configs first (OmegaConf only): a bad --encoder is reported at once.
    from resireg_train.playground.config import encoder_spec, reads_model_path, resireg_defaults

    try:
        spec = encoder_spec(args.encoder, args.model_path)
        resireg_defaults()
    except ValueError as err:
        parser.exit(2, f"resireg-playground: error: {err}\n")
    if reads_model_path(spec):  # the loader's rule, before torch (resireg.specs.exports)
        from resireg.specs.exports import export_source_problem

        problem = export_source_problem(spec["path"]) or _uncached_repo(spec["path"])
        if problem:
            parser.exit(2, f"resireg-playground: error: --model-path: {problem}\n")
    os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")  # no request leaves the machine
    # torch, the models and Gradio load only now.
    try:
        import gradio  # noqa: F401
    except ImportError as err:
        parser.exit(2, f"resireg-playground: error: {err}; install the extra: "
                    'pip install -e ".[playground]"\n')  # fmt: skip
    from resireg.models import WeightsUnavailableError
    from resireg.models.factory import resolve_device
    from resireg_train.config.errors import error_message
    from resireg_train.playground.app import build_app, launch
    from resireg_train.playground.core import Playground

    device = str(resolve_device(args.device))
    try:
        prior = _prior(args.prior, args.prior_model, device)
        playground = Playground.from_config(
            args.encoder, args.model_path, device=device, short_side=args.short_side, prior=prior
        )
    except (ValueError, TypeError, FileNotFoundError, WeightsUnavailableError) as err:
        parser.exit(2, f"resireg-playground: error: {error_message(err)}\n")
    name = args.encoder or args.model_path
    print(f"resireg-playground: {name} on {device}, panels {playground.panels}", flush=True)
    launch(build_app(playground, title=f"ReSiReg playground: {name}"), args.host, args.port)


if __name__ == "__main__":
    main()
