"""The NGP NeRF of PIE-NeRF §3.1: hash-grid field, occupancy grid, ray-marched volume rendering, density σ(x), ∇σ(x).

PIE-NeRF trains an instant-NGP NeRF (Müller et al. 2022, §5.4) on the input photos and then reads its
density σ(x) to place particles (§4.1, Eq. 3 needs ‖∇σ‖) and renders it, warped, for the deformed scene.

The field (:class:`NGPField`), as instant-NGP:

* a point ``x`` (metres) is mapped to the unit cube by the scene box, ``u = (x − lo) / (hi − lo)``, and
  encoded on a multiresolution hash grid (:class:`kernels.hashgrid.HashGridEncoding`, Eq. 2–4 there);
* a density MLP (one hidden layer of 64 ReLU units, no biases) maps the ``L·F`` features to 16 outputs
  ``h``; ``σ = exp(h_0)`` per metre (:func:`truncated_exp`), and ``h`` is the geometric feature;
* a colour MLP (two hidden layers of 64, sigmoid output) maps ``h`` and the view direction's real
  spherical harmonics up to degree 4 (:func:`spherical_harmonics`, 16 values) to RGB in [0, 1].

The occupancy grid (:class:`OccupancyGrid`) keeps a decaying maximum of σ per cell of a ``G³`` grid
over the box and marks a cell occupied while its value exceeds the threshold; rendering
(:func:`render_rays`) marches only through occupied cells and composites with early termination
(:mod:`kernels.volume_render`).

Spatial gradient (:class:`NerfDensity`): the hash-grid kernels give no derivative with respect to
positions, but the torch reference encoding (:func:`kernels.reference.hashgrid.hashgrid_forward_torch`)
is differentiable in ``x`` (its trilinear weights are), so ∇σ is computed by autograd through it and
the MLP, as the paper does ("differentiating the NGP-NeRF using AutoDiff", §4.1). This is the exact
derivative of the σ the kernels evaluate (the two encodings agree to float32 rounding), piecewise
smooth: it jumps across the faces of the finest grid cells, as the trilinear interpolant does.
Finite differences were the alternative; they smooth over a cell but cost six field evaluations and a
step to choose, and agree with autograd to O(h²) inside a cell (``tests/pienerf/test_nerf.py``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch

from kernels import backend
from kernels.fused_mlp import FusedMLP
from kernels.hashgrid import HashGridConfig, HashGridEncoding
from kernels.reference.hashgrid import hashgrid_forward_torch
from kernels.volume_render import composite, march_rays
from pienerf.sim.density import GRADIENT_CHUNK, DensityField

__all__ = [
    "NGPConfig",
    "InferenceMLP",
    "MLP_EXECUTORS",
    "NGPField",
    "NerfDensity",
    "OccupancyGrid",
    "render_rays",
    "spherical_harmonics",
    "truncated_exp",
]


MLP_EXECUTORS = ("auto", "fused", "torch")
"""Values of :attr:`NGPConfig.mlp`."""


@dataclass(frozen=True)
class NGPConfig:
    """Hyper-parameters of the NGP NeRF (instant-NGP's NeRF defaults).

    Attributes:
        hashgrid: the position encoding; its ``max_resolution`` counts cells across the scene box.
        density_hidden: width of the density MLP's hidden layer.
        geometric_features: outputs of the density MLP besides log-density (instant-NGP: 15).
        color_hidden: width of the colour MLP's hidden layers.
        color_layers: hidden layers of the colour MLP.
        sh_degree: bands of spherical harmonics encoding the view direction (4: ``4² = 16`` values).
        grid_resolution: ``G``, occupancy cells per box edge.
        grid_decay: factor applied to the occupancy grid's stored density at every update (EMA of maxima).
        grid_threshold: optical thickness ``σ · min_step`` below which a cell counts as empty
            (instant-NGP: 0.01, i.e. a cell must absorb at least 1 % per step).
        samples_per_diagonal: the constant step is the box diagonal over this (instant-NGP: √3 / 1024
            in its unit cube).
        cone_angle: step growth with depth, ``δ(t) = clamp(t · cone_angle, min_step, 64 · min_step)``;
            0 for object-centred synthetic scenes, ~1/256 for large real ones.
        max_samples: most samples per ray.
        transmittance_threshold: compositing stops once transmittance falls below it.
        mlp: what evaluates the MLPs: ``"fused"`` (:class:`kernels.fused_mlp.FusedMLP`'s kernels, float16 on CUDA,
            float32 tiles on the CPU), ``"torch"`` (one ``Linear`` after another) or ``"auto"``: the fused kernels on
            CUDA and torch on the CPU (Warp's CPU tiles run on one thread), torch wherever a hidden width is not a
            multiple of 16. The weights and their state-dict keys are the same whichever runs them. The default is
            ``"torch"``: the fused kernels' CUDA build is not yet measured against cuBLAS (``docs/benchmarks.md``),
            so they run only when asked for.
    """

    hashgrid: HashGridConfig = field(default_factory=HashGridConfig)
    density_hidden: int = 64
    geometric_features: int = 15
    color_hidden: int = 64
    color_layers: int = 2
    sh_degree: int = 4
    grid_resolution: int = 128
    grid_decay: float = 0.95
    grid_threshold: float = 0.01
    samples_per_diagonal: int = 1024
    cone_angle: float = 0.0
    max_samples: int = 1024
    transmittance_threshold: float = 1e-4
    mlp: str = "torch"

    def __post_init__(self):
        if self.mlp not in MLP_EXECUTORS:
            raise ValueError(f"mlp must be one of {MLP_EXECUTORS}, got {self.mlp!r}")
        if self.mlp == "fused" and (self.density_hidden % 16 or self.color_hidden % 16):
            raise ValueError(
                f"mlp='fused' needs hidden widths that are multiples of 16, got density_hidden={self.density_hidden}, "
                f"color_hidden={self.color_hidden}; pick such widths or mlp='torch'"
            )
        if not 1 <= self.sh_degree <= 4:
            raise ValueError(f"sh_degree must be 1 to 4 bands, got {self.sh_degree}")
        positive = ("density_hidden", "color_hidden", "color_layers", "grid_resolution", "samples_per_diagonal")
        for name in positive + ("max_samples",):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.geometric_features < 0 or not 0.0 < self.grid_decay <= 1.0 or self.cone_angle < 0.0:
            raise ValueError(f"need geometric_features >= 0, 0 < grid_decay <= 1 and cone_angle >= 0, got {self}")

    def to_dict(self) -> dict:
        """Plain dictionary (nested for ``hashgrid``), for checkpoints."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> NGPConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``TypeError`` naming them."""
        values = dict(values)
        values["hashgrid"] = HashGridConfig(**values.get("hashgrid", {}))
        return cls(**values)

    def min_step(self, aabb: torch.Tensor) -> float:
        """The smallest (with ``cone_angle = 0`` the only) marching step, metres, for scene box ``aabb [2, 3]``."""
        return float(torch.linalg.vector_norm(aabb[1] - aabb[0])) / self.samples_per_diagonal


class _TruncatedExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(max=15.0))


def truncated_exp(x: torch.Tensor) -> torch.Tensor:
    """Density activation ``σ = exp(x)`` whose derivative is capped at ``exp(15)`` (instant-NGP §5.4).

    The exponential lets σ span the orders of magnitude between empty space and opaque surfaces;
    clamping its derivative keeps one large pre-activation from blowing up a training step.
    """
    return _TruncatedExp.apply(x)


# Real spherical harmonics Y_l^m on the unit sphere (orthonormal), bands l = 0..3; constants are
# the normalisations sqrt((2l + 1) / 4π · (l − |m|)! / (l + |m|)!) times the polynomial factors.
_SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, 0.31539156525252005, 0.5462742152960396)
_SH_C3 = (0.5900435899266435, 2.890611442640554, 0.4570457994644658, 0.3731763325901154, 1.445305721320277)


