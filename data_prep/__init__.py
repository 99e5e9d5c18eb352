"""Curated multi-view video datasets: scene format, converters, depth alignment, synthetic scenes, clips.

Uses ``diff4splat`` (render, io, cameras) to synthesise and validate data.
"""
