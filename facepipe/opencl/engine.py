"""The OpenCL replay engine: NumpyEvaluator's evaluation, per chunk of frames on a device.

Per chunk of C frames (C = ``chunk``, padded to the kernels' vector width):

1. host: handle displacements U (H, 3, C), strain features (F, C), PSD distances (P, C), the
   novelty gate's site confidences (F, C) and the head motion (12, C) — O(C·(H + P·F)) numbers;
2. ``large_scale``: large = rest + B·U, every row of B read once per chunk;
3. ``detail``: per vertex and frame, the normal (summed over the vertex's faces through a CSR
   adjacency), the tangent frame, the WPSD distances over the vertex's ≤ K edges (or the PSD
   ones), the RBF sum, local → world, the head motion, and the store in (C, V, 3) order;
4. optionally ``final_normals``: unit normals of the final surface, for export.

Chunks are pipelined (:meth:`OpenCLEvaluator.stream`): while the device computes chunk k, a
worker thread hands chunk k − 1 (mapped, not copied, on a CPU device) to the caller's sink, which
writes it to disk or copies it into memory. Device memory is a fixed set of chunk-sized buffers,
so any take length runs in bounded memory.

Arithmetic is float32 (the reference is float64); results agree to ~1e-6 of the mesh size.
"""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp

from facepipe.core.psd import psd_distances
from facepipe.core.strain import strain_features
from facepipe.opencl.adjacency import vertex_face_ring, vertex_fans
from facepipe.opencl.device import _cl, build_program, device_label, open_device
from scipy.sparse.csgraph import reverse_cuthill_mckee
from facepipe.core.psd import edge_weight_matrix, spread_subset
from facepipe.core.local_strain import StrainOperator, ring_strain_coefficients

METHOD_CODES = {"none": 0, "psd": 1, "wpsd": 2, "local_strain": 3}
RV = 4  # vertices per work-item in the B product: 4 rows × 3 coordinates of accumulators


# ----------------------------------------------------------------------------- mesh tables


def locality_order(faces: np.ndarray, n_vertices: int, mode="auto") -> np.ndarray | None:
    """A vertex order that keeps mesh neighbours close in memory (reverse Cuthill–McKee).

    The kernels gather the positions of every vertex's ring; when neighbours are far apart in
    the vertex order each gather is a cache miss. ``mode``: "auto" reorders only when RCM at
    least halves the mean index distance across mesh edges (a scan-ordered grid already is
    local; a shuffled or concatenated mesh is not), "rcm" always, "none" never, or an explicit
    (V,) permutation.

    Returns
    -------
    perm : (V,) int64 with perm[i] = the original vertex at position i, or None (keep the order).
    """
    if mode is None or (isinstance(mode, str) and mode == "none"):
        return None
    if not isinstance(mode, str):
        perm = np.asarray(mode, dtype=np.int64)
        if perm.shape != (n_vertices,) or not np.array_equal(np.sort(perm), np.arange(n_vertices)):
            raise ValueError("reorder: not a permutation of the vertices")
        return perm

    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    i = faces.ravel()
    j = np.roll(faces, -1, axis=1).ravel()
    g = sp.coo_matrix((np.ones(i.size, dtype=np.int8), (i, j)), shape=(n_vertices, n_vertices)).tocsr()
    perm = reverse_cuthill_mckee((g + g.T).tocsr(), symmetric_mode=True).astype(np.int64)
    if mode == "auto":
        inv = np.empty(n_vertices, dtype=np.int64)
        inv[perm] = np.arange(n_vertices)
        before = np.abs(i - j).mean() if i.size else 0.0
        after = np.abs(inv[i] - inv[j]).mean() if i.size else 0.0
        if not after * 2.0 < before:
            return None
    return perm


