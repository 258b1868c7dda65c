"""PIE-NeRF: physics-based interactive elastodynamics of NeRF scenes with meshless Q-GMLS."""
