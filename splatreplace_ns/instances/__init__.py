"""Instances (paper §4.1). In: a trained model (its Gaussians, rendered features or masks' votes) and one click per
instance. Out: per-Gaussian instance ids and classes, the leftovers to carve, per-view 2D masks; for a capture
without masks, the masks themselves, made geometrically on the base model (no learned weights) or with an ONNX SAM."""
