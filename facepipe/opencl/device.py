"""Choosing and opening an OpenCL device, and building the replay kernels once per process.

Device choice, first match wins:

1. ``--device SPEC`` (the ``device`` argument): ``P`` or ``P:D`` (platform and device index, as
   ``PYOPENCL_CTX``), ``gpu`` / ``cpu``, or a case-insensitive part of the platform or device
   name (``pocl``, ``nvidia``, ``a100``);
2. the ``PYOPENCL_CTX`` environment variable (same forms as pyopencl understands);
3. the first GPU of any platform;
4. the first CPU device, PoCL's first (it ships with facepipe as a PyPI wheel, so a machine
   without any vendor driver still has it).

Choices 3 and 4 pass over devices whose compiler cannot build a trivial kernel (:func:`compiles`):
the PyPI PoCL's LLVM 14 does not know some newer CPUs; a distribution's PoCL (Debian's
``pocl-opencl-icd``) beside it then serves.

No platform at all (or no pyopencl) is an :class:`OpenCLUnavailable`, an ``InputError``: the
CLI exits with status 2 and the hint to use ``--backend numpy``.
"""

from __future__ import annotations

import os
import threading
from importlib import resources

from facepipe.errors import InputError

HINT = ("use --backend numpy, or install an OpenCL driver (pip install pocl-binary-distribution; where its "
        "LLVM does not know the CPU, your distribution's PoCL, e.g. apt install pocl-opencl-icd)")

_lock = threading.Lock()
_contexts: dict = {}
_programs: dict = {}


class OpenCLUnavailable(InputError):
    """No usable OpenCL platform/device: say so and point at the NumPy backend."""

    def __init__(self, message: str):
        super().__init__(message, hint=HINT)


def _cl():
    try:
        import pyopencl as cl  # lazily: facepipe runs without an OpenCL driver
    except Exception as exc:  # ImportError, or a broken ICD loader
        raise OpenCLUnavailable(f"OpenCL is not available: pyopencl cannot be imported ({exc})") from None
    return cl


def list_devices() -> list[tuple[int, int, object]]:
    """Every (platform index, device index, pyopencl.Device); empty when there is no platform."""
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except Exception:  # clGetPlatformIDs fails with PLATFORM_NOT_FOUND_KHR when no ICD is installed
        return []
    found = []
    for pi, platform in enumerate(platforms):
        try:
            devices = platform.get_devices()
        except Exception:
            continue
        found.extend((pi, di, d) for di, d in enumerate(devices))
    return found


def device_label(device) -> str:
    """'NAME (PLATFORM, GPU|CPU, N compute units)' — what replay.json and the logs record."""
    cl = _cl()
    kind = "GPU" if device.type & cl.device_type.GPU else "CPU" if device.type & cl.device_type.CPU else "other"
    return f"{device.name.strip()} ({device.platform.name.strip()}, {kind}, {device.max_compute_units} compute units)"


def _match(spec: str, devices: list) -> object | None:
    cl = _cl()
    spec = spec.strip()
    parts = spec.split(":")
    if all(p.isdigit() for p in parts) and len(parts) <= 2:
        pi = int(parts[0])
        di = int(parts[1]) if len(parts) == 2 else 0
        for p, d, dev in devices:
            if p == pi and d == di:
                return dev
        return None
    low = spec.lower()
    if low in ("gpu", "cpu"):
        want = cl.device_type.GPU if low == "gpu" else cl.device_type.CPU
        return next((dev for _, _, dev in devices if dev.type & want), None)
    for _, _, dev in devices:
        if low in dev.name.lower() or low in dev.platform.name.lower():
            return dev
    return None


