"""sg-nerfstudio: Scene Grounding In the Wild (CVPR 2026) as a nerfstudio plugin."""

__version__ = "0.1.0"
