"""The adapters of :mod:`models.backbone`: ``ours``, ``wan`` (Wan2.2-TI2V-5B), ``cogvideox`` (CogVideoX-5B-I2V) over
``diffusers_backbone``, and ``sizes`` (the diffusers ones on the meta device). All but ``ours`` import diffusers,
so only :func:`models.backbone_model.backbone_class` imports them."""
