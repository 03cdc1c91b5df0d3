"""3D instance segmentation (paper §4.1): contrastive features, click queries, space carving."""
