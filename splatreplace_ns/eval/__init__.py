"""Evaluation (``ns-eval``). In: a trained pipeline and the dataset's ground truth (masks, object poses, sizes,
clicks). Out: full-image and masked PSNR/SSIM, per instance and per view, LPIPS/KID only from local weights, and
segmentation and registration scores."""

