"""What the ROS 2 tests share: Fast DDS restricted to shared memory (tests/fastdds_shm.xml), a
ROS domain of this test process, an executor spinning in a thread, and the check that a process
opened no UDP socket.

Import this module before rclpy creates a context: the environment it sets is read then. The
ROS wheels' ``.pth`` bootstrapper re-executes every Python start of the environment once with
``LD_LIBRARY_PATH`` set (~45 ms): the subprocess tests pay it per process.
"""

import os
import threading
import time
from pathlib import Path

from helpers.paths import TESTS

PROFILE = TESTS / "fastdds_shm.xml"


def ros_env(env=None):
    """``env`` (default this process's) with the shared-memory profile, Fast DDS and this test
    process's own ROS domain (0..99 from its PID, so parallel test workers never meet)."""
    env = dict(os.environ if env is None else env)
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(PROFILE)
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env.setdefault("RESIREG_TEST_DOMAIN", str(os.getpid() % 100))
    env["ROS_DOMAIN_ID"] = env["RESIREG_TEST_DOMAIN"]
    env.pop("ROS_LOCALHOST_ONLY", None)
    env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    return env


os.environ.update(ros_env())


def udp_sockets(pid):
    """Inodes of the UDP / UDPv6 sockets process ``pid`` holds open: those of its socket file
    descriptors (/proc/<pid>/fd) that its network namespace lists in /proc/<pid>/net/udp{,6}."""
    udp = set()
    for name in ("udp", "udp6"):
        path = Path(f"/proc/{pid}/net/{name}")
        if path.is_file():
            for line in path.read_text().splitlines()[1:]:
                udp.add(line.split()[9])
    held = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            held.add(target[len("socket:[") : -1])
    return udp & held


class Spinner:
    """An executor spinning ``nodes`` in a background thread until :meth:`stop`."""

    def __init__(self, context, *nodes):
        from rclpy.executors import MultiThreadedExecutor

        self.executor = MultiThreadedExecutor(num_threads=2, context=context)
        for node in nodes:
            self.executor.add_node(node)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # the context was shut down
                return

    def add(self, node):
        self.executor.add_node(node)

    def remove(self, node):
        self.executor.remove_node(node)

    def stop(self):
        self._stop.set()
        self.thread.join(5)
        self.executor.shutdown()


def wait_for(predicate, timeout=20.0, what="condition"):
    """Poll ``predicate`` until it is true; an AssertionError naming ``what`` after ``timeout``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")