def compact_edges(edge_index: np.ndarray, edge_weight: np.ndarray):
    """Move each vertex's non-zero WPSD edges to the front: (index, weight, count (V,) int32).

    The kernel loops over ``count`` edges only (a dropped edge contributes nothing).
    """
    order = np.argsort(edge_weight == 0, axis=1, kind="stable")
    index = np.take_along_axis(edge_index, order, axis=1)
    weight = np.take_along_axis(edge_weight, order, axis=1)
    return (np.ascontiguousarray(index, dtype=np.int32), np.ascontiguousarray(weight, dtype=np.float32),
            (weight != 0).sum(axis=1).astype(np.int32))


def _site_gate(model):
    """The model's novelty gate with α replaced by the identity, so ``confidence`` gives per-site
    factors (Q, F), or None.

    The gate's confidence is α · s(f) (per-site factors s spread over the vertices by the WPSD
    weights); the kernel does the α-sum over the same compacted edge lists. Checked here on a few
    strain vectors and an even sample of vertices, so a gate that stops factoring this way fails
    loudly, not silently.
    """

    F = int(model.edges.shape[0])
    site_gate = model.novelty_gate(sp.identity(F, format="csr"))
    if site_gate is None:
        return None
    rows = spread_subset(model.n_vertices, 4096)
    alpha = edge_weight_matrix(model.edge_index[rows], model.edge_weight[rows], F)
    rng = np.random.default_rng(0)
    probe = rng.normal(scale=0.05, size=(3, F)) + model.basis_features[-1].astype(np.float64)
    # handle displacements for a gate that tests motion too: the last example's, perturbed
    moves = model.example_handles[-1].astype(np.float64) - model.rest[model.handle_vertices].astype(np.float64) \
        if model.example_handles is not None else np.zeros((len(model.handle_vertices), 3))
    moves = moves[None] + rng.normal(scale=0.05 * float(np.median(model.rest_lengths)), size=(3,) + moves.shape)
    expected = model.novelty_gate(alpha).confidence(probe, moves)
    got = np.asarray(alpha @ site_gate.confidence(probe, moves).T).T
    if not np.allclose(got, expected, rtol=1e-6, atol=1e-9):
        raise RuntimeError("the model's novelty gate is not α · (per-site factors): update facepipe/opencl")
    return site_gate


def _largest_divisor(n: int, limit: int) -> int:
    for d in range(max(1, min(n, limit)), 0, -1):
        if n % d == 0:
            return d
    return 1


def _check_destination(destination: np.ndarray | None, shape: tuple) -> None:
    if destination is not None and (destination.shape != shape or destination.dtype != np.float32
                                    or not destination.flags.c_contiguous):
        raise ValueError(f"destination: a C-ordered float32 array of shape {shape} is needed, "
                         f"not {destination.dtype} {destination.shape}")


# ----------------------------------------------------------------------------- the engine


class _Slot:
    """Device buffers of one chunk in flight: inputs, outputs, and the host arrays being uploaded."""

    def __init__(self):
        self.inputs = {}
        self.outputs = {}
        self.host = ()
        # this chunk's final-positions buffer: outputs["final"], or one over the caller's memory,
        # and where in it (floats) the positions start
        self.final = None
        self.final_offset = 0


