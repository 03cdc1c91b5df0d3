"""Instances (paper §4.1): clicks → per-Gaussian instance ids, from contrastive features, from 2D masks by vote, or
geometrically on the base model; carving; per-view 2D masks."""
