"""splatreplace_ns: Splat and Replace (3D reconstruction with repetitive elements) for nerfstudio."""

__version__ = "0.1.0"
