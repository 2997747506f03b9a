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
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facepipe.cli.preview import load_truth, to_head_space, view_direction
from facepipe.core.edits import HandleEdit, apply_edits
from facepipe.core.strain import strain_features
from facepipe.editor.edits_model import EditHistory
from facepipe.io.model_file import Model
from facepipe.pipeline.replay import NumpyEvaluator

# the browser evaluates meshes whose B fits in this many bytes (float32); larger ones go to the server
BROWSER_B_BYTES = 96 * 2 ** 20


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


class EditorSession:
    """What one ``facepipe edit`` serves: evaluation of edited frames and the edit history.

    Parameters
    ----------
    model : the baked model; take : the prepared take (or :func:`rest_take`).
    edits_path : where Save writes EDITS.json (its edits, if it exists, are loaded by the caller).
    mode : "browser", "server" or "auto" (browser when B fits :data:`BROWSER_B_BYTES`).
    engine : the server's evaluator for server mode (default NumPy); the pose terms always use
        the NumPy reference's gate.
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
            mode = "browser" if model.B.size * 4 <= BROWSER_B_BYTES else "server"
        self.mode = mode
        self.engine = engine if engine is not None else self.reference
        self.rest_handles = model.rest[model.handle_vertices].astype(np.float64)
        self.truth = None
        if truth_path is not None:
            self.truth = load_truth(truth_path, take.frames, model.n_vertices)

    # ------------------------------------------------------------------ pose terms

    def handles(self, index: int, preview: HandleEdit | None = None) -> np.ndarray:
        """Head-space handle positions (H, 3) of frame row ``index`` with the edits (and a drag's
        uncommitted ``preview``) applied."""
        edits = self.history.edits + ([preview] if preview is not None else [])
        head = self.take.head[index:index + 1]
        return apply_edits(head, self.take.frames[index:index + 1], edits)[0].astype(np.float64)

    def pose_terms(self, handles: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Strain features (F,) and the gate's per-site confidence (F,) (None without a gate) —
        exactly the numbers the replay's NumPy evaluator forms for these handles."""
        features = strain_features(handles[None], self.reference.edges, self.reference.rest_lengths)
        details = self.reference.details
        gate = None if details is None or details.method == "none" else details.gate
        if gate is None or gate.tau <= 0:
            return features[0], None
        u = handles[None] - self.rest_handles[None]
        return features[0], gate.site_confidence(gate.novelty(features, u))[0]

    def evaluate(self, handles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Final and large-scale positions (V, 3) float32 of one frame on the server's engine."""
        final, large = self.engine.evaluate(handles[None], with_large=True)
        return np.asarray(final[0], dtype=np.float32), np.asarray(large[0], dtype=np.float32)

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
        gate = self.reference.details.gate if self.reference.details is not None else None
        return {
            "mode": self.mode,
            "engine": getattr(self.engine, "device", "cpu (numpy)") if self.mode == "server" else "browser (JavaScript)",
            "vertices": model.n_vertices, "handles": len(model.handle_vertices), "features": len(model.edges),
            "method": model.method, "gate": gate is not None and gate.tau > 0,
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
                          edge_index=m.edge_index.astype(np.uint32), edge_weight=m.edge_weight.astype(np.float32))
        return pack_arrays(arrays, self.meta())
