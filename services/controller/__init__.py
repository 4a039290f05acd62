"""COSMOS 3D Search: controller."""
