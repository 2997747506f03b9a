"""Choosing the replay backend: OpenCL when asked for, or (auto) when a device works; else NumPy."""

from __future__ import annotations

from facepipe.errors import InputError


def opencl_or_fallback(rep, backend: str, build, fallback):
    """``build()`` (an OpenCL evaluator), or ``fallback()`` with a note when OpenCL is unavailable
    or its driver fails, unless the user asked for OpenCL (``backend == "opencl"``: the error stands)."""
    from facepipe.opencl import OpenCLUnavailable

    try:
        evaluator = build()
    except OpenCLUnavailable as exc:
        if backend == "opencl":
            raise
        rep.say(f"note: {str(exc).splitlines()[0]}; replaying with the NumPy backend")
        return fallback()
    except InputError:
        raise
    except Exception as exc:  # a driver that lists a device but cannot build or run the kernels
        if backend == "opencl":
            raise
        rep.say(f"note: OpenCL failed ({exc.__class__.__name__}: {exc}); replaying with the NumPy backend")
        return fallback()
    rep.say(f"OpenCL device: {evaluator.device}")
    return evaluator
