"""The playground's Gradio page (``resireg-playground``).

Left: an upload (any file; it is checked here, so a file that is not an image is reported in
the page, not by the browser), the example images, the text queries and ReSiReg's parameters
as sliders starting at ``conf/resireg/default.yaml``. Right: the status line (errors appear
here), the image as encoded, one panel per variant (BB, Lite, Full, and Full with the SAM 2
prior when a prior is loaded) and the seconds each took. Element ids (``status``,
``map-bb``, ``map-full``, ``timings``...) are stable: the browser test reads them.
"""

from __future__ import annotations

import logging
import signal
import threading
from pathlib import Path
from typing import Any

import gradio as gr

from resireg_train.playground.core import (
    LABELS,
    Playground,
    PlaygroundError,
    load_image,
    render,
    timing_table,
)
from resireg_train.playground.examples import EXAMPLES, example_image

__all__ = ["build_app", "launch", "run_query"]

log = logging.getLogger(__name__)

#: Slider ranges (the value always starts at the YAML default; a range grows to include it).
_RANGES: dict[str, tuple[float, float, float]] = {
    "n_prototypes": (1, 256, 1),
    "alpha": (0.1, 50.0, 0.1),
    "tau": (0.0, 1.0, 0.01),
    "upscale": (1, 4, 1),
}
_TITLES = {"n_prototypes": "prototypes n", "alpha": "alpha", "tau": "tau (gate)",
           "upscale": "upscale s"}  # fmt: skip


def _slider(name: str, value: Any, variant: str) -> gr.Slider:
    lo, hi, step = _RANGES[name]
    return gr.Slider(minimum=min(lo, value), maximum=max(hi, value), step=step, value=value,
                     label=f"{variant} {_TITLES[name]}", elem_id=f"{variant}-{name}")  # fmt: skip


def _error(message: str) -> str:
    return f"**Error:** {message}"


def run_query(
    playground: Playground,
    path: str | None,
    example: str,
    text: str,
    short_side: float,
    *values: float,
) -> list[Any]:
    """What the Run button does: ``[status, canvas, *panels, timings]`` (the page's outputs).

    ``path`` is the upload (``None``: the ``example`` image); ``values`` are the sliders,
    Lite ``alpha, tau, upscale`` then Full ``n_prototypes, alpha, tau, upscale``. A bad
    upload, no query or a bad parameter gives an ``Error:`` status and empty panels; an
    unexpected failure too (logged with its traceback), so the server keeps serving.
    """
    lite = dict(zip(("alpha", "tau", "upscale"), values[:3], strict=True))
    full = dict(zip(("n_prototypes", "alpha", "tau", "upscale"), values[3:], strict=True))
    blank = [None] * (1 + len(playground.panels))
    try:
        image = load_image(path) if path else example_image(example)
        result = playground.compute(image, text, lite=lite, full=full, short_side=int(short_side))
    except (PlaygroundError, ValueError) as err:  # ReSiReg's errors name the bad parameter
        return [_error(str(err)), *blank, ""]
    except Exception as err:  # noqa: BLE001 - shown in the page; the server goes on
        log.exception("playground query failed")
        return [_error(f"{type(err).__name__}: {err}"), *blank, ""]
    shown = render(result)
    source = f"upload {Path(path).name}" if path else f"example {example!r}"
    done = f"Done: {source}, queries {', '.join(map(repr, result.queries))}."
    return [done, result.canvas, *(shown[k] for k in playground.panels), timing_table(result)]


