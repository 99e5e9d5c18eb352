"""Video backbones: VAE + text encoder + camera-conditioned video transformer (docs/DESIGN.md, "Backbones").

``base`` (the interface) and ``ours`` import only torch; ``wan`` and ``cogvideox`` import diffusers and
transformers (``pip install diff4splat[diffusers]``), so they are imported only where a diffusers backbone is used.
"""
