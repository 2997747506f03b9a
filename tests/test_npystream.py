"""The streaming .npy writer: the same file whether written directly or through the page cache."""

import errno
import os

import numpy as np
import pytest

from facepipe.io import npy_stream as npystream
from facepipe.io.npy_stream import BLOCK, NpyWriter, npy_header


def _rows(shape, seed=0):
    return np.random.default_rng(seed).normal(size=shape)


@pytest.mark.parametrize("direct", [True, False])
@pytest.mark.parametrize("chunks", [[7], [1, 2, 4], [3, 3, 1]])
def test_round_trip_in_any_chunking(tmp_path, monkeypatch, direct, chunks):
    # a buffer of three blocks makes the 12 kB rows cross it, and 1001 × 3 float32 rows end mid-block
    monkeypatch.setattr(npystream, "BUFFER", 3 * BLOCK)
    data = _rows((7, 1001, 3))
    path = tmp_path / "p.npy"
    with NpyWriter(path, data.shape, direct=direct) as w:
        start = 0
        for n in chunks:
            w.write(data[start:start + n])
            start += n
    if direct and not w.direct:
        pytest.skip("this file system does not do direct I/O (the buffered path wrote it)")
    assert path.stat().st_size == BLOCK + data.size * 4
    back = np.load(path)
    assert back.dtype == np.float32 and back.shape == data.shape
    np.testing.assert_array_equal(back, data.astype(np.float32))
    np.testing.assert_array_equal(np.load(path, mmap_mode="r")[3], data[3].astype(np.float32))


def test_header_is_one_block_that_numpy_reads(tmp_path):
    header = npy_header((5, 530000, 3), np.float32)
    assert len(header) == BLOCK and header.endswith(b"\n")
    path = tmp_path / "h.npy"
    path.write_bytes(header)
    with open(path, "rb") as fh:
        assert np.lib.format.read_magic(fh) == (1, 0)
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        assert fh.tell() == BLOCK
    assert (shape, fortran, dtype) == ((5, 530000, 3), False, np.dtype(np.float32))


def _is_direct(fd) -> bool:
    import fcntl

    return bool(fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_DIRECT)


def _refuse_direct_open(monkeypatch):
    real_open = os.open

    def no_direct(path, flags, *args):
        if flags & getattr(os, "O_DIRECT", 0):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_open(path, flags, *args)

    monkeypatch.setattr(npystream.os, "open", no_direct)


def _refuse_direct_writes(monkeypatch):
    real_write = os.write

    def refuse_direct(fd, data):
        if _is_direct(fd):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_write(fd, data)

    monkeypatch.setattr(npystream.os, "write", refuse_direct)


@pytest.mark.parametrize("refuse", [
    _refuse_direct_open,
    # some file systems open with O_DIRECT and refuse the writes (EINVAL): the header's write
    # says so and the same bytes are written buffered
    pytest.param(_refuse_direct_writes,
                 marks=pytest.mark.skipif(not hasattr(os, "O_DIRECT"), reason="no direct I/O on this system")),
], ids=["open", "writes"])
def test_falls_back_to_buffered_where_direct_io_is_refused(tmp_path, monkeypatch, refuse):
    refuse(monkeypatch)
    data = _rows((4, 10, 3), seed=1)
    with NpyWriter(tmp_path / "b.npy", data.shape, direct=True) as w:
        w.write(data)
    assert not w.direct
    np.testing.assert_array_equal(np.load(tmp_path / "b.npy"), data.astype(np.float32))


