"""JPEG math shared by the toolkit and the trainer: quantization tables, the observation operator (JO) and the
DCT-domain supervision (DS). Tables are always 8x8 in natural row-major order, indexed [v, u] (row = vertical
frequency), as Pillow >= 8.3 returns them."""

# The operator and the losses are exported lazily, so that ``jsgs.jpeg.tables`` (numpy only) stays importable
# without paying for torch.
_EXPORTS = {
    "jpeg_observe": "observe",
    "MODES": "observe",
    "SAMPLING_FACTORS": "observe",
    "dct_supervision": "supervision",
    "DctSupervision": "supervision",
    "omega": "supervision",
    "photometric_loss": "losses",
    "photometric_terms": "losses",
    "obs_loss": "losses",
    "ObservationLoss": "losses",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):  # noqa: ANN202 - module-level lazy attribute (PEP 562)
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
