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
    places = np.concatenate([np.asarray(p, dtype=int) for _, p in groups])
    heights = np.concatenate([np.full(len(p), m.size1()) for m, p in groups])
    top = np.zeros(places.max() + 1, dtype=int)
    top[np.sort(places)] = np.concatenate([[0], np.cumsum(heights[np.argsort(places)])[:-1]])
    rows, cols, picks, source, offset = {}, {}, {}, [], 0
    for stacked, group in groups:
        # every block of a map has one sparsity: read the first block's, column-major
        row, col = (np.asarray(v) for v in
                    stacked[:, :stacked.size2() // len(group)].sparsity().get_triplet())
        for j, place in enumerate(group):
            rows[place], cols[place] = top[place] + row, place * width + col
            picks[place] = offset + j * row.size + np.arange(row.size)
        source.append(stacked.nz[:])
        offset += row.size * len(group)
    order = sorted(rows)
    row, col, pick = (np.concatenate([v[p] for p in order]) for v in (rows, cols, picks))
    height, size = int(heights.sum()), len(order) * width
    if below is not None:
        extra_row, extra_col = (np.asarray(v) for v in below.sparsity().get_triplet())
        row = np.concatenate([row, height + extra_row])
        col = np.concatenate([col, extra_col])
        pick = np.concatenate([pick, offset + np.arange(extra_row.size)])
        source.append(ca.MX(ca.DM(below.nonzeros())))
        height += below.size1()
        # two runs, each in column-major order: a stable sort by column merges them
        merged = np.argsort(col, kind="stable")
        row, col, pick = row[merged], col[merged], pick[merged]
    if upper:
        kept = row <= col
        row, col, pick = row[kept], col[kept], pick[kept]
    colind = np.searchsorted(col, np.arange(size + 1))
    sparsity = ca.Sparsity(height, size, colind.tolist(), row.tolist())
    return ca.MX(sparsity, ca.vertcat(*source)[pick.tolist()])
