"""A synthetic multi-view capture of the dressed mannequin: cameras, a ray-traced renderer and the capture files.

PhysAvatar's input is "multiview videos of T frames and C views" of a person in loose clothes (§3.1). Here the
person is the project's mannequin wearing a garment simulated with known parameters (§3.2, Eq. 5), so every
later stage (tracking §3.1, physics estimation §3.2, appearance §3.3) can be scored against the truth. This
package films that scene with a static ring of pinhole cameras:

- :mod:`~physavatar.capture.rig`: the cameras (:class:`CameraRig`) and the light (:class:`Lighting`);
- :mod:`~physavatar.capture.dataset`: :class:`Capture` and its files (``transforms.json``, images, masks, truth);
- :mod:`~physavatar.capture.shading`: the ray-traced renderer that films the scene (:func:`render_capture`).

A researcher brings a real capture as a folder (``docs/capture.md``): the video, the body sequence and the garment.

- :mod:`~physavatar.capture.folder`: :func:`load_capture_folder` reads it into a :class:`CaptureFolder` (y-up);
- :mod:`~physavatar.capture.check`: :func:`check_capture` finds every problem in it before any heavy work;
- :mod:`~physavatar.capture.layout`: the one parser of capture folders that both, and :func:`load_capture`, use.
"""

from physavatar.capture.check import MAX_EXTENT, CaptureCheck, check_capture
from physavatar.capture.dataset import Capture, load_capture, load_truth, write_capture
from physavatar.capture.folder import CaptureFolder, from_capture_axes, load_capture_folder, to_capture_axes
from physavatar.capture.layout import (
    FRAME_KEYS,
    INTRINSIC_KEYS,
    TRANSFORMS,
    UP_AXES,
    CaptureIndex,
    Findings,
    Problem,
    body_paths,
    boundary_path,
    garment_path,
    read_body,
    read_boundary,
    read_garment,
    read_index,
    read_view,
    read_views,
)
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
    "FRAME_KEYS",
    "INTRINSIC_KEYS",
    "MAX_EXTENT",
    "TRANSFORMS",
    "UP_AXES",
    "CameraRig",
    "Capture",
    "CaptureCheck",
    "CaptureFolder",
    "CaptureIndex",
    "Findings",
    "Lighting",
    "Problem",
    "ViewShading",
    "body_paths",
    "boundary_path",
    "check_capture",
    "dressed_scene",
    "garment_albedo",
    "garment_path",
    "hemisphere_directions",
    "from_capture_axes",
    "load_capture",
    "load_capture_folder",
    "load_truth",
    "read_body",
    "read_boundary",
    "read_garment",
    "read_index",
    "read_view",
    "read_views",
    "render_capture",
    "shade_mesh",
    "to_capture_axes",
    "write_capture",
]
