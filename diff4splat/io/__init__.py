"""File IO: Gaussians (INRIA PLY), depth (EXR), video/images (OpenCV), camera paths (JSON, RealEstate10K).

Every writer is atomic: it writes a temporary file beside the target and renames it
(:func:`atomic_output_path`), so a crash never leaves a half-written output. Every output folder is
written by :func:`output_dir`, which also decides whether an existing folder may be replaced.
"""
from diff4splat.io.atomic import atomic_output_path
from diff4splat.io.cameras import load_cameras_json, load_realestate10k, save_cameras_json, save_realestate10k
from diff4splat.io.exr import load_depth_exr, save_depth_exr
from diff4splat.io.image import load_image, preprocess_image
from diff4splat.io.output_folders import MARKER, OutputDirError, check_output_dir, output_dir
from diff4splat.io.ply import load_ply, ply_bytes, ply_property_names, save_ply
from diff4splat.io.video import load_video, save_image, save_video, to_uint8

__all__ = ["save_ply", "ply_bytes", "load_ply", "ply_property_names", "save_depth_exr", "load_depth_exr", "save_video",
           "load_video", "save_image", "to_uint8", "load_image", "preprocess_image", "atomic_output_path", "output_dir",
           "check_output_dir", "OutputDirError", "MARKER", "save_cameras_json", "load_cameras_json",
           "load_realestate10k", "save_realestate10k"]
