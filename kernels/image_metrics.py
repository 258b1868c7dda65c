"""Image quality metrics: PSNR and SSIM, in torch (any device, batched, differentiable).

SSIM is the standard one of Wang et al. 2004 ("Image quality assessment: from error visibility to
structural similarity", Eq. 13): local means, variances and covariance under an 11×11 Gaussian window of
standard deviation 1.5 pixels, ``C1 = (0.01 L)²``, ``C2 = (0.03 L)²`` for dynamic range ``L``, evaluated
where the window fits inside the image ("valid") and averaged over positions and colour channels. These
are the settings NeRF papers report (the window of ``skimage.metrics.structural_similarity`` with
``gaussian_weights=True, use_sample_covariance=False``).
"""

from __future__ import annotations

import torch

__all__ = ["gaussian_window", "psnr", "ssim", "ssim_map"]


def psnr(prediction: torch.Tensor, target: torch.Tensor, max_value: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio ``10 log10(L² / MSE)``, dB, over all elements.

    Args:
        prediction, target: tensors of one shape, values in ``[0, L]``.
        max_value: ``L``, the dynamic range.

    Returns:
        Scalar tensor, dB (``inf`` for identical inputs).
    """
    _check_pair(prediction, target)
    mse = torch.mean((prediction.double() - target.double()) ** 2)
    return (10.0 * torch.log10(max_value**2 / mse)).to(prediction.dtype)


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None) -> torch.Tensor:
    """Normalised 1-D Gaussian ``[size]`` (the separable factor of SSIM's 2-D window)."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def ssim(
    prediction: torch.Tensor,
    target: torch.Tensor,
    max_value: float = 1.0,
    window_size: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    compute_dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Mean structural similarity of Wang et al. 2004 (Eq. 13) with a Gaussian window (module docstring).

    Args:
        prediction, target: ``[H, W, C]`` or ``[N, H, W, C]`` images in ``[0, L]``, at least
            ``window_size`` pixels on each side.
        max_value: ``L``, the dynamic range.
        window_size, sigma: the Gaussian window, pixels.
        k1, k2: stabilising constants, ``C_i = (k_i L)²``.
        compute_dtype: precision of the local statistics; float64 for reported metrics, float32 where SSIM is a
            loss evaluated thousands of times (faster, differences ~1e-6; ``docs/benchmarks.md``).

    Returns:
        Scalar tensor in ``[-1, 1]``: the SSIM map averaged over valid positions, channels and images.
    """
    values = ssim_map(prediction, target, max_value, window_size, sigma, k1, k2, compute_dtype)
    return values.mean().to(prediction.dtype)


def ssim_map(
    prediction: torch.Tensor,
    target: torch.Tensor,
    max_value: float = 1.0,
    window_size: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    compute_dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """The SSIM of every valid window position (:func:`ssim`'s arguments), for losses weighted per pixel.

    Returns:
        ``[N, H − w + 1, W − w + 1, C]`` (``N = 1`` for one ``[H, W, C]`` image) in ``compute_dtype``: position
        ``(i, j)`` is the window centred on pixel ``(i + w // 2, j + w // 2)``, ``w = window_size``.
    """
    _check_pair(prediction, target)
    if prediction.dim() not in (3, 4):
        raise ValueError(f"ssim expects [H, W, C] or [N, H, W, C] images, got shape {tuple(prediction.shape)}")
    if min(prediction.shape[-3:-1]) < window_size:
        raise ValueError(
            f"images of {prediction.shape[-3]}x{prediction.shape[-2]} pixels are smaller than the "
            f"{window_size}x{window_size} SSIM window; compare larger images or pass a smaller window_size"
        )
    x = _to_nchw(prediction, compute_dtype)
    y = _to_nchw(target, compute_dtype)
    channels = x.shape[1]
    g = gaussian_window(window_size, sigma, dtype=x.dtype, device=x.device)

    def blur(image: torch.Tensor) -> torch.Tensor:
        rows = torch.nn.functional.conv2d(image, g.view(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)
        return torch.nn.functional.conv2d(rows, g.view(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1, c2 = (k1 * max_value) ** 2, (k2 * max_value) ** 2
    values = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return values.permute(0, 2, 3, 1)


def _to_nchw(images: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    images = images.to(dtype)
    if images.dim() == 3:
        images = images[None]
    return images.permute(0, 3, 1, 2).contiguous()


def _check_pair(prediction: torch.Tensor, target: torch.Tensor) -> None:
    if prediction.shape != target.shape:
        raise ValueError(
            f"prediction {tuple(prediction.shape)} and target {tuple(target.shape)} must have the same shape"
        )
    if not (prediction.is_floating_point() and target.is_floating_point()):
        raise TypeError("metrics take floating-point images in [0, max_value]; convert uint8 images to float / 255")
