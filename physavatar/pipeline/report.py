"""The pipeline's report: the markdown table, the plots and the image strips its stages write.

``evaluate/report.md`` follows the structure of the paper's Table 2 (Chamfer distance, F-score, mean vertex error,
PSNR and SSIM per method on a motion unseen in fitting); ``chamfer.png`` and ``metrics.png`` plot the same scores,
``estimate/estimate.png`` the parameter estimation's iterations, and ``relit.png``/``comparison.png`` are strips of
rendered views. Every file goes through the ``staging`` step it is given (:data:`physavatar.result_files.Staging`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from physavatar.fit.estimation import (
    FabricParameters,
)
from physavatar.result_files import Staging, save_figure, write_png

__all__ = [
    "SMOKE_NOTE",
    "plot_estimation",
    "plot_report",
    "report_markdown",
    "write_strip",
]

SMOKE_NOTE = (
    "Smoke size: this run only checks that every stage works. Its scores and estimates (e.g. the κ_s error) come from "
    "a few frames of tiny images and a handful of iterations and mean nothing; run without --smoke for results."
)


def report_markdown(report: dict, out: Path) -> str:
    """``report.md``'s text: the scores of every method (Table 2's columns), then the estimate and the appearance
    read from ``out``'s ``estimate/`` and ``appearance/`` folders where they exist."""
    lines = [
        f"# PhysAvatar on a synthetic capture: evaluation on the unseen motion '{report['motion']}'",
        "",
        *([f"**{SMOKE_NOTE}**", ""] if report.get("smoke_size") else []),
        f"{report['frames']} frames. CD: Chamfer distance (×10⁻⁶ m², point-to-surface); F-score at τ = 1 mm; "
        "PSNR/SSIM of renders against renders of the truth under the capture's light.",
        "",
        "| method | CD (×10⁻⁶ m²) ↓ | F-score ↑ | mean vertex error (mm) ↓ | PSNR (dB) ↑ | SSIM ↑ |",
        "|---|---|---|---|---|---|",
    ]
    for entry in report["methods"].values():
        lines.append(
            f"| {entry['label']} | {entry['chamfer'] * 1e6:.3f} | {entry['fscore']:.3f} | "
            f"{entry['vertex_error'] * 1e3:.2f} | {entry['psnr']:.2f} | {entry['ssim']:.4f} |"
        )
    estimate_path = out / "estimate" / "estimate.json"
    if estimate_path.is_file():
        est = json.loads(estimate_path.read_text())
        truth = est["truth"]
        lines += [
            "",
            f"## Physics estimation (reference: {est['reference']}"
            + ("" if est["reference"] == "images" else " meshes")
            + f"; ρ fixed at {truth['density']:g} kg/m³)",
            "",
            "Only κ_s/ρ and κ_b/ρ are identifiable from geometry: scaling ρ, κ_s and κ_b together scales the "
            "incremental potential and leaves the motion unchanged.",
            "",
            f"Truth: κ_s = {truth['kappa_s']:.4f}, κ_b = {truth['kappa_b']:.4f}.",
            "",
            "| method | iterations | simulations | time (s) | κ_s | κ_b | error κ_s/ρ | error κ_b/ρ |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name, m in est["methods"].items():
            lines.append(
                f"| {name} | {m['iterations']} | {m['simulations']} | {m['seconds']:.1f} | "
                f"{m['final']['kappa_s']:.4f} | {m['final']['kappa_b']:.4f} | "
                f"{m['ratio_errors']['kappa_s_over_rho'] * 100:+.1f} % | "
                f"{m['ratio_errors']['kappa_b_over_rho'] * 100:+.1f} % |"
            )
    look_path = out / "appearance" / "appearance.json"
    if look_path.is_file():
        look = json.loads(look_path.read_text())
        lines += [
            "",
            "## Appearance",
            "",
            f"Mean albedo error: {look['albedo_error']:.4f} estimated against {look['baked_albedo_error']:.4f} for the "
            "texture baked from the Gaussians' colours (shadows included).",
        ]
    return "\n".join(lines) + "\n"


def plot_report(report: dict, folder: Path, staging: Staging) -> None:
    """``chamfer.png`` (Chamfer distance per frame and method) and ``metrics.png`` (the mean scores) in ``folder``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for key, entry in report["methods"].items():
        if key == "without_appearance":
            continue
        ax.plot(np.array(entry["chamfer_per_frame"]) * 1e6, label=entry["label"])
    ax.set_xlabel("frame")
    ax.set_ylabel("Chamfer distance (×10⁻⁶ m²)")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.legend()
    ax.set_title(f"garment geometry on the unseen motion '{report['motion']}'")
    fig.tight_layout()
    try:
        save_figure(fig, folder / "chamfer.png", staging)
    finally:
        plt.close(fig)

    labels = [e["label"] for e in report["methods"].values()]
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2))
    for ax, (metric, title, scale) in zip(
        axes,
        (("chamfer", "CD (×10⁻⁶ m²) ↓", 1e6), ("fscore", "F-score ↑", 1.0), ("psnr", "PSNR (dB) ↑", 1.0)),
        strict=True,
    ):
        ax.bar(range(len(labels)), [e[metric] * scale for e in report["methods"].values()], color="#4c72b0")
        ax.set_xticks(range(len(labels)), labels, rotation=20, ha="right", fontsize=8)
        ax.set_title(title)
    fig.tight_layout()
    try:
        save_figure(fig, folder / "metrics.png", staging)
    finally:
        plt.close(fig)


def plot_estimation(
    runs: dict, truth: FabricParameters | None, path: Path, staging: Staging, loss: str = "Eq. 6 loss (m²)"
) -> None:
    """The estimators' iterations (``runs``: name → a result with ``history``, the parameters, and ``loss``, as
    :class:`~physavatar.fit.EstimationResult`) against ``truth`` (``None`` for a capture without one), as one PNG at
    ``path``; ``loss`` titles the loss's panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2))
    for name, result in runs.items():
        axes[0].plot([p.kappa_s for p in result.history], label=name)
        axes[1].plot([p.kappa_b for p in result.history], label=name)
        axes[2].plot(result.loss, label=name)
    if truth is not None:
        axes[0].axhline(truth.kappa_s, color="k", ls="--", lw=0.8)
        axes[1].axhline(truth.kappa_b, color="k", ls="--", lw=0.8)
    for ax, title in zip(axes, ("κ_s", "κ_b", loss), strict=True):
        ax.set_title(title)
        ax.set_xlabel("iteration")
    axes[2].set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    try:
        save_figure(fig, path, staging)
    finally:
        plt.close(fig)


def write_strip(images: torch.Tensor, path: Path, staging: Staging) -> None:
    """Views ``[N, H, W, 3]`` side by side as one PNG, written through ``staging``."""
    strip = torch.cat(list(images), dim=1).clamp(0, 1)
    write_png(path, (strip * 255).round().to(torch.uint8).numpy(), staging)