def spherical_harmonics(directions: torch.Tensor, degree: int = 4) -> torch.Tensor:
    """Real spherical harmonics of unit directions, the view-direction encoding of instant-NGP (§5.4).

    Args:
        directions: ``[N, 3]`` unit vectors.
        degree: number of bands ``1..4``.

    Returns:
        ``[N, degree²]``: band 0, then band 1 ``(y, z, x)`` and so on, each orthonormal over the sphere
        (``∫ Y_a Y_b dω = δ_ab``).
    """
    if not 1 <= degree <= 4:
        raise ValueError(f"degree must be 1 to 4 bands, got {degree}")
    x, y, z = directions.unbind(-1)
    out = [torch.full_like(x, _SH_C0)]
    if degree > 1:
        out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if degree > 2:
        xx, yy, zz = x * x, y * y, z * z
        a, b, c = _SH_C2
        out += [a * x * y, -a * y * z, b * (3.0 * zz - 1.0), -a * x * z, c * (xx - yy)]
    if degree > 3:
        a, b, c, d, e = _SH_C3
        out += [
            -a * y * (3.0 * xx - yy),
            b * x * y * z,
            -c * y * (5.0 * zz - 1.0),
            d * z * (5.0 * zz - 3.0),
            -c * x * (5.0 * zz - 1.0),
            e * z * (xx - yy),
            -a * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def _weights_loaded(field: NGPField, incompatible_keys) -> None:
    """``load_state_dict``'s post-hook of :class:`NGPField`: the loaded weights are a new generation."""
    field.mark_weights_changed()


class NGPField(torch.nn.Module):
    """Radiance field ``(x, d) → (σ, rgb)`` of instant-NGP over a scene box (module docstring).

    Changing the weights in place is announced by :meth:`mark_weights_changed`, which bumps
    :attr:`weights_version`: the trainer does so after each optimiser step and each swap of weights, and
    ``load_state_dict`` does so by itself. Copies made from the weights (a renderer's float16 MLPs) are kept while the
    version they were made at is the field's.

    Args:
        config: hyper-parameters.
        aabb: ``[2, 3]`` scene box ``(lo, hi)``, metres; density outside it is 0.
    """

    def __init__(self, config: NGPConfig | None = None, aabb: torch.Tensor | None = None):
        super().__init__()
        self.weights_version = 0
        """Generation of the weights, bumped by :meth:`mark_weights_changed`."""
        # a field loaded as part of a larger module runs this hook too (a module-level function: the field pickles)
        self.register_load_state_dict_post_hook(_weights_loaded)
        self.config = config or NGPConfig()
        aabb = torch.tensor([[-1.5] * 3, [1.5] * 3]) if aabb is None else torch.as_tensor(aabb, dtype=torch.float32)
        if aabb.shape != (2, 3) or not bool((aabb[1] > aabb[0]).all()):
            raise ValueError(f"aabb must be [2, 3] (lo, hi) with hi > lo on every axis, got {aabb.tolist()}")
        self.register_buffer("aabb", aabb.float().clone())
        c = self.config
        self.encoding = HashGridEncoding(c.hashgrid)
        outputs = 1 + c.geometric_features
        self.density_mlp = torch.nn.Sequential(
            torch.nn.Linear(c.hashgrid.output_dim, c.density_hidden, bias=False),
            torch.nn.ReLU(),
            torch.nn.Linear(c.density_hidden, outputs, bias=False),
        )
        layers: list[torch.nn.Module] = [torch.nn.Linear(outputs + c.sh_degree**2, c.color_hidden, bias=False)]
        for _ in range(c.color_layers - 1):
            layers += [torch.nn.ReLU(), torch.nn.Linear(c.color_hidden, c.color_hidden, bias=False)]
        layers += [torch.nn.ReLU(), torch.nn.Linear(c.color_hidden, 3, bias=False), torch.nn.Sigmoid()]
        self.color_mlp = torch.nn.Sequential(*layers)
        fused = c.mlp == "fused" or (c.mlp == "auto" and c.density_hidden % 16 == 0 and c.color_hidden % 16 == 0)
        if fused:  # the same layers, the same state-dict keys
            executor = "warp" if c.mlp == "fused" else "auto"
            self.density_mlp = FusedMLP(self.density_mlp, executor)
            self.color_mlp = FusedMLP(self.color_mlp, executor)

    def mark_weights_changed(self) -> None:
        """Announce that the weights changed in place (an optimiser step, a copy into the parameters): bumps
        :attr:`weights_version`, so that copies made from the old weights are made again (the encoding's float16
        table among them, :meth:`~kernels.hashgrid.HashGridEncoding.mark_table_changed`, and the fused MLPs' packed
        weights, :meth:`~kernels.fused_mlp.FusedMLP.mark_weights_changed`)."""
        self.weights_version += 1
        self.encoding.mark_table_changed()
        for mlp in (self.density_mlp, self.color_mlp):
            if isinstance(mlp, FusedMLP):
                mlp.mark_weights_changed()

    def to_unit_cube(self, x: torch.Tensor) -> torch.Tensor:
        """World points ``[N, 3]`` (metres) to the encoding's unit cube, ``(x − lo) / (hi − lo)``."""
        lo, hi = self.aabb[0].to(x), self.aabb[1].to(x)
        return (x - lo) / (hi - lo)

    def _density_outputs(
        self, x: torch.Tensor, differentiable_in_x: bool = False, density_mlp: torch.nn.Module | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """σ ``[N]`` (per metre, 0 outside the box) and the density MLP's outputs ``h`` ``[N, 1 + geometric]``.

        ``differentiable_in_x`` encodes with the torch reference (differentiable in ``x``, any float dtype)
        instead of the kernels; with a float16 table it reads the kernels' float16 copy, not differentiable in the
        table. ``density_mlp``: evaluate this copy of the density MLP instead (see
        :meth:`radiance`).
        """
        if differentiable_in_x:
            unit = self.to_unit_cube(x)
            table = self.encoding.table
            if self.config.hashgrid.table_dtype != "float32":  # the values the kernels read: σ and ∇σ of one field
                table = self.encoding.read_table().to(unit.dtype)
            features = hashgrid_forward_torch(unit, table, self.encoding.resolutions)
        else:
            unit = self.to_unit_cube(x.detach().float())
            features = self.encoding(unit.contiguous())
        if density_mlp is None:
            h = self.density_mlp(features)
        else:  # a copy, maybe of another dtype (float16): its inputs in its own
            dtype = density_mlp.dtype if isinstance(density_mlp, InferenceMLP) else next(density_mlp.parameters()).dtype
            h = density_mlp(features.to(dtype))
        inside = ((unit >= 0.0) & (unit <= 1.0)).all(dim=-1)
        # At least float32: under float16 autocast the MLP's outputs are float16, whose exp overflows at σ ≈ 6.5e4.
        sigma = torch.where(inside, truncated_exp(h[:, 0].to(torch.promote_types(h.dtype, torch.float32))), 0.0)
        return sigma, h

    def density(self, x: torch.Tensor, differentiable_in_x: bool = False) -> torch.Tensor:
        """Volume density σ ``[N]``, per metre, at world points ``x [N, 3]`` (float32, backend device).

        ``differentiable_in_x``: through the torch reference of the encoding, differentiable in ``x`` and in any
        float dtype, instead of the float32 kernels."""
        return self._density_outputs(x, differentiable_in_x=differentiable_in_x)[0]

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density ``σ [N]`` (per metre) and colour ``rgb [N, 3]`` in [0, 1] at points ``x [N, 3]`` seen along
        unit directions ``d [N, 3]``."""
        return self.radiance(x, self.encode_directions(d))

    def encode_directions(self, d: torch.Tensor) -> torch.Tensor:
        """The colour MLP's view input for unit directions ``d [N, 3]``: spherical harmonics ``[N, sh_degree²]``.

        A renderer encodes each camera ray once and hands every sample of the ray its row (:meth:`radiance`),
        instead of evaluating the ~30 products of the harmonics per sample.
        """
        return spherical_harmonics(d, self.config.sh_degree)

    def radiance(
        self,
        x: torch.Tensor,
        encoded_directions: torch.Tensor,
        mlps: tuple[torch.nn.Module, torch.nn.Module] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` with the directions already encoded by :meth:`encode_directions` (``[N, sh_degree²]``).

        ``mlps``: ``(density, colour)`` copies of the MLPs to evaluate instead of the field's own, e.g. a renderer's
        float16 ones (:meth:`half_mlps`), which spare float16 autocast a cast of every weight at every call.
        """
        density_mlp, color_mlp = mlps if mlps is not None else (self.density_mlp, self.color_mlp)
        sigma, h = self._density_outputs(x, density_mlp=density_mlp)
        rgb = color_mlp(torch.cat([h, encoded_directions.to(h.dtype)], dim=-1))
        return sigma, rgb

    def half_mlps(self) -> tuple[torch.nn.Module, torch.nn.Module]:
        """Float16 MLPs ``(density, colour)`` for :meth:`radiance`, for inference only: the field's own fused MLPs
        where they run the float16 kernels (on CUDA; they follow the weights by themselves), else float16 copies
        (:class:`InferenceMLP`; copies: they do not follow later training, see :attr:`weights_version`)."""
        mlps = (self.density_mlp, self.color_mlp)
        if all(isinstance(m, FusedMLP) and m.runs_kernels(self.aabb.device) for m in mlps):
            return mlps
        return tuple(InferenceMLP(mlp, torch.float16) for mlp in mlps)


class InferenceMLP(torch.nn.Module):
    """A copy of one of :class:`NGPField`'s MLPs (bias-free ``Linear`` layers, ``ReLU`` between them, an optional
    last ``Sigmoid``) for rendering, without gradients, in a chosen dtype.

    On CUDA each hidden layer's ReLU runs in its matrix product's epilogue (cuBLASLt, through
    ``torch._addmm_activation``): a layer's activations are then written once instead of being written, read and
    written again by a separate ReLU, a large share of a deformed frame's MLP time (``docs/benchmarks.md``,
    ``pienerf.render``). Elsewhere the same products and ``relu_`` in place.

    Args:
        mlp: the field's ``torch.nn.Sequential``.
        dtype: the copy's dtype (e.g. ``torch.float16``); its inputs are cast to it.
    """

    def __init__(self, mlp: torch.nn.Sequential, dtype: torch.dtype):
        super().__init__()
        kinds = [type(layer) for layer in mlp]
        linear = [layer for layer in mlp if isinstance(layer, torch.nn.Linear)]
        expected = [torch.nn.Linear] + [torch.nn.ReLU, torch.nn.Linear] * (len(linear) - 1)
        if kinds not in (expected, expected + [torch.nn.Sigmoid]) or any(layer.bias is not None for layer in linear):
            raise ValueError(f"InferenceMLP takes bias-free Linear layers with ReLU between them, got {kinds}")
        self.dtype = dtype
        self.sigmoid = kinds[-1] is torch.nn.Sigmoid
        with torch.no_grad():
            for i, layer in enumerate(linear):  # weights transposed once: x @ Wᵀ as addmm's [in, out] operand
                self.register_buffer(f"weight{i}", layer.weight.detach().t().to(dtype).contiguous())
        self.layers = len(linear)
        self._zero: dict[int, torch.Tensor] = {}

    def _weights(self) -> list[torch.Tensor]:
        return [getattr(self, f"weight{i}") for i in range(self.layers)]

    @torch.no_grad()
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.to(self.dtype)
        weights = self._weights()
        fused = x.is_cuda and hasattr(torch, "_addmm_activation")
        for w in weights[:-1]:
            if fused:  # relu(0 + x W) in the product's epilogue
                zero = self._zero.get(w.shape[1])
                if zero is None or zero.device != w.device:
                    zero = self._zero[w.shape[1]] = w.new_zeros(w.shape[1])
                x = torch._addmm_activation(zero, x, w)
            else:
                x = torch.relu_(x @ w)
        x = x @ weights[-1]
        return torch.sigmoid(x) if self.sigmoid else x


class OccupancyGrid(torch.nn.Module):
    """Which cells of a ``G³`` grid over the scene box may hold density (instant-NGP Appendix E.2).

    Each update evaluates σ at one random point per chosen cell and stores ``max(decay · old, σ)``; a
    cell is occupied while that value exceeds ``min(threshold, mean over the grid)`` (the mean keeps a
    faint scene from vanishing). Cells start occupied, so rendering samples everything until the
    first update.

    Args:
        aabb: ``[2, 3]`` scene box, metres.
        resolution: ``G``, cells per edge.
        decay: factor applied to stored densities at each update.
        threshold: density, per metre, below which a cell is empty.
    """

    def __init__(self, aabb: torch.Tensor, resolution: int = 128, decay: float = 0.95, threshold: float = 1.0):
        super().__init__()
        if resolution < 1 or not 0.0 < decay <= 1.0 or threshold < 0.0:
            raise ValueError(
                f"need resolution >= 1, 0 < decay <= 1, threshold >= 0; got {resolution}, {decay}, {threshold}"
            )
        self.resolution, self.decay, self.threshold = int(resolution), float(decay), float(threshold)
        shape = (self.resolution,) * 3
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32).clone())
        self.register_buffer("density", torch.zeros(shape))
        self.register_buffer("occupied", torch.ones(shape, dtype=torch.bool))

    @classmethod
    def for_field(cls, field: NGPField) -> OccupancyGrid:
        """The grid a field's config asks for: threshold ``grid_threshold / min_step`` per metre."""
        c = field.config
        threshold = c.grid_threshold / c.min_step(field.aabb.cpu())
        return cls(field.aabb, c.grid_resolution, c.grid_decay, threshold).to(field.aabb.device)

    @property
    def cell_size(self) -> torch.Tensor:
        """``[3]`` edge lengths of a cell, metres."""
        return (self.aabb[1] - self.aabb[0]) / self.resolution

    @torch.no_grad()
    def update(
        self,
        density_fn,
        samples: int | None = None,
        generator: torch.Generator | None = None,
        chunk: int = 1 << 18,
    ) -> None:
        """One EMA update from fresh density samples.

        Args:
            density_fn: ``x [N, 3] (metres) → σ [N]`` (e.g. :meth:`NGPField.density`).
            samples: ``None`` evaluates every cell (instant-NGP's warm-up); else ``samples`` cells drawn
                uniformly plus ``samples`` drawn among the occupied ones; the rest only decay.
            generator: random source for the cells and the points in them.
            chunk: points per ``density_fn`` call.
        """
        device = self.density.device
        cells = self.resolution**3
        if samples is None:
            index = torch.arange(cells, device=device)
        else:
            occupied = torch.nonzero(self.occupied.flatten()).flatten()
            index = torch.randint(cells, (samples,), generator=generator, device=device)
            if occupied.numel() > 0:
                pick = torch.randint(occupied.numel(), (samples,), generator=generator, device=device)
                index = torch.cat([index, occupied[pick]])
        g = self.resolution
        ijk = torch.stack([index // (g * g), (index // g) % g, index % g], dim=-1)
        offset = torch.rand(index.shape[0], 3, generator=generator, device=device)
        points = self.aabb[0] + (ijk + offset) * self.cell_size
        sigma = torch.cat([density_fn(points[i : i + chunk]) for i in range(0, points.shape[0], chunk)])
        fresh = torch.zeros(cells, device=device).scatter_reduce(0, index, sigma.float(), reduce="amax")
        self.density.copy_(torch.maximum(self.density * self.decay, fresh.view_as(self.density)))
        threshold = min(self.threshold, float(self.density.mean()))
        self.occupied.copy_(self.density > threshold)

    def is_occupied(self, x: torch.Tensor) -> torch.Tensor:
        """bool ``[N]``: whether world points ``x [N, 3]`` fall in an occupied cell (False outside the box)."""
        u = (x - self.aabb[0].to(x)) / self.cell_size.to(x)
        inside = ((u >= 0) & (u < self.resolution)).all(dim=-1)
        ijk = u.floor().long().clamp(0, self.resolution - 1)
        return inside & self.occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    @property
    def occupancy_fraction(self) -> float:
        """Share of cells occupied."""
        return float(self.occupied.float().mean())


def render_rays(
    field: NGPField,
    grid: OccupancyGrid,
    origins: torch.Tensor,
    directions: torch.Tensor,
    near: float | torch.Tensor = 0.0,
    far: float | torch.Tensor = 1e10,
    background: torch.Tensor | tuple[float, float, float] = (1.0, 1.0, 1.0),
    *,
    chunk: int | None = 4096,
    jitter: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Render rays through the field: march, evaluate, composite over a background (PIE-NeRF §3.1).

    Differentiable with respect to the field's parameters (wrap in ``torch.no_grad()`` to render).

    Args:
        field, grid: the NeRF and its occupancy grid.
        origins, directions: ``[R, 3]`` ray origins (metres) and unit directions, backend device.
        near, far: scalars or ``[R]``: the depth interval to sample, metres (clipped to the box).
        background: ``[3]`` or ``[R, 3]`` colour behind the scene, composited with ``1 − opacity``.
        chunk: rays marched and evaluated at a time (bounds memory); ``None`` for one batch.
        jitter: ``[R]`` in ``[0, 1)``: offset of each ray's first sample, in steps (training).

    Returns:
        ``rgb [R, 3]``, ``opacity [R]`` (``Σ w_i``), ``depth [R]`` (expected depth of the surface hit,
        ``Σ w_i t_i / Σ w_i``, metres; 0 where nothing is hit) and ``samples_per_ray [R]`` (int32, samples
        marched).
    """
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"chunk must be a positive number of rays or None (one batch), got {chunk!r}")
    c = field.config
    rays = origins.shape[0]
    device = origins.device
    background = torch.as_tensor(background, dtype=torch.float32, device=device)
    if background.shape not in ((3,), (rays, 3)):
        raise ValueError(f"background must be [3] or [R, 3] = [{rays}, 3], got {tuple(background.shape)}")
    background = background.expand(rays, 3)
    near = torch.as_tensor(near, dtype=torch.float32, device=device).expand(rays)
    far = torch.as_tensor(far, dtype=torch.float32, device=device).expand(rays)
    min_step = c.min_step(field.aabb.cpu())
    step = max(rays, 1) if chunk is None else chunk
    parts = []
    for a in range(0, rays, step):
        b = min(a + step, rays)
        samples = march_rays(
            origins[a:b].contiguous(),
            directions[a:b].contiguous(),
            near[a:b],
            far[a:b],
            grid.occupied,
            field.aabb.cpu(),
            min_step,
            max_step=64.0 * min_step if c.cone_angle > 0.0 else None,
            cone_angle=c.cone_angle,
            max_samples=c.max_samples,
            jitter=None if jitter is None else jitter[a:b],
        )
        sigma, rgb = field(samples.positions, directions[a:b][samples.ray_indices])
        out = composite(
            sigma.contiguous(),
            rgb.contiguous(),
            samples.deltas,
            samples.depths,
            samples.ray_offsets,
            transmittance_threshold=c.transmittance_threshold,
        )
        opacity = out["opacity"]
        parts.append(
            {
                "rgb": out["color"] + (1.0 - opacity)[:, None] * background[a:b],
                "opacity": opacity,
                "depth": torch.where(opacity > 1e-6, out["depth"] / opacity.clamp_min(1e-6), 0.0),
                "samples_per_ray": samples.counts,
            }
        )
    if not parts:
        empty = torch.zeros(0, device=device)
        return {"rgb": empty.view(0, 3), "opacity": empty, "depth": empty, "samples_per_ray": empty.int()}
    return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}


class NerfDensity(DensityField):
    """A trained NGP NeRF's density σ(x) and its gradient ∇σ(x), for particle sampling (PIE-NeRF §4.1, Eq. 3).

    ∇σ is autograd through the differentiable torch encoding (module docstring), :data:`GRADIENT_CHUNK`
    points at a time.

    Args:
        field: the trained field (its parameters are not changed).
        chunk: points per kernel call in :meth:`density`.
    """

    def __init__(self, field: NGPField, chunk: int = 1 << 18):
        self.field = field
        self.chunk = int(chunk)

    @property
    def bounds(self):
        aabb = self.field.aabb.detach().double().cpu()
        return aabb[0], aabb[1]

    @torch.no_grad()
    def density(self, x: torch.Tensor) -> torch.Tensor:
        """σ ``[N]`` (per metre) at ``x [N, 3]`` (metres), in ``x``'s dtype and device."""
        _check_points(x)
        points = x.detach().to(device=backend.torch_device(), dtype=torch.float32)
        sigma = [self.field.density(points[i : i + self.chunk]) for i in range(0, points.shape[0], self.chunk)]
        return (torch.cat(sigma) if sigma else points.new_zeros(0)).to(device=x.device, dtype=x.dtype)

    def density_grad(self, x: torch.Tensor) -> torch.Tensor:
        """∇σ ``[N, 3]`` (per square metre) at ``x [N, 3]``, by autograd through the torch encoding."""
        _check_points(x)
        grad = torch.empty(x.shape, dtype=torch.float32, device=backend.torch_device())
        points = x.detach().to(device=grad.device, dtype=torch.float32)
        for start in range(0, points.shape[0], GRADIENT_CHUNK):
            chunk = points[start : start + GRADIENT_CHUNK].clone().requires_grad_(True)
            with torch.enable_grad():
                sigma, _ = self.field._density_outputs(chunk, differentiable_in_x=True)
                (grad[start : start + GRADIENT_CHUNK],) = torch.autograd.grad(sigma.sum(), chunk)
        return grad.to(device=x.device, dtype=x.dtype)


def _check_points(x: torch.Tensor) -> None:
    if not isinstance(x, torch.Tensor) or not x.is_floating_point():
        raise TypeError(f"points must be a floating-point torch.Tensor, got {getattr(x, 'dtype', type(x).__name__)}")
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {tuple(x.shape)}")
