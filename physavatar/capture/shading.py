"""The capture's ray-traced renderer: the dressed scene, its Lambertian shading with shadows and ambient occlusion.

Image formation, per pixel ``p`` whose first hit lies on face ``f`` (a Lambertian surface, the model the
appearance stage of §3.3 inverts):

    I(p) = clamp(ρ_f ⊙ (L_a · AO(p) + L_s · max(0, n̂ · l̂) · V(p)), 0, 1)

* ``ρ_f`` is the face's RGB albedo (a per-face "texture"), ``L_a`` the uniform sky (ambient) radiance and
  ``L_s`` the sun's, both RGB multipliers of the albedo (:class:`Lighting`).
* ``n̂`` is the face's geometric normal turned toward the camera (surfaces are two-sided: a garment is a
  sheet), ``l̂`` the unit direction toward the sun.
* ``V(p)`` is 1 when a shadow ray from the hit toward the sun escapes the scene, else 0 (hard shadows).
* ``AO(p)`` is the fraction of ``S`` cosine-weighted hemisphere rays around ``n̂`` that escape the scene: the
  cosine-weighted visibility of a uniform sky, so an unoccluded surface receives exactly ``L_a``. The ``S``
  directions are one fixed low-discrepancy set (a rank-1 lattice on the unit square with a random shift drawn
  from ``seed``, mapped to the hemisphere by Malley's method), the same in every pixel's tangent frame: the
  image is a deterministic function of the geometry, without per-pixel noise.

All rays (primary, shadow, occlusion) go through one Warp BVH (:class:`kernels.raycast.MeshBVH`) holding the
garment and the body together and refitted every frame, so the body shadows and hides the garment and the
garment the body. Secondary rays leave the surface ``bias`` metres along ``n̂``.


Cost: a pixel that sees the scene costs 2 + ``ao_samples`` rays (figures in ``docs/benchmarks.md``).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from kernels import backend
from kernels.raycast import MeshBVH
from physavatar.capture.dataset import Capture
from physavatar.capture.rig import CameraRig, Lighting

_RAYS_PER_LAUNCH = 1 << 20  # occlusion rays per BVH launch: bounds the memory of one batch
_GOLDEN = 0.5 * (math.sqrt(5.0) - 1.0)

__all__ = [
    "ViewShading",
    "dressed_scene",
    "garment_albedo",
    "hemisphere_directions",
    "render_capture",
    "shade_mesh",
]

# ---------------------------------------------------------------------------------------------------------------
# Scene and shading
# ---------------------------------------------------------------------------------------------------------------


def garment_albedo(
    rest_vertices: torch.Tensor,
    faces: torch.Tensor,
    pattern: str = "stripes",
    colors=((0.80, 0.22, 0.20), (0.92, 0.86, 0.70)),
    bands: int = 8,
    axis: int | None = None,
) -> torch.Tensor:
    """A two-colour per-face albedo laid out on the rest geometry: the garment's printed "texture".

    The pattern is a function of each face's centroid in the rest shape, so it moves with the cloth. Stripes
    alternate along one axis; checks alternate along the two axes of largest extent.

    Args:
        rest_vertices: ``[V, 3]`` rest positions, m.
        faces: ``[F, 3]`` vertex indices.
        pattern: ``"stripes"`` or ``"checks"``.
        colors: two RGB albedos in [0, 1].
        bands: stripes (or checks per row) across the rest shape's largest extent.
        axis: axis the stripes alternate along (0, 1, 2); ``None``: the rest shape's longest axis.

    Returns:
        ``[F, 3]`` float32 albedo in [0, 1] (CPU).
    """
    if pattern not in ("stripes", "checks"):
        raise ValueError(f"pattern must be 'stripes' or 'checks', got {pattern!r}")
    if int(bands) < 1:
        raise ValueError(f"bands must be at least 1, got {bands}")
    palette = torch.as_tensor(colors, dtype=torch.float32)
    if palette.shape != (2, 3) or bool((palette < 0).any() | (palette > 1).any()):
        raise ValueError(f"colors must be two RGB albedos in [0, 1], got {colors!r}")
    rest = rest_vertices.detach().cpu().double()
    centroid = rest[faces.detach().cpu().long()].mean(1)
    lo = rest.amin(0)
    extent = rest.amax(0) - lo
    order = torch.argsort(extent, descending=True).tolist()
    if axis is not None:
        if axis not in (0, 1, 2):
            raise ValueError(f"axis must be 0, 1, 2 or None, got {axis!r}")
        order = [axis] + [a for a in order if a != axis]
    period = max(float(extent.max()), 1e-12) / int(bands)
    cell = torch.floor((centroid - lo) / period * (1.0 - 1e-9)).long()
    parity = cell[:, order[0]] if pattern == "stripes" else cell[:, order[0]] + cell[:, order[1]]
    return palette[parity % 2].contiguous()


def dressed_scene(
    garment_frames: torch.Tensor,
    garment_faces: torch.Tensor,
    body_frames: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Garment and body as one mesh sequence (garment faces first), the scene one BVH holds.

    Args:
        garment_frames: ``[T, V, 3]`` (or ``[V, 3]`` for one frame) garment vertices, m.
        garment_faces: ``[F, 3]``.
        body_frames: ``[T, B, 3]`` (or ``[B, 3]``) body vertices, m, or ``None`` for the garment alone.
        body_faces: ``[Fb, 3]``, given with ``body_frames``.

    Returns:
        ``vertices [T, V + B, 3]`` float32, ``faces [F + Fb, 3]`` int64 and ``F``, the garment's face count
        (faces ``0..F−1`` are the garment's).
    """
    garment_frames = _frames(garment_frames, "garment_frames")
    garment_faces = _faces(garment_faces, garment_frames.shape[1], "garment_faces")
    if (body_frames is None) != (body_faces is None):
        raise ValueError("pass body_frames and body_faces together (or neither, for the garment alone)")
    if body_frames is None:
        return garment_frames.float(), garment_faces, garment_faces.shape[0]
    body_frames = _frames(body_frames, "body_frames")
    body_faces = _faces(body_faces, body_frames.shape[1], "body_faces")
    if body_frames.shape[0] != garment_frames.shape[0]:
        raise ValueError(
            f"garment_frames holds {garment_frames.shape[0]} frames but body_frames {body_frames.shape[0]}; "
            "pass one body pose per garment frame"
        )
    vertices = torch.cat([garment_frames.float(), body_frames.float()], 1)
    faces = torch.cat([garment_faces, body_faces + garment_frames.shape[1]])
    return vertices, faces, garment_faces.shape[0]


