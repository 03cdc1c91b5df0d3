"""Per-Gaussian contrastive features (paper §4.1): the loss on rendered features."""
