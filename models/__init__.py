"""The D3LVO network in PyTorch: one module per paper component, plus loss, data and training."""

from .config import D3LVOConfig

__all__ = ["D3LVOConfig"]