def select_device(spec: str | None = None):
    """The pyopencl.Device to use (see the module docstring for the order of choice)."""
    cl = _cl()
    devices = list_devices()
    if not devices:
        raise OpenCLUnavailable("no OpenCL platform or device was found")
    names = ", ".join(f"{p}:{d} {dev.name.strip()}" for p, d, dev in devices)
    for source, value in (("--device", spec), ("PYOPENCL_CTX", os.environ.get("PYOPENCL_CTX"))):
        if value:
            dev = _match(value, devices)
            if dev is None:
                raise InputError(f"{source} {value!r} matches no OpenCL device (found: {names})",
                                 hint="give P:D, gpu, cpu or part of a device name; or use --backend numpy")
            return dev
    working = [(p, d, dev) for p, d, dev in devices if compiles(dev)]
    if not working:
        raise OpenCLUnavailable(f"no OpenCL device here can compile kernels (found: {names}; "
                                f"{_compile_errors[devices[0][2].int_ptr]})")
    gpu = next((dev for _, _, dev in working if dev.type & cl.device_type.GPU), None)
    if gpu is not None:
        return gpu
    cpus = [dev for _, _, dev in working if dev.type & cl.device_type.CPU]
    pocl = [dev for dev in cpus if "portable computing language" in dev.platform.name.lower()]
    return (pocl or cpus or [working[0][2]])[0]


_compile_errors: dict = {}
_probe_lock = threading.Lock()


def compiles(device) -> bool:
    """Whether ``device``'s compiler builds a trivial kernel (checked once per process). A driver
    can list a device it cannot compile for: PoCL whose LLVM is older than the CPU names it
    'generic' and refuses every kernel; the automatic choice passes such a device over (its
    reason kept for the error when none is left), so another driver's device serves."""
    cl = _cl()
    with _probe_lock:
        if device.int_ptr not in _compile_errors:
            try:
                cl.Program(cl.Context([device]), "__kernel void probe(__global float *a) { a[0] = 1.0f; }").build()
                _compile_errors[device.int_ptr] = None
            except Exception as exc:  # a driver's build failure: its message is the reason
                reason = " ".join(str(exc).split())[:300]
                _compile_errors[device.int_ptr] = f"{device.platform.version.strip()}: {reason}"
        return _compile_errors[device.int_ptr] is None


def open_device(spec: str | None = None):
    """(context, device) for ``spec``, one context per device per process."""
    device = select_device(spec)
    return device_context(device), device


def device_context(device):
    """The process's one context on ``device`` (a pyopencl.Device)."""
    cl = _cl()
    with _lock:
        key = device.int_ptr
        if key not in _contexts:
            _contexts[key] = cl.Context([device])
        return _contexts[key]


def opencl_available(spec: str | None = None) -> bool:
    """True when a device can be selected (one that compiles a trivial kernel, unless asked for by name)."""
    try:
        select_device(spec)
        return True
    except InputError:
        return False


def kernel_source(name: str = "replay.cl") -> str:
    """The text of a kernel file shipped as package data."""
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def build_program(context, defines: dict, name: str = "replay.cl"):
    """Compile a kernel file with ``-D`` constants, once per (context, source, constants) per process.

    The key holds the source text itself, not only the file's name: a source changed in the same
    process (an edited kernel, a benchmark's variant of it) is compiled, not served the program
    built from the old text."""
    cl = _cl()
    options = tuple(f"-D{k}={v}" for k, v in sorted(defines.items())) + ("-cl-mad-enable",)
    source = kernel_source(name)
    key = (context.int_ptr, name, source, options)
    with _lock:
        program = _programs.get(key)
        if program is None:
            try:
                program = cl.Program(context, source).build(options=list(options))
            except cl.RuntimeError:
                device = context.devices[0]
                if compiles(device):
                    raise  # the kernel's own error: the driver builds other programs
                where = " for this CPU" if device.type & cl.device_type.CPU else ""
                raise OpenCLUnavailable(f"the OpenCL driver {device.platform.version.strip()!r} cannot compile "
                                        f"kernels{where} ({_compile_errors[device.int_ptr]})") from None
            _programs[key] = program
        return program
