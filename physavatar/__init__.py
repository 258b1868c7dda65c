"""PhysAvatar: garment physics and appearance from multi-view video, and animation under new motions."""