def build_app(playground: Playground, title: str = "ReSiReg playground") -> gr.Blocks:
    """The page for ``playground`` (not launched)."""
    lite0, full0 = playground.defaults["lite"], playground.defaults["full"]
    panels = playground.panels
    first = next(iter(EXAMPLES))
    with gr.Blocks(title=title, analytics_enabled=False) as demo:
        gr.Markdown(
            f"# {title}\nCosine similarity of every patch with each text query: the encoder's "
            "own language tokens (BB), ReSiReg Lite and ReSiReg Full"
            + (" and Full with the SAM 2 prior" if "full_prior" in panels else "")
            + ". One colour scale per query, shared by the panels."
        )
        with gr.Row():
            with gr.Column(scale=1):
                upload = gr.File(label="Upload an image", type="filepath", elem_id="upload")
                example = gr.Radio(choices=list(EXAMPLES), value=first, elem_id="example",
                                   label="... or an example (scikit-image)")  # fmt: skip
                queries = gr.Textbox(value=EXAMPLES[first][1], elem_id="queries",
                                     label="Text queries, comma-separated")  # fmt: skip
                run = gr.Button("Run", variant="primary", elem_id="run")
                short = gr.Slider(minimum=16, maximum=max(1024, playground.short_side or 0),
                                  step=1, value=playground.short_side, elem_id="short-side",
                                  label="image shorter side (px)")  # fmt: skip
                with gr.Accordion("ReSiReg parameters (conf/resireg/default.yaml)"):
                    lite_sliders = [
                        _slider(k, lite0[k], "lite") for k in ("alpha", "tau", "upscale")
                    ]
                    full_sliders = [_slider(k, full0[k], "full")
                                    for k in ("n_prototypes", "alpha", "tau", "upscale")]  # fmt: skip
            with gr.Column(scale=3):
                status = gr.Markdown("Pick an example or upload an image, then Run.",
                                     elem_id="status")  # fmt: skip
                canvas = gr.Image(label="image as encoded", type="numpy", format="png",
                                  interactive=False, elem_id="canvas", height=240)  # fmt: skip
                with gr.Row():
                    images = [gr.Image(label=LABELS[k], type="numpy", format="png",
                                       interactive=False, elem_id=f"map-{k.replace('_', '-')}")
                              for k in panels]  # fmt: skip
                timings = gr.Markdown(elem_id="timings")

        def on_upload(path: str | None) -> tuple[str, Any]:
            if path is None:
                return "Upload removed: the example is used.", None
            try:
                image = load_image(path)
            except PlaygroundError as err:
                return _error(str(err)), None
            return f"Loaded the upload ({image.width} x {image.height} px); press Run.", image

        def on_example(name: str) -> tuple[Any, str]:
            return None, EXAMPLES[name][1]  # an example replaces the upload

        def on_run(path: str | None, name: str, text: str, side: float, *values: float):
            return run_query(playground, path, name, text, side, *values)

        inputs = [upload, example, queries, short, *lite_sliders, *full_sliders]
        outputs = [status, canvas, *images, timings]
        upload.change(on_upload, upload, [status, canvas], api_visibility="private")
        example.input(on_example, example, [upload, queries], api_visibility="private")
        run.click(on_run, inputs, outputs, api_name="run")  # also gradio_client's /run
        queries.submit(on_run, inputs, outputs, api_visibility="private")  # Enter = Run
    return demo


def launch(demo: gr.Blocks, host: str = "127.0.0.1", port: int | None = None) -> None:
    """Serve ``demo`` until Ctrl-C or SIGTERM (``port=None``: Gradio's first free port from 7860).

    No share link, no server-side rendering, system fonts only (no request leaves the
    machine)."""
    theme = gr.themes.Default(font=["ui-sans-serif", "system-ui", "sans-serif"],
                              font_mono=["ui-monospace", "monospace"])  # fmt: skip
    # SIGTERM (kill, a service manager, a container's stop) closes the server as Ctrl-C does:
    # Gradio's block_thread closes it on KeyboardInterrupt and returns (exit 0). Set before the
    # server starts: one that comes as soon as the page answers is handled too.
    main = threading.current_thread() is threading.main_thread()  # where handlers may be set
    previous = signal.signal(signal.SIGTERM, _interrupt) if main else None
    try:
        # quiet: Gradio would also print "To create a public link, set `share=True`", advice
        # this page (127.0.0.1 by default, no request leaving the machine) must not follow; the
        # one line a user needs, the address, is printed here.
        demo.queue(default_concurrency_limit=1).launch(
            server_name=host, server_port=port, share=False, ssr_mode=False, show_error=True,
            theme=theme, max_file_size="50mb", footer_links=[], quiet=True,
            prevent_thread_lock=True,
        )  # fmt: skip
        print(f"* Running on local URL:  {demo.local_url}", flush=True)
        demo.block_thread()  # until Ctrl-C or SIGTERM
    except KeyboardInterrupt:  # one that came before block_thread took over
        demo.close()
    finally:
        if main:
            signal.signal(signal.SIGTERM, previous)


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")
