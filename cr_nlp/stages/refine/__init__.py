"""Stage 2, refine: batched projected Levenberg–Marquardt in JAX, penalties for the rest."""