@pytest.mark.parametrize("direct", [True, False])
def test_a_failed_write_is_the_error_raised_and_everything_is_released(tmp_path, monkeypatch, direct):
    """A disk error in the middle of a file (raised on the writer's thread, as replay's sink
    raises it) comes out as itself, not as an error of the clean-up; the file and the staging
    buffer are released while it propagates (its traceback holds the writing frames)."""
    from concurrent.futures import ThreadPoolExecutor

    monkeypatch.setattr(npystream, "BUFFER", 3 * BLOCK)
    real_write = os.write
    calls = []

    def failing(fd, data):
        calls.append(fd)
        if len(calls) == 3:
            raise OSError(errno.EIO, "Input/output error")
        return real_write(fd, data)

    monkeypatch.setattr(npystream.os, "write", failing)
    data = _rows((7, 1001, 3))
    with pytest.raises(OSError) as info:
        with NpyWriter(tmp_path / "e.npy", data.shape, direct=direct) as w, \
                ThreadPoolExecutor(1) as sink:
            for k in range(7):
                sink.submit(w.write, data[k:k + 1]).result()
    assert info.value.errno == errno.EIO and len(calls) == 3
    assert w._fd is None
    if w.direct:
        assert w._buf.closed


@pytest.mark.parametrize("direct", [True, False])
def test_refuses_incomplete_files_and_wrong_rows(tmp_path, direct):
    with pytest.raises(RuntimeError, match="wrote 1 of 2"):
        with NpyWriter(tmp_path / "a.npy", (2, 3), direct=direct) as w:
            w.write(np.zeros((1, 3)))
    with pytest.raises(ValueError, match="do not fit"):
        NpyWriter(tmp_path / "b.npy", (2, 3), direct=direct).write(np.zeros((1, 4)))
    with pytest.raises(ValueError, match="do not fit"):
        with NpyWriter(tmp_path / "c.npy", (2, 3), direct=direct) as w:
            w.write(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="no open file"):
        NpyWriter(None, (2, 3)).write(np.zeros((1, 3)))


def test_rows_produced_where_placement_says_go_out_without_a_copy(tmp_path, monkeypatch):
    """Rows made in placement()'s memory at its offset are written from there (the staged partial
    block put in front of them); the file is the same as with ordinary writes, whatever mix of
    placed, unplaced and odd-sized chunks, in two alternating regions."""
    shape = (23, 337, 3)  # a row of 4044 bytes: chunks never end on a block
    data = np.random.default_rng(4).normal(size=shape).astype(np.float32)
    placed = []
    real = NpyWriter._write_placed
    monkeypatch.setattr(NpyWriter, "_write_placed", lambda self, region, n: (placed.append(n), real(self, region, n)))
    path = tmp_path / "p.npy"
    with NpyWriter(path, shape) as w:
        if not w.direct:
            pytest.skip("no direct I/O on this file system")
        start = 0
        for k, n in enumerate([5, 3, 7, 1, 7]):
            spot = w.placement(start, n, k % 2)
            assert spot is not None
            memory, offset = spot
            assert memory.ctypes.data % BLOCK == 0 and (BLOCK + start * 4044) % BLOCK == offset * 4
            if k == 3:  # a chunk made elsewhere: the ordinary, copying write
                w.write(data[start:start + n])
            else:
                rows = memory[offset:offset + n * 337 * 3].reshape(n, 337, 3)
                rows[...] = data[start:start + n]
                w.write(rows)
            start += n
    assert placed == [n * 4044 for n in (5, 3, 7, 7)]
    assert np.array_equal(np.load(path), data)
    assert NpyWriter(tmp_path / "b.npy", shape, direct=False).placement(0, 5) is None


def test_placement_memory_is_kept_in_the_callers_dict(tmp_path):
    """Writers given one ``regions`` dict reuse its memory (no fresh pages per file) and leave it
    open; each file is still whole."""
    regions = {}
    shape = (6, 101, 3)
    data = np.arange(np.prod(shape), dtype=np.float32).reshape(shape)
    addresses = []
    for name in ("a.npy", "b.npy"):
        with NpyWriter(tmp_path / name, shape, regions=regions) as w:
            if not w.direct:
                pytest.skip("no direct I/O on this file system")
            memory, offset = w.placement(0, 6, 0)
            addresses.append(memory.ctypes.data)
            rows = memory[offset:offset + data.size].reshape(shape)
            rows[...] = data
            w.write(rows)
        assert np.array_equal(np.load(tmp_path / name), data)
    assert addresses[0] == addresses[1] and not regions[0].closed
