"""Gaussian scenes: static Gaussians (3DGS), dynamic scenes (canonical Gaussians + deformation at key times,
optional temporal support), quaternions, and the CPU kernel of a scene at a time."""
