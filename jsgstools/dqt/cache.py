"""The parser's caches: decoded tables by their DQT bytes and quality estimates by table bytes."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from jsgs.jpeg.tables import QualityEstimate
    from jsgstools.dqt.header import QuantTable

# Decoded tables by their DQT bytes (Pq/Tq byte + entries) and non-IJG quality estimates by table bytes: a
# folder of photos repeats a handful of tables, and decoding/estimating them again costs more than parsing
# the rest of the header. Bounded; ``clear_caches`` empties them (the benchmark's cold-cache column).
_CACHE_MAX = 4096
_TABLE_CACHE: dict[bytes, QuantTable] = {}
_ESTIMATE_CACHE: dict[bytes, QualityEstimate] = {}


def clear_caches() -> None:
    """Forget every cached table and quality estimate."""
    _TABLE_CACHE.clear()
    _ESTIMATE_CACHE.clear()


