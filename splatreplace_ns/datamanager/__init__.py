"""Data (first stage). In: a capture folder (``transforms.json`` or a COLMAP ``sparse/0``, images, optional depth,
instance masks, ``clicks.json``). Out: nerfstudio's dataparser outputs and full-image batches on the CPU (images,
depth, instance masks, contrastive pixel samples), clicks mapped to the trained images, masks made from clicks
written beside ``transforms.json``."""

