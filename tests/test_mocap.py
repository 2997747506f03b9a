"""Tests of facepipe.mocap: CSV takes (read, write, errors) and gap filling."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facepipe.errors import InputError
from facepipe.mocap import facepipe_csv as mocap
from facepipe.mocap import Take, fill_gaps, parse_frame_slice, read_take, write_take_csv
from tests.conftest import mutate_bytes

ICT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict"
NAMES = ["A", "B", "C"]


def needs_ict():
    if not (ICT / "train_mocap.csv").is_file():
        pytest.skip(f"the ICT kit is not at {ICT} (the shared data folder is absent)")


def ict_markers():
    with open(ICT / "markers.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return [r["name"] for r in rows], np.array([int(r["vertex"]) for r in rows])


def make_take(T=12, names=NAMES, seed=0, missing=0.0) -> Take:
    rng = np.random.default_rng(seed)
    pos = rng.normal(scale=5.0, size=(T, len(names), 3))
    if missing:
        gone = rng.random((T, len(names))) < missing
        gone[np.arange(T), rng.integers(0, len(names), T)] = False  # a marker visible in every frame
        pos[gone] = np.nan
    return Take(frames=np.arange(T, dtype=np.int64), times=np.arange(T) / 30.0, positions=pos,
                marker_names=list(names))


def write(tmp_path: Path, text: str | bytes, name="take.csv") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return path


def assert_valid_take(take: Take, names) -> None:
    T = take.n_frames
    assert T >= 1
    assert take.positions.shape == (T, len(names), 3) and take.positions.dtype == np.float64
    assert take.frames.shape == (T,) and take.frames.dtype == np.int64
    assert take.times.shape == (T,) and np.isfinite(take.times).all()
    assert (np.diff(take.frames) > 0).all() and (np.diff(take.times) > 0).all()
    assert not np.isinf(take.positions).any()
    assert (~take.missing).any(axis=1).all()
    assert take.marker_names == list(names)


HEADER = "frame,time,A_x,A_y,A_z,B_x,B_y,B_z,C_x,C_y,C_z"
GOOD = [
    "0,0.000000,1.00000,2.00000,3.00000,4.00000,5.00000,6.00000,7.00000,8.00000,9.00000",
    "1,0.033333,1.10000,2.10000,3.10000,,,,7.10000,8.10000,9.10000",
    "2,0.066667,1.20000,2.20000,3.20000,4.20000,5.20000,6.20000,7.20000,8.20000,9.20000",
    "3,0.100000,1.30000,2.30000,3.30000,4.30000,5.30000,6.30000,7.30000,8.30000,9.30000",
]


def good_csv(rows=GOOD, header=HEADER) -> str:
    return "\n".join([header, *rows]) + "\n"


# --------------------------------------------------------------------------- reading


def test_round_trip(tmp_path):
    take = make_take(T=40, missing=0.2)
    write_take_csv(tmp_path / "t.csv", take)
    back = read_take(tmp_path / "t.csv", NAMES)
    np.testing.assert_array_equal(back.frames, take.frames)
    np.testing.assert_allclose(back.times, take.times, atol=5e-7)
    np.testing.assert_array_equal(np.isnan(back.positions), np.isnan(take.positions))
    np.testing.assert_allclose(back.positions, take.positions, atol=5e-6, equal_nan=True)
    assert back.fps == pytest.approx(30.0, rel=1e-4)
    assert back.extra_markers == [] and back.path == str(tmp_path / "t.csv")
    np.testing.assert_array_equal(back.lines, np.arange(40) + 2)


def test_rig_order_and_extra_markers(tmp_path):
    take = make_take(T=5, names=["A", "B", "EXTRA", "C"])
    write_take_csv(tmp_path / "t.csv", take)
    back = read_take(tmp_path / "t.csv", ["C", "A", "B"])
    assert back.marker_names == ["C", "A", "B"]
    assert back.extra_markers == ["EXTRA"]
    np.testing.assert_allclose(back.positions, take.positions[:, [3, 0, 1]], atol=5e-6)


def test_extra_marker_with_junk_is_ignored(tmp_path):
    rows = [r + ",junk,?,x" for r in GOOD]
    back = read_take(write(tmp_path, good_csv(rows, HEADER + ",Z_x,Z_y,Z_z")), NAMES)
    assert back.extra_markers == ["Z"]
    assert back.positions[3, 2, 2] == pytest.approx(9.3)


def test_missing_samples_and_lenient_forms(tmp_path):
    # NaN literals, exponents, spaces, CRLF, a byte-order mark, blank lines.
    rows = ["0, 0.0 ,1e0,2.0E+00,+3,NaN,nan, -NAN,7.,.8,9", "", "1,0.05,1.5,2.5,3.5,4.5,5.5,6.5,7.5,8.5,9.5"]
    text = "\ufeff" + HEADER + "\r\n" + "\r\n".join(rows) + "\r\n\r\n"
    take = read_take(write(tmp_path, text), NAMES)
    np.testing.assert_array_equal(take.frames, [0, 1])
    np.testing.assert_allclose(take.positions[0, 0], [1, 2, 3])
    assert np.isnan(take.positions[0, 1]).all()
    np.testing.assert_allclose(take.positions[0, 2], [7, 0.8, 9])
    np.testing.assert_array_equal(take.lines, [2, 4])
    assert take.fps == pytest.approx(20.0)


def test_nan_cells_stay_on_the_fast_path(tmp_path, monkeypatch):
    take = make_take(T=30, missing=0.3, seed=5)
    write_take_csv(tmp_path / "t.csv", take)
    text = (tmp_path / "t.csv").read_text()
    lines = [",".join(c or ("NaN", "nan", "-NAN")[i % 3] for i, c in enumerate(ln.split(","))) for ln in text.splitlines()]
    write(tmp_path, "\n".join(lines) + "\n", "nan.csv")

    def no_slow_path(*args):
        raise AssertionError("the per-cell path was used")

    with monkeypatch.context() as m:
        m.setattr(mocap, "_parse_block_slow", no_slow_path)
        back = read_take(tmp_path / "nan.csv", NAMES)
    np.testing.assert_array_equal(np.isnan(back.positions), np.isnan(take.positions))
    # Only a whole NaN field is a missing sample.
    write(tmp_path, text.replace(",,", ",nannan,", 1), "bad.csv")
    with pytest.raises(InputError, match="'nannan' is not a number"):
        read_take(tmp_path / "bad.csv", NAMES)


def test_partly_missing_sample_counts_as_missing(tmp_path):
    rows = list(GOOD)
    rows[2] = rows[2].replace("4.20000,", ",", 1)
    take = read_take(write(tmp_path, good_csv(rows)), NAMES)
    assert np.isnan(take.positions[2, 1]).all()
    assert take.missing[:, 1].tolist() == [False, True, True, False]


def test_frames_slice(tmp_path):
    take = make_take(T=20)
    write_take_csv(tmp_path / "t.csv", take)
    part = read_take(tmp_path / "t.csv", NAMES, frames=slice(5, 9))
    np.testing.assert_array_equal(part.frames, [5, 6, 7, 8])
    np.testing.assert_array_equal(part.lines, [7, 8, 9, 10])
    np.testing.assert_allclose(part.positions, take.positions[5:9], atol=5e-6)
    assert part.fps == pytest.approx(30.0, rel=1e-4)
    np.testing.assert_array_equal(read_take(tmp_path / "t.csv", NAMES, frames="-3:").frames, [17, 18, 19])
    assert parse_frame_slice("10:") == slice(10, None)
    with pytest.raises(InputError, match="selects none of the 20 frames"):
        read_take(tmp_path / "t.csv", NAMES, frames="30:40")
    for bad in ["a:b", "5", "1:2:0", ""]:
        with pytest.raises(InputError, match="bad frame range"):
            parse_frame_slice(bad)


def test_frame_without_markers_outside_the_slice_is_fine(tmp_path):
    rows = list(GOOD)
    rows[0] = "0,0.000000" + ",,," * 3
    path = write(tmp_path, good_csv(rows))
    with pytest.raises(InputError, match="every marker is missing"):
        read_take(path, NAMES)
    assert read_take(path, NAMES, frames="1:").n_frames == 3


def test_single_frame_has_no_fps(tmp_path):
    take = read_take(write(tmp_path, good_csv(GOOD[:1])), NAMES)
    assert take.n_frames == 1 and math.isnan(take.fps)


def test_unknown_suffix_is_sniffed(tmp_path):
    take = read_take(write(tmp_path, good_csv(), "take.txt"), NAMES)
    assert take.n_frames == 4
    take = read_take(write(tmp_path, good_csv(), "take.dat"), NAMES)
    assert take.n_frames == 4 and take.format == "facepipe-csv"
    with pytest.raises(InputError, match="unknown mocap format '.bin'"):
        read_take(write(tmp_path, b"\x01\x02binary", "take.bin"), NAMES)
    with pytest.raises(InputError, match="not a C3D file"):
        read_take(write(tmp_path, b"\x01\x50binary", "take.c3d"), NAMES)


def test_many_blocks_on_threads(tmp_path, monkeypatch):
    """Long takes are parsed in blocks on several threads: same values, same first error."""
    take = make_take(T=300, missing=0.1, seed=3)
    write_take_csv(tmp_path / "t.csv", take)
    whole = read_take(tmp_path / "t.csv", NAMES)
    monkeypatch.setattr(mocap, "_BLOCK_BYTES", 500)  # ~6 rows a block
    monkeypatch.setenv("FACEPIPE_THREADS", "4")
    blocks = read_take(tmp_path / "t.csv", NAMES)
    np.testing.assert_array_equal(blocks.positions, whole.positions)
    np.testing.assert_array_equal(blocks.times, whole.times)
    lines = (tmp_path / "t.csv").read_text().splitlines()
    for n in (250, 40):  # two bad cells: the earlier line is reported
        lines[n - 1] = lines[n - 1].replace(",", ",oops", 1).replace(",oops", ",", 1)
        fields = lines[n - 1].split(",")
        fields[4] = "oops"
        lines[n - 1] = ",".join(fields)
    write(tmp_path, "\n".join(lines) + "\n", "bad.csv")
    with pytest.raises(InputError, match=r"line 40, column 'A_z': 'oops' is not a number"):
        read_take(tmp_path / "bad.csv", NAMES)


@pytest.mark.ict
def test_ict_train_matches_truth():
    needs_ict()
    names, vertex = ict_markers()
    take = read_take(ICT / "train_mocap.csv", names)
    assert take.positions.shape == (120, 96, 3)
    assert take.extra_markers == [] and not take.missing.any()
    truth = np.load(ICT / "train_truth.npz")
    np.testing.assert_allclose(take.positions, truth["positions"][:, vertex], atol=1e-5)
    np.testing.assert_array_equal(take.frames, truth["frame"])
    np.testing.assert_allclose(take.times, truth["time"], atol=1e-6)
    assert take.fps == pytest.approx(30.0, rel=1e-3)


@pytest.mark.ict
def test_ict_noisy_gaps_filled_and_reported():
    needs_ict()
    names, _ = ict_markers()
    take = read_take(ICT / "noisy_mocap.csv", names)
    missing = take.missing
    assert 0.03 < missing.mean() < 0.05  # the kit says 4.1 %
    filled, report = fill_gaps(take.positions, times=take.times, marker_names=names, path=take.path)
    json.dumps(report)
    assert not np.isnan(filled).any()
    np.testing.assert_array_equal(filled[~missing], take.positions[~missing])
    total = report["total"]
    assert total["filled"] == total["missing"] == int(missing.sum()) and total["unfilled"] == 0
    assert total["missing_fraction"] == pytest.approx(missing.mean())
    assert 3 <= total["longest_gap"] <= 40  # the kit's gaps are 3-40 frames
    assert total["gaps"] == sum(r["gaps"] for r in report["markers"].values()) > 0
    for name, r in report["markers"].items():
        assert r["filled"] == int(missing[:, names.index(name)].sum())


# --------------------------------------------------------------------------- bad input


def _replace_row(i, row):
    rows = list(GOOD)
    rows[i] = row
    return good_csv(rows)


BAD = {
    "empty": ("", [r"the take is empty", "hint: a facepipe take starts with the header"]),
    "blank": ("\n  \n\n", [r"the take is empty"]),
    "no frame column": (good_csv(header=HEADER.replace("frame", "frm")), [r"line 1 \(header\): no 'frame' column"]),
    "no time column": (good_csv(header=HEADER.replace("time", "t")), [r"no 'time' column"]),
    "semicolons": ("frame;time;A_x;A_y;A_z\n0;0;1;2;3\n", [r"no 'frame' and no 'time' column", "uses commas"]),
    "incomplete triple": (good_csv(header=HEADER.replace("B_y", "Q_y")),
                          [r"line 1 \(header\): marker B has B_x, B_z but no B_y"]),
    "duplicate column": (good_csv(header=HEADER.replace("C_x", "A_x")), [r"column 'A_x' appears twice"]),
    "bad column name": (good_csv(header=HEADER.replace("C_x", "C-x")), [r"column 9 'C-x' is neither"]),
    "trailing comma in header": (good_csv(header=HEADER + ","), [r"column 12 has no name \(a trailing comma\?\)"]),
    "non-numeric": (_replace_row(1, GOOD[1].replace("8.10000", "8.1O000")),
                    [r"line 3, column 'C_y': '8.1O000' is not a number", "hint: write a decimal number"]),
    "non-utf8 cell": (_replace_row(2, GOOD[2].replace("1.20000", "1.2\xe9")).encode("latin-1"),
                      [r"line 4, column 'A_x': '1.2\ufffd' is not a number"]),
    "truncated last row": (good_csv()[:-30], [r"line 5: 8 fields, the header has 11 \(truncated row\)", "cut off"]),
    "extra fields": (_replace_row(0, GOOD[0] + ",1.0"), [r"line 2: 12 fields, the header has 11 \(extra fields\)"]),
    "unsorted frames": (_replace_row(2, GOOD[2].replace("2,", "0,", 1)),
                        [r"frame 0 \(line 4\): frame number goes back from frame 1 \(line 3\)", "sort the file"]),
    "duplicate frame": (_replace_row(2, GOOD[2].replace("2,", "1,", 1)),
                        [r"frame 1 \(line 4\): frame number repeats frame 1 \(line 3\)"]),
    "non-integer frame": (_replace_row(1, GOOD[1].replace("1,", "1.5,", 1)),
                          [r"line 3, column 'frame': the frame number is missing or not an integer"]),
    "empty frame": (_replace_row(1, GOOD[1][1:]), [r"line 3, column 'frame'"]),
    "missing time": (_replace_row(1, GOOD[1].replace("0.033333", "")),
                     [r"frame 1 \(line 3\): the time is missing"]),
    "time going back": (_replace_row(2, GOOD[2].replace("0.066667", "0.01")),
                        [r"frame 2 \(line 4\): time 0.01 s is not after"]),
    "infinite value": (_replace_row(3, GOOD[3].replace("5.30000", "inf")),
                       [r"frame 3 \(line 5\): marker B \(B_y\) is infinite"]),
    "every marker missing": (_replace_row(2, "2,0.066667" + ",,," * 3 ),
                             [r"frame 2 \(line 4\): every marker is missing", "--frames"]),
    "only a header": (HEADER + "\n", [r"the take has no frames"]),
    "binary": (b"\x00\x01\x02frame,time\x00" * 10, [r"binary file"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_names_the_problem(tmp_path, case):
    text, patterns = BAD[case]
    path = write(tmp_path, text)
    with pytest.raises(InputError) as err:
        read_take(path, NAMES)
    message = str(err.value)
    assert message.startswith(str(path) + ": ")
    for pattern in patterns:
        assert re.search(pattern, message), f"{pattern!r} not in {message!r}"


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(InputError, match="mocap take not found"):
        read_take(tmp_path / "nope.csv", NAMES)
    with pytest.raises(InputError, match="is a folder"):
        read_take(tmp_path, NAMES)


def test_absent_rig_markers_are_named(tmp_path):
    path = write(tmp_path, good_csv(header=HEADER.replace("B_", "b_")))
    with pytest.raises(InputError) as err:
        read_take(path, ["A", "B", "C", "D"])
    message = str(err.value)
    assert "2 rig marker(s) absent from the take: B, D" in message
    assert "mark the marker `ignore` in markers.csv" in message
    assert "b -> B" in message  # the likely rename


# --------------------------------------------------------------------------- fuzzing

ALPHABET_TOKENS = [b",", b"\n", b"\r\n", b"", b"-", b".", b"e", b"5", b"0", b"nan", b"inf", b" ", b"\x00",
                   b"\xff", b"frame", b"time", b"A_x", b"Z_y", b"1e999", b"99999999999999999999", b'"']


@st.composite
def mutated_csv(draw):
    data = bytearray(good_csv(GOOD + [r.replace(r.split(",")[0], str(int(r.split(",")[0]) + 4), 1)
                                      .replace("0.", "1.", 1) for r in GOOD]).encode())
    return mutate_bytes(draw, data, ALPHABET_TOKENS, edits=6, insert=4, delete=12, swap=True)


def _read_or_input_error(path, data):
    path.write_bytes(data)
    try:
        take = read_take(path, NAMES)
    except InputError as exc:
        assert str(exc)
        return
    assert_valid_take(take, NAMES)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=300) | mutated_csv())
def test_fuzz_read_take_returns_take_or_input_error(tmp_path_factory, data):
    _read_or_input_error(tmp_path_factory.getbasetemp() / "fuzz.csv", data)


@settings(max_examples=200, deadline=None)
@given(cells=st.lists(
    st.floats(-1e6, 1e6).map(lambda v: f"{v:.5f}")
    | st.builds(lambda v, k: f"{v:.{k}f}", st.floats(-1e9, 1e9), st.integers(0, 8))
    | st.text(alphabet="0123456789.-+eE ", max_size=8)
    | st.just(""),
    min_size=1, max_size=12,
))
def test_fast_parser_agrees_with_float(cells):
    """The vectorised parser gives float()'s value for every cell it accepts."""
    out = mocap._parse_block_fast((",".join(cells) + "\n").encode(), 1, len(cells))
    plain = all(re.fullmatch(r"-?\d+\.\d{5}", c) and len(c) <= 17 for c in cells)
    if plain:
        assert out is not None  # the common case must stay on the fast path
    if out is None:
        return
    for cell, value in zip(cells, out[0]):
        assert mocap._NUMBER_RE.match(cell.encode()) or cell == ""
        expected = float(cell) if cell else math.nan
        assert value == expected or (math.isnan(value) and math.isnan(expected))
        assert math.copysign(1, value) == math.copysign(1, expected) or math.isnan(expected)


