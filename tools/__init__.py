"""Developer tools for COSMOS 3D Search (asset generation)."""
