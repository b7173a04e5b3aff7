"""Block-diagonal derivatives of an NLP made of many like blocks (the rods of a tension
motion), assembled from CasADi maps by one nonzero gather.

A map evaluates the blocks of one kind side by side: its outputs are the blocks stacked
horizontally. Splitting them and ``diagcat``-ing the pieces copies every nonzero several
times (on a 60-waypoint motion's Jacobian, 600 000 nonzeros, about 25 ms of each 100 ms
evaluation); here the full matrix's nonzeros are picked once from the maps' nonzeros by
an index computed when the NLP is built.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

Stacked = tuple[Any, list[int]]
"""A map's output (the blocks of its rods side by side) and the rods' places (0, 1, …) in
the NLP's order."""


def columns_in_order(groups: list[Stacked]) -> Any:
    """One column (MX) of the maps' dense column outputs (rows × rods), the rods in the
    NLP's order."""
    heights, source, offset = {}, [], 0
    for stacked, places in groups:
        rows = stacked.size1()
        for j, place in enumerate(places):
            heights[place] = offset + j * rows + np.arange(rows)
        source.append(ca.vec(stacked))
        offset += rows * len(places)
    pick = np.concatenate([heights[p] for p in sorted(heights)]).astype(int).tolist()
    return ca.vertcat(*source)[pick]


def block_diagonal(groups: list[Stacked], width: int, below: ca.DM | None = None,
                   upper: bool = False) -> Any:
    """The block-diagonal MX of the maps' matrix outputs (each rod's block ``width``
    columns wide), the rods in the NLP's order, then the constant rows ``below`` (over all
    the blocks' columns); ``upper``: only the upper triangle."""
    blocks = {}
    source, offset = [], 0
    for stacked, places in groups:
        row, col = (np.asarray(v) for v in stacked.sparsity().get_triplet())
        each = row.size // len(places)                    # every block has one sparsity
        for j, place in enumerate(places):
            blocks[place] = (stacked.size1(), row[:each], col[:each], offset + j * each)
        source.append(stacked.nz[:])
        offset += row.size
    rows, cols, picks, top = [], [], [], 0
    for place in sorted(blocks):
        height, row, col, start = blocks[place]
        rows.append(top + row), cols.append(place * width + col)
        picks.append(start + np.arange(row.size))
        top += height
    size = len(blocks) * width
    if below is not None:
        row, col = (np.asarray(v) for v in below.sparsity().get_triplet())
        rows.append(top + row), cols.append(col), picks.append(offset + np.arange(row.size))
        source.append(ca.MX(ca.DM(below.nonzeros())))
        top += below.size1()
    row, col, pick = (np.concatenate(v) for v in (rows, cols, picks))
    if upper:
        kept = row <= col
        row, col, pick = row[kept], col[kept], pick[kept]
    order = np.lexsort((row, col))                         # CasADi's column-major order
    sparsity = ca.Sparsity.triplet(top, size, row[order].tolist(), col[order].tolist())
    return ca.MX(sparsity, ca.vertcat(*source)[pick[order].tolist()])
