"""planners: game-theoretic and single-agent planners for the racing arena (JAX)."""
