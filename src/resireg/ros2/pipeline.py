"""The live node's frame path without ROS: pairing, keyframes and the mapping thread.

Messages come in one at a time (:class:`FramePairer`); each depth image is a candidate frame,
as in a bag (:mod:`resireg.sources.rosbag`): the colour image of the nearest stamp within
``tolerance`` (:func:`pair_nearest`), the latest camera info received up to its stamp (else the
first), the camera pose at its stamp (a pose source of :mod:`resireg.ros2.poses`: a
``PoseStamped`` / ``Odometry`` topic and a fixed camera offset, or tf). A depth image is decided as soon as nothing that could still
arrive would change the answer: a colour image stamped as far past it as its best match (or
``tolerance``) has arrived (stamps increase per topic) and the pose source has a sample at or
after its stamp; or else
after ``max_wait`` seconds, with what has arrived. Frames leave in stamp order, so a live
stream is paired as the whole recording would be. Messages whose stamp goes back or repeats on
their topic are left out (``bad_stamp``), as in a bag.

Keyframes (:class:`KeyframeFilter`): a frame whose camera moved at least ``translation`` metres
or turned at least ``rotation`` radians since the last keyframe (OTAS's rule; 0 takes every
frame). :class:`MapWorker` maps them in its own thread: a bounded queue (a new keyframe past
``queue_size`` drops the oldest, counted as ``queue_full``), windows of ``window`` consecutive
keyframes (or the ones it has after ``window_timeout`` seconds) made by :func:`windows` and fused
with :meth:`resireg.mapping.SemanticMap.add`, exactly as ``resireg-map`` does, under a lock the
queries, saves and clears share.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# The frame records, windows, pairing and pose interpolation of resireg-map's readers.
from resireg.sources.frames import FrameCounts, RGBDFrame, SkippedFrame, windows
from resireg.sources.pairing import pair_nearest

__all__ = [
    "FramePairer",
    "KeyframeFilter",
    "MapWorker",
    "rotation_angle",
]

log = logging.getLogger(__name__)


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """The angle in radians of the rotation between two ``[4, 4]`` poses."""
    r = a[:3, :3].T @ b[:3, :3]
    return float(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2))))


class KeyframeFilter:
    """OTAS's keyframe rule: a pose is a keyframe when it moved at least ``translation`` metres
    or turned at least ``rotation`` radians from the last keyframe (the first pose is one)."""

    def __init__(self, translation: float, rotation: float) -> None:
        self.translation, self.rotation = float(translation), float(rotation)
        self.last: np.ndarray | None = None

    def __call__(self, pose: np.ndarray) -> bool:
        if self.last is not None:
            moved = float(np.linalg.norm(pose[:3, 3] - self.last[:3, 3]))
            if moved < self.translation and rotation_angle(self.last, pose) < self.rotation:
                return False
        self.last = np.array(pose, dtype=np.float64)
        return True

    def reset(self) -> None:
        self.last = None


@dataclass
class _Depth:
    stamp: float
    msg: Any
    frame_id: str
    received: float  # time.monotonic()


@dataclass
class _Colour:
    stamp: float
    msg: Any
    used: bool = False
    image: np.ndarray | str | None = None  # decoded (or why it cannot be), once


@dataclass
class Intake:
    """What :class:`FramePairer` counted: depth images received, candidate frames dropped by
    kind (``unpaired``, ``no_pose``, ``undecodable``, ``bad_stamp``, ``size_mismatch``,
    ``no_camera_info``, ``overflow``), colour images no depth image took, and colour / camera
    info messages left out for their stamps."""

    received: int = 0
    dropped: Counter = field(default_factory=Counter)
    reasons: dict[str, str] = field(default_factory=dict)
    unpaired_colour: int = 0
    colour_stamp_faults: int = 0

    def skip(self, record: SkippedFrame) -> SkippedFrame:
        self.dropped[record.kind] += 1
        self.reasons.setdefault(record.kind, f"{record.name}: {record.reason}")
        return record


class FramePairer:
    """Live pairing of depth, colour, camera info and pose (module docstring).

    Args:
        poses: a pose source: ``lookup(stamp, frame_id) -> (pose or None, why, final)``.
        topics: ``colour``, ``depth``, ``camera_info`` topic names (records are named
            ``<depth topic>@<stamp>``, reasons name the others).
        tolerance: seconds between a depth image and its colour image.
        max_wait: seconds a depth image waits for what would decide it.
        depth_scale: metres per unit of 16UC1 depth.
        decode_colour / decode_depth: message -> array (ValueError when not decodable).
        buffer_size: messages kept per input; a depth image past it is dropped (``overflow``).
        camera_frame: the pose's frame (``None``: the depth image's ``header.frame_id``).

    ``on_colour_fault`` (``None``, or called with ``"<colour topic>@<stamp>: why"`` for each
    colour image left out for its stamp, as a bag's ``colour_stamp_faults`` name them): what
    the owner keeps of them beyond the count (the live source lists them for results.json).
    """

    def __init__(self, poses: Any, topics: dict[str, str], tolerance: float, max_wait: float,
                 depth_scale: float, decode_colour: Callable[[Any], np.ndarray],
                 decode_depth: Callable[[Any, float], np.ndarray], buffer_size: int = 30,
                 camera_frame: str | None = None) -> None:  # fmt: skip
        self.poses, self.topics = poses, topics
        self.tolerance, self.max_wait = float(tolerance), float(max_wait)
        self.depth_scale, self.buffer_size = float(depth_scale), int(buffer_size)
        self.decode_colour, self.decode_depth = decode_colour, decode_depth
        self.camera_frame = camera_frame
        self.colours: deque[_Colour] = deque()
        self.pending: deque[_Depth] = deque()
        self.infos: deque[tuple[float, np.ndarray, tuple[int, int]]] = deque(maxlen=buffer_size)
        self.first_info: tuple[float, np.ndarray, tuple[int, int]] | None = None
        self.counts = Intake()
        self.last_depth = -math.inf
        self.lock = threading.Lock()
        self.on_colour_fault: Callable[[str], None] | None = None

    # ------------------------------------------------------------------ inputs
    def colour(self, stamp: float, msg: Any) -> None:
        with self.lock:
            if self.colours and stamp <= self.colours[-1].stamp:
                self.counts.colour_stamp_faults += 1
                if self.on_colour_fault is not None:
                    topic, last = self.topics["colour"], self.colours[-1].stamp
                    self.on_colour_fault(f"{topic}@{stamp:.6f}: header stamp {stamp:.6f} on "
                                         f"{topic} is not after {last:.6f}, the stamp of a "
                                         "message received before it: stamps go back or "
                                         "repeat")  # fmt: skip
                return
            self.colours.append(_Colour(float(stamp), msg))
            while len(self.colours) > self.buffer_size:
                self._evict_colour()

    def info(self, stamp: float, k: np.ndarray, size: tuple[int, int]) -> None:
        with self.lock:
            if not np.isfinite(k).all():
                return
            entry = (float(stamp), np.asarray(k, dtype=np.float64).reshape(3, 3), size)
            if self.infos and stamp < self.infos[-1][0]:
                return
            self.infos.append(entry)
            if self.first_info is None:
                self.first_info = entry

    def depth(self, stamp: float, msg: Any, frame_id: str, now: float) -> list[SkippedFrame]:
        """Add a depth image (a candidate frame); returns those dropped at once."""
        out = []
        with self.lock:
            self.counts.received += 1
            name = f"{self.topics['depth']}@{stamp:.6f}"
            if stamp <= self.last_depth:
                out.append(self.counts.skip(SkippedFrame(
                    name, f"header stamp {stamp:.6f} on {self.topics['depth']} is not after "
                    f"{self.last_depth:.6f}: stamps go back or repeat", "bad_stamp")))  # fmt: skip
                return out
            self.last_depth = float(stamp)
            self.pending.append(_Depth(float(stamp), msg, frame_id, now))
            while len(self.pending) > self.buffer_size:
                old = self.pending.popleft()
                out.append(self.counts.skip(SkippedFrame(
                    f"{self.topics['depth']}@{old.stamp:.6f}",
                    f"more than buffer_size={self.buffer_size} depth images waiting to be "
                    "paired", "overflow")))  # fmt: skip
        return out

    # ------------------------------------------------------------------ pairing
    def poll(self, now: float) -> list[tuple[RGBDFrame | SkippedFrame, float]]:
        """The depth images decided by now, in stamp order, each as an :class:`RGBDFrame` or a
        :class:`SkippedFrame`, with the time it was received."""
        out = []
        with self.lock:
            while self.pending:
                d = self.pending[0]
                record = self._decide(d, now)
                if record is None:
                    break
                self.pending.popleft()
                if isinstance(record, SkippedFrame):
                    self.counts.skip(record)
                out.append((record, d.received))
                # a later depth image is stamped after this one: colour images older than
                # this stamp less the tolerance can pair with none of them
                while self.colours and self.colours[0].stamp < d.stamp - self.tolerance:
                    self._evict_colour()
        return out

    def _evict_colour(self) -> None:
        c = self.colours.popleft()
        if not c.used:
            self.counts.unpaired_colour += 1

    def _decide(self, d: _Depth, now: float) -> RGBDFrame | SkippedFrame | None:
        expired = now - d.received >= self.max_wait
        name = f"{self.topics['depth']}@{d.stamp:.6f}"
        stamps = np.array([c.stamp for c in self.colours], dtype=np.float64)
        m = int(pair_nearest(np.array([d.stamp]), stamps, self.tolerance)[0])
        # decided once a colour image no nearer one can follow has arrived: stamps increase,
        # so any later one lies beyond the latest (and of two equally near the earlier wins)
        reach = self.tolerance if m < 0 else abs(stamps[m] - d.stamp)
        decided = stamps.size > 0 and stamps[-1] >= d.stamp + reach
        if not (decided or expired):
            return None
        if m < 0:
            why = f"no {self.topics['colour']} image within {self.tolerance} s"
            if stamps.size:
                near = stamps[np.abs(stamps - d.stamp).argmin()]
                why += f" (the nearest received is {near - d.stamp:+.3f} s away)"
            else:
                why += " (none received)"
            return SkippedFrame(name, why, "unpaired")
        if self.first_info is None:
            if not expired:
                return None
            return SkippedFrame(name, f"no {self.topics['camera_info']} message yet",
                                "no_camera_info")  # fmt: skip
        pose, why, final = self.poses.lookup(d.stamp, self.camera_frame or d.frame_id)
        if not (final or expired):
            return None
        if pose is None:
            return SkippedFrame(name, why, "no_pose")
        try:
            depth = self.decode_depth(d.msg, self.depth_scale)
        except Exception as err:  # any decoding failure: the message is at fault
            return SkippedFrame(name, str(err), "undecodable")
        c = self.colours[m]
        c.used = True
        if c.image is None:
            try:
                c.image = self.decode_colour(c.msg)
            except Exception as err:
                c.image = f"{self.topics['colour']}@{c.stamp:.6f}: {err}"
            c.msg = None  # decoded: the message is no longer needed
        if isinstance(c.image, str):
            return SkippedFrame(name, f"colour {c.image}", "undecodable")
        info = self.first_info
        for entry in self.infos:  # the latest at or before the stamp (else the first)
            if entry[0] <= d.stamp:
                info = entry
        _, k, (h, w) = info
        if h and w and depth.shape != (h, w):
            return SkippedFrame(
                name,
                f"depth image {depth.shape[1]}x{depth.shape[0]} but {self.topics['camera_info']}"
                f"@{info[0]:.6f} is for {w}x{h}: its K is of another resolution (give the "
                "depth image's own camera info)",
                "size_mismatch",
            )
        return RGBDFrame(c.image, depth, k.copy(), np.asarray(pose, dtype=np.float64), d.stamp,
                         name)  # fmt: skip

    def sizes(self) -> dict[str, int]:
        """Messages held now (each bounded by ``buffer_size``)."""
        with self.lock:
            return {"colour": len(self.colours), "depth": len(self.pending),
                    "camera_info": len(self.infos)}  # fmt: skip


class MapWorker:
    """The mapping thread (module docstring).

    Args:
        smap: the :class:`~resireg.mapping.SemanticMap` (replaced by :meth:`clear`).
        make_map: a new empty map of the same settings (for :meth:`clear`).
        window: frames per :meth:`SemanticMap.add`.
        queue_size: keyframes waiting at most.
        window_timeout: seconds to wait for a window's frames before mapping fewer.
        max_depth: metres (:func:`windows`'s rule).
        on_window: called (in the thread) after each mapped window with the window and its
            record (``frames``, ``seconds``, ``latency``: from the last frame's arrival).
    """

    def __init__(self, smap: Any, make_map: Callable[[], Any], window: int, queue_size: int,
                 window_timeout: float, max_depth: float | None,
                 on_window: Callable[[dict, dict], None] | None = None) -> None:  # fmt: skip
        self.smap, self.make_map = smap, make_map
        self.window, self.queue_size = int(window), int(queue_size)
        self.window_timeout, self.max_depth = float(window_timeout), max_depth
        self.on_window = on_window
        self.lock = threading.RLock()  # the map: windows, queries, saves, clears
        self.cond = threading.Condition()  # the queue
        self.stats_lock = threading.Lock()  # the counts (read by the status, never held long)
        self.windows = 0
        self.queue: deque[tuple[RGBDFrame, float]] = deque()
        self.counts = FrameCounts()  # windows()'s record of the frames it was given
        self.dropped: Counter = Counter()  # queue_full, cleared, non_finite, map_full
        self.max_queue = 0
        self.last: dict[str, Any] = {}
        self.busy = False
        self._held = 0  # keyframes of the window being mapped
        self.error: BaseException | None = None
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="resireg-map", daemon=True)

    def start(self) -> MapWorker:
        self._thread.start()
        return self

    def put(self, frame: RGBDFrame, received: float) -> None:
        """Queue a keyframe; past ``queue_size`` the oldest waiting one is dropped."""
        with self.cond:
            self.queue.append((frame, received))
            dropped = 0
            while len(self.queue) > self.queue_size:
                self.queue.popleft()
                dropped += 1
            self.max_queue = max(self.max_queue, len(self.queue))
            self.cond.notify_all()
        if dropped:
            with self.stats_lock:
                self.dropped["queue_full"] += dropped

    def pending(self) -> int:
        """Keyframes queued or being mapped."""
        with self.cond:
            return len(self.queue) + (self._held if self.busy else 0)

    def _take(self) -> list[tuple[RGBDFrame, float]] | None:
        """Up to ``window`` keyframes: a full window at once, fewer after ``window_timeout``
        seconds without one, what is left at stop; ``None`` when stopped and empty."""
        with self.cond:
            deadline = None
            while True:
                if len(self.queue) >= self.window or (self._stop and self.queue):
                    break
                if self._stop:
                    return None
                if self.queue:
                    deadline = deadline or time.monotonic() + self.window_timeout
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self.cond.wait(left)
                else:
                    deadline = None
                    self.cond.wait(0.5)
            n = min(self.window, len(self.queue))
            taken = [self.queue.popleft() for _ in range(n)]
            self.busy, self._held = True, n
            return taken

    def _run(self) -> None:
        from resireg.mapping import MapFullError
        from resireg.mapping.semantic_map import ENCODER_OUTPUT
        from resireg.method.checks import NonFiniteError

        while True:
            taken = self._take()
            if taken is None:
                return
            try:
                with self.stats_lock:
                    batches = list(windows([f for f, _ in taken], self.window, self.counts,
                                           max_depth=self.max_depth))  # fmt: skip
                for batch in batches:
                    t0 = time.perf_counter()
                    try:
                        with self.lock:
                            self.smap.add(batch["image"], batch["depth"], batch["intrinsics"],
                                          batch["pose"])  # fmt: skip
                    except NonFiniteError as err:
                        if not str(err).startswith(ENCODER_OUTPUT):
                            raise
                        with self.stats_lock:
                            self.dropped["non_finite"] += len(batch["name"])
                        log.warning("window %s .. %s skipped: %s", batch["name"][0],
                                    batch["name"][-1], err)  # fmt: skip
                        continue
                    except MapFullError as err:
                        with self.stats_lock:
                            self.dropped["map_full"] += len(batch["name"])
                        log.error("%s", err)
                        continue
                    arrived = max(r for _, r in taken)
                    record = {"frames": len(batch["name"]), "seconds": time.perf_counter() - t0,
                              "latency": time.monotonic() - arrived, "stamp": batch["stamp"][-1]}  # fmt: skip
                    with self.stats_lock:
                        self.counts.used += len(batch["name"])
                        self.windows += 1
                        self.last = record
                    if self.on_window is not None:
                        self.on_window(batch, dict(record))
            except BaseException as err:  # the thread ends: the node reports it
                self.error = err
                log.exception("the mapping thread stopped")
                return
            finally:
                with self.cond:
                    self.busy = False
                    self.cond.notify_all()

    def drain(self, timeout: float = 60.0) -> bool:
        """Wait until the queue is empty and no window is being mapped."""
        end = time.monotonic() + timeout
        with self.cond:
            while self.queue or self.busy:
                if self.error is not None:
                    return False
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self.cond.wait(min(left, 0.1))
        return True

    def stop(self, timeout: float | None = None) -> None:
        """Map what is queued, then end the thread."""
        with self.cond:
            self._stop = True
            self.cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def clear(self) -> int:
        """Empty the map (a new one of the same settings) and drop the queued keyframes
        (counted as ``cleared``); returns the voxels removed."""
        with self.cond:
            cleared = len(self.queue)
            self.queue.clear()
        with self.stats_lock:
            self.dropped["cleared"] += cleared
        with self.lock:
            removed = len(self.smap)
            meta = dict(self.smap.meta)
            self.smap = self.make_map()
            self.smap.meta = meta
            return removed

    def stats(self) -> dict[str, Any]:
        """Frames used, dropped by kind, windows mapped, the last window's record."""
        with self.stats_lock:
            dropped = Counter(self.counts.skipped)
            dropped.update(self.dropped)
            return {"used": self.counts.used, "dropped": dict(dropped), "windows": self.windows,
                    "last": dict(self.last), "reasons": dict(self.counts.reasons),
                    "depth_out_of_range": self.counts.depth_out_of_range}  # fmt: skip