# --------------------------------------------------------------------------- gap filling


def test_fill_gaps_exact_on_linear_motion():
    times = np.cumsum(np.random.default_rng(1).uniform(0.02, 0.05, 50))  # uneven sampling
    velocity = np.array([[1.0, -2.0, 0.5], [0.0, 3.0, -1.0]])
    truth = np.array([[0.1, 0.2, 0.3], [1.0, 2.0, 3.0]]) + times[:, None, None] * velocity
    pos = truth.copy()
    pos[5:17, 0] = np.nan
    pos[30, 0] = np.nan
    pos[20:40, 1] = np.nan
    filled, report = fill_gaps(pos, times=times, marker_names=["P", "Q"])
    np.testing.assert_allclose(filled, truth, atol=1e-12)
    assert report["markers"]["P"] == {"gaps": 2, "filled": 13, "unfilled": 0, "longest_gap": 12}
    assert report["markers"]["Q"] == {"gaps": 1, "filled": 20, "unfilled": 0, "longest_gap": 20}
    assert report["total"]["longest_gap_marker"] == "Q"
    json.dumps(report)


def test_fill_gaps_holds_the_ends():
    pos = np.arange(30, dtype=float)[:, None, None] * np.ones((1, 1, 3))
    pos[:4] = np.nan
    pos[25:] = np.nan
    filled, report = fill_gaps(pos)
    np.testing.assert_array_equal(filled[:4, 0], np.tile(pos[4, 0], (4, 1)))
    np.testing.assert_array_equal(filled[25:, 0], np.tile(pos[24, 0], (5, 1)))
    assert report["markers"]["marker0"] == {"gaps": 2, "filled": 9, "unfilled": 0, "longest_gap": 5}


