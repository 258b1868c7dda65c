"""PSNR and SSIM of novel-view synthesis: :mod:`kernels.image_metrics`, the layer both pipelines share."""

from kernels.image_metrics import gaussian_window, psnr, ssim

__all__ = ["gaussian_window", "psnr", "ssim"]
