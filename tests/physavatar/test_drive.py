"""The body driver: the body collider and the boundary targets of each step (PhysAvatar §3.2, Eq. 5)."""

import pytest
import torch

from physavatar.body import Body, walk
from physavatar.drive import BodyDriver
from physavatar.garment import boundary_targets, procedural_skirt, select_boundary


@pytest.fixture(scope="module")
def dressed():
    body = Body.mannequin(spacing=0.03)
    skirt = procedural_skirt(body, rings=4, segments=12)
    return body, skirt, select_boundary(skirt, body, mode="waist")


def test_controls_are_the_skinned_body_and_targets_of_consecutive_frames(dressed):
    body, skirt, boundary = dressed
    motion = walk(body.skeleton)
    driver = BodyDriver.from_motion(body, motion, skirt.vertices, boundary, steps=3)
    assert driver.frames == 4 and driver.dt == 1.0 / motion.fps
    skinned = body.skin(motion.rotations[:4], motion.root_translation[:4])
    targets = boundary_targets(body, skirt.vertices[boundary], motion.rotations[:4], motion.root_translation[:4])
    for t in range(3):
        control = driver.control(t)
        assert torch.equal(control.body_start, skinned[t]) and torch.equal(control.body_end, skinned[t + 1])
        assert torch.equal(control.boundary_index, boundary) and torch.equal(control.boundary_target, targets[t + 1])
    with pytest.raises(IndexError, match=r"step 3 is outside 0\.\.2"):
        driver.control(3)


def test_a_clip_too_short_is_refused_with_the_fix(dressed):
    body, skirt, boundary = dressed
    motion = walk(body.skeleton, duration=0.2)  # 6 poses
    with pytest.raises(ValueError, match=r"frames \(6\) must lie in 1\.\.5: the motion holds 6 poses.*fewer frames"):
        BodyDriver.from_motion(body, motion, skirt.vertices, boundary, steps=6)


def test_mismatched_sequences_are_refused():
    with pytest.raises(ValueError, match="one \\[D, 3\\] row per body frame"):
        BodyDriver(torch.zeros(3, 5, 3), torch.arange(2), torch.zeros(2, 2, 3), 25.0)
