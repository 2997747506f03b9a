"""Choosing where replay evaluates: OpenCL when asked for, or (auto) when a device works; else the
NumPy reference, with the reason."""

from __future__ import annotations

from facepipe.errors import InputError


def opencl_or_fallback(backend: str, build, fallback, note=None):
    """``build()`` (an OpenCL evaluator), or ``fallback()`` when OpenCL is unavailable or its driver
    fails, unless the user asked for OpenCL (``backend == "opencl"``: the error stands).
    ``note(text)`` is told why it fell back."""
    from facepipe.opencl import OpenCLUnavailable

    note = note or (lambda text: None)
    try:
        return build()
    except OpenCLUnavailable as exc:
        if backend == "opencl":
            raise
        note(f"{str(exc).splitlines()[0]}; replaying with the NumPy backend")
    except InputError:
        raise
    except Exception as exc:  # a driver that lists a device but cannot build or run the kernels
        if backend == "opencl":
            raise
        note(f"OpenCL failed ({exc.__class__.__name__}: {exc}); replaying with the NumPy backend")
    return fallback()


def marker_evaluator(model, backend: str, device: str | None, chunk: int, note=None):
    """The marker replay's evaluator for ``backend`` (auto, opencl or numpy), see :func:`opencl_or_fallback`."""
    from facepipe.pipeline.replay import NumpyEvaluator

    if backend == "numpy":
        return NumpyEvaluator(model)
    from facepipe.opencl import OpenCLEvaluator

    return opencl_or_fallback(backend, lambda: OpenCLEvaluator(model, device=device, chunk=chunk),
                              lambda: NumpyEvaluator(model), note)


def cache_evaluator(details, backend: str, device: str | None, chunk: int, note=None):
    """The evaluator of a mesh cache replayed as a take: the OpenCL cache engine for ``details``
    (a :class:`~facepipe.pipeline.cache_replay.CacheDetails`) where :func:`opencl_or_fallback`
    allows, else ``details`` itself (NumPy)."""
    if backend == "numpy":
        return details
    from facepipe.opencl.cache_engine import OpenCLCacheEvaluator

    return opencl_or_fallback(backend, lambda: OpenCLCacheEvaluator(details.model, details.cache, details.pose, details,
                                                                    device=device, chunk=chunk),
                              lambda: details, note)
