"""The parser's caches: decoded tables by their DQT bytes and quality estimates by table bytes."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from jsgs.jpeg.tables import QualityEstimate

# Decoded tables by their DQT bytes (Pq/Tq byte + entries) and non-IJG quality estimates by table bytes: a
# folder of photos repeats a handful of tables, and decoding/estimating them again costs more than parsing
# the rest of the header. Bounded; ``clear_caches`` empties them (the benchmark's cold-cache column).
_CACHE_MAX = 4096
# the table cache's values are ``jsgstools.dqt.header.QuantTable``s, not named here: header imports this
# module, and this one imports nothing of the parser's
_TABLE_CACHE: dict[bytes, Any] = {}
_ESTIMATE_CACHE: dict[bytes, QualityEstimate] = {}


def clear_caches() -> None:
    """Forget every cached table and quality estimate."""
    _TABLE_CACHE.clear()
    _ESTIMATE_CACHE.clear()


