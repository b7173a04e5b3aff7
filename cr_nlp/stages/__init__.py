"""The three solver stages: explore (seeds, beam), refine (batched LM in JAX), polish (Ipopt)."""