class OpenCLEvaluator:
    """Evaluate a model on frames of handle positions with OpenCL (same interface as NumpyEvaluator).

    Parameters
    ----------
    model : a loaded :class:`facepipe.io.model_file.Model`.
    device : device spec (see :mod:`facepipe.opencl.device`); None: PYOPENCL_CTX, else the first
        GPU, else PoCL's CPU device.
    chunk : frames per launch (rounded up to the vector width); B is read once per chunk.
    reorder : vertex order for locality, see :func:`locality_order` (output is always in the
        rest mesh's order).
    vector_width : frames per work-item; default on a CPU the device's preferred float vector
        width when it is 16 (AVX-512) and the chunk has 16 frames or more, else 8 (AVX2 lanes); 1 on
        a GPU (a warp covers 32 frames of one vertex).
    slots : chunks in flight (2: one computing while the previous one is written).
    detail_weights : optional (weights (V, P, 3), const (V, 3)) replacing the model's RBF weights
        and constant (PSD/WPSD; a local-strain model's kernel weights and None): the band of the
        details a point cache lacks (:func:`facepipe.core.detail_bands.banded_detail_model`).
    _stages : benchmark only: 3 (default) computes everything; 1 skips the fine scale, 2 the
        frames, 0 both (wrong results, used to time the stages by difference).

    Attributes
    ----------
    backend : "opencl"; device : the device's description (written to replay.json).
    stage_seconds : device time of the ``large_scale`` and fused ``frames_fine_scale`` kernels
        (profiling events), ``normals`` when asked for, and ``output`` (time in the sink).

    Example
    -------
    >>> ev = OpenCLEvaluator(load_model("model.npz"))        # doctest: +SKIP
    >>> ev.evaluate(handles).shape                           # doctest: +SKIP
    (32, 20000, 3)
    """

    backend = "opencl"
    takes_placement = True  # stream(placement=): final positions produced in the caller's memory

    def __init__(self, model, device: str | None = None, chunk: int = 32, reorder="auto",
                 vector_width: int | None = None, slots: int = 2, detail_weights: tuple | None = None,
                 _stages: int = 3):
        cl = _cl()
        self.model = model
        self.context, self.cl_device = open_device(device)
        self.device = device_label(self.cl_device)
        dev = self.cl_device
        gpu = bool(dev.type & cl.device_type.GPU)
        # whether evaluating takes the host's own cores (a CPU device): work overlapped with it
        # then only competes for them
        self.on_host_cores = not gpu
        # a CPU's widest vector (PoCL reports 16 floats where it compiles for AVX-512, 8 for AVX2):
        # the B product runs at that width's FMA rate; never wider than the chunk asked for
        self.vw = int(vector_width or (1 if gpu else 16 if dev.preferred_vector_width_float >= 16
                                       and int(chunk) >= 16 else 8))
        if self.vw not in (1, 2, 4, 8, 16):
            raise ValueError(f"vector_width {self.vw} is not 1, 2, 4, 8 or 16")
        self.chunk = max(self.vw, -(-int(chunk) // self.vw) * self.vw)
        self.n_slots = max(1, int(slots))
        self.queue = cl.CommandQueue(self.context, properties=cl.command_queue_properties.PROFILING_ENABLE)
        self.stage_seconds = {"large_scale": 0.0, "frames_fine_scale": 0.0, "output": 0.0}

        V = model.n_vertices
        H = int(model.handle_vertices.shape[0])
        method = model.method
        self.V, self.H, self.method = V, H, method
        self.perm = locality_order(model.triangles, V, reorder)
        order = self.perm if self.perm is not None else np.arange(V)
        inv = np.empty(V, dtype=np.int64)
        inv[order] = np.arange(V)

        # host-side constants for the per-chunk tables (float64, as the reference computes them)
        self.rest_handles = model.rest[model.handle_vertices].astype(np.float64)
        self.edges = model.edges.astype(np.int64)
        self.rest_lengths = model.rest_lengths.astype(np.float64)
        self.basis = model.basis_features.astype(np.float64)
        # the novelty gate (novelty.NoveltyGate) scales the details by a per-vertex confidence α · s(f)
        # over per-site factors s: the host computes s per frame, the kernel the α-weighted sum
        self.gate = None
        if method not in ("none", "local_strain") and float(model.meta.get("novelty_tau", 0) or 0) > 0:
            self.gate = _site_gate(model)
        P = self.basis.shape[0] if method != "none" else 1
        if method == "local_strain":
            P = int(model.strain_samples.shape[1])
        F = max(1, int(self.edges.shape[0]))
        K = int(model.edge_index.shape[1]) if model.edge_index.ndim == 2 and model.edge_index.shape[1] else 1
        self.P, self.F, self.K = P, F, K

        # work-group shapes: frames × vertices; vertex counts padded to whole groups
        max_wg = int(dev.max_work_group_size)
        lanes = self.chunk // self.vw
        self.local0 = _largest_divisor(lanes, max(1, max_wg // 4))
        self.local1 = max(1, min(16 if not gpu else 8, max_wg // self.local0))
        self.Vp = -(-V // (RV * self.local1)) * (RV * self.local1)
        self.Vd = -(-V // self.local1) * self.local1

        program = build_program(self.context, {"VW": self.vw, "H": H, "RV": RV, "METHOD": METHOD_CODES[method],
                                               "P": P, "K": K, "F": F, "GATE": int(self.gate is not None),
                                               "STAGES": int(_stages), "PREFETCH": int(not gpu)})
        self._k_large = cl.Kernel(program, "large_scale")
        self._k_detail = cl.Kernel(program, "detail")
        self._k_normals = cl.Kernel(program, "final_normals")

        B = np.zeros((self.Vp, H), dtype=np.float32)
        B[:V] = model.B[order]
        rest = np.zeros((self.Vp, 3), dtype=np.float32)
        rest[:V] = model.rest[order]
        faces = inv[model.triangles.astype(np.int64)]
        fan_ptr, fan = vertex_fans(faces, V)
        self.fan_entries = int(fan.shape[0])  # (the benchmark's byte and FLOP counts)
        # each face's own entry: only the local-strain kernel's sums need it
        ptr, ring = vertex_face_ring(faces, V) if method == "local_strain" \
            else (np.zeros(V + 1, np.int32), np.zeros((1, 2), np.int32))
        neighbor = inv[model.frame_neighbors.astype(np.int64)[order]].astype(np.int32)
        if method == "none":
            ei = np.zeros((V, 1), np.int32)
            ew = np.zeros((V, 1), np.float32)
            count = np.zeros(V, np.int32)
            rbf_w = np.zeros((V, 1, 3), np.float32)
            rbf_c = np.zeros((V, 3), np.float32)
            basis = np.zeros((1, F), np.float32)
            wpsd_const = np.zeros((V, 1), np.float32)
        else:
            ei, ew, count = compact_edges(model.edge_index[order], model.edge_weight[order])
            w, c = (model.rbf_weights, model.rbf_const) if detail_weights is None or method == "local_strain" \
                else detail_weights
            rbf_w = np.ascontiguousarray(np.asarray(w)[order], dtype=np.float32)
            rbf_c = np.ascontiguousarray(np.asarray(c)[order], dtype=np.float32)
            basis, wpsd_const = self._wpsd_tables(ei, ew) if method == "wpsd" \
                else (np.zeros((1, F), np.float32), np.zeros((V, 1), np.float32))  # (PSD: distances from the host)
        strain = self._local_strain_tables(model, order, inv)
        if method == "local_strain":  # (a cache take's added bands: detail_weights' kernel weights)
            w = model.strain_weights if detail_weights is None else detail_weights[0]
            rbf_w = np.ascontiguousarray(np.asarray(w)[order], dtype=np.float32)
        self._static = {name: self._upload(a) for name, a in {
            "B": B, "rest": rest, "ring_ptr": ptr, "ring": ring, "fan_ptr": fan_ptr, "fan": fan,
            "neighbor": neighbor, "edge_count": count,
            "edge_index": ei, "edge_weight": ew, "basis": basis, "rbf_weights": rbf_w, "rbf_const": rbf_c,
            "out_index": order.astype(np.int32), "wpsd_const": wpsd_const, **strain}.items()}
        C = self.chunk
        self._large = self._buffer(self.Vp * 3 * C * 4)
        self._final_vc = None
        self._slots = [_Slot() for _ in range(self.n_slots)]
        self.static_bytes = int(sum(b.size for b in self._static.values()))
        # a writer's placement memory, kept between replays (NpyWriter(regions=)): pages faulted
        # in once per evaluator, not once per file
        self.placement_regions: dict = {}

    def _wpsd_tables(self, edge_index: np.ndarray, edge_weight: np.ndarray):
        """The WPSD kernel's expanded distances (replay.cl): the basis as −2 b (P, F) and per vertex
        Σ_k α_k b_{p,e_k}² (V, P); float32. Both from the basis and weights as the kernel holds them
        (float32), so at a pose's own features the three sums agree but for their rounding."""
        basis = self.basis.astype(np.float32)
        const = np.empty((edge_index.shape[0], basis.shape[0]), np.float32)
        alpha = edge_weight.astype(np.float64)
        for p, row in enumerate(basis.astype(np.float64)):  # one pose at a time: a (V, K) temporary
            const[:, p] = (alpha * row[edge_index] ** 2).sum(axis=1)
        return np.ascontiguousarray(-2.0 * basis), const

    def _local_strain_tables(self, model, order: np.ndarray, inv: np.ndarray) -> dict:
        """The local-strain model's tables in the engine's vertex order (placeholders for the other
        methods): per ring entry the strain's coefficients over its edges' Gram matrix, per vertex
        the strain's constant and the training poses' strains; sets ``strain_inv`` = −1 / (2σ²)."""
        self.strain_inv = 0.0
        if self.method != "local_strain":
            return {"strain_coeff": np.zeros(9, np.float32), "strain_const": np.zeros(3, np.float32),
                    "strain_samples": np.zeros(3, np.float32)}
        rest = model.rest.astype(np.float64)[order]
        faces = inv[model.triangles.astype(np.int64)]
        op = StrainOperator.of(rest, faces, inv[model.frame_neighbors.astype(np.int64)[order]])
        coeff, const = ring_strain_coefficients(rest, op)
        self.strain_inv = -0.5 / float(model.meta["strain_width"]) ** 2
        return {"strain_coeff": coeff.reshape(-1, 9).astype(np.float32), "strain_const": const.astype(np.float32),
                "strain_samples": np.ascontiguousarray(model.strain_samples[order], dtype=np.float32)}

    # ------------------------------------------------------------------ buffers

    def _upload(self, array: np.ndarray):
        cl = _cl()
        array = np.ascontiguousarray(array)
        if array.size == 0:
            array = np.zeros(1, dtype=array.dtype)
        return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=array)

    def _buffer(self, nbytes: int, host: bool = False):
        cl = _cl()
        flags = cl.mem_flags.READ_WRITE
        if host:  # output the host maps: on a CPU device the map is the buffer itself, no copy
            flags |= cl.mem_flags.ALLOC_HOST_PTR
        return cl.Buffer(self.context, flags, size=max(4, int(nbytes)))

    def _slot_buffers(self, slot: _Slot, with_large: bool, with_normals: bool, with_final: bool = True) -> None:
        C, V = self.chunk, self.V
        if not slot.inputs:
            sizes = {"U": self.H * 3 * C, "features": self.F * C, "psd_r": self.P * C, "site": self.F * C,
                     "rigid": 12 * C}
            slot.inputs = {k: self._buffer(4 * n) for k, n in sizes.items()}
        frame_bytes = C * V * 3 * 4
        # (no device-side final buffer while the kernel writes the positions into host memory)
        for name, wanted in (("final", with_final), ("large", with_large), ("normals", with_normals)):
            if wanted and name not in slot.outputs:
                slot.outputs[name] = self._buffer(frame_bytes, host=True)
        if with_normals and self._final_vc is None:
            self._final_vc = self._buffer(self.Vp * 3 * C * 4)

    # ------------------------------------------------------------------ per-chunk tables

    def _tables(self, head: np.ndarray, R: np.ndarray | None, t: np.ndarray | None) -> dict:
        """Host-side inputs of one chunk, padded to C frames (padding frames: rest pose)."""
        n, C = head.shape[0], self.chunk
        U = np.zeros((self.H, 3, C), dtype=np.float32)
        U[:, :, :n] = np.transpose(head - self.rest_handles, (1, 2, 0))
        features = np.zeros((self.F, C), dtype=np.float32)
        psd_r = np.zeros((self.P, C), dtype=np.float32)
        site = np.zeros((self.F, C), dtype=np.float32)
        if self.method in ("psd", "wpsd") and self.edges.shape[0]:
            f = strain_features(head, self.edges, self.rest_lengths)  # (n, F) float64
            features[:, :n] = f.T
            if self.method == "psd":
                psd_r[:, :n] = psd_distances(f, self.basis).T
            if self.gate is not None:  # on the host, the NumPy reference's own code (float64)
                site[:, :n] = self.gate.confidence(f, head - self.rest_handles).T
        rigid = np.zeros((12, C), dtype=np.float32)
        rigid[[0, 4, 8]] = 1.0
        if R is not None:
            rigid[:9, :n] = np.asarray(R, dtype=np.float64).reshape(n, 9).T
        if t is not None:
            rigid[9:, :n] = np.asarray(t, dtype=np.float64).reshape(n, 3).T
        return {"U": U, "features": features, "psd_r": psd_r, "site": site, "rigid": rigid}

    # ------------------------------------------------------------------ launch

    def _enqueue(self, slot: _Slot, head, R, t, with_large: bool, with_normals: bool) -> dict:
        """Upload a chunk's tables and launch its kernels; returns the kernels' events."""
        ev_large = self._launch_large_scale(slot, self._tables(head, R, t))
        events = self._launch_fine_scale(slot, head.shape[0], with_large, with_normals)
        events["large_scale"] = ev_large
        return events

    def _launch_large_scale(self, slot: _Slot, tables: dict):
        """Upload a chunk's host tables (:meth:`_tables`) and launch ``large_scale`` into
        ``self._large``; returns its event."""
        cl = _cl()
        q, s, C = self.queue, self._static, self.chunk
        uploads = [cl.enqueue_copy(q, slot.inputs[k], v, is_blocking=False) for k, v in tables.items()]
        slot.host = tables  # must outlive the non-blocking uploads
        lanes = C // self.vw
        self._k_large.set_args(s["B"], slot.inputs["U"], s["rest"], self._large, np.int32(C))
        return cl.enqueue_nd_range_kernel(q, self._k_large, (lanes, self.Vp // RV), (self.local0, self.local1),
                                          wait_for=uploads)

    def _launch_fine_scale(self, slot: _Slot, n: int, with_large: bool, with_normals: bool,
                           wait_for=None, large=None) -> dict:
        """Launch the frames + details kernel (and the normals') on the large-scale surface in
        ``large`` (default ``self._large``: a (Vp, 3, C) float32 buffer); returns their events (the
        large scale's is the caller's)."""
        cl = _cl()
        q, s, C = self.queue, self._static, self.chunk
        lanes = C // self.vw
        flags = (1 if with_large else 0) | (2 if with_normals else 0)
        out = slot.outputs
        large = self._large if large is None else large
        final = out["final"] if slot.final is None else slot.final
        self._k_detail.set_args(
            large, np.int32(C), np.int32(n), np.int32(self.V), s["ring_ptr"], s["ring"], s["fan_ptr"], s["fan"],
            s["neighbor"],
            s["edge_count"], s["edge_index"], s["edge_weight"], s["basis"], slot.inputs["features"],
            slot.inputs["psd_r"], slot.inputs["site"], s["rbf_weights"], s["rbf_const"], slot.inputs["rigid"],
            s["out_index"], final, out.get("large", final),
            final if self._final_vc is None else self._final_vc,
            np.int32(flags), s["strain_coeff"], s["strain_const"], s["strain_samples"], np.float32(self.strain_inv),
            np.int32(slot.final_offset if slot.final is not None else 0), s["wpsd_const"])
        ev_detail = cl.enqueue_nd_range_kernel(q, self._k_detail, (lanes, self.Vd), (self.local0, self.local1),
                                               wait_for=wait_for)
        events = {"frames_fine_scale": ev_detail, "last": ev_detail}
        if with_normals:
            self._k_normals.set_args(self._final_vc, np.int32(C), np.int32(n), np.int32(self.V), s["fan_ptr"],
                                     s["fan"], slot.inputs["rigid"], s["out_index"], out["normals"])
            events["normals"] = events["last"] = cl.enqueue_nd_range_kernel(
                q, self._k_normals, (lanes, self.Vd), (self.local0, self.local1))
        return events

    def _account(self, events: dict) -> None:
        for stage, ev in events.items():
            if stage != "last":
                ns = ev.profile.end - ev.profile.start
                self.stage_seconds[stage] = self.stage_seconds.get(stage, 0.0) + ns * 1e-9

    # ------------------------------------------------------------------ public API

    def _host_output(self, destination: np.ndarray | None, placement, start: int, stop: int, index: int):
        """(buffer, offset in floats) the kernel writes frames start:stop into in place, on a
        device that runs on the host's cores (CL_MEM_USE_HOST_PTR: the positions need no copy from
        device memory): ``destination[start:stop]``, or the memory ``placement(start, n, index)``
        gives; (None, 0) otherwise (a GPU; no destination; the placement declines)."""
        if not self.on_host_cores:
            return None, 0
        cl = _cl()
        flags = cl.mem_flags.WRITE_ONLY | cl.mem_flags.USE_HOST_PTR
        if destination is not None:
            return cl.Buffer(self.context, flags, hostbuf=destination[start:stop]), 0
        placed = placement(start, stop - start, index) if placement is not None else None
        if placed is None:
            return None, 0
        memory, offset = placed
        return cl.Buffer(self.context, flags, hostbuf=memory), int(offset)

    def stream(self, head: np.ndarray, sink, R: np.ndarray | None = None, t: np.ndarray | None = None,
               with_large: bool = False, with_normals: bool = False, destination: np.ndarray | None = None,
               placement=None) -> None:
        """Evaluate a whole take chunk by chunk, pipelined; hand every chunk to ``sink`` in order.

        Parameters
        ----------
        head : (T, H, 3) handle positions in head (rig) space, rig units.
        sink : callable(start, final, large, normals) called from one worker thread, in frame
            order: ``final`` (n, V, 3) float32 positions of frames start:start+n; ``large`` the
            large-scale positions and ``normals`` the final unit normals, or None when not asked
            for. The arrays are views of device memory, valid only during the call: copy or
            write them.
        R, t : optional (T, 3, 3), (T, 3) head motion applied to the output (world = R p + t).
        destination : optional (T, V, 3) float32 C-ordered array for the final positions. On a
            CPU device the kernel writes them there in place (no copy from device memory); on a
            GPU they are copied there. Either way ``final`` handed to ``sink`` is then
            ``destination[start:start+n]``, already filled.
        placement : optional callable(start, n, index) → (memory, offset) or None: on a CPU device,
            frames start:start+n are written in place into ``memory`` (a 1-D float32 array)
            from ``offset`` floats on, and ``final`` is that view of it (how
            :meth:`facepipe.io.npy_stream.NpyWriter.placement` lets a chunk go to disk with no
            copy). ``index`` (0 … slots − 1) names the chunk's slot: the memory given for one
            index is not written again before the sink has had the chunk.
        """
        cl = _cl()
        head = np.asarray(head, dtype=np.float64)
        T, C, V = head.shape[0], self.chunk, self.V
        _check_destination(destination, (T, V, 3))

        def deliver(start, maps, events):
            for _, ev in maps:
                ev.wait()
            self._account(events)
            t0 = time.perf_counter()
            arrays = {name: arr for name, (arr, _) in zip(("final", "large", "normals"), maps)}
            final = arrays["final"]
            if destination is not None:
                place = destination[start:start + final.shape[0]]
                if final.ctypes.data != place.ctypes.data:  # a GPU's (or a driver that copied): copy
                    place[...] = final
                final = place
            sink(start, final, arrays.get("large") if with_large else None,
                 arrays.get("normals") if with_normals else None)
            self.stage_seconds["output"] += time.perf_counter() - t0

        def retire(item):
            future, maps = item
            try:
                future.result()
            finally:
                for arr, ev in maps:
                    ev.wait()
                    arr.base.release(self.queue)

        # chunks in flight, oldest first; chunk k uses slot k % n_slots, so the oldest one is
        # always the one whose slot the next chunk needs
        inflight: deque = deque()
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="facepipe-sink") as pool:
            try:
                for k, s in enumerate(range(0, T, C)):
                    e = min(T, s + C)
                    if len(inflight) == self.n_slots:
                        retire(inflight.popleft())
                    slot = self._slots[k % self.n_slots]
                    slot.final, slot.final_offset = self._host_output(destination, placement, s, e,
                                                                      k % self.n_slots)
                    self._slot_buffers(slot, with_large, with_normals, with_final=slot.final is None)
                    events = self._enqueue(slot, head[s:e], None if R is None else R[s:e],
                                           None if t is None else t[s:e], with_large, with_normals)
                    buffers = [(slot.outputs["final"], 0) if slot.final is None else (slot.final, slot.final_offset)] \
                        + ([(slot.outputs["large"], 0)] if with_large else []) \
                        + ([(slot.outputs["normals"], 0)] if with_normals else [])
                    maps = []
                    for buffer, offset in buffers:
                        arr, ev = cl.enqueue_map_buffer(self.queue, buffer, cl.map_flags.READ, 4 * offset,
                                                        (e - s, V, 3), np.float32, wait_for=[events["last"]],
                                                        is_blocking=False)
                        maps.append((arr, ev))
                    inflight.append((pool.submit(deliver, s, maps, events), maps))
                    self.queue.flush()
            finally:
                # retire the rest in order; the first error (device or sink) propagates
                error = None
                while inflight:
                    try:
                        retire(inflight.popleft())
                    except BaseException as exc:  # noqa: BLE001 - re-raised below
                        error = error or exc
                self.queue.finish()
                if error is not None:
                    raise error

    @property
    def novelty_fits_at_cap(self) -> int | None:
        """Novelty-gate fits stopped by their iteration cap so far (None without a gate)."""
        return None if self.gate is None else self.gate.unconverged_fits

    def evaluate(self, handle_positions: np.ndarray, with_large: bool = False, rigid=None,
                 with_normals: bool = False, out: np.ndarray | None = None):
        """Final positions (C, V, 3) float32 for head-space handle positions (C, H, 3).

        Parameters
        ----------
        with_large : also return the large-scale positions.
        rigid : optional (R (C, 3, 3), t (C, 3)) head motion applied to the outputs.
        with_normals : also return the final surface's unit normals (C, V, 3).
        out : optional (C, V, 3) float32 C-ordered array for the final positions (on a CPU
            device the kernels write into it in place).

        Returns
        -------
        final, or (final, large), or (final, normals), or (final, large, normals).
        """
        head = np.asarray(handle_positions, dtype=np.float64)
        T = head.shape[0]
        final = np.empty((T, self.V, 3), dtype=np.float32) if out is None else out
        large = np.empty_like(final) if with_large else None
        normals = np.empty_like(final) if with_normals else None

        def sink(start, f, l, n):
            stop = start + f.shape[0]
            if large is not None:
                large[start:stop] = l
            if normals is not None:
                normals[start:stop] = n

        R, t = (None, None) if rigid is None else rigid
        self.stream(head, sink, R, t, with_large=with_large, with_normals=with_normals, destination=final)
        out = (final,) + ((large,) if with_large else ()) + ((normals,) if with_normals else ())
        return out[0] if len(out) == 1 else out
