"""The operator's side of COSMOS 3D Search: the ``cosmos`` command, the local stack, the bench."""
