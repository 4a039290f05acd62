"""Training the shipped detector: dataset rendering, the PyTorch model, training and export."""
