"""The rows of the tension LM (``stages.refine._tension_lm``) that have a check of their
own: the self-clearance rows of a rod's backbone against the verdict's capsules
(``world.check.check_chains``, numpy segment distances)."""

from __future__ import annotations

import numpy as np

from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import StaticsConfig
from cr_nlp.stages.refine._tension_lm import TensionTerms, self_rows
from cr_nlp.world.check import check_chains
from cr_nlp.world.clearance import chain_self_clearance_numpy

FTDCR = load_robot("ftdcr_v6_cosserat")       # 3 segments: the first and last are checked
PER_SEGMENT = 10


def _hairpins(count: int, seed: int) -> np.ndarray:
    """Backbones (count, 31, 3) m that go up, turn on a half circle (the middle segment)
    and come down beside themselves, some through their own first segment, some clear."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, PER_SEGMENT + 1)
    chains = []
    for _ in range(count):
        radius = rng.uniform(0.002, 0.02)                    # m: the turn's radius
        up = np.stack([0 * s, 0 * s, 0.1 * s], axis=1)
        angle = np.pi * s[1:]
        turn = np.stack([radius * (1 - np.cos(angle)), 0 * angle,
                         0.1 + radius * np.sin(angle)], axis=1)
        down = turn[-1] + np.stack([rng.uniform(-0.01, 0.01) * s[1:], 0 * s[1:],
                                    -0.03 * s[1:]], axis=1)
        chain = np.concatenate([up, turn, down])
        twist = rng.normal(size=3)
        chains.append(chain @ _rotation(twist).T + rng.normal(scale=0.1, size=3))
    return np.array(chains)


def _rotation(v: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(v)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / angle
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def test_the_self_rows_see_the_verdicts_self_distance() -> None:
    """Spheres of the backbone radius at the points and midpoints lie inside the verdict's
    capsules, so their distance is never below the capsules' and exceeds it by at most
    the chain's covering gap; only segments at least two apart count (the hairpin's turn
    touches both of its neighbours); the jitted rows are the hinge of that distance."""
    import jax

    chains = _hairpins(200, seed=0)
    verdict = check_chains(FTDCR, None, chains, PER_SEGMENT).self_distance
    spheres = chain_self_clearance_numpy(FTDCR, chains)
    assert (verdict < 0).sum() > 20 and (verdict > 0.005).sum() > 20   # both kinds drawn
    r, h = FTDCR.backbone_radius, 0.1 / PER_SEGMENT
    cover = 2 * (np.sqrt(r * r + (h / 4) ** 2) - r)     # a capsule's points to its spheres
    assert np.all(spheres >= verdict - 1e-12)
    assert np.all(spheres <= verdict + cover + 1e-12), (spheres - verdict).max()

    band, weight = 0.003, 10.0
    terms = TensionTerms(FTDCR, StaticsConfig(), False, clearance_band=band,
                         self_weight=weight)
    with jax.enable_x64(True):
        rows = np.asarray(jax.jit(jax.vmap(lambda p: self_rows(terms, p)))(chains))
    np.testing.assert_allclose(rows.max(axis=1), weight * np.maximum(band - spheres, 0.0),
                               atol=1e-12)
    assert np.all(rows >= 0.0)


def test_world_frame_undoes_base_frame_on_a_turned_base() -> None:
    """``world_frame`` is ``base_frame``'s inverse, checked on a base turned 90° about x:
    the base's z axis is the world's −y."""
    from dataclasses import replace

    from cr_nlp.stages.refine._tension_lm import base_frame, world_frame

    half = np.sqrt(0.5)
    turned = replace(FTDCR, base_wxyz=(half, half, 0.0, 0.0))
    np.testing.assert_allclose(world_frame(turned, [0.0, 0.0, 1.0]), [0.0, -1.0, 0.0],
                               atol=1e-15)
    vectors = np.random.default_rng(2).normal(size=(5, 3))
    np.testing.assert_allclose(world_frame(turned, base_frame(turned, vectors)), vectors,
                               atol=1e-15)
