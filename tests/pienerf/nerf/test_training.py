"""Truncated, foreign and tampered checkpoints end in a clear ``ValueError`` naming the file."""

import copy
import random
from dataclasses import replace

import pytest
import torch

from kernels.hashgrid import HashGridConfig
from pienerf.nerf.field import NGPConfig, NGPField, OccupancyGrid
from pienerf.nerf.fitting import NerfFit
from pienerf.nerf.training import TrainConfig, load_checkpoint, save_checkpoint

TINY = NGPConfig(
    hashgrid=HashGridConfig(levels=2, features=2, log2_table_size=6, base_resolution=4, max_resolution=8),
    density_hidden=8,
    color_hidden=8,
    color_layers=1,
    grid_resolution=4,
)
AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


@pytest.fixture
def checkpoint(tmp_path):
    torch.manual_seed(0)
    field = NGPField(TINY, AABB)
    return save_checkpoint(tmp_path / "tiny.pt", field, OccupancyGrid.for_field(field), 5, TrainConfig(steps=10))


def test_a_valid_checkpoint_loads(device, checkpoint):
    loaded = load_checkpoint(checkpoint)
    assert loaded.step == 5 and loaded.train_config.steps == 10


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda raw: raw[: len(raw) // 3], "not a readable checkpoint"),
        (lambda raw: raw[:10], "not a readable checkpoint"),
        (lambda raw: bytes(random.Random(1).randrange(256) for _ in range(4096)), "not a readable checkpoint"),
        (lambda raw: b"", "not a readable checkpoint"),
        (lambda raw: b"format: pienerf\n", "not a readable checkpoint"),
    ],
)
def test_damaged_bytes_name_the_file(device, checkpoint, damage, message):
    checkpoint.write_bytes(damage(checkpoint.read_bytes()))
    with pytest.raises(ValueError, match=message) as error:
        load_checkpoint(checkpoint)
    assert str(checkpoint) in str(error.value)


def _tamper(payload: dict, edit: str) -> dict:
    payload = copy.deepcopy(payload)
    if edit == "step":
        payload["step"] = "five"
    elif edit == "huge table":
        payload["config"]["hashgrid"]["log2_table_size"] = 30
        payload["config"]["hashgrid"]["levels"] = 64
    elif edit == "huge grid":
        payload["grid"]["resolution"] = 5000
    elif edit == "aabb":
        payload["aabb"] = "the unit cube"
    elif edit == "field":
        payload["field"] = [1, 2, 3]
    elif edit == "config":
        payload["config"] = {"no_such_setting": 1}
    elif edit == "format":
        payload["format"] = 3
    return payload


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ("step", "holds step 'five'"),
        ("huge table", "holds inconsistent parts .*the config asks for at least"),
        ("huge grid", r"holds inconsistent parts .*grid density is \(4, 4, 4\), not 5000³"),
        ("aabb", "holds inconsistent parts"),
        ("field", "holds inconsistent parts .*'field' must map"),
        ("config", "holds inconsistent parts .*no_such_setting"),
        ("format", "has format 3"),
    ],
)
def test_tampered_payloads_are_refused_before_allocating(device, checkpoint, edit, message):
    payload = torch.load(checkpoint, weights_only=True)
    torch.save(_tamper(payload, edit), checkpoint)
    with pytest.raises(ValueError, match=message) as error:
        load_checkpoint(checkpoint)
    assert str(checkpoint) in str(error.value)


_ODD = [None, -1, 0, 2**40, 1e300, float("nan"), "x", [], {}, torch.zeros(0), torch.zeros(3, 3), True]


def _leaves(tree, prefix=()):
    """Paths to every entry of nested dicts."""
    for key, value in tree.items():
        yield (*prefix, key)
        if isinstance(value, dict):
            yield from _leaves(value, (*prefix, key))


def test_fuzzed_checkpoints_load_or_fail_clearly(device, checkpoint):
    rng = random.Random(4)
    valid = torch.load(checkpoint, weights_only=True)
    paths = list(_leaves(valid))
    raw = checkpoint.read_bytes()
    refused = 0
    for case in range(60):
        if case % 3 == 0:  # bytes: flip a few, or cut
            damaged = bytearray(raw)
            for _ in range(rng.randint(1, 6)):
                damaged[rng.randrange(len(damaged))] = rng.randrange(256)
            checkpoint.write_bytes(bytes(damaged) if rng.random() < 0.7 else raw[: rng.randrange(len(raw))])
        else:  # structure: an entry replaced or removed
            payload = copy.deepcopy(valid)
            *parents, key = rng.choice(paths)
            where = payload
            for name in parents:
                where = where[name]
            if rng.random() < 0.8:
                where[key] = rng.choice(_ODD)
            else:
                del where[key]
            torch.save(payload, checkpoint)
        try:
            load_checkpoint(checkpoint)
        except ValueError as error:
            assert str(checkpoint) in str(error), f"case {case}: {error}"
            refused += 1
    assert refused > 30


def test_the_table_dtype_round_trips_through_configs_and_checkpoints(device, tmp_path, checkpoint):
    half = NGPConfig(**{**TINY.__dict__, "hashgrid": replace(TINY.hashgrid, table_dtype="float16")})
    assert NGPConfig.from_dict(half.to_dict()) == half and half.to_dict()["hashgrid"]["table_dtype"] == "float16"
    torch.manual_seed(0)
    field = NGPField(half, AABB)
    path = save_checkpoint(tmp_path / "half.pt", field, OccupancyGrid.for_field(field), 3)
    loaded = load_checkpoint(path)
    assert loaded.field.config == half and loaded.field.encoding.table.dtype == torch.float32
    assert torch.equal(loaded.field.encoding.table.cpu(), field.encoding.table.detach())
    assert torch.equal(loaded.field.encoding.read_table().cpu(), field.encoding.table.detach().half())

    # A checkpoint written before the setting existed has no table_dtype: it loads with the float32 table.
    payload = torch.load(checkpoint, weights_only=True)
    del payload["config"]["hashgrid"]["table_dtype"]
    torch.save(payload, checkpoint)
    assert load_checkpoint(checkpoint).field.config.hashgrid.table_dtype == "float32"

    # A fit's digest names its NeRF in caches and assets: a float16 table is another NeRF; a float32 one digests as
    # before the setting existed (the shipped NeRF's name, tests/pienerf/viewer, still matches).
    fit = NerfFit()
    half_fit = replace(fit, ngp=replace(fit.ngp, hashgrid=replace(fit.ngp.hashgrid, table_dtype="float16")))
    assert half_fit.digest(scene="plant") != fit.digest(scene="plant")
