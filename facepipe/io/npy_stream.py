"""Writing a large ``.npy`` file as a stream of rows, around the page cache where the system allows.

A replay writes ~25 MB per frame at 530k vertices, far more than anything reads back soon.
Buffered writes pass all of it through the page cache: the copy and the cache's page
allocation can cost as much CPU as the evaluation itself on a machine with few cores
(most where the cache has to grow into memory not used before), and a long take pushes
everything else out of the cache. So on Linux the rows go to the disk with ``O_DIRECT``
through one reused, page-aligned buffer: the disk's speed is the limit, and the CPU cost is a
memcpy (``make bench`` measures both ways of writing). Where direct I/O is not available (other systems, tmpfs, some
network and copy-on-write file systems refuse it), the same bytes are written buffered.

The header is padded to one 4 KiB block (a valid ``.npy`` 1.0 header: numpy pads to any
length as long as the text ends with a newline), so the data starts on a block boundary.
"""

from __future__ import annotations

import errno
import mmap
import os

import numpy as np

BLOCK = 4096  # direct I/O alignment: offsets, lengths and memory (covers 512-byte sectors too)
BUFFER = 16 << 20  # bytes staged per direct write


def npy_header(shape: tuple, dtype, size: int = BLOCK) -> bytes:
    """A ``.npy`` 1.0 header of exactly ``size`` bytes for a C-order array."""
    text = repr({"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
                 "shape": tuple(int(n) for n in shape)})
    prefix = np.lib.format.MAGIC_PREFIX + bytes([1, 0])
    room = size - len(prefix) - 2
    if len(text) + 1 > room or room > 0xFFFF:
        raise ValueError(f"a .npy header for shape {shape} does not fit in {size} bytes")
    text = text.encode("latin1").ljust(room - 1) + b"\n"
    return prefix + len(text).to_bytes(2, "little") + text