def hemisphere_directions(count: int, seed: int = 0) -> torch.Tensor:
    """``[count, 3]`` float64 cosine-weighted directions about +z: the fixed occlusion rays of every pixel.

    Point ``k`` of the rank-1 lattice ``((k + ½) / S, k·φ mod 1)`` (φ the golden ratio's fraction) is shifted by
    one random offset drawn from ``seed`` (modulo 1, which keeps the lattice's stratification) and mapped to the
    unit disk and up to the hemisphere (Malley's method), so the directions' density is ``cos θ / π``.
    """
    if int(count) < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    shift = torch.rand(2, generator=torch.Generator().manual_seed(int(seed)), dtype=torch.float64)
    k = torch.arange(int(count), dtype=torch.float64)
    u1 = torch.remainder((k + 0.5) / count + shift[0], 1.0)
    u2 = torch.remainder(k * _GOLDEN + shift[1], 1.0)
    r, phi = torch.sqrt(u1), 2.0 * math.pi * u2
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1.0 - u1).clamp_min(0.0))], 1)


class ViewShading(NamedTuple):
    """One rendered view and its light transport (every map row-major, ``[H, W]`` pixels).

    Attributes:
        rgb: ``[H, W, 3]`` float32 colour in [0, 1], the background where the ray misses.
        face: ``[H, W]`` int64 face of the first hit, −1 on a miss.
        ao: ``[H, W]`` float32 ambient occlusion ``AO`` in [0, 1] (fraction of sky rays escaping), 0 on a miss.
        sun: ``[H, W]`` float32 sun term ``max(0, n̂ · l̂) · V`` in [0, 1], 0 on a miss.
        depth: ``[H, W]`` float32 distance from the camera centre to the hit along the ray, m; inf on a miss.
    """

    rgb: torch.Tensor
    face: torch.Tensor
    ao: torch.Tensor
    sun: torch.Tensor
    depth: torch.Tensor


