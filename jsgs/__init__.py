"""JSGS: JPEG State-Guided Supervision for 3D Gaussian Splatting.

The trainer side of the project. Importable with torch (and gsplat for CUDA rendering) alone: nothing here
imports pycolmap or OpenCV, so a GPU machine needs only torch, gsplat and a few small wheels.
"""

__version__ = "0.2.0"
