"""COSMOS 3D Search: optimizer."""
