"""``resireg-ros2``: the live mapping node (:class:`resireg.ros2.node.ResiregMapNode`), with
rclpy's argument handling::

    resireg-ros2 --ros-args -p model_path:=<export> -p source.world_frame:=odom \\
        -r __node:=resireg_map -p source.colour_topic:=/camera/camera/color/image_raw

Every parameter, its default and where the default is read: ``resireg-ros2 --parameters``
(docs/robot.md). Ctrl-C (SIGINT) or SIGTERM maps the queued keyframes, saves the map and
publishes it once more, then ends the ROS context (rclpy's own signal handlers, which end the
context first, are not installed: the final publish needs it). Exit status: 0,
2 for a bad parameter or a missing ``robot`` extra (one line on stderr), 1 for a failure of
the mapping thread.

A parameter given by its old name (``-p configuration:=full``, ``-p rerun.save:=m.rrd``, the
same keys in a ``--params-file``) runs as the new one (``variant``, ``viewer.*``) with one
warning line until the release that removes the old name
(:data:`resireg.ros2.settings.RENAMED_PARAMETERS`); the old and the new name given together exit
2 with one line naming both, before anything starts.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable

__all__ = ["main"]

PROG = "resireg-ros2"


def missing_rclpy() -> str | None:
    import importlib.util

    for module in ("rclpy", "sensor_msgs", "std_srvs", "nav_msgs", "visualization_msgs"):
        if importlib.util.find_spec(module) is None:
            return module
    return None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else [PROG, *argv])
    if "--parameters" in argv[1:]:
        from resireg.ros2.settings import SettingsError, parameter_table

        try:
            print(parameter_table())
        except SettingsError as err:
            print(f"{PROG}: error: {err}", file=sys.stderr)
            return 2
        return 0
    import tempfile
    from pathlib import Path

    from resireg.ros2.settings import SettingsError, current_arguments

    # parameters given by an old name (-p configuration:=..., a params file's rerun.*) take the
    # new one before rclpy reads them; the renamed files' copies live until rclpy.init read them
    renamed = tempfile.TemporaryDirectory(prefix="resireg-ros2-")
    try:
        try:
            argv = current_arguments(argv, lambda line: print(f"{PROG}: warning: {line}",
                                     file=sys.stderr), Path(renamed.name))  # fmt: skip
        except SettingsError as err:
            print(f"{PROG}: error: {err}", file=sys.stderr)
            return 2
        return _run(argv, renamed.cleanup)
    finally:
        renamed.cleanup()


def _rcl_message(err: BaseException) -> str:
    """rcl's message in one line, without the C source locations it appends
    (``, at /project/src/parse.c:782``) and its "failed to initialize rcl: " prefix."""
    text = " ".join(str(err).split())
    text = re.sub(r", at \S+:\d+", "", text)
    return text.removeprefix("failed to initialize rcl: ")


def _run(argv: list[str], parsed: Callable[[], None]) -> int:
    """The node of ``argv`` (today's names); ``parsed`` is called once rclpy has read them."""
    missing = missing_rclpy()
    if missing is not None:
        print(f"{PROG}: error: needs the 'robot' extra ({missing} not installed): pip install "
              '"resireg[robot]" (in a clone: pip install -e ".[robot]" -c constraints.txt), '
              "or source a ROS 2 Jazzy install", file=sys.stderr)  # fmt: skip
        return 2
    import signal

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from resireg.ros2.settings import SettingsError

    def stop(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    # SIGINT and SIGTERM end the spin in this thread; the node then closes in order (save,
    # publish) while the context is valid, and only then is the context shut down.
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except RuntimeError as err:  # rcl's RCLError: a params file missing or not YAML, a bad -r
        print(f"{PROG}: error: {_rcl_message(err)}", file=sys.stderr)
        return 2
    finally:
        parsed()  # rcl has read the parameter files (or failed to)
    previous = signal.signal(signal.SIGTERM, stop)
    node = None
    try:
        from resireg.ros2.node import ResiregMapNode

        try:
            node = ResiregMapNode()
        except SettingsError as err:
            print(f"{PROG}: error: {err}", file=sys.stderr)
            return 2
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        try:
            executor.spin()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
    finally:
        try:
            if node is not None:
                folder = node.close()
                if folder is not None:
                    print(f"{PROG}: map saved to {folder} ({len(node.worker.smap)} voxels, "
                          f"{node.worker.smap.frames} frames)", flush=True)  # fmt: skip
                node.destroy_node()
        finally:
            signal.signal(signal.SIGTERM, previous)
            rclpy.try_shutdown()
    return 1 if node is not None and node.worker.error is not None else 0


if __name__ == "__main__":
    sys.exit(main())
