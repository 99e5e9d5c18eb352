"""Training of diff4splat's networks: losses, the three progressive stages, the trainer, evaluation.

Depends on ``models`` and ``diff4splat``; nothing there imports this package.
"""
import diff4splat  # noqa: F401  first, before torch: its preflight check and the OpenMP environment (diff4splat/__init__.py)
