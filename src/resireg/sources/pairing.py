"""Timestamp pairing and pose composition shared by every source (the bag reader, the TUM
reader, the live ROS 2 node), with numpy and scipy only.

**Pairing.** :func:`pair_nearest` gives every anchor stamp (depth) the nearest stamp of another
stream (colour) within a tolerance, ties to the earlier one (``numpy.searchsorted``), as TUM's
``associate.py`` does for one pair (it also makes the pairs one-to-one; a depth stream faster
than colour here reuses a colour image). **Poses.** :class:`PoseTrack` interpolates a stamped
pose stream at a time ``t``, as tf2 does: between the samples just before and after ``t``, the
translation linearly and the rotation by spherical linear interpolation
(``scipy.spatial.transform.Slerp``), provided the two are at most ``max_gap`` seconds apart; a
time before the first or after the last sample takes that sample if it is within ``tolerance``
(tf2 would refuse to extrapolate at all), else has no pose. **tf.** :class:`TfTree` holds one
:class:`PoseTrack` per (parent, child) edge of ``/tf`` and ``/tf_static`` and composes the
chain between two frames at a time. **Stamp faults.** :func:`stamp_faults` finds the messages
of a stream whose header stamp goes back or repeats (a restamped or replayed stream).
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict, deque
from collections.abc import Iterable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

__all__ = ["PoseTrack", "TfTree", "pair_nearest", "pose_matrix", "stamp_faults"]


def pair_nearest(anchors: np.ndarray, stamps: np.ndarray, tolerance: float) -> np.ndarray:
    """For each anchor time the index of the nearest of ``stamps`` (sorted ascending) within
    ``tolerance`` seconds, else -1; of two equally near stamps the earlier wins."""
    anchors = np.asarray(anchors, dtype=np.float64)
    stamps = np.asarray(stamps, dtype=np.float64)
    out = np.full(anchors.shape[0], -1, dtype=np.int64)
    if stamps.size == 0:
        return out
    if np.any(np.diff(stamps) < 0):
        raise ValueError("pair_nearest: stamps must be sorted ascending")
    right = np.searchsorted(stamps, anchors, side="left").clip(0, stamps.size - 1)
    left = (right - 1).clip(0, stamps.size - 1)
    d_left, d_right = np.abs(anchors - stamps[left]), np.abs(stamps[right] - anchors)
    best = np.where(d_left <= d_right, left, right)
    ok = np.minimum(d_left, d_right) <= tolerance
    out[ok] = best[ok]
    return out


def pose_matrix(translation: Iterable[float], quaternion_xyzw: Iterable[float]) -> np.ndarray:
    """``[4, 4]`` float64 from a translation and a unit quaternion ``(x, y, z, w)`` (ROS's and
    TUM's order; scipy's ``Rotation.from_quat`` normalises it)."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(np.asarray(list(quaternion_xyzw), dtype=np.float64)).as_matrix()
    m[:3, 3] = np.asarray(list(translation), dtype=np.float64)
    return m


class PoseTrack:
    """A stamped pose stream (module docstring): ``at(t)`` -> ``[4, 4]`` or ``None``.

    Args:
        stamps: ``[N]`` seconds (any order; sorted here, a repeated stamp keeps its last pose).
        poses: ``[N, 4, 4]`` rigid transforms.
        tolerance: seconds a time may lie before the first / after the last sample.
        max_gap: the longest interval in seconds between two samples interpolated across.
        static: one pose valid at every time (``/tf_static``).
    """

    def __init__(self, stamps, poses, tolerance: float = 0.02, max_gap: float = 0.5,
                 static: bool = False) -> None:  # fmt: skip
        stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        if stamps.shape[0] != poses.shape[0] or stamps.shape[0] == 0:
            raise ValueError(f"PoseTrack: {stamps.shape[0]} stamps for {poses.shape[0]} poses")
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
        last = np.append(stamps[1:] != stamps[:-1], True)  # a repeated stamp: its last pose
        self.stamps, self.poses = stamps[last], poses[last]
        self.tolerance, self.max_gap = float(tolerance), float(max_gap)
        self.static = static
        self._slerp = (
            Slerp(self.stamps, Rotation.from_matrix(self.poses[:, :3, :3]))
            if self.stamps.size > 1
            else None
        )

    def __len__(self) -> int:
        return int(self.stamps.size)

    def at(self, t: float) -> np.ndarray | None:
        if self.static:
            return self.poses[-1]
        s = self.stamps
        i = int(np.searchsorted(s, t, side="left"))
        if i < s.size and s[i] == t:
            return self.poses[i]
        if i == 0:
            return self.poses[0] if s[0] - t <= self.tolerance else None
        if i == s.size:
            return self.poses[-1] if t - s[-1] <= self.tolerance else None
        t0, t1 = s[i - 1], s[i]
        if t1 - t0 > self.max_gap:
            return None
        w = (t - t0) / (t1 - t0)
        out = np.eye(4)
        out[:3, :3] = self._slerp([t]).as_matrix()[0]
        out[:3, 3] = (1 - w) * self.poses[i - 1, :3, 3] + w * self.poses[i, :3, 3]
        return out


