"""Physics estimation from tracked meshes (PhysAvatar §3.1 → §3.2): a small multi-view capture rendered on the CPU,
tracked with mesh-aligned Gaussians, and the fabric fitted to the tracked meshes, scored against the truth."""

import dataclasses

import pytest
import torch

from physavatar.capture import CameraRig, Lighting, garment_albedo, render_capture
from physavatar.fit.estimation import FabricParameters, estimate_analytic, rollout
from physavatar.fit.tracking import TrackConfig, track
from tests.physavatar.fit.test_estimation import swing

FRAMES = 24  # the paper's sequence length for material estimation (Appendix A.3.1)
TRUTH = FabricParameters(320.0, 0.3, 6.0)  # a stretchy fabric, stiff in bending
START = FabricParameters(320.0, 0.6, 3.0)  # both stiffnesses two-fold off


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Small tensors run faster on one thread than on cores shared with other processes."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_estimation_from_tracked_meshes_recovers_both_ratios(device):
    """The swinging 0.4 m sheet of the estimation tests, filmed by 4 cameras at 96² px for 24 frames, tracked, and
    fitted from a two-fold error: κ_s/ρ and κ_b/ρ come within 10 % of the truth (measured: +4 % and +2 %).

    The scenario shows what it is asked to measure. Over the paper's 24 frames, with κ_s = 0.3 (the sheet stretches
    0.7 % on average, 5 % at most) and κ_b = 6 (a bending length of about 6 cm), a 10 % change of κ_s or κ_b moves the
    sheet by 0.58 or 0.42 mm (RMS over vertices and frames). For the 12 frames of κ_s = 1.5, κ_b = 0.8 of the exact-mesh
    test those are 0.14 and 0.05 mm, far below the 2 mm the tracked meshes are off (one Gaussian per 7 px face cannot
    reproduce the rendered faces' sharp edges): there κ_b/ρ came out 2.4× too high. Tracking lets each edge stretch by
    5 % without cost (``iso_tolerance``): under Eq. 2 alone the tracked sheet kept 0.03 % of its 0.7 % mean stretch
    and κ_s/ρ came out 15 % high at 100 iterations a frame (at these 60: κ_s/ρ 6 %, κ_b/ρ 7.5 % high).
    """
    problem = swing(FRAMES)
    truth_frames = rollout(problem, TRUTH, device=device).frames
    first = truth_frames[0]
    eyes = [[0.0, 0.2, 0.9], [0.7, 0.1, 0.6], [-0.7, 0.1, 0.6], [0.0, -0.3, 0.8]]
    rig = CameraRig.look_at(eyes, first.mean(0).tolist(), 96, 96, fov_deg=40.0)
    albedo = garment_albedo(first, problem.faces, pattern="checks", bands=6)
    film = render_capture(
        truth_frames, problem.faces, None, None, albedo, None, rig, Lighting(), problem.fps, ao_samples=4
    )
    config = TrackConfig(first_iterations=100, iterations=60, lr_vertices=2e-3, iso_tolerance=0.05)
    tracked = track(film, first, problem.faces, None, None, config, truth=truth_frames, progress=False)
    motion = float(torch.linalg.norm(truth_frames - first, dim=2).mean())
    assert motion > 0.04  # the sheet swings by centimetres
    assert float(tracked.vertex_error[1:].max()) < 0.2 * motion  # the tracked meshes are close, not exact

    fitted = estimate_analytic(
        dataclasses.replace(problem, reference=tracked.vertices), START, device=device, progress=False
    )
    for got, expected, name in zip(fitted.ratios, TRUTH.ratios, ("κ_s/ρ", "κ_b/ρ"), strict=True):
        assert got == pytest.approx(expected, rel=0.1), f"{name}: {got:.4g} against {expected:.4g}"
