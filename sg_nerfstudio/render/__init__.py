"""Gaussian rasterization with gsplat's calling convention: gsplat on CUDA, pure PyTorch on CPU."""

from sg_nerfstudio.render.rasterization import rasterize, resolve_backend

__all__ = ["rasterize", "resolve_backend"]
