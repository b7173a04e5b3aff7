"""Stage 1, explore: starting points for the LM (seed pool, roadmap, guesses, sequences)."""
