"""Take formats behind the registry: C3D, TRC, Vicon Nexus CSV, Motive CSV (and the facepipe CSV).

Round trips through each writer and reader, units, subject prefixes, duplicate / absent /
extra markers, vendor header quirks, bad input with named lines, and bounded fuzzing.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facepipe.errors import InputError
from facepipe.mocap import (FORMATS, Take, match_markers, normalise_units, read_take, registry, unit_factor, write_take)
from tests.conftest import mutate_bytes

NAMES = ["M001", "M002", "M003", "S01", "S02"]
VENDOR = ["c3d", "trc", "vicon-csv", "motive-csv"]
SUFFIX = {"c3d": ".c3d", "trc": ".trc", "vicon-csv": ".csv", "motive-csv": ".csv", "facepipe-csv": ".csv"}


def make_take(T=25, names=NAMES, seed=0, first=0, units="cm") -> Take:
    rng = np.random.default_rng(seed)
    pos = rng.normal(scale=5.0, size=(T, len(names), 3)) + [0.0, 160.0, 20.0]
    pos[3:7, 1] = np.nan  # a gap
    pos[min(10, T - 1), 0] = np.nan
    frames = np.arange(first, first + T, dtype=np.int64)
    return Take(frames=frames, times=frames / 30.0, positions=pos, marker_names=list(names), units=units, fps=30.0)


def written(tmp_path, fmt, take=None, units="mm", subject="Actor", name="take"):
    take = take or make_take()
    path = tmp_path / f"{name}{SUFFIX[fmt]}"
    write_take(path, take, fmt, units=units, subject=subject)
    return path, take


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("fmt", VENDOR + ["facepipe-csv"])
def test_round_trip_in_mm_with_subject_prefix(tmp_path, fmt):
    units = None if fmt == "facepipe-csv" else "mm"  # the facepipe CSV has no units: rig units
    path, take = written(tmp_path, fmt, units=units)
    back = read_take(path, list(reversed(NAMES)), units="cm")
    assert back.format == fmt and back.units == "cm"
    assert back.source_units == ("cm" if fmt == "facepipe-csv" else "mm")
    expected = take.positions[:, ::-1]
    np.testing.assert_array_equal(np.isnan(back.positions), np.isnan(expected))
    # C3D stores float32 (7 digits of ~1600 mm); text formats 5-6 decimals of mm
    np.testing.assert_allclose(back.positions, expected, atol=2e-5, equal_nan=True)
    np.testing.assert_array_equal(back.frames, take.frames)
    np.testing.assert_allclose(back.times, take.times, atol=1e-6)
    assert back.markers["subject"] == "Actor" and len(back.markers["renamed"]) == len(NAMES)
    assert back.markers["absent"] == [] and back.extra_markers == []


def test_c3d_more_than_255_markers_uses_labels2(tmp_path):
    names = [f"P{i:03d}" for i in range(300)]
    take = make_take(T=4, names=names, first=7)
    path = tmp_path / "big.c3d"
    write_take(path, take, units="mm")
    import ezc3d

    params = ezc3d.c3d(str(path))["parameters"]["POINT"]
    assert len(params["LABELS"]["value"]) == 255 and len(params["LABELS2"]["value"]) == 45
    back = read_take(path, names[250:260], units="cm")
    np.testing.assert_allclose(back.positions, take.positions[:, 250:260], atol=2e-5)
    np.testing.assert_array_equal(back.frames, take.frames)
    assert len(back.extra_markers) == 290


def test_c3d_negative_residual_is_missing(tmp_path):
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [60.0]
    c["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    c["parameters"]["POINT"]["LABELS"]["value"] = ("A", "B")
    pts = np.ones((4, 2, 3))
    pts[:3] = np.arange(18).reshape(3, 2, 3) / 10.0
    c["data"]["points"] = pts
    res = np.zeros((1, 2, 3))
    res[0, 1, 2] = -1.0  # B in frame 2: coordinates present, residual says missing
    c["data"]["meta_points"] = {"residuals": res, "camera_masks": np.zeros((7, 2, 3), dtype=bool)}
    c.write(str(tmp_path / "r.c3d"))
    take = read_take(tmp_path / "r.c3d", ["A", "B"], units="cm")
    assert np.isnan(take.positions[2, 1]).all() and not np.isnan(take.positions[:2, 1]).any()
    np.testing.assert_allclose(take.positions[0, 0], pts[:3, 0, 0] * 100)
    np.testing.assert_allclose(take.times, np.arange(3) / 60.0)


# --------------------------------------------------------------------------- units and names


def test_units():
    assert normalise_units("Millimeters") == "mm" and normalise_units(" METERS ") == "m"
    assert normalise_units(None) is None and normalise_units("") is None
    assert unit_factor("mm", "cm") == pytest.approx(0.1) and unit_factor("in", "cm") == pytest.approx(2.54)
    with pytest.raises(InputError, match="unknown length unit 'furlong'"):
        normalise_units("furlong")


def test_take_units_override_and_unknown_unit_in_file(tmp_path):
    path, take = written(tmp_path, "trc", units="mm")
    back = read_take(path, NAMES, units="cm", take_units="cm")  # the user knows better than the file
    np.testing.assert_allclose(back.positions, take.positions * 10, atol=1e-4, equal_nan=True)
    text = path.read_text().replace("\tmm\t", "\tfurlongs\t", 1)
    path.write_text(text)
    with pytest.raises(InputError, match=r"unknown length unit \(line 3, Units\) 'furlongs'"):
        read_take(path, NAMES, units="cm")


def test_match_prefixes_duplicates_absent_and_subjects():
    m = match_markers(["Bob:A", "Bob:B", "Bob:A", "X"], ["B", "A"])
    assert m.index.tolist() == [1, 0]
    assert m.report["duplicates"] == {"A": ["Bob:A", "Bob:A"]} and m.report["extra"] == ["X"]
    assert m.report["renamed"] == {"Bob:B": "B", "Bob:A": "A"} and m.report["subject"] == "Bob"
    # an exact name wins over a prefixed one
    assert match_markers(["Bob:A", "A"], ["A"]).index.tolist() == [1]
    with pytest.raises(InputError, match="several subjects that match the rig: Amy, Bob"):
        match_markers(["Bob:A", "Amy:B"], ["A", "B"])
    m = match_markers(["Bob:A", "Amy:A", "Amy:B"], ["A", "B"], subject="Amy")
    assert m.index.tolist() == [1, 2]
    with pytest.raises(InputError, match="subject 'Zoe' is not in the take"):
        match_markers(["Bob:A"], ["A"], subject="Zoe")
    m = match_markers(["A", "B", "C"], ["A", "B", "D"], absent="missing")
    assert m.index.tolist() == [0, 1, -1] and m.report["absent"] == ["D"]
    with pytest.raises(InputError, match="2 rig marker\\(s\\) absent from the take: C, D"):
        match_markers(["A", "x"], ["A", "C", "D"], absent="missing")  # most absent: the wrong take
    with pytest.raises(InputError, match="perhaps Bob:m002 -> M002"):
        match_markers(["Bob:M001", "Bob:m002"], ["M001", "M002"])


@pytest.mark.parametrize("fmt", VENDOR)
def test_absent_marker_is_a_nan_column_when_allowed(tmp_path, fmt):
    path, take = written(tmp_path, fmt)
    back = read_take(path, NAMES + ["M009"], units="cm", absent="missing")
    assert np.isnan(back.positions[:, -1]).all() and back.markers["absent"] == ["M009"]
    with pytest.raises(InputError, match="1 rig marker\\(s\\) absent from the take: M009"):
        read_take(path, NAMES + ["M009"], units="cm")


# --------------------------------------------------------------------------- vendor quirks


def test_vicon_blocks_around_trajectories(tmp_path):
    path, take = written(tmp_path, "vicon-csv")
    body = path.read_text()
    text = ("Devices\n1000\n,,Force Plate,,\nFrame,Sub Frame,Fx,Fy,Fz\n,,N,N,N\n1,0,1,2,3\n\n" + body
            + "\nModel Outputs\n30\n,,Actor:Angle,,\nFrame,Sub Frame,X,Y,Z\n,,deg,deg,deg\n1,0,5,6,7\n")
    path.write_text(text)
    back = read_take(path, NAMES, units="cm")
    assert back.n_frames == take.n_frames
    np.testing.assert_allclose(back.positions, take.positions, atol=2e-5, equal_nan=True)
    path.write_text(body.replace("\n,,mm,mm,mm,mm", "\n,,mm,mm,mm,cm", 1))
    with pytest.raises(InputError, match="markers in different units"):
        read_take(path, NAMES, units="cm")
    path.write_text(body.replace("Trajectories\n30", "Trajectories\nfast", 1))
    with pytest.raises(InputError, match="line 2: 'fast' is not a frame rate"):
        read_take(path, NAMES, units="cm")


def test_motive_ignores_rigid_bodies_and_reads_blank_as_missing(tmp_path):
    lines = [
        "Format Version,1.23,Take Name,t,Export Frame Rate,120.000000,Length Units,Meters,Coordinate Space,Global",
        "",
        ",Type,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Marker,Marker,Marker,"
        "Rigid Body Marker,Rigid Body Marker,Rigid Body Marker",
        ",Name,Head,Head,Head,Head,Head,Head,Head,Actor:A,Actor:A,Actor:A,Head:A,Head:A,Head:A",
        ",ID,1,1,1,1,1,1,1,2,2,2,3,3,3",
        ",,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Position,Position,Position,"
        "Position,Position,Position",
        "Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,X,Y,Z,X,Y,Z",
        "0,0.000000,0,0,0,1,1,2,3,0.1,0.2,0.3,9,9,9",
        "1,0.008333,0,0,0,1,1,2,3,,,,9,9,9",
    ]
    path = tmp_path / "m.csv"
    path.write_text("\n".join(lines) + "\n")
    take = read_take(path, ["A"], units="cm", allow_empty_frames=True)
    assert take.format == "motive-csv"
    np.testing.assert_allclose(take.positions[0, 0], [10, 20, 30])
    assert np.isnan(take.positions[1, 0]).all()
    path.write_text("\n".join(lines[:3] + lines[4:]) + "\n")  # no Name row
    with pytest.raises(InputError, match="line 6: the header has no Name row above it"):
        read_take(path, ["A"], units="cm", allow_empty_frames=True)


# --------------------------------------------------------------------------- bad input


def _cut(text: str, n: int) -> str:
    return text[:-n]


@pytest.mark.parametrize("fmt", ["trc", "vicon-csv", "motive-csv"])
def test_text_formats_bad_input_names_line(tmp_path, fmt):
    path, take = written(tmp_path, fmt)
    good = path.read_text()
    lines = good.rstrip("\n").split("\n")
    sep = "\t" if fmt == "trc" else ","
    # a non-numeric cell, named by line and column
    row = len(lines) - 3
    cells = lines[row].split(sep)
    cells[3] = "1.2.3"
    bad = lines[:row] + [sep.join(cells)] + lines[row + 1:]
    path.write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError, match=rf"line {row + 1}, column '.*': '1.2.3' is not a number"):
        read_take(path, NAMES, units="cm")
    # a file cut off in its last row
    path.write_text(good.rstrip("\n")[:-12])
    with pytest.raises(InputError, match="truncated row"):
        read_take(path, NAMES, units="cm")
    # rows out of order
    swapped = lines[:-2] + [lines[-1], lines[-2]]
    path.write_text("\n".join(swapped) + "\n")
    with pytest.raises(InputError, match="frame number goes back"):
        read_take(path, NAMES, units="cm")
    # a repeated row
    path.write_text("\n".join(lines + [lines[-1]]) + "\n")
    with pytest.raises(InputError, match="frame number repeats"):
        read_take(path, NAMES, units="cm")
    # empty
    path.write_text("")
    with pytest.raises(InputError, match="empty"):
        read_take(path, NAMES, units="cm")


def test_damaged_c3d_is_an_input_error_not_a_crash(tmp_path):
    path, _ = written(tmp_path, "c3d")
    data = path.read_bytes()
    for cut in (len(data) // 2, 700, 520):  # the C3D library segfaults on some of these
        p = tmp_path / f"cut{cut}.c3d"
        p.write_bytes(data[:cut])
        with pytest.raises(InputError, match="C3D"):
            read_take(p, NAMES, units="cm")
    (tmp_path / "text.c3d").write_text("hello, world\n" * 50)
    with pytest.raises(InputError, match="not a C3D file"):
        read_take(tmp_path / "text.c3d", NAMES)
    (tmp_path / "empty.c3d").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        read_take(tmp_path / "empty.c3d", NAMES)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="crash isolation needs fork")
def test_a_crash_of_the_c3d_library_becomes_an_input_error():
    from facepipe.mocap.c3d import _isolated

    def crash(path):
        os.kill(os.getpid(), signal.SIGSEGV)

    with pytest.raises(InputError, match="damaged \\(the C3D library crashed reading it: SIGSEGV\\)"):
        _isolated(crash, "x.c3d")
    with pytest.raises(InputError, match="not a readable C3D file \\(ValueError: bad\\)"):
        _isolated(lambda path: (_ for _ in ()).throw(ValueError("bad")), "x.c3d")
    assert _isolated(lambda path: {"a": np.arange(3)}, "x.c3d")["a"].tolist() == [0, 1, 2]


def test_take_larger_than_memory_is_refused_before_reading(tmp_path, monkeypatch):
    path, _ = written(tmp_path, "trc")
    monkeypatch.setattr(registry, "available_memory", lambda: 1000)
    with pytest.raises(InputError, match=r"reading it needs about .* GB of memory.*\n  hint: split the take"):
        read_take(path, NAMES, units="cm")


def test_every_marker_missing_in_a_frame(tmp_path):
    take = make_take(T=6)
    take.positions[2] = np.nan
    path = tmp_path / "t.trc"
    write_take(path, take, units="mm")
    with pytest.raises(InputError, match=r"frame 2 \(line 9\): every marker is missing"):
        read_take(path, NAMES, units="cm")
    back = read_take(path, NAMES, units="cm", allow_empty_frames=True)  # replay interpolates such frames
    assert np.isnan(back.positions[2]).all()


def test_registry_lists_every_format():
    assert set(FORMATS) == {"facepipe-csv", "c3d", "trc", "vicon-csv", "motive-csv", "openface-csv", "uv-csv"}
    for fmt in FORMATS.values():
        assert callable(fmt.reader) and callable(fmt.writer)


# --------------------------------------------------------------------------- fuzzing

TOKENS = [b",", b"\t", b"\n", b"", b"-", b".", b"e", b"5", b"nan", b" ", b"\x00", b"\xff", b"Frame", b"mm",
          b"Marker", b"Position", b"Trajectories", b"X", b"999999999999999999999", b'"', b":"]


def _mutate(draw, data: bytearray) -> bytes:
    return mutate_bytes(draw, data, TOKENS, edits=5, insert=3, delete=10)


_SEEDS: dict[str, bytes] = {}


def _seed(fmt: str, tmp_dir: Path) -> bytes:
    if fmt not in _SEEDS:
        take = make_take(T=5)
        path = tmp_dir / f"seed{SUFFIX[fmt]}"
        write_take(path, take, fmt, units="mm", subject="Actor")
        _SEEDS[fmt] = path.read_bytes()
    return _SEEDS[fmt]


def _read_or_input_error(path: Path, data: bytes) -> None:
    path.write_bytes(data)
    try:
        take = read_take(path, NAMES, units="cm")
    except InputError as exc:
        assert str(exc)
        return
    assert take.positions.shape == (take.n_frames, len(NAMES), 3) and take.n_frames >= 1
    assert (np.diff(take.frames) > 0).all() and np.isfinite(take.times).all()
    assert not np.isinf(take.positions).any()


@pytest.mark.parametrize("fmt", ["trc", "vicon-csv", "motive-csv"])
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_fuzz_text_formats(tmp_path_factory, fmt, data):
    base = tmp_path_factory.getbasetemp()
    blob = data.draw(st.builds(lambda: None).flatmap(lambda _: st.just(_seed(fmt, base))))
    mutated = _mutate(data.draw, bytearray(blob))
    _read_or_input_error(base / f"fuzz{SUFFIX[fmt]}", mutated)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_c3d(tmp_path_factory, data):
    base = tmp_path_factory.getbasetemp()
    blob = bytearray(_seed("c3d", base))
    for _ in range(data.draw(st.integers(1, 4))):
        kind = data.draw(st.sampled_from(["flip", "truncate", "zero"]))
        at = data.draw(st.integers(0, len(blob) - 1))
        if kind == "flip":
            blob[at] = data.draw(st.integers(0, 255))
        elif kind == "truncate":
            del blob[max(at, 2):]
        else:
            blob[at:at + 16] = bytes(min(16, len(blob) - at))
    _read_or_input_error(base / "fuzz.c3d", bytes(blob))