class NpyWriter:
    """Write a ``.npy`` file of known shape sequentially: the header, then rows in order.

    Memory stays bounded for any take length (nothing is mapped); ``close`` checks that every
    row was written. ``path=None`` makes a writer that accepts nothing (an absent output).
    ``direct``: try ``O_DIRECT`` (default: where the system has it); ``self.direct`` says
    whether it is in use. ``regions``: a dict in which :meth:`placement` keeps its memory, to be
    reused by the next writer given the same dict (one producer, one file at a time).

    Example
    -------
    >>> with NpyWriter("positions.npy", (T, V, 3)) as w:   # doctest: +SKIP
    ...     w.write(chunk)                                  # (n, V, 3), any float dtype
    """

    def __init__(self, path, shape: tuple, dtype=np.float32, direct: bool | None = None, regions: dict | None = None):
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        self.rows = 0
        # placement memory: the caller's dict when given (kept and reused by later writers, so a
        # producer that writes file after file does not fault fresh pages in for each), else ours
        self._own_regions = regions is None
        self._regions: dict = {} if regions is None else regions
        self.direct = False
        self._fd = None
        self._staged = 0  # bytes waiting in the buffer (direct I/O)
        if path is None:
            return
        header = npy_header(self.shape, self.dtype)
        self._size = len(header) + int(np.prod(self.shape)) * self.dtype.itemsize
        if direct is None:
            direct = hasattr(os, "O_DIRECT")
        if direct:
            self._open_direct(path, header)
        if not self.direct:
            self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_BINARY", 0), 0o666)
            self._write_all(header)

    def _open_direct(self, path, header: bytes) -> None:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_DIRECT, 0o666)
        except OSError as exc:
            if exc.errno in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
                return  # this file system does not do direct I/O: buffered
            raise
        self._fd = fd
        self._buf = mmap.mmap(-1, BUFFER)  # page-aligned memory, reused for every write
        self._view = np.frombuffer(self._buf, dtype=np.uint8)
        self._view[:len(header)] = np.frombuffer(header, dtype=np.uint8)
        self._staged = len(header)
        try:
            self._flush_blocks()  # the header block: a file system that refuses direct writes says so now
        except OSError as exc:
            self._fd = None
            os.close(fd)
            self._view = None
            self._buf.close()
            if exc.errno != errno.EINVAL:
                raise
            return
        self.direct = True

    def placement(self, start: int, n: int, index: int = 0):
        """Memory to produce rows start:start+n in so that :meth:`write` sends them to the disk with
        no copy: (memory, offset) — a page-aligned 1-D array of this writer's dtype and the
        element offset where row ``start`` must begin, so that the rows sit on the file's block
        grid — or None where the writer is not direct. ``index`` names one of several regions in
        use at once (a producer fills one while the writer writes another); each is reused by
        later calls with the same index. Rows produced there are written by ``write(rows)`` with
        ``rows`` that view of the memory, in the file's order as always.
        """
        if not self.direct:
            return None
        row_bytes = int(np.prod(self.shape[1:])) * self.dtype.itemsize
        lead = (BLOCK + start * row_bytes) % BLOCK  # where the rows fall within their first block
        need = -(-(lead + n * row_bytes) // BLOCK) * BLOCK
        region = self._regions.get(index)
        if region is None or len(region) < need:
            if region is not None:
                try:
                    region.close()
                except BufferError:  # still viewed by a producer; freed with it
                    pass
            region = self._regions[index] = mmap.mmap(-1, need)
        if lead % self.dtype.itemsize:
            return None
        return np.frombuffer(region, dtype=self.dtype), lead // self.dtype.itemsize

    def _placed_region(self, rows: np.ndarray):
        """The region ``rows`` were produced in at the offset :meth:`placement` gave for this
        writer's position, or None."""
        address = rows.ctypes.data
        for region in self._regions.values():
            base = np.frombuffer(region, dtype=np.uint8).ctypes.data
            if base + self._staged == address and self._staged + rows.nbytes <= len(region):
                return region
        return None

    def _write_placed(self, region, nbytes: int) -> None:
        """Rows already in ``region`` after the staged partial block: that block goes in front,
        the whole blocks to the disk straight from the region, the last partial one is staged."""
        view = np.frombuffer(region, dtype=np.uint8)
        staged = self._staged
        view[:staged] = self._view[:staged]
        end = staged + nbytes
        whole = end - end % BLOCK
        if whole:
            with memoryview(region)[:whole] as blocks:
                self._write_all(blocks)
        self._view[:end - whole] = view[whole:end]
        self._staged = end - whole

    def write(self, rows: np.ndarray) -> None:
        rows = np.ascontiguousarray(rows, dtype=self.dtype)
        if rows.shape[1:] != self.shape[1:] or self.rows + rows.shape[0] > self.shape[0]:
            raise ValueError(f"rows {rows.shape} do not fit {self.shape} after {self.rows} rows")
        if self._fd is None:
            raise ValueError("this writer has no open file (no path, or closed)")
        region = self._placed_region(rows) if self.direct and self._regions else None
        if region is not None:  # produced where placement() said: no copy
            self._write_placed(region, rows.nbytes)
            self.rows += rows.shape[0]
            return
        data = memoryview(rows.reshape(-1)).cast("B")
        if not self.direct:
            self._write_all(data)
        else:
            src = np.frombuffer(data, dtype=np.uint8)
            done = 0
            while done < len(src):
                n = min(len(src) - done, BUFFER - self._staged)
                self._view[self._staged:self._staged + n] = src[done:done + n]
                self._staged += n
                done += n
                self._flush_blocks()
        self.rows += rows.shape[0]

    def _flush_blocks(self) -> None:
        """Write the staged whole blocks; the partial last block moves to the buffer's start."""
        whole = self._staged - self._staged % BLOCK
        if whole:
            with memoryview(self._buf)[:whole] as blocks:
                self._write_all(blocks)
            tail = self._staged - whole
            self._view[:tail] = self._view[whole:self._staged]
            self._staged = tail

    def _write_all(self, data) -> None:
        rest = memoryview(data)
        try:
            while len(rest):
                rest = rest[os.write(self._fd, rest):]
        finally:
            # a write error's traceback keeps this frame: without the view in it, the staging
            # buffer can still be closed while that error propagates
            rest.release()

    def close(self) -> None:
        if self._fd is None:
            return
        try:
            if self.direct and self._staged:
                # the last partial block goes out whole (direct writes are whole blocks); the
                # file is then cut back to its size
                pad = -self._staged % BLOCK
                self._view[self._staged:self._staged + pad] = 0
                self._staged += pad
                self._flush_blocks()
                os.ftruncate(self._fd, self._size)
        finally:
            self._release()
        if self.rows != self.shape[0]:
            raise RuntimeError(f"wrote {self.rows} of {self.shape[0]} rows")

    def _release(self) -> None:
        if self._fd is not None:
            # forgotten before it is closed: were close() to fail, no later call (``__del__``)
            # would close the number again, by then perhaps another file's
            fd, self._fd = self._fd, None
            os.close(fd)
        if self.direct:
            self._view = None
            try:
                self._buf.close()
            except BufferError:  # still viewed (an error's traceback holds a slice): freed with it
                pass
        if self._own_regions:
            for region in self._regions.values():
                try:
                    region.close()
                except BufferError:  # still viewed by a producer; freed with it
                    pass
            self._regions = {}

    def __del__(self):
        try:
            self._release()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self._release()
