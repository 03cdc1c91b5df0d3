"""Shared templates (paper §4.3). In: the accepted registrations and the instances' Gaussians. Out: one template per
class in template space, each instance as a pose and SH offsets, composed into the scene at every render; the
check after fine-tuning; export as plain Gaussians and as an instanced file."""