def shade_mesh(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    albedo: torch.Tensor,
    rig: CameraRig,
    camera: int,
    lighting: Lighting,
    ao_samples: int = 16,
    seed: int = 0,
    *,
    background=(1.0, 1.0, 1.0),
    bias: float = 1e-4,
    bvh: MeshBVH | None = None,
    device: str | None = None,
) -> ViewShading:
    """Render one camera's view of a mesh: first hits, sun with hard shadows, sky with ambient occlusion.

    ``rgb = clamp(albedo_f ⊙ (L_a · AO + L_s · max(0, n̂ · l̂) · V), 0, 1)`` (module docstring). All secondary rays
    go through :meth:`kernels.raycast.MeshBVH.cast`.

    Args:
        vertices: ``[V, 3]`` positions, m.
        faces: ``[F, 3]`` vertex indices.
        albedo: ``[F, 3]`` per-face RGB albedo in [0, 1].
        rig: the cameras.
        camera: index of the camera to render.
        lighting: sky and sun.
        ao_samples: occlusion rays per pixel ``S``; 0 skips them (``AO = 1``).
        seed: picks the shift of the occlusion directions (:func:`hemisphere_directions`).
        background: RGB of pixels that see nothing.
        bias: offset of secondary rays' origins along the normal, m (about 1e-4 of the scene's size).
        bvh: a :class:`MeshBVH` already holding ``vertices`` and ``faces`` (skips the build; refit it per frame).
        device: ``"cpu"`` or ``"cuda"``; ``None`` keeps the kernels' device or picks the default.

    Returns:
        :class:`ViewShading` with maps on the kernels' device.
    """
    backend.init(device)
    dev = backend.torch_device()
    if bvh is None:
        vertices = _check_mesh_vertices(vertices)
        bvh = MeshBVH(vertices.to(dev, torch.float32), _faces(faces, vertices.shape[0], "faces").to(dev))
    elif tuple(bvh.vertices.shape) != tuple(vertices.shape) or bvh.faces.shape[0] != faces.shape[0]:
        raise ValueError(
            f"bvh holds {bvh.vertices.shape[0]} vertices and {bvh.faces.shape[0]} faces but the mesh has "
            f"{vertices.shape[0]} and {faces.shape[0]}; build the bvh from this mesh"
        )
    face_count = bvh.faces.shape[0]
    if not isinstance(albedo, torch.Tensor) or tuple(albedo.shape) != (face_count, 3):
        raise ValueError(f"albedo must be [{face_count}, 3] (one RGB per face), got {tuple(albedo.shape)}")
    if int(ao_samples) < 0 or not bias >= 0.0:
        raise ValueError(f"ao_samples must be >= 0 and bias (m) >= 0, got {ao_samples} and {bias}")

    origins, directions = rig.rays(camera, dev)
    hits = bvh.cast(origins, directions)
    pixel = torch.nonzero(hits.face >= 0).flatten()
    face = hits.face.long()[pixel]
    direction = directions[pixel]
    point = origins[pixel] + hits.t[pixel, None] * direction
    normal = _face_normals(bvh.vertices, bvh.faces)[face]
    normal = torch.where(((normal * direction).sum(1) > 0.0)[:, None], -normal, normal)  # toward the camera
    start = point + bias * normal

    toward_sun = torch.tensor(lighting.sun_direction, dtype=torch.float32, device=dev)
    sun = (normal @ toward_sun).clamp_min(0.0)
    lit = torch.nonzero(sun > 0.0).flatten()
    if len(lit):
        blocked = bvh.cast(start[lit], toward_sun.expand(len(lit), 3)).face >= 0
        sun[lit[blocked]] = 0.0
    ao = _ambient_occlusion(bvh, start, normal, int(ao_samples), seed)

    color = albedo.to(dev, torch.float32)[face] * (
        torch.tensor(lighting.ambient, device=dev) * ao[:, None] + torch.tensor(lighting.sun, device=dev) * sun[:, None]
    )
    count = origins.shape[0]
    rgb = torch.tensor(_rgb(background, "background"), dtype=torch.float32, device=dev).repeat(count, 1)
    rgb[pixel] = color.clamp(0.0, 1.0)
    face_map = torch.full((count,), -1, dtype=torch.int64, device=dev)
    face_map[pixel] = face
    ao_map = torch.zeros(count, device=dev)
    ao_map[pixel] = ao
    sun_map = torch.zeros(count, device=dev)
    sun_map[pixel] = sun
    shape = (rig.height, rig.width)
    return ViewShading(
        rgb.view(*shape, 3), face_map.view(shape), ao_map.view(shape), sun_map.view(shape), hits.t.view(shape)
    )


