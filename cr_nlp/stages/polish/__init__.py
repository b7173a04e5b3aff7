"""Stage 3, polish: Ipopt with the constraints as constraints, and the one acceptance."""
