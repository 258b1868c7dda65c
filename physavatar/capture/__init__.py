"""A synthetic multi-view capture of the dressed mannequin: cameras, a ray-traced renderer and the capture files.

PhysAvatar's input is "multiview videos of T frames and C views" of a person in loose clothes (§3.1). Here the
person is the project's mannequin wearing a garment simulated with known parameters (§3.2, Eq. 5), so every
later stage (tracking §3.1, physics estimation §3.2, appearance §3.3) can be scored against the truth. This
package films that scene with a static ring of pinhole cameras:

- :mod:`~physavatar.capture.rig`: the cameras (:class:`CameraRig`) and the light (:class:`Lighting`);
- :mod:`~physavatar.capture.dataset`: :class:`Capture` and its files (``transforms.json``, images, masks, truth);
- :mod:`~physavatar.capture.shading`: the ray-traced renderer that films the scene (:func:`render_capture`).
"""

from physavatar.capture.dataset import Capture, load_capture, load_truth, write_capture
from physavatar.capture.rig import CameraRig, Lighting
from physavatar.capture.shading import (
    ViewShading,
    dressed_scene,
    garment_albedo,
    hemisphere_directions,
    render_capture,
    shade_mesh,
)

__all__ = [
    "Capture",
    "CameraRig",
    "Lighting",
    "ViewShading",
    "dressed_scene",
    "garment_albedo",
    "hemisphere_directions",
    "load_capture",
    "load_truth",
    "render_capture",
    "shade_mesh",
    "write_capture",
]
