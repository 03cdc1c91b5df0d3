"""Evaluation (``ns-eval``). In: a trained pipeline and the dataset's ground truth (masks, object poses, sizes,
clicks). Out: full-image and masked PSNR/SSIM, per instance and per view, LPIPS/KID only from local weights, and
segmentation and registration scores; with true depth, masks and poses, the PSNR on the test pixels seen on their
own copy, only on another copy of their class, or never (classed in ``coverage``, scored in ``coverage_scores``)."""

