"""COSMOS 3D Search: detector."""