class TfTree:
    """The tf graph: per (parent, child) edge a :class:`PoseTrack`; :meth:`lookup` composes the
    chain from one frame to another at a time (edges walked either way, inverted backwards)."""

    def __init__(self, tolerance: float, max_gap: float) -> None:
        self.tolerance, self.max_gap = tolerance, max_gap
        self.samples: dict[tuple[str, str], list[tuple[float, np.ndarray]]] = defaultdict(list)
        self.static: set[tuple[str, str]] = set()
        self.tracks: dict[tuple[str, str], PoseTrack] = {}

    def add(self, parent: str, child: str, stamp: float, m: np.ndarray, static: bool) -> None:
        edge = (parent.lstrip("/"), child.lstrip("/"))
        self.samples[edge].append((stamp, m))
        if static:
            self.static.add(edge)

    def build(self) -> None:
        for edge, items in self.samples.items():
            stamps, poses = zip(*items, strict=True)
            self.tracks[edge] = PoseTrack(stamps, np.stack(poses), self.tolerance, self.max_gap,
                                          static=edge in self.static)  # fmt: skip

    @property
    def frames(self) -> set[str]:
        return {f for edge in self.tracks for f in edge}

    def chain(self, source: str, target: str) -> list[tuple[tuple[str, str], bool]] | None:
        """Edges from ``source`` to ``target`` (breadth first), each with ``True`` if walked
        parent -> child."""
        source, target = source.lstrip("/"), target.lstrip("/")
        nbrs: dict[str, list[tuple[str, tuple[str, str], bool]]] = defaultdict(list)
        for parent, child in self.tracks:
            nbrs[parent].append((child, (parent, child), True))
            nbrs[child].append((parent, (parent, child), False))
        prev: dict[str, tuple[str, tuple[str, str], bool] | None] = {source: None}
        todo = deque([source])
        while todo:
            node = todo.popleft()
            if node == target:
                break
            for nxt, edge, forward in nbrs[node]:
                if nxt not in prev:
                    prev[nxt] = (node, edge, forward)
                    todo.append(nxt)
        if target not in prev:
            return None
        path, node = [], target
        while prev[node] is not None:
            node_prev, edge, forward = prev[node]
            path.append((edge, forward))
            node = node_prev
        return path[::-1]

    def lookup(self, chain, t: float) -> np.ndarray | None:
        """``T_source_target`` at ``t`` along ``chain`` (``None`` if an edge has no pose)."""
        out = np.eye(4)
        for edge, forward in chain:
            m = self.tracks[edge].at(t)
            if m is None:
                return None
            out = out @ (m if forward else np.linalg.inv(m))
        return out


def stamp_faults(items: Sequence[tuple[float, int]], topic: str) -> dict[int, str]:
    """Positions (in bag order) of ``(header stamp, bag time)`` items whose stamp does not
    come after every stamp of an earlier-received message of the topic (a stream restamped
    back in time, or a duplicate), and of messages received at one bag time with one stamp
    (which of the two is which cannot be told); each with the reason."""
    faults: dict[int, str] = {}
    latest, latest_time = -math.inf, None
    i = 0
    while i < len(items):
        j = i
        while j < len(items) and items[j][1] == items[i][1]:
            j += 1
        group = range(i, j)
        stamps = Counter(items[k][0] for k in group)
        for k in group:
            stamp, bag_time = items[k]
            if stamp <= latest:
                faults[k] = (f"header stamp {stamp:.6f} on {topic} is not after {latest:.6f}, "
                             f"the stamp of a message received before it (bag time {latest_time}"
                             f" < {bag_time}): stamps go back or repeat")  # fmt: skip
            elif stamps[stamp] > 1:
                faults[k] = (f"header stamp {stamp:.6f} on {topic} is shared by "
                             f"{stamps[stamp]} messages received at bag time {bag_time}: a "
                             "duplicate stamp")  # fmt: skip
        top = max(items[k][0] for k in group)
        if top > latest:
            latest, latest_time = top, items[i][1]
        i = j
    return faults
