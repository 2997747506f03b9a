"""The editor's state on the server: the model, the prepared take, the edits, and evaluation.

Evaluation splits where it is cheapest to do each part:

* pose terms, the same size at any mesh resolution — handle positions with the edits applied
  (:func:`facepipe.core.edits.apply_edits`, what ``replay --edits`` calls), strain features, and
  the novelty gate's per-site confidence (its non-negative fits) — always here, with the replay's
  own code;
* the per-vertex work — u = B·u_H, local frames, WPSD distances through α, details — in the
  browser (``browser`` mode: the model's arrays are shipped once in a compact binary, the page
  gets the pose terms per frame) or here, on the replay's engine (``server`` mode: positions
  stream to the page as float32).
"""

from __future__ import annotations

import json
import multiprocessing
import struct
import threading
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from facepipe.core.render import view_direction
from facepipe.pipeline.evaluate import load_truth, to_head_space
from facepipe.core.edits import HandleEdit, apply_edits
from facepipe.core.psd import edge_weight_matrix
from facepipe.core.strain import strain_features
from facepipe.editor.drag_patch import DragPatch
from facepipe.editor.edits_model import EditHistory
from facepipe.errors import InputError
from facepipe.io.model_file import Model
from facepipe.pipeline.replay import NumpyEvaluator

# the browser evaluates meshes whose B fits in this many bytes (float32); larger ones go to the server
BROWSER_B_BYTES = 96 * 2 ** 20
# the page's evaluation (static/evaluate.js) has the details of these methods; others (the
# local-strain model) are evaluated on the server
BROWSER_METHODS = ("none", "psd", "wpsd")


@dataclass
class Take:
    """A take prepared as replay prepares it: head-space handles and the head motion per frame."""

    head: np.ndarray          # (T, H, 3) float
    rotation: np.ndarray      # (T, 3, 3)
    translation: np.ndarray   # (T, 3)
    frames: np.ndarray        # (T,) frame numbers
    times: np.ndarray         # (T,) seconds
    name: str


def rest_take(model: Model) -> Take:
    """No take: one frame, the rest pose, to pose the face from scratch."""
    head = model.rest[model.handle_vertices][None].astype(np.float64)
    return Take(head, np.eye(3)[None], np.zeros((1, 3)), np.array([0]), np.array([0.0]), "(rest pose)")


def pack_arrays(arrays: dict[str, np.ndarray], meta: dict) -> bytes:
    """A compact binary bundle: u32 header length, JSON header (meta and, per array, dtype, shape,
    byte offset), then each array's bytes at an 8-byte aligned offset (so typed arrays view them)."""
    entries, blobs, offset = {}, [], 0
    for name, array in arrays.items():
        array = np.ascontiguousarray(array)
        pad = (-offset) % 8
        blobs.append(b"\0" * pad)
        offset += pad
        entries[name] = {"dtype": array.dtype.str, "shape": list(array.shape), "offset": offset}
        blobs.append(array.tobytes())
        offset += array.nbytes
    header = json.dumps({"meta": meta, "arrays": entries}).encode()
    header += b" " * ((-(4 + len(header))) % 8)
    return struct.pack("<I", len(header)) + header + b"".join(blobs)


_WORKER_GATE = None


def _start_gate_worker(gate) -> None:
    global _WORKER_GATE
    _WORKER_GATE = gate


def _site_confidence(features: np.ndarray, displacements: np.ndarray) -> np.ndarray:
    return _WORKER_GATE.site_confidences(features, displacements)


class GateCache:
    """The novelty gate's exact per-site confidences by handle positions (its non-negative fits
    take tens to hundreds of milliseconds a frame, the rest of a frame a few), and the latest one,
    which a drag uses while the exact fits for the current pose run in the background.

    The fits run in a worker process of their own: their many small steps would otherwise hold
    the interpreter's lock that the server's answers to the page need."""

    def __init__(self, gate, rest_handles: np.ndarray, size: int = 512):
        self.gate = gate
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_start_gate_worker, initargs=(gate,))
        self.rest_handles = rest_handles
        self.size = size
        self._cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self.latest: np.ndarray | None = None

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

    @staticmethod
    def key(handles: np.ndarray) -> bytes:
        return np.ascontiguousarray(handles, dtype=np.float64).tobytes()

    def get(self, handles: np.ndarray) -> np.ndarray | None:
        with self._lock:
            return self._cache.get(self.key(handles))

    def compute(self, handles: np.ndarray, features: np.ndarray) -> np.ndarray:
        """The exact site confidence (F,): the replay's NumPy gate on these handles."""
        found = self.get(handles)
        if found is not None:
            return found
        u = handles[None] - self.rest_handles[None]
        site = self._pool.submit(_site_confidence, features[None], u).result()[0]
        with self._lock:
            self._cache[self.key(handles)] = site
            while len(self._cache) > self.size:
                self._cache.popitem(last=False)
            self.latest = site
        return site


