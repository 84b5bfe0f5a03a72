"""Frozen modules: the behaviour shared by the backbone, the text tower and the teachers."""

from __future__ import annotations

from torch import nn

__all__ = ["FrozenModule"]


class FrozenModule(nn.Module):
    """A module that never trains: call :meth:`freeze` once its parameters exist.

    After :meth:`freeze` no parameter requires grad, and the module stays in eval mode
    whatever a parent's ``.train()`` asks (so dropout / drop-path never switch on).
    """

    def freeze(self) -> None:
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> FrozenModule:
        return super().train(False)
