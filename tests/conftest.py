"""Shared test fixtures: small analytic meshes, the location of the ICT kit, the command line
runner and the replayed export rig."""

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
ICT = SHARED / "data" / "ict"


def ict_or_skip() -> Path:
    """The ICT kit folder, or skip: CI has ../shared beside the checkout, a fresh clone may not."""
    if not (ICT / "neutral.obj").is_file():
        pytest.skip(f"ICT kit not found at {ICT} (../shared is not beside this checkout)")
    return ICT


@pytest.fixture(scope="session")
def ict_rig_fit():
    """The ICT kit's rig (configs/ict.toml) and its fit with the config's settings, made once per
    session and shared: tests must not change them (copy what they modify)."""
    ict_or_skip()
    from facepipe.pipeline.fit import fit_rig
    from facepipe.pipeline.rig import load_rig

    rig = load_rig(ROOT / "configs" / "ict.toml")
    return rig, fit_rig(rig)


def run_cli(*args) -> int:
    """Run the command line with ``args`` (made strings); its exit code."""
    from facepipe.cli.commands import main

    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in args])
    return exc.value.code


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The small replayed rig of :mod:`tests.export_rig` (built once per session); a test
    module may define its own ``rig``."""
    from tests.export_rig import build

    return build(tmp_path_factory.getbasetemp() / "export_rig")


def grid(nx: int = 12, ny: int = 10, curved: bool = True, size: float = 10.0):
    """A triangulated (nx × ny)-vertex sheet, optionally bent like a cylinder patch.

    Returns vertices (V, 3) float64 and faces (T, 3) int64.
    """
    u, v = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny), indexing="xy")
    x = size * (u - 0.5)
    y = size * (v - 0.5)
    z = -0.08 * size * (2 * u - 1) ** 2 if curved else np.zeros_like(x)
    V = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return V, F


@pytest.fixture
def sheet():
    return grid()


def mutate_bytes(draw, data: bytearray, tokens: list[bytes], edits: int, insert: int, delete: int,
                 swap: bool = False) -> bytes:
    """Fuzzing: 1 to ``edits`` random edits of ``data`` (in place) drawn with hypothesis's ``draw``.

    An edit inserts one of ``tokens`` or up to ``insert`` random bytes, deletes up to ``delete``
    bytes, replaces a byte, truncates, duplicates a line, or (``swap``) swaps two lines.
    """
    import hypothesis.strategies as st

    kinds = ["insert", "delete", "replace", "truncate"] + (["swap"] if swap else []) + ["dup"]
    for _ in range(draw(st.integers(1, edits))):
        kind = draw(st.sampled_from(kinds))
        at = draw(st.integers(0, len(data)))
        if kind == "insert":
            data[at:at] = draw(st.sampled_from(tokens) | st.binary(max_size=insert))
        elif kind == "delete":
            del data[at:at + draw(st.integers(1, delete))]
        elif kind == "replace" and at < len(data):
            data[at] = draw(st.integers(0, 255))
        elif kind == "truncate":
            del data[at:]
        else:
            lines = bytes(data).split(b"\n")
            i, j = draw(st.integers(0, len(lines) - 1)), draw(st.integers(0, len(lines) - 1))
            if kind == "swap":
                lines[i], lines[j] = lines[j], lines[i]
            else:
                lines.insert(i, lines[j])
            data = bytearray(b"\n".join(lines))
    return bytes(data)


def pytest_collection_modifyitems(config, items):
    """Mark what `make test-fast` leaves out: tests on the ICT kit (``ict``: they use its fixture or
    call :func:`ict_or_skip`) and end-to-end runs of the command line over a whole pipeline
    (``slow``: they use a module's ``pipeline`` fixture or run the benchmark)."""
    import inspect

    for item in items:
        fixtures = set(getattr(item, "fixturenames", ()))
        try:
            source = inspect.getsource(item.function)
        except (OSError, TypeError):
            source = ""
        if "ict_rig_fit" in fixtures or "ict_or_skip" in source or "ict_fit" in fixtures:
            item.add_marker(pytest.mark.ict)
        if "pipeline" in fixtures or "bench" in item.name:
            item.add_marker(pytest.mark.slow)


def add_detached_part(obj: Path, offset) -> int:
    """Append a small closed octahedron (its own vertices, one UV) away from the face to an OBJ;
    the index of its first vertex."""
    text = obj.read_text()
    n_v = sum(1 for line in text.splitlines() if line.startswith("v "))
    n_vt = sum(1 for line in text.splitlines() if line.startswith("vt "))
    corners = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]) * 0.8 + offset
    faces = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5), (0, 3, 5)]
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in corners] + ["vt 0.5 0.5"]
    lines += ["f " + " ".join(f"{n_v + i + 1}/{n_vt + 1}" for i in f) for f in faces]
    obj.write_text(text.rstrip("\n") + "\n" + "\n".join(lines) + "\n")
    return n_v

