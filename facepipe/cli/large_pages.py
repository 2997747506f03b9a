"""Transparent huge pages for the process's heap (Linux, glibc 2.35 or later).

A bake or a replay allocates gigabytes: the sparse factor, the large-scale basis, the parsed
meshes, the per-frame buffers. NumPy asks the kernel for huge pages for its own large arrays,
but the memory that glibc's ``malloc`` hands to SciPy, MKL (PARDISO's factor), the OpenCL
driver and Python's bytes comes in 4 KB pages: on the 530k-vertex bake that is about 850,000
page faults, each a trip through the kernel (dearer on a virtual machine). glibc's tunable
``glibc.malloc.hugetlb=1`` makes ``malloc`` advise huge pages too (where the system's
transparent huge pages are in ``madvise`` mode). A tunable is read when a process starts, so
the command line starts itself once more with it set, before it imports anything heavy; its
children (the examples' reader, Dask workers) inherit it.

``FACEPIPE_LARGE_PAGES=0`` (or ``false``, ``no``, ``off``) turns this off. Nothing changes where it
cannot help: another OS or C library, an older glibc, huge pages ``always`` on (or ``never``), or
the tunable already set.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

TUNABLE = "glibc.malloc.hugetlb"
OPT_OUT = "FACEPIPE_LARGE_PAGES"
THP_MODE = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def _glibc_version() -> tuple[int, ...] | None:
    """glibc's version as the C library itself reports it (``confstr``), or None for another
    C library or OS."""
    try:
        text = os.confstr("CS_GNU_LIBC_VERSION") or ""
    except (ValueError, OSError, AttributeError):  # no such name here: not glibc
        return None
    name, _, version = text.partition(" ")
    try:
        return tuple(int(part) for part in version.split(".")) if name == "glibc" else None
    except ValueError:
        return None


def _thp_mode() -> str | None:
    """The bracketed choice of ``always [madvise] never``, or None where unreadable."""
    try:
        text = THP_MODE.read_text()
    except OSError:
        return None
    start, end = text.find("["), text.find("]")
    return text[start + 1:end] if 0 <= start < end else None


def large_page_environment(environ=None) -> dict | None:
    """The environment with the tunable added, or None where it would change nothing."""
    environ = os.environ if environ is None else environ
    current = environ.get("GLIBC_TUNABLES", "")
    # set already (by an earlier start, or by the user): the restarted process stops here
    if TUNABLE in current or sys.platform != "linux":
        return None
    if environ.get(OPT_OUT, "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    version = _glibc_version()
    if version is None or version < (2, 35) or _thp_mode() != "madvise":
        return None
    return {**environ, "GLIBC_TUNABLES": f"{current}:{TUNABLE}=1" if current else f"{TUNABLE}=1"}


def restart_with_large_pages() -> None:
    """Replace this process by the same command with the tunable set (see the module's text);
    returns only where that would change nothing, or where the restart fails."""
    environment = large_page_environment()
    if environment is None or not sys.executable:  # (an embedding interpreter may not know its binary)
        return
    argv = list(getattr(sys, "orig_argv", [])) or [sys.executable, *sys.argv]
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, [sys.executable, *argv[1:]], environment)
    except OSError:  # the command goes on as it is: only slower
        return
