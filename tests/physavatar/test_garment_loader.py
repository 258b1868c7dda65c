"""Malformed OBJ/PLY garments end in a ``ValueError`` naming the file (and the line, for OBJ text)."""

import random

import numpy as np
import pytest
import trimesh

from physavatar.garment import Garment, load_garment
from physavatar.shapes import grid_sheet


@pytest.fixture(scope="module")
def sheet() -> trimesh.Trimesh:
    """A 5 × 8 vertex sheet, 0.35 m tall in y: a valid garment-sized mesh."""
    vertices, faces = grid_sheet(5, 8, 0.05)
    return trimesh.Trimesh(vertices.numpy(), faces.numpy(), process=False)


def _obj_lines(sheet: trimesh.Trimesh) -> list[str]:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in sheet.vertices]
    return lines + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in sheet.faces]


def _write(tmp_path, name: str, lines: list[str]):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_the_fixture_loads(sheet, tmp_path):
    garment = load_garment(_write(tmp_path, "sheet.obj", _obj_lines(sheet)))
    assert garment.faces.shape == (len(sheet.faces), 3)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda lines, v: lines + ["f 1 2 999"],
            r"sheet\.obj:{last}: face vertex '999' is not an index of the file's 40 ",
        ),
        (lambda lines, v: lines + ["f 1 2"], r"sheet\.obj:{last}: a face needs at least three vertices"),
        (lambda lines, v: lines + ["f 1 two 3"], r"sheet\.obj:{last}: face vertex 'two' is not an index"),
        (lambda lines, v: lines + ["f 0 1 2"], r"sheet\.obj:{last}: face vertex '0' is not an index"),
        (lambda lines, v: ["v 0 nan 0"] + lines, r"sheet\.obj:1: a vertex needs three finite numbers"),
        (lambda lines, v: ["v 0 1"] + lines, r"sheet\.obj:1: a vertex needs three finite numbers"),
        (lambda lines, v: ["v 1e308 0 0", "v -1e308 0 0"] + lines, r"sheet\.obj: coordinates reach 1e\+308"),
        (lambda lines, v: ["# only a comment"], r"sheet\.obj: no triangles found"),
    ],
)
def test_malformed_obj_names_file_and_line(sheet, tmp_path, edit, message):
    lines = edit(_obj_lines(sheet), len(sheet.vertices))
    with pytest.raises(ValueError, match=message.format(last=len(lines))):
        load_garment(_write(tmp_path, "sheet.obj", lines))


def test_binary_obj_names_the_line(sheet, tmp_path):
    path = tmp_path / "sheet.obj"
    path.write_bytes(("\n".join(_obj_lines(sheet)[:3]) + "\n").encode() + bytes(range(128, 256)))
    with pytest.raises(ValueError, match=r"sheet\.obj:4: not a text OBJ file"):
        load_garment(path)


def _ply(sheet: trimesh.Trimesh, encoding: str) -> bytes:
    return trimesh.exchange.ply.export_ply(sheet, encoding=encoding)


def test_malformed_ply_names_the_file(sheet, tmp_path):
    text = _ply(sheet, "ascii").decode()
    head, body = text.split("end_header\n")
    rows = body.splitlines()
    rows[-1] = "3 0 1 4000"  # a face beyond the vertices
    path = tmp_path / "sheet.ply"
    path.write_text(head + "end_header\n" + "\n".join(rows) + "\n")
    with pytest.raises(ValueError, match=r"sheet\.ply: 1 faces \(e\.g\. faces \d+\) name vertices beyond its 40"):
        load_garment(path)
    path.write_bytes(_ply(sheet, "binary")[:-40])  # truncated binary
    with pytest.raises(ValueError, match=r"sheet\.ply: "):
        load_garment(path)
    path.write_text(text.replace("element vertex 40", "element vertex 1000000000000"))
    with pytest.raises(ValueError, match=r"sheet\.ply: "):
        load_garment(path)


def _expected(error: Exception, name: str) -> bool:
    return type(error) is ValueError and str(error).startswith(name)


_ODD = ["nan", "inf", "-1", "0", "1e400", "x", "99999", "-99999", "1/2/3", "//", "1e308", "4", "#", "f", "v", ""]


def test_fuzzed_obj_files_load_or_fail_clearly(sheet, tmp_path):
    rng = random.Random(5)
    base = _obj_lines(sheet)
    outcomes = {"loaded": 0, "refused": 0}
    for case in range(80):
        lines = list(base)
        for _ in range(rng.randint(1, 3)):
            row = rng.randrange(len(lines))
            action = rng.random()
            if action < 0.6:
                tokens = lines[row].split()
                tokens[rng.randrange(len(tokens))] = rng.choice(_ODD)
                lines[row] = " ".join(tokens)
            elif action < 0.75:
                del lines[row]
            elif action < 0.9:
                lines.insert(row, lines[rng.randrange(len(lines))])
            else:
                lines = lines[:row]
            if not lines:
                break
        path = _write(tmp_path, "fuzz.obj", lines)
        try:
            garment = load_garment(path, scale=None)
        except ValueError as error:
            assert _expected(error, "fuzz.obj"), f"case {case}: {error}"
            outcomes["refused"] += 1
        else:
            assert isinstance(garment, Garment) and np.isfinite(garment.vertices.numpy()).all()
            outcomes["loaded"] += 1
    assert outcomes["loaded"] > 3 and outcomes["refused"] > 30, outcomes


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_fuzzed_ply_files_load_or_fail_clearly(sheet, tmp_path, encoding):
    rng = random.Random(6 if encoding == "ascii" else 7)
    raw = _ply(sheet, encoding)
    header_end = raw.index(b"end_header\n") + len(b"end_header\n")
    path = tmp_path / "fuzz.ply"
    for case in range(40):
        damaged = bytearray(raw)
        if case % 4 == 0:
            damaged = damaged[: rng.randrange(len(damaged))]
        else:
            for _ in range(rng.randint(1, 4)):
                at = rng.randrange(len(damaged)) if rng.random() < 0.3 else rng.randrange(header_end, len(damaged))
                damaged[at] = rng.choice(b"0123456789-.e \nxyz\xff\x00") if encoding == "ascii" else rng.randrange(256)
        path.write_bytes(bytes(damaged))
        try:
            garment = load_garment(path, scale=None)
        except ValueError as error:
            assert _expected(error, "fuzz.ply"), f"case {case}: {error}"
        else:
            assert np.isfinite(garment.vertices.numpy()).all()
