"""Contrastive features (paper §4.1). In: per-Gaussian features rendered into a training view and the sampled pixels'
instance labels. Out: the contrastive loss that pulls an instance's features together and pushes others apart."""
