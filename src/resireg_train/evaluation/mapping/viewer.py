"""``resireg-map``'s Rerun view: :class:`resireg.mapping.viewer.RerunView` (it moved to the core
package, where the live ROS 2 node logs the same entities)."""

from resireg.mapping.viewer import RerunView

__all__ = ["RerunView"]
