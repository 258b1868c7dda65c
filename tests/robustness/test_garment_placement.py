"""A garment that is not worn by the body is refused with the measured distance and a fix, never simulated falling."""

import pytest
import torch
import trimesh

from physavatar.body import Body
from physavatar.garment import MAX_GAP, load_garment, place_on_body, procedural_skirt


@pytest.fixture(scope="module")
def body() -> Body:
    return Body.mannequin(spacing=0.03)


@pytest.fixture(scope="module")
def skirt(body):
    return procedural_skirt(body, rings=4, segments=12)


def _moved(skirt, offset):
    return skirt.replace(skirt.vertices + torch.tensor(offset, dtype=torch.float64), f"moved by {offset} m")


def test_a_fitted_skirt_is_kept_as_it_is(skirt, body):
    assert place_on_body(skirt, body) is skirt


def test_a_skirt_a_few_centimetres_off_the_body_is_still_worn(skirt, body):
    placed = place_on_body(_moved(skirt, [0.0, 0.0, 0.04]), body)
    assert float(body.signed_distance(placed.vertices).min()) > 1e-3


def test_a_skirt_five_metres_away_is_refused_naming_both_boxes(skirt, body):
    with pytest.raises(ValueError, match=r"not on the body: its bounding box \[4\.\d\d.* does not overlap the body's"):
        place_on_body(_moved(skirt, [5.0, 0.0, 0.0]), body)


def test_a_skirt_in_front_of_the_body_is_refused(skirt, body):
    with pytest.raises(ValueError, match=r"not on the body.*does not overlap.*move or scale it onto the body"):
        place_on_body(_moved(skirt, [0.0, 0.0, 0.5]), body)


def test_a_skirt_around_the_head_is_refused_with_its_distance(skirt, body):
    lifted = _moved(skirt, [0.0, 1.0, 0.0])  # hem at 1.66 m: the box overlaps the body's (up to 1.75 m)
    with pytest.raises(ValueError, match=r"nearest vertex is \d+ mm from the body surface, farther than 100 mm"):
        place_on_body(lifted, body)
    assert place_on_body(lifted, body, max_gap=1.0) is not None  # the option the message names lets it through


def test_max_gap_must_be_a_finite_distance_above_the_margin(skirt, body):
    assert MAX_GAP == pytest.approx(0.1)
    for bad in (0.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="max_gap must be a finite distance above margin"):
            place_on_body(skirt, body, max_gap=bad)


def test_a_garment_auto_rescaled_off_the_body_is_refused_naming_the_rescale(skirt, body, tmp_path):
    """A 0.2x skirt about the origin (inside the body, 8 cm tall) is read as decametres and scaled x10 about the
    origin, which lifts it above the head: placement must refuse it and say what the loading did."""
    path = tmp_path / "small_skirt.obj"
    trimesh.Trimesh((0.2 * skirt.vertices).numpy(), skirt.faces.numpy(), process=False).export(path)
    garment = load_garment(path)
    assert any("scaled by 10 about the origin" in note for note in garment.notes)
    with pytest.raises(ValueError, match=r"not on the body: .* mm from the body surface.*scaled by 10.*scale=1"):
        place_on_body(garment, body)
    kept = load_garment(path, scale=1)  # the fix the message names keeps the file's coordinates
    assert kept.notes == ()
    torch.testing.assert_close(kept.vertices, 0.2 * skirt.vertices, atol=1e-6, rtol=0)
