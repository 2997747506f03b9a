"""The OpenCL replay path: kernels shipped as package data (``*.cl``) and their host code; and
the bake's geodesic distances on the CPU device (:mod:`facepipe.opencl.geodesics`).

``OpenCLEvaluator`` has NumpyEvaluator's interface (``evaluate(handles, with_large=False)``,
``backend``, ``device``, ``stage_seconds``) plus ``stream`` for pipelined replay; the device is
chosen as :mod:`facepipe.opencl.device` describes. pyopencl is imported only when a device is
opened, so ``import facepipe.opencl`` is cheap and works without OpenCL.
"""

from facepipe.opencl.device import (HINT, OpenCLUnavailable, device_label, list_devices, opencl_available, select_device)
from facepipe.opencl.adjacency import vertex_face_ring, vertex_fans
from facepipe.opencl.engine import OpenCLEvaluator, compact_edges, locality_order

__all__ = ["HINT", "OpenCLEvaluator", "OpenCLUnavailable", "compact_edges", "device_label", "list_devices",
           "locality_order", "opencl_available", "select_device", "vertex_face_ring", "vertex_fans"]