def _ambient_occlusion(bvh: MeshBVH, start: torch.Tensor, normal: torch.Tensor, samples: int, seed: int):
    """``[P]`` fraction of ``samples`` cosine-weighted rays from ``start [P, 3]`` about ``normal`` that escape."""
    if samples == 0 or not len(start):
        return torch.ones(len(start), dtype=torch.float32, device=start.device)
    local = hemisphere_directions(samples, seed).to(start.device, torch.float32)
    tangent, bitangent = _tangent_frame(normal)
    escaped = torch.empty(len(start), dtype=torch.float32, device=start.device)
    rows = max(1, _RAYS_PER_LAUNCH // samples)
    for lo in range(0, len(start), rows):
        hi = min(lo + rows, len(start))
        world = (
            local[None, :, 0:1] * tangent[lo:hi, None]
            + local[None, :, 1:2] * bitangent[lo:hi, None]
            + local[None, :, 2:3] * normal[lo:hi, None]
        )
        origin = start[lo:hi, None].expand_as(world)
        miss = bvh.cast(origin.reshape(-1, 3), world.reshape(-1, 3)).face < 0
        escaped[lo:hi] = miss.view(hi - lo, samples).float().mean(1)
    return escaped


def _tangent_frame(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit tangents completing unit ``normal [P, 3]`` to a right-handed frame (Duff et al. 2017)."""
    x, y, z = normal.unbind(1)
    sign = torch.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    tangent = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], 1)
    bitangent = torch.stack([b, sign + y * y * a, -y], 1)
    return tangent, bitangent


def _face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """``[F, 3]`` unit geometric normals ``(v1 − v0) × (v2 − v0)`` (zero for degenerate faces)."""
    v = vertices[faces.long()]
    return torch.nn.functional.normalize(torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], dim=1), dim=1)


def render_capture(
    garment_frames: torch.Tensor,
    garment_faces: torch.Tensor,
    body_frames: torch.Tensor | None,
    body_faces: torch.Tensor | None,
    garment_albedo: torch.Tensor,
    body_albedo,
    rig: CameraRig,
    lighting: Lighting,
    fps: float,
    background=(1.0, 1.0, 1.0),
    progress: bool | Callable[[int, int], None] | None = None,
    *,
    ao_samples: int = 16,
    seed: int = 0,
    quantize: bool = True,
    device: str | None = None,
) -> Capture:
    """Film the dressed body with every camera of ``rig`` at every frame (:func:`shade_mesh` per view).

    Args:
        garment_frames: ``[T, V, 3]`` garment vertices per frame, m (e.g. ``SimulationResult.garment_frames``).
        garment_faces: ``[F, 3]``.
        body_frames: ``[T, B, 3]`` body vertices per frame, m, or ``None`` to film the garment alone.
        body_faces: ``[Fb, 3]`` (``None`` with ``body_frames``).
        garment_albedo: ``[F, 3]`` per-face RGB albedo in [0, 1] (:func:`garment_albedo`).
        body_albedo: ``[Fb, 3]`` per-face albedo or one RGB ``[3]`` for the whole body.
        rig: the cameras.
        lighting: sky and sun.
        fps: frames per second of the sequence.
        background: RGB of pixels that see nothing.
        progress: ``True`` writes one line per frame to stderr; a callable receives ``(frame, frame_count)``
            after each frame; ``None``/``False`` is silent.
        ao_samples, seed: occlusion rays per pixel and the shift of their directions (:func:`shade_mesh`).
        quantize: round images to 8 bits as a camera does (then :func:`write_capture` stores them exactly).
        device: ``"cpu"`` or ``"cuda"``; ``None`` keeps the kernels' device or picks the default.

    Returns:
        :class:`Capture` on the CPU; masks mark pixels whose first hit is the garment.
    """
    backend.init(device)
    dev = backend.torch_device()
    vertices, faces, garment_face_count = dressed_scene(garment_frames, garment_faces, body_frames, body_faces)
    albedo = _scene_albedo(garment_albedo, body_albedo, garment_face_count, faces.shape[0])
    albedo = albedo.to(dev)
    frames = vertices.shape[0]
    faces = faces.to(dev)
    bvh = MeshBVH(vertices[0].to(dev), faces)
    images = torch.empty(frames, len(rig), rig.height, rig.width, 3, dtype=torch.float32)
    masks = torch.empty(frames, len(rig), rig.height, rig.width, dtype=torch.bool)
    for t in range(frames):
        if t:
            bvh.refit(vertices[t].to(dev))
        for c in range(len(rig)):
            view = shade_mesh(
                bvh.vertices, faces, albedo, rig, c, lighting, ao_samples, seed, background=background, bvh=bvh
            )
            images[t, c] = view.rgb.cpu()
            masks[t, c] = ((view.face >= 0) & (view.face < garment_face_count)).cpu()
        if callable(progress):
            progress(t + 1, frames)
        elif progress:
            covered = float(masks[t].float().mean())
            print(f"frame {t + 1}/{frames}: {len(rig)} views, garment covers {covered:.1%} of pixels", file=sys.stderr)
    if quantize:
        images = torch.round(images * 255.0) / 255.0
    return Capture(images, masks, rig, float(fps), lighting, _rgb(background, "background"))


def _scene_albedo(garment, body, garment_face_count: int, face_count: int) -> torch.Tensor:
    garment = torch.as_tensor(garment, dtype=torch.float32).cpu()
    if tuple(garment.shape) != (garment_face_count, 3):
        raise ValueError(
            f"garment_albedo must be [{garment_face_count}, 3] (one RGB per garment face), got {tuple(garment.shape)}"
        )
    body_count = face_count - garment_face_count
    body = torch.as_tensor(body if body is not None else (0.7, 0.7, 0.7), dtype=torch.float32).cpu()
    if body.shape == (3,):
        body = body.expand(body_count, 3)
    if tuple(body.shape) != (body_count, 3):
        raise ValueError(f"body_albedo must be one RGB [3] or [{body_count}, 3] per body face, got {tuple(body.shape)}")
    albedo = torch.cat([garment, body])
    if not bool(torch.isfinite(albedo).all() & (albedo >= 0).all()):
        raise ValueError("albedo values must be finite and non-negative (a physical albedo lies in [0, 1])")
    return albedo.contiguous()


# ---------------------------------------------------------------------------------------------------------------
# Checks
# ---------------------------------------------------------------------------------------------------------------


def _frames(frames: torch.Tensor, name: str) -> torch.Tensor:
    if not isinstance(frames, torch.Tensor) or not frames.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {getattr(frames, 'dtype', type(frames))}")
    if frames.dim() == 2:
        frames = frames[None]
    if frames.dim() != 3 or frames.shape[2] != 3 or frames.shape[0] == 0 or frames.shape[1] == 0:
        raise ValueError(f"{name} must be [T, N, 3] vertex positions (m) with T, N >= 1, got {tuple(frames.shape)}")
    if not bool(torch.isfinite(frames).all()):
        raise ValueError(f"{name} holds NaN or inf positions")
    return frames.detach().cpu()


def _faces(faces: torch.Tensor, vertex_count: int, name: str) -> torch.Tensor:
    faces = torch.as_tensor(faces)
    if faces.dim() != 2 or faces.shape[1] != 3 or faces.is_floating_point() or faces.shape[0] == 0:
        raise ValueError(f"{name} must be a non-empty integer [F, 3] tensor, got {faces.dtype} {tuple(faces.shape)}")
    faces = faces.long()
    if int(faces.min()) < 0 or int(faces.max()) >= vertex_count:
        raise ValueError(f"{name} index vertices {int(faces.min())}..{int(faces.max())} but there are {vertex_count}")
    return faces


def _check_mesh_vertices(vertices: torch.Tensor) -> torch.Tensor:
    if not isinstance(vertices, torch.Tensor) or vertices.dim() != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be a [V, 3] tensor, got {tuple(getattr(vertices, 'shape', ()))}")
    return vertices


def _rgb(value, name: str) -> tuple[float, float, float]:
    rgb = tuple(float(c) for c in np.asarray(value, dtype=np.float64).reshape(-1))
    if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
        raise ValueError(f"{name} must be an RGB triple in [0, 1], got {value!r}")
    return rgb
