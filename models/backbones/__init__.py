"""The adapters of the video backbone interface (:mod:`models.backbone`, docs/DESIGN.md, "Backbones"): ``ours`` (our
networks), ``wan`` (Wan2.2-TI2V-5B) and ``cogvideox`` (CogVideoX-5B-I2V) over what the diffusers ones share
(``diffusers_backbone``), and ``sizes``, the diffusers ones built on the meta device from their Hub configurations.

``ours`` imports only torch; the others import diffusers and transformers (``pip install diff4splat[diffusers]``), so
they are imported only where a diffusers backbone is used (:func:`models.backbone_model.backbone_class`).
"""
