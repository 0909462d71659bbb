"""jsgstools: dataset preparation for JSGS (DQT inspection, mixed-quality compression, COLMAP validation,
manifests, a synthetic default scene)."""

from jsgs import __version__

__all__ = ["__version__"]
