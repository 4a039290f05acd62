"""COSMOS 3D Search: common."""
