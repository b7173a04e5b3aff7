"""Batch chunking shared by the batched stages: a few compiled shapes for any batch size."""

from __future__ import annotations

SMALLEST_CHUNK = 128
"""Fewest problems per compiled LM call (64 per core on 2 cores)."""


def chunk_plan(count: int, largest: int, smallest: int = SMALLEST_CHUNK,
               large: int | None = None) -> list[int]:
    """Chunk sizes that cover ``count`` problems with fewer than ``smallest`` padded rows,
    using only two compiled shapes: the largest power of two ≤ ``largest`` ("big") for
    whole big chunks, and ``smallest`` chunks for the rest (one more big chunk instead
    when the rest is within ``smallest`` of it). Measured (tdcr4_ext, lattice, 100
    targets): one chunk size per batch ran the 1200 coarse problems as 2 × 1024 and the
    300 refined ones as 512 (41 % padding); a plan over every power of two between the
    two sizes padded little but compiled up to four shapes per solver, about 26 s each
    from a cold cache; this one pads as little with two.

    ``large`` (a power of two above ``largest``): a batch of at least that many runs whole
    chunks of it first, a third shape that only such batches compile (fewer program
    launches per target: ``IKConfig.large_chunk_size``)."""
    if count <= 0:
        return []
    if large is not None and large > largest and count >= large:
        return [large] * (count // large) + chunk_plan(count % large, largest, smallest)
    big = smallest
    while big * 2 <= max(largest, smallest):
        big *= 2
    n_big, rest = divmod(count, big)
    if rest > big - smallest:
        n_big, rest = n_big + 1, 0
    return [big] * n_big + [smallest] * -(-rest // smallest)