def test_fill_gaps_single_visible_sample_is_held():
    pos = np.full((6, 1, 3), np.nan)
    pos[2, 0] = [1, 2, 3]
    filled, _ = fill_gaps(pos)
    np.testing.assert_array_equal(filled[:, 0], np.tile([1, 2, 3], (6, 1)))


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), gap=st.integers(1, 8))
def test_fill_gaps_stays_between_the_neighbours(seed, gap):
    """PCHIP never overshoots: a gap's values lie between the samples around it."""
    rng = np.random.default_rng(seed)
    pos = rng.normal(size=(40, 2, 3)).cumsum(axis=0) * rng.uniform(0.01, 100)
    start = int(rng.integers(1, 40 - gap))
    pos[start:start + gap, 0] = np.nan
    filled, report = fill_gaps(pos)
    before, after = pos[start - 1, 0], pos[start + gap, 0]
    lo, hi = np.minimum(before, after), np.maximum(before, after)
    tol = 1e-9 * (1 + np.nanmax(np.abs(pos)))
    assert (filled[start:start + gap, 0] >= lo - tol).all() and (filled[start:start + gap, 0] <= hi + tol).all()
    np.testing.assert_array_equal(filled[:, 1], pos[:, 1])
    assert report["markers"]["marker0"]["longest_gap"] == gap


