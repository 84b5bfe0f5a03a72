"""The node's topics: the message types it accepts on its inputs, the QoS of its input
subscriptions (``qos``: ``sensor_data`` or ``reliable``) and of its latched outputs, and the
subscription to an input once a publisher shows its type on the graph (rclpy).

Imported by :mod:`resireg.ros2.node` and :mod:`resireg.ros2.source` (the live source subscribes
as the node does).
"""

from __future__ import annotations

from typing import Any

from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

__all__ = ["IMAGE_TYPES", "POSE_TYPES", "input_qos", "latched_qos", "msg_type",
           "subscribe_published"]  # fmt: skip

_IMAGE, _COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
_POSE, _ODOMETRY = "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry"
#: The types an image input (colour or depth) may have, as the graph names them.
IMAGE_TYPES = (_IMAGE, _COMPRESSED)
#: The types a pose input may have.
POSE_TYPES = (_POSE, _ODOMETRY)


def msg_type(name: str):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CompressedImage, Image

    return {_IMAGE: Image, _COMPRESSED: CompressedImage, _POSE: PoseStamped,
            _ODOMETRY: Odometry}[name]  # fmt: skip


def input_qos(qos: str, buffer_size: int) -> QoSProfile:
    """The QoS of the image, camera-info and pose subscriptions: ``sensor_data`` (best effort,
    as camera drivers publish) or ``reliable`` (keep the last ``buffer_size``)."""
    if qos == "sensor_data":
        return qos_profile_sensor_data
    return QoSProfile(depth=int(buffer_size), reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST)  # fmt: skip


def latched_qos() -> QoSProfile:
    """The QoS of the node's map and query outputs: reliable, transient local (a late RViz
    gets the last message)."""
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)  # fmt: skip


def subscribe_published(node: Node, wanted: dict[str, tuple[str, tuple[str, ...]]],
                        subscribed: dict[str, str], handlers: dict[str, Any],
                        qos: QoSProfile) -> None:  # fmt: skip
    """Subscribe ``node`` to each input of ``wanted`` (``key -> (topic, accepted types)``) once
    a publisher shows its type on the graph (an image topic is ``Image`` or
    ``CompressedImage``); ``subscribed`` (``key -> type``) records those done."""
    if len(subscribed) == len(wanted):
        return
    graph = dict(node.get_topic_names_and_types())
    for key, (topic, types) in wanted.items():
        if key in subscribed:
            continue
        found = [t for t in graph.get(node.resolve_topic_name(topic), []) if t in types]
        if found:
            node.create_subscription(msg_type(found[0]), topic, handlers[key], qos)
            subscribed[key] = found[0]
            node.get_logger().info(f"subscribed to {topic} ({found[0]})")
