"""The viser viewer's controls (in nerfstudio's viewer). In: clicks in the 3D view. Out: instance selections for the
segmentation stage, and pixel clicks on the base model for making masks."""