def test_fill_gaps_max_gap_leaves_long_gaps():
    pos = np.arange(40, dtype=float)[:, None, None] * np.ones((1, 2, 3))
    pos[3:5, 0] = np.nan   # 2 frames: filled
    pos[10:20, 0] = np.nan  # 10 frames: left
    pos[35:, 1] = np.nan   # 5 frames at the end: left
    original = pos.copy()
    filled, report = fill_gaps(pos, max_gap=4, marker_names=["P", "Q"])
    np.testing.assert_array_equal(pos, original)  # the input is not modified
    np.testing.assert_allclose(filled[3:5, 0], pos[[2], 0] + [[1], [2]])
    assert np.isnan(filled[10:20, 0]).all() and np.isnan(filled[35:, 1]).all()
    assert report["markers"]["P"] == {"gaps": 2, "filled": 2, "unfilled": 10, "longest_gap": 10}
    assert report["total"]["unfilled"] == 15 and report["total"]["filled"] == 2


def test_fill_gaps_never_visible_marker_is_named():
    pos = np.zeros((5, 3, 3))
    pos[:, 1] = np.nan
    pos[:, 2, 0] = np.nan  # one coordinate missing is a missing sample
    with pytest.raises(InputError, match="never visible in the take: Q, R") as err:
        fill_gaps(pos, marker_names=["P", "Q", "R"], path="take.csv")
    assert str(err.value).startswith("take.csv: ") and "ignore" in str(err.value)


def test_fill_gaps_without_gaps():
    pos = np.random.default_rng(0).normal(size=(7, 2, 3))
    filled, report = fill_gaps(pos)
    np.testing.assert_array_equal(filled, pos)
    assert report["total"]["gaps"] == 0 and report["total"]["longest_gap_marker"] is None