class _SiteFactors:
    """Stands in for the OpenCL engine's site gate: given per-site confidences, unchanged."""

    unconverged_fits = 0

    def __init__(self, site: np.ndarray):
        self.site = site

    def confidence(self, features, displacements=None):
        return np.repeat(self.site[None], len(features), axis=0)


class _VertexFactors(_SiteFactors):
    """Stands in for the NumPy evaluator's gate: given per-site confidences, spread by α."""

    def __init__(self, site: np.ndarray, alpha):
        super().__init__(np.asarray(alpha @ site).ravel())


class EditorSession:
    """What one ``facepipe edit`` serves: evaluation of edited frames and the edit history.

    Parameters
    ----------
    model : the baked model; take : the prepared take (or :func:`rest_take`).
    edits_path : where Save writes EDITS.json (its edits, if it exists, are loaded by the caller).
    mode : "browser", "server" or "auto" (browser when B fits :data:`BROWSER_B_BYTES` and the page
        has the model's method, :data:`BROWSER_METHODS`; "browser" for another method is an InputError).
    engine : the server's evaluator for server mode (default NumPy).
    truth_path : optional truth .npz for the error heat map.
    """

    def __init__(self, model: Model, take: Take, edits_path: Path, edits: list[HandleEdit] | None = None,
                 mode: str = "auto", engine=None, truth_path=None):
        self.model = model
        self.take = take
        self.edits_path = Path(edits_path)
        self.history = EditHistory(edits)
        self.reference = NumpyEvaluator(model)
        if mode == "auto":
            mode = "browser" if model.B.size * 4 <= BROWSER_B_BYTES and model.method in BROWSER_METHODS else "server"
        if mode == "browser" and model.method not in BROWSER_METHODS:
            raise InputError(f"the page evaluates PSD and WPSD models; this model's details ({model.method}) are "
                             "evaluated on the server", path=model.path or None,
                             hint="use --evaluate server (or auto, which chooses it)")
        self.mode = mode
        self.engine = engine if engine is not None else self.reference
        self.engine_lock = threading.Lock()
        self.rest_handles = model.rest[model.handle_vertices].astype(np.float64)
        details = self.reference.details
        gate = None if details is None or details.method == "none" else details.gate
        self.gates = GateCache(gate, self.rest_handles) if gate is not None and gate.tau > 0 else None
        self.alpha = edge_weight_matrix(model.edge_index, model.edge_weight, len(model.edges))  # the gate's α
        self._patch: tuple[tuple, DragPatch] | None = None
        self.patch_serial = 0  # names the current patch in the page's messages
        self.truth = None
        if truth_path is not None:
            self.truth = load_truth(truth_path, take.frames, model.n_vertices,
                                    file_order=lambda: model.weld_index)  # (a welded rig: its mesh file's order too)

    def close(self) -> None:
        """Stop the gate's worker process."""
        if self.gates is not None:
            self.gates.close()

    # ------------------------------------------------------------------ pose terms

    def handles(self, index: int, preview: HandleEdit | None = None) -> np.ndarray:
        """Head-space handle positions (H, 3) of frame row ``index`` with the edits (and a drag's
        uncommitted ``preview``) applied."""
        edits = self.history.edits + ([preview] if preview is not None else [])
        head = self.take.head[index:index + 1]
        return apply_edits(head, self.take.frames[index:index + 1], edits)[0].astype(np.float64)

    def pose_terms(self, handles: np.ndarray, exact: bool = True) -> tuple[np.ndarray, np.ndarray | None, bool]:
        """Strain features (F,), the gate's per-site confidence (F,) (None without a gate), and
        whether that confidence is exact — the numbers the replay's NumPy evaluator forms for
        these handles — or, with ``exact`` False and the fits not yet made, the latest exact one."""
        features = strain_features(handles[None], self.reference.edges, self.reference.rest_lengths)[0]
        if self.gates is None:
            return features, None, True
        site = self.gates.get(handles)
        if site is not None:
            return features, site, True
        if exact or self.gates.latest is None:
            return features, self.gates.compute(handles, features), True
        return features, self.gates.latest, False

    def exact_gate(self, handles: np.ndarray) -> None:
        """Make the exact gate of these handles (for a later :meth:`pose_terms`)."""
        if self.gates is not None:
            self.gates.compute(handles, self.pose_terms(handles, exact=False)[0])

    # ------------------------------------------------------------------ server-side positions

    def evaluate(self, handles: np.ndarray, site: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Final and large-scale positions (V, 3) float32 of one frame on the server's engine,
        with the gate's per-site confidence ``site`` (default: the exact one)."""
        if self.gates is not None and site is None:
            site = self.pose_terms(handles)[1]
        with self.engine_lock:
            engine = self.engine
            if site is not None:
                if isinstance(engine, NumpyEvaluator):
                    engine.details = replace(engine.details, gate=_VertexFactors(site, self.alpha))
                else:
                    engine.gate = _SiteFactors(site)
            final, large = engine.evaluate(handles[None], with_large=True)
        return np.asarray(final[0], dtype=np.float32), np.asarray(large[0], dtype=np.float32)

    def drag_patch(self, row: int, preview: HandleEdit | None, exact: bool):
        """A drag of one handle whose gate's exact fits are not yet made is evaluated on a
        :class:`DragPatch` from the frame without it: (handles, the patch, whether the patch is new,
        offset); None when the frame is to be evaluated whole."""
        if preview is None or len(preview.offsets) != 1:
            return None
        handles = self.handles(row, preview)
        features, site, is_exact = self.pose_terms(handles, exact)
        if is_exact:
            return None
        (handle, offset), = preview.offsets.items()
        key = (row, handle, id(self.history.edits))
        new = self._patch is None or self._patch[0] != key
        if new:
            base = self.handles(row)
            base_final, base_large = self.evaluate(base, site)
            self._patch = (key, DragPatch(self.model, handle, base, base_final, base_large, site,
                                          incidence=self.reference.incidence))
            self.patch_serial += 1
        return handles, self._patch[1], new, offset

    def positions(self, row: int, preview: HandleEdit | None, exact: bool):
        """Handles, final and large positions of a frame row (with a drag's preview), and whether
        they are exact (see :meth:`drag_patch` for a drag without the gate's exact fits)."""
        drag = self.drag_patch(row, preview, exact)
        if drag is not None:
            handles, patch, _, offset = drag
            final, large = patch.evaluate(offset)
            return handles, final, large, False
        handles = self.handles(row, preview)
        features, site, is_exact = self.pose_terms(handles, exact)
        final, large = self.evaluate(handles, site)
        return handles, final, large, is_exact

    def truth_frame(self, index: int) -> np.ndarray | None:
        """The truth of frame row ``index`` in head space (the page shows the face there), float32."""
        if self.truth is None:
            return None
        positions, rows = self.truth
        x = to_head_space(np.asarray(positions[rows[index]], dtype=np.float64), self.take.rotation[index],
                          self.take.translation[index])
        return np.asarray(x, dtype=np.float32)

    # ------------------------------------------------------------------ what the page loads

    def meta(self) -> dict:
        model = self.model
        return {
            "mode": self.mode,
            "engine": getattr(self.engine, "device", "cpu (numpy)") if self.mode == "server" else "browser (JavaScript)",
            "vertices": model.n_vertices, "handles": len(model.handle_vertices), "features": len(model.edges),
            "method": model.method, "gate": self.gates is not None,
            "handle_names": model.marker_names, "units": model.meta.get("units"),
            "frames": [float(f) for f in self.take.frames], "times": [float(t) for t in self.take.times],
            "take": self.take.name, "truth": self.truth is not None,
            "view": [float(v) for v in view_direction(model)],
            "marker_size": float(np.median(model.rest_lengths)) * 0.09,
            "edits_path": str(self.edits_path),
        }

    def model_bundle(self) -> bytes:
        """The arrays the page needs: the mesh always; B and the detail model in browser mode."""
        m = self.model
        arrays = {"rest": m.rest.astype(np.float32), "triangles": m.triangles.astype(np.uint32),
                  "handle_vertices": m.handle_vertices.astype(np.uint32)}
        if self.mode == "browser":
            arrays.update(B=m.B.astype(np.float32), frame_neighbors=m.frame_neighbors.astype(np.uint32),
                          basis_features=m.basis_features.astype(np.float32),
                          rbf_weights=m.rbf_weights.astype(np.float32), rbf_const=m.rbf_const.astype(np.float32),
                          edge_index=m.edge_index.astype(np.uint32), edge_weight=m.edge_weight.astype(np.float32),
                          # a drag's steps form their strain features in the page
                          edges=m.edges.astype(np.uint32), rest_lengths=m.rest_lengths.astype(np.float64))
        return pack_arrays(arrays, self.meta())
