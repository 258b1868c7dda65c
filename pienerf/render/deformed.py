"""Rendering the deformed NeRF by quadratic ray warping, with a ground plane and shadow map (PIE-NeRF §4.6, Fig. 7–8).

The NeRF is trained on the rest shape; after the solver moves the body (q), every sample x̃ on a camera ray
through the deformed scene is warped back to its rest position x (:func:`kernels.warp_rays.warp_round`,
Eq. 19–21, from the three nearest deformed integrator points) and the NeRF is queried there (σ, rgb).

Marching. The occupancy grid lives in rest space, so the renderer warps it forward once per frame: every
occupied rest cell's eight corners go through the same second-order expansion about the cell's nearest rest
IP, x̃ = x + u_k + (F_k − I) d + ½ ∇F_k : d d with d = x − x_k (Eq. 19, explicit in this direction), and every
deformed cell the corners' bounding box overlaps is marked. The march runs through that deformed grid over the
field's box grown by whole cells to hold the deformed IPs (padded by their cutoff); after the warp a sample is
kept only if its rest position falls in an occupied rest cell, so the splat needs to be conservative only,
not exact. The splat is written in displacements, so with q = 0 it returns every corner bit for bit, the
deformed grid equals the rest grid, the march emits the samples :func:`pienerf.nerf.render_rays` emits and the
image is identical to the undeformed NeRF's (as long as every occupied rest cell lies within an IP's cutoff).

Rounds. Rays are marched, warped, shaded and composited in rounds, as instant-NGP renders: each ray keeps where
its march stopped and its running colour, opacity, ``Σ w t`` and transmittance; a round marches at most ``k``
more samples (``k`` doubling, on CUDA 8, 16, … up to 128; on the CPU 1, 2, … up to 32) for every ray still alive,
warps and shades them, composites them and drops the rays that left the box or passed ``far`` or whose
transmittance fell below the threshold. Samples behind an opaque surface are thus never warped or queried, and a
frame is 5–10 rounds of a few kernel launches and one host sync each, over all rays at once on CUDA, instead of
one march, warp and query per chunk of 4096 rays. The resumed
march emits exactly the samples of a full march and the compositing is the same arithmetic, so the image is the
full march's (bit for bit at q = 0 against :func:`pienerf.nerf.render_rays` with the Taichi kernels; with the Warp
kernels, CUDA's default, to the last bit of the compositing's ``exp``; to float rounding of the field's batched
queries otherwise). How much is saved depends on the NeRF's opacity: on the analytic teapot (opaque within
2 mm) with its rod bent, a 40² view marched 10.5k samples (queried 3.8k) where a full march marches 38.3k; the
teapot's fitted NeRF (:func:`pienerf.scenes.scene_nerf`, whose inside stays translucent: transmittance
reaches 0.5 about 12 samples past the surface but 0.01 only after ~60) marched 707k of 746k samples at 200² and
queried 592k of 624k.

View direction. The NeRF is queried with the camera ray's own direction, not one rotated by F⁻¹: the captured
radiance's view dependence (highlights) belongs to the world's lights, which do not turn with the material.
For the Lambertian scenes of this project both choices give the same image.

Empty space. A sample whose nearest deformed IP is farther than ``cutoff_scale`` times that IP's cuboid
half-diagonal (the radius of the sphere through the cuboid's corners, §4.4) is empty (σ = 0).

Shadows (Fig. 7). With a :class:`GroundPlane`, a shadow map over the ground square under the object holds the
transmittance toward one directional light, T = exp(−∫σ) along the light ray from each texel, accumulated by
the same warped march; camera rays that reach the ground see ``albedo · (k_a + k_d · max(0, n·l) · T)`` behind
the object (Lambert, as :func:`kernels.raycast.shade`), so the shadow moves and softens with the deformed NeRF.

:class:`MeshAlbedoField` is a radiance field that needs no training: the density of an embedded scene's
analytic solids and the albedo of the nearest mesh vertex. The warping tests and benchmarks use it, so that
warping is judged independently of NeRF training noise; a trained :class:`pienerf.nerf.NGPField` plugs into
the same renderer. On the teapot with its rod dragged 30 cm sideways (``tests/pienerf/test_render.py``, 64²
from above, against the deformed mesh's albedo), the rod region reached 12.8 dB with the quadratic warp,
11.8 dB with the linear one (whose rod shows kinks between IPs, as in Fig. 8) and 10.3 dB unwarped; the whole
image 23.9, 23.0 and 19.1 dB. The remaining error is the Taylor expansions' reach: the rod has one IP per
10–15 cm.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch

from kernels import backend
from kernels.spatial_hash import SpatialHash
from kernels.volume_render import composite_accumulate, composite_start, gather_ray_rows, march_resume, march_start
from kernels.warp_rays import splat_occupancy, warp_round
from pienerf.nerf.cameras import Cameras
from pienerf.nerf.field import NGPField, OccupancyGrid, render_rays
from pienerf.sim.model import QGMLSModel

__all__ = [
    "LIGHT_DIRECTION",
    "MODES",
    "DeformedFrame",
    "DeformedRenderer",
    "GroundPlane",
    "RenderStats",
    "bucket_size",
]

LIGHT_DIRECTION = (0.35, 1.0, 0.55)
"""Direction toward the directional light of the renders (world, y up): from above, front-right."""

MODES = ("quadratic", "linear", "rest")
"""Warping modes: Newton on the quadratic expansion (Eq. 20), the first-order warp (Fig. 8), or no warp."""


@dataclass(frozen=True)
class GroundPlane:
    """A lit ground under the object that receives its shadow (Fig. 7).

    Attributes:
        height: the plane y = height, metres.
        albedo: ground colour in [0, 1].
        light_direction: direction toward the directional light (normalised here).
        ambient: ``k_a``, fraction of the albedo reflected everywhere.
        diffuse: ``k_d``, fraction reflected under an unoccluded light.
        extent: half-size of the ground square (and of the shadow map) around the object, metres; rays
            missing the square see the background.
        shadow_resolution: texels per side of the shadow map.
    """

    height: float = 0.0
    albedo: tuple[float, float, float] = (0.75, 0.75, 0.72)
    light_direction: tuple[float, float, float] = LIGHT_DIRECTION
    ambient: float = 0.3
    diffuse: float = 0.7
    extent: float = 1.5
    shadow_resolution: int = 128

    def __post_init__(self):
        light = torch.tensor(self.light_direction, dtype=torch.float64)
        if light.shape != (3,) or not bool(light[1] > 0):
            raise ValueError(f"light_direction must be a 3-vector pointing up (y > 0), got {self.light_direction}")
        if not (self.extent > 0 and self.shadow_resolution >= 2 and self.ambient >= 0 and self.diffuse >= 0):
            raise ValueError(f"need extent > 0 m, shadow_resolution >= 2, ambient, diffuse >= 0; got {self}")


@dataclass
class DeformedFrame:
    """Everything the warped march needs for one deformation q (built by :meth:`DeformedRenderer.frame`).

    Attributes:
        ip_deformed: float32 ``[K, 3]`` x̃_k, metres.
        ip_displacement: float32 ``[K, 3]`` u(x_k), metres.
        F: float32 ``[K, 3, 3]``; grad_F: float32 ``[K, 3, 3, 3]`` per metre (Eq. 12, 15).
        ip_hash: spatial hash over ``ip_deformed`` for the 3-nearest-IP queries.
        aabb: float32 ``[2, 3]`` march box, metres, on the host (the march and the splat take it there);
            occupancy: bool ``[Gx, Gy, Gz]`` deformed-space grid over it.
    """

    ip_deformed: torch.Tensor
    ip_displacement: torch.Tensor
    F: torch.Tensor
    grad_F: torch.Tensor
    ip_hash: SpatialHash
    aabb: torch.Tensor
    occupancy: torch.Tensor


def _compact(mask: torch.Tensor, count: int, size: int | None = None) -> torch.Tensor:
    """int64 ``[size]`` indices of the True entries of ``mask [N]``, ascending, where ``count`` is their number
    (known already): unlike ``nonzero`` this needs no host sync on CUDA. ``size`` (≥ count, default count) pads
    with index 0."""
    return torch.nonzero_static(mask, size=count if size is None else size, fill_value=0).view(-1)


def bucket_size(count: int) -> int:
    """``count`` rounded up to one of 8 sizes an octave (at most an eighth more, multiples of 128).

    The field's matrix products then see few shapes however a round's sample count varies from frame to frame:
    cuBLAS chooses its kernel per new shape on the host, a cost paid by every product of a new shape
    (``docs/benchmarks.md``, ``pienerf.render``).
    """
    step = max(128, 1 << max(count.bit_length() - 4, 0))
    return -(-count // step) * step


@dataclass
class RenderStats:
    """What the warped march of the last :meth:`DeformedRenderer.render` did (camera rays and shadow map together).

    Attributes:
        rounds: march–shade–composite rounds.
        samples_marched: samples emitted by the march through the deformed occupancy grid.
        samples_queried: samples the NeRF was evaluated at: the marched ones that some IP reaches and whose rest
            position lies in an occupied rest cell.
    """

    rounds: int = 0
    samples_marched: int = 0
    samples_queried: int = 0


class DeformedRenderer:
    """Renders a rest-space NeRF deformed by a Q-GMLS body (PIE-NeRF §4.6; module docstring).

    Rays are rendered in rounds with early termination, as instant-NGP's inference does. Each ray keeps the depth
    its march resumes from and its running compositing sums (colour, opacity, ``Σ w t``, transmittance); a round
    marches at most ``k`` more samples for every ray still alive (:func:`kernels.volume_render.march_resume`); every
    filled slot is then warped to rest and tested for being worth a NeRF query (some IP reaches it and its rest
    position lies in an occupied rest cell; the others have σ = 0, and compositing them would change nothing) by
    :func:`kernels.warp_rays.warp_round`; one host sync counts the samples marched and kept and the rays going on; and
    the kept samples are queried and composited onto the sums (:func:`kernels.volume_render.composite_accumulate`).
    A ray drops out once it leaves the box or passes ``far`` or once its transmittance falls below the field's
    ``transmittance_threshold``, so the samples behind an opaque surface are never warped or queried. ``k``
    doubles from ``first_round_steps`` up to ``steps_per_round`` (and down to what ``round_samples`` allows), so a
    frame takes few rounds, each a handful of kernel launches and one host sync.
    A resumed march emits exactly the samples one full march emits and the compositing runs the same arithmetic,
    so the image is the one a full march and composite give.

    Args:
        field: the rest-space radiance field (:class:`pienerf.nerf.NGPField` or :class:`MeshAlbedoField`).
        grid: its occupancy grid (rest space).
        model: the discretised body whose IPs drive the warp.
        cutoff_scale: a sample is empty beyond this many cuboid half-diagonals of its nearest IP.
        newton_iterations, newton_tolerance: Newton settings of the quadratic warp (tolerance in metres).
        chunk: rays per batch of ``mode="rest"``, which renders by :func:`pienerf.nerf.render_rays`.
        first_round_steps: samples per ray of the first round. ``None``: 16 on CUDA, 1 on the CPU.
        steps_per_round: most samples a ray marches in one round. ``None``: 128 on CUDA, 32 on the CPU. On CUDA
            a round costs launches and syncs whatever its size, so few large rounds win
            (``docs/benchmarks.md``).
        round_samples: most samples marched in one round over all rays (bounds memory; rays are taken this many
            at a time). ``None``: 2²³ on CUDA (all rays of an 800² frame at once), 2¹⁸ on the CPU.
        half_precision: evaluate the field's MLPs in float16 (``torch.autocast``), as instant-NGP's fully fused MLPs
            do; the hash encoding, σ's exponential and the compositing stay float32. ``None``: for an
            :class:`pienerf.nerf.NGPField` on CUDA. Its error is far below a pixel's quantisation and it saves time
            (``docs/benchmarks.md``).
        framework: ``"taichi"`` or ``"warp"``, the kernels of a round (march, warp, composite); ``None``:
            :func:`kernels.backend.default_framework` (Warp on CUDA, where a frame issues dozens of launches and a
            Warp launch costs the host less than a Taichi one).

    Attributes:
        stats: :class:`RenderStats` of the last :meth:`render`.
    """

    def __init__(
        self,
        field,
        grid: OccupancyGrid,
        model: QGMLSModel,
        *,
        cutoff_scale: float = 1.5,
        newton_iterations: int = 10,
        newton_tolerance: float = 1e-6,
        chunk: int = 4096,
        first_round_steps: int | None = None,
        steps_per_round: int | None = None,
        round_samples: int | None = None,
        half_precision: bool | None = None,
        framework: str | None = None,
    ):
        if not cutoff_scale > 0:
            raise ValueError(f"cutoff_scale must be positive (cuboid half-diagonals), got {cutoff_scale}")
        device = backend.torch_device()
        if round_samples is None:
            round_samples = 1 << 23 if device.type == "cuda" else 1 << 18
        if first_round_steps is None:
            first_round_steps = 16 if device.type == "cuda" else 1
        if steps_per_round is None:
            steps_per_round = 128 if device.type == "cuda" else 32
        if min(first_round_steps, steps_per_round, round_samples) < 1:
            raise ValueError(
                "first_round_steps, steps_per_round and round_samples must be at least 1, got "
                f"{first_round_steps}, {steps_per_round} and {round_samples}"
            )
        self.field, self.grid, self.model = field, grid, model
        self.newton_iterations, self.newton_tolerance, self.chunk = newton_iterations, newton_tolerance, chunk
        self.first_round_steps, self.steps_per_round = int(first_round_steps), int(steps_per_round)
        self.round_samples = int(round_samples)
        if half_precision is None:
            half_precision = device.type == "cuda" and isinstance(field, NGPField)
        self.half_precision = bool(half_precision)
        self._half_copies, self._half_key = None, None  # float16 MLPs, and (field, its weights_version) they copy
        # (directions, a copy of them or the caller's key, what the encoding depends on, encoded): _encode
        self._encoded = None
        self.framework = backend.check_framework(framework)
        self._rest_occupancy = grid.occupied.to(device=device, dtype=torch.uint8).contiguous()
        self._rest_aabb = grid.aabb.detach().float().cpu()
        if self.half_precision and device.type != "cuda":
            raise ValueError("half_precision needs the CUDA backend (float16 matmuls); pass half_precision=False")
        self.stats = RenderStats()
        ips = model.ips
        self.ip_rest = ips.position.to(device)
        self.cutoff = (cutoff_scale * 0.5 * torch.linalg.vector_norm(ips.extent, dim=1)).float().to(device)
        self._cutoff_max, self._cutoff_median = float(self.cutoff.max()), float(self.cutoff.median())
        self._knn_radius = 2.0 * self._cutoff_max
        self.min_step = field.config.min_step(field.aabb.cpu())
        occupied = torch.nonzero(grid.occupied).to(device)
        cell_size = grid.cell_size.to(device=device, dtype=torch.float64)
        self._cell_size_host = cell_size.cpu()  # the splat's kernel takes it by value
        self._cells_lo = grid.aabb.to(device=device, dtype=torch.float64)[0] + occupied * cell_size
        # float32 rest box and cell on the host, from which each frame grows its deformed grid (frame)
        self._rest_box = (*self._rest_aabb, self._cell_size_host.float())
        centres = (self._cells_lo + 0.5 * cell_size).float().contiguous()
        rest_hash = SpatialHash(self.ip_rest.float().contiguous(), self._cutoff_median)
        nearest, _ = rest_hash.knn(centres, 1, max_radius=float(torch.linalg.vector_norm(grid.aabb[1] - grid.aabb[0])))
        self._cell_ip = nearest[:, 0].long()

    def _half_mlps(self):
        """The field's MLPs in float16 (:meth:`pienerf.nerf.NGPField.half_mlps`), copied again whenever the field's
        weights changed since the last copy (:attr:`pienerf.nerf.NGPField.weights_version`)."""
        key = (self.field, self.field.weights_version)
        if self._half_key is None or self._half_key[0] is not key[0] or self._half_key[1] != key[1]:
            self._half_copies, self._half_key = self.field.half_mlps(), key
        return self._half_copies

    def _encode(self, directions: torch.Tensor, reuse: bool, key=None) -> torch.Tensor:
        """The field's encoding ``[R, C]`` of the rays' unit directions ``[R, 3]``
        (:meth:`pienerf.nerf.NGPField.encode_directions`; float16 under :attr:`half_precision`).

        With ``reuse`` the last camera rays' encoding is kept and handed back for the same field, field config and
        precision while :meth:`render` is given the same directions: the caller's ``key`` (hashable, naming the
        directions) equal to the last one, or, without a key, the very same tensor holding the same values as then
        (one comparison with a copy kept of them). A still camera (a viewer's, a benchmark's) then skips the
        encoding's ~40 small elementwise operations and its cast over every ray each frame. The tensor itself is
        held, so its memory cannot pass to another tensor that would then be taken for it.
        """
        depends_on = (self.field, self.field.config, self.half_precision)
        cached = self._encoded  # (directions, key, copy of the directions or None, depends_on, encoded)
        if reuse and cached is not None and cached[3] == depends_on:  # the field by identity, its config by value
            if key is not None:
                same = cached[1] is not None and cached[1] == key
            else:
                same = cached[1] is None and cached[0] is directions and torch.equal(cached[2], directions)
            if same:
                return cached[4]
        with self._precision():  # once per ray, not per sample (and gathered in float16 under half precision)
            encoded = self.field.encode_directions(directions)
            if self.half_precision:
                encoded = encoded.half()
        if reuse:
            self._encoded = (directions, key, directions.clone() if key is None else None, depends_on, encoded)
        return encoded

    def _precision(self):
        """The context the field's queries run in: float16 autocast with :attr:`half_precision`."""
        if self.half_precision:
            return torch.autocast("cuda", dtype=torch.float16)
        return contextlib.nullcontext()

    # -- per-frame state ------------------------------------------------------------------------

    def frame(self, q: torch.Tensor) -> DeformedFrame:
        """Deformed IPs, their spatial hash and the deformed occupancy grid for DOFs q ``[nT, 3]``."""
        position, F, grad_F = self.model.ip_state(q)
        displacement = position - self.model.ips.position  # in float64: exactly 0 for q = 0
        device = backend.torch_device()
        ip_deformed = position.float().to(device).contiguous()
        # The frame's one transfer to the host: the deformed IPs' bounds, which size the grid. The box and the shape
        # are then worked out on the host (float32, as the rest grid's box), where the splat and the march read them.
        bounds = torch.stack([ip_deformed.amin(0), ip_deformed.amax(0)]).cpu()
        pad = self._cutoff_max
        rest_lo, rest_hi, cell = self._rest_box
        grow_lo = torch.ceil(((rest_lo - (bounds[0] - pad)) / cell).clamp_min(0))
        grow_hi = torch.ceil((((bounds[1] + pad) - rest_hi) / cell).clamp_min(0))
        aabb = torch.stack([rest_lo - grow_lo * cell, rest_hi + grow_hi * cell])
        shape = tuple(int(v) for v in (self.grid.resolution + grow_lo + grow_hi).tolist())
        F64, G64, u64 = (t.to(device) for t in (F, grad_F, displacement))
        occupancy = splat_occupancy(
            self._cells_lo, self._cell_size_host, self._cell_ip, self.ip_rest, u64, F64, G64, aabb.double(), shape
        )
        return DeformedFrame(
            ip_deformed=ip_deformed,
            ip_displacement=displacement.float().to(device).contiguous(),
            F=F.float().to(device).contiguous(),
            grad_F=grad_F.float().to(device).contiguous(),
            ip_hash=SpatialHash(ip_deformed, self._cutoff_median),
            aabb=aabb,
            occupancy=occupancy,
        )

    # -- rendering -------------------------------------------------------------------------------

    @torch.no_grad()
    @backend.one_torch_thread_on_cpu()
    def render(
        self,
        q: torch.Tensor,
        cameras: Cameras | None = None,
        *,
        rays: tuple[torch.Tensor, torch.Tensor] | None = None,
        view: int = 0,
        mode: str = "quadratic",
        resolution: int | None = None,
        background=(1.0, 1.0, 1.0),
        ground: GroundPlane | None = None,
        frame: DeformedFrame | None = None,
        directions_key=None,
    ) -> dict[str, torch.Tensor]:
        """Render the body deformed by q (Eq. 19–21), optionally over a shadowed ground (Fig. 7).

        On the CPU torch runs on one thread meanwhile (:func:`kernels.backend.one_torch_thread_on_cpu`; the Taichi
        kernels still use every core): the rounds' many small tensor operations cost more in waking and waiting
        for a second thread than they gain, most of all on shared cores (``docs/benchmarks.md``).

        Args:
            q: ``[nT, 3]`` generalized coordinates (Eq. 9); ignored with ``mode="rest"``.
            cameras: the view ``view`` of these cameras is rendered, at ``resolution × resolution`` pixels
                over its image (default: the cameras' own size); or
            rays: ``(origins [R, 3], unit directions [R, 3])``, metres, instead of cameras. Passing the very same
                float32 directions tensor (on the backend device) frame after frame, unchanged, reuses its encoding
                (:meth:`_encode`).
            directions_key: a hashable the caller changes whenever the rays' directions change (say, the camera's
                pose and pixel grid): the encoding of the last call's directions is reused while the key is the same,
                without comparing the directions' values. ``None``: compare them.
            mode: ``"quadratic"`` (Eq. 20), ``"linear"`` (first-order warp) or ``"rest"`` (the undeformed NeRF,
                :func:`pienerf.nerf.render_rays`).
            background: ``[3]`` colour behind everything.
            ground: a lit ground plane that receives the object's shadow.
            frame: :meth:`frame` of this very q, to reuse (e.g. for several views of one state); ``None`` builds it.

        Returns:
            ``rgb`` (``[H, W, 3]`` for cameras, ``[R, 3]`` for rays; object over ground over background),
            ``alpha`` (object opacity), ``depth`` (object's expected depth, metres, 0 where empty); with a
            ground also ``ground_transmittance`` (light reaching the ground seen in each pixel, 1 off the
            ground), ``on_ground`` (bool: the ray meets the ground square behind the object) and ``shadow_map``
            ``[M, M]`` (transmittance to the light over the ground square).
        """
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; valid modes: {', '.join(MODES)}")
        origins, directions, image_shape = self._rays(cameras, rays, view, resolution)
        self.stats = RenderStats()
        device = backend.torch_device()
        background = torch.as_tensor(background, dtype=torch.float32, device=device)
        if background.shape != (3,):
            raise ValueError(f"background must be an RGB triple, got shape {tuple(background.shape)}")
        if frame is None and not (mode == "rest" and ground is None):
            frame = self.frame(self.check_q(q))
        if mode == "rest" and ground is None:
            out = render_rays(self.field, self.grid, origins, directions, background=background, chunk=self.chunk)
            result = {"rgb": out["rgb"], "alpha": out["opacity"], "depth": out["depth"]}
        else:
            far = torch.full((origins.shape[0],), 1e10, device=device)
            if ground is not None:
                t_ground = (ground.height - origins[:, 1]) / directions[:, 1]
                hits_plane = (directions[:, 1] < 0) & (t_ground > 0)
                far = torch.where(hits_plane, t_ground, far)
            color, opacity, depth = self._trace(origins, directions, far, frame, mode, directions_key=directions_key)
            behind = background.expand_as(color)
            result = {"alpha": opacity, "depth": torch.where(opacity > 1e-6, depth / opacity.clamp_min(1e-6), 0.0)}
            if ground is not None:
                shaded, transmittance, shadow_map = self._ground(
                    origins, directions, far, hits_plane, frame, mode, ground
                )
                behind = torch.where(shaded.isnan(), behind, shaded)
                result["ground_transmittance"] = transmittance
                result["on_ground"] = ~shaded[:, 0].isnan()
                result["shadow_map"] = shadow_map
            result["rgb"] = color + (1.0 - opacity)[:, None] * behind
        if image_shape is not None:
            result = {k: (v if k == "shadow_map" else v.reshape(*image_shape, *v.shape[1:])) for k, v in result.items()}
        return result

    def _trace(
        self, origins, directions, far, frame: DeformedFrame, mode: str, camera: bool = True, directions_key=None
    ):
        """Premultiplied colour ``[R, 3]``, opacity ``[R]`` and ``Σ w t`` ``[R]`` of rays through the deformed body,
        marched, warped, shaded and composited in rounds (class docstring). ``camera``: these are the camera's rays,
        whose encoded directions :meth:`_encode` keeps for the next frame (the shadow map's are not)."""
        if mode == "rest":
            out = render_rays(
                self.field, self.grid, origins, directions, far=far, background=(0.0, 0.0, 0.0), chunk=self.chunk
            )
            return out["rgb"], out["opacity"], out["depth"] * out["opacity"]
        c = self.field.config
        count, device = origins.shape[0], origins.device
        aabb = frame.aabb.cpu()  # a no-op for frame's own (on the host); else one transfer per trace, not per round
        grid = frame.occupancy.view(torch.uint8)  # the same bytes: bool is stored as 0 or 1
        march = march_start(origins, directions, 0.0, far, aabb)
        encoded = self._encode(directions, reuse=camera, key=directions_key)
        sums = composite_start(count, device)
        settings = dict(
            max_step=64.0 * self.min_step if c.cone_angle > 0.0 else None,
            cone_angle=c.cone_angle,
            max_samples=c.max_samples,
            transmittance=sums.transmittance,
            transmittance_threshold=c.transmittance_threshold,
        )
        budget = self.round_samples
        for start in range(0, count, budget):
            rays = torch.arange(start, min(start + budget, count), device=device)
            k = min(self.first_round_steps, self.steps_per_round)
            while rays.shape[0] > 0:
                k = max(1, min(k, budget // rays.shape[0]))
                batch = march_resume(
                    march,
                    origins,
                    directions,
                    rays,
                    grid,
                    aabb,
                    self.min_step,
                    samples_per_ray=k,
                    framework=self.framework,
                    **settings,
                )
                rest, keep = warp_round(
                    batch.positions,
                    batch.counts,
                    frame.ip_hash,
                    frame.ip_displacement,
                    frame.F,
                    frame.grad_F,
                    self.cutoff,
                    self._rest_occupancy,
                    self._rest_aabb,
                    max_radius=self._knn_radius,
                    quadratic=mode == "quadratic",
                    iterations=self.newton_iterations,
                    tolerance=self.newton_tolerance,
                    framework=self.framework,
                )
                # The round's one host sync: samples marched, samples worth a query, and rays going on (the others'
                # marches are over: box exit, far, max_samples or opaque).
                going_on = batch.counts == k
                marched, kept, alive = torch.stack([batch.counts.sum(), keep.sum(), going_on.sum()]).tolist()
                self.stats.rounds += 1
                self.stats.samples_marched += marched
                self.stats.samples_queried += kept
                if kept > 0:
                    self._shade_round(sums, rays, k, batch, rest, keep, kept, encoded)
                rays = rays[_compact(going_on, alive)]
                k = min(2 * k, self.steps_per_round)
        return sums.color, sums.opacity, sums.depth

    def _shade_round(self, sums, rays, k, batch, rest, keep, kept, encoded):
        """Query the field at a round's ``kept`` samples worth it (``keep [A · k]``) and composite them onto the rays'
        sums.

        The other samples have σ = 0 (no IP reaches them or their rest cell is empty): compositing them changes
        nothing (α = 0 exactly, T unchanged), so only the kept ones are queried and composited, in ray order.
        (Querying every marched sample with σ zeroed instead saves the count but not the time:
        ``docs/benchmarks.md``.)
        """
        # the kept samples' slots of the round's [A · k], in ray order, padded to a bucketed count (bucket_size)
        padded = _compact(keep, kept, bucket_size(kept) if rest.is_cuda else kept)
        index = padded[:kept]
        offsets = torch.zeros(rays.shape[0] + 1, dtype=torch.int32, device=rest.device)
        offsets[1:] = torch.cumsum(keep.view(-1, k).sum(1, dtype=torch.int32), 0)
        with self._precision():
            query = (rest[padded], gather_ray_rows(encoded, rays, padded, k))
            if self.half_precision and isinstance(self.field, NGPField):
                sigma, rgb = self.field.radiance(*query, mlps=self._half_mlps())
            else:
                sigma, rgb = self.field.radiance(*query)
        sigma, rgb = sigma[:kept], rgb[:kept]
        composite_accumulate(
            sums,
            rays,
            sigma.float().contiguous(),
            rgb.float().contiguous(),
            batch.deltas.view(-1)[index],
            batch.depths.view(-1)[index],
            offsets,
            transmittance_threshold=self.field.config.transmittance_threshold,
            framework=self.framework,
        )

    def _ground(self, origins, directions, t_ground, hits_plane, frame: DeformedFrame, mode: str, ground: GroundPlane):
        """Shaded ground colour per camera ray (NaN off the ground square), its light transmittance, and the
        shadow map: transmittance toward the light from each texel of the ground square (Fig. 7)."""
        device = origins.device
        light = torch.nn.functional.normalize(torch.tensor(ground.light_direction, dtype=torch.float32), dim=0)
        light = light.to(device)
        centre = 0.5 * (frame.ip_deformed.amin(0) + frame.ip_deformed.amax(0))
        M, half = ground.shadow_resolution, ground.extent
        texel = (torch.arange(M, device=device, dtype=torch.float32) + 0.5) / M * 2.0 * half - half
        tx, tz = torch.meshgrid(texel + centre[0], texel + centre[2], indexing="ij")
        texel_points = torch.stack([tx, torch.full_like(tx, ground.height), tz], dim=-1).reshape(-1, 3)
        _, opacity, _ = self._trace(
            texel_points.contiguous(),
            light.expand_as(texel_points).contiguous(),
            torch.full((texel_points.shape[0],), 1e10, device=device),
            frame,
            mode,
            camera=False,
        )
        shadow_map = (1.0 - opacity).clamp(0.0, 1.0).reshape(M, M)

        hit = origins + t_ground[:, None] * directions
        local = (hit[:, [0, 2]] - centre[[0, 2]]) / half  # [-1, 1] over the square
        on_ground = hits_plane & (local.abs() <= 1.0).all(dim=1)
        # grid_sample reads (x → last axis, y → first axis); the map is indexed [x, z].
        lookup = torch.nn.functional.grid_sample(
            shadow_map[None, None],
            local.flip(1)[None, None],
            mode="bilinear",
            padding_mode="border",
            align_corners=False,
        )[0, 0, 0]
        transmittance = torch.where(on_ground, lookup, 1.0)
        albedo = torch.tensor(ground.albedo, dtype=torch.float32, device=device)
        lambert = float(light[1])  # n = +y
        shade = (ground.ambient + ground.diffuse * lambert * transmittance).clamp(0.0, 1.0)
        shaded = torch.where(on_ground[:, None], (albedo * shade[:, None]).clamp(0.0, 1.0), math.nan)
        return shaded, transmittance, shadow_map

    # -- arguments -------------------------------------------------------------------------------

    def check_q(self, q: torch.Tensor) -> torch.Tensor:
        """``q`` when it is the model's DOFs ``[nT, 3]``, else a ValueError naming the expected shape."""
        expected = (self.model.shape_count, 3)
        if not isinstance(q, torch.Tensor) or tuple(q.shape) != expected:
            raise ValueError(f"q must be the model's DOFs {list(expected)}, got {list(getattr(q, 'shape', []))}")
        return q.to(dtype=torch.float64, device=self.model.device)

    def _rays(self, cameras, rays, view, resolution):
        device = backend.torch_device()
        if (cameras is None) == (rays is None):
            raise ValueError("pass either cameras (with view and resolution) or rays=(origins, directions)")
        if rays is not None:
            origins, directions = (torch.as_tensor(r, dtype=torch.float32, device=device).contiguous() for r in rays)
            if origins.dim() != 2 or origins.shape[1] != 3 or origins.shape != directions.shape:
                raise ValueError(
                    f"rays must be origins and directions [R, 3], got {tuple(origins.shape)} and "
                    f"{tuple(directions.shape)}"
                )
            return origins, directions, None
        width, height = (cameras.width, cameras.height) if resolution is None else (resolution, resolution)
        if width < 1 or height < 1:
            raise ValueError(f"resolution must be a positive number of pixels, got {resolution}")
        origins, directions = cameras.grid_rays(view, width, height)
        return origins.float().to(device).contiguous(), directions.float().to(device).contiguous(), (height, width)
