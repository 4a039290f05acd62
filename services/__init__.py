"""COSMOS 3D Search services."""
