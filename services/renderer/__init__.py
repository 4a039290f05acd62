"""COSMOS 3D Search: renderer."""
