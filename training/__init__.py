"""Training of diff4splat's networks: losses, the three progressive stages, the trainer, evaluation.

Depends on ``models`` and ``diff4splat``; nothing there imports this package.
"""
