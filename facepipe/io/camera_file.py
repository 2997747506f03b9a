"""Camera calibration files: OpenCV FileStorage (YAML/XML, as ``cv2.FileStorage`` writes) or JSON.

Keys: ``image_width``, ``image_height``, ``camera_matrix`` (3 × 3) and ``distortion_coefficients``
(FileStorage) or ``dist_coeffs`` (JSON; ``distortion_coefficients`` is accepted too, and the
names other tools use: see :func:`_read_json`). The FileStorage form is read by OpenCV itself,
so whatever ``cv2.FileStorage`` writes reads back, in YAML, XML or JSON.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np

from facepipe.core.camera import Camera
from facepipe.errors import InputError

__all__ = ["read_camera", "write_camera"]

_DISTORTION_SIZES = (0, 4, 5, 8, 12, 14)
_HINT = ("write the calibration as OpenCV does (cv2.FileStorage with image_width, image_height, camera_matrix, "
         "distortion_coefficients) or as JSON with image_width, image_height, camera_matrix, dist_coeffs")


def read_camera(path) -> Camera:
    """Read and check a calibration file.

    Raises
    ------
    InputError
        Missing or unreadable file, a missing key, a camera matrix that is not 3 × 3 with a
        positive focal length and a last row of (0, 0, 1), a distortion vector of a size OpenCV
        does not know, non-positive image size, non-finite values.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("camera calibration not found", path=path, hint="give the calibration file with --camera")
    if path.suffix.lower() == ".json":
        matrix, dist, width, height = _read_json(path)
    else:
        matrix, dist, width, height = _read_filestorage(path)
    return _checked(path, matrix, dist, width, height)


#: names calibration tools give the same things in JSON, first the ones facepipe writes
_MATRIX_KEYS = ("camera_matrix", "K", "intrinsics", "intrinsic_matrix")
_DISTORTION_KEYS = ("dist_coeffs", "distortion_coefficients", "dist", "distortion", "D")
_SIZE_KEYS = (("image_width", "image_height"), ("width", "height"))
_SIZE_PAIR_KEYS = ("image_size", "resolution", "size")


def _read_json(path: Path):
    """A JSON calibration: facepipe's (image_width, image_height, camera_matrix, dist_coeffs), one
    OpenCV's FileStorage wrote (its matrices as ``opencv-matrix`` objects: read by OpenCV), or the
    same under the names other tools use (K / intrinsics, or fx fy cx cy; dist / distortion / D;
    width and height, or image_size / resolution [w, h])."""
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not a readable JSON calibration ({exc})", path=path, hint=_HINT) from None
    if not isinstance(data, dict):
        raise InputError("the JSON calibration is not an object of keys", path=path, hint=_HINT)
    if any(isinstance(v, dict) and v.get("type_id") == "opencv-matrix" for v in data.values()):
        return _read_filestorage(path)
    matrix = next((data[k] for k in _MATRIX_KEYS if k in data), None)
    if matrix is None and all(k in data for k in ("fx", "fy", "cx", "cy")):
        matrix = [[data["fx"], data.get("skew", 0.0), data["cx"]], [0.0, data["fy"], data["cy"]], [0.0, 0.0, 1.0]]
    if matrix is None:
        raise InputError("the calibration lacks 'camera_matrix' (or K, or fx fy cx cy)", path=path, hint=_HINT)
    dist = next((data[k] for k in _DISTORTION_KEYS if k in data), [])
    size = next(((data[w], data[h]) for w, h in _SIZE_KEYS if w in data and h in data), None)
    if size is None:
        pair = next((data[k] for k in _SIZE_PAIR_KEYS if k in data), None)
        if isinstance(pair, (list, tuple)) and len(pair) == 2:
            size = tuple(pair)
    if size is None:
        raise InputError("the calibration lacks 'image_width' and 'image_height' (or image_size [w, h])", path=path,
                         hint=_HINT)
    try:
        matrix = np.asarray(matrix, dtype=np.float64)
        dist = np.asarray(dist if dist is not None else [], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("camera_matrix and dist_coeffs must be arrays of numbers", path=path, hint=_HINT) from None
    return matrix, dist, size[0], size[1]


def _read_filestorage(path: Path):
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # (OpenCV's parser errors can surface as SystemError)
        reason = str(exc.__cause__ or exc).strip().splitlines() or ["parse error"]
        raise InputError(f"OpenCV cannot read this calibration ({reason[-1]})", path=path, hint=_HINT) from None
    try:
        if not fs.isOpened():
            raise InputError("OpenCV cannot read this calibration", path=path, hint=_HINT)

        def node(key):
            try:
                n = fs.getNode(key)
            except (cv2.error, SystemError):  # the file's top level is not a map of keys
                raise InputError("OpenCV reads no map of keys in this calibration", path=path, hint=_HINT) from None
            if n.empty() or n.isNone():
                raise InputError(f"the calibration lacks {key!r}", path=path, hint=_HINT)
            return n

        def matrix_of(n, key):
            _check_matrix_node(n, key, path)  # before OpenCV reads it: an inconsistent one corrupts its heap
            try:
                m = n.mat()
            except (cv2.error, SystemError) as exc:  # rows, cols, dt or data that do not make a matrix
                reason = str(exc).strip().splitlines() or ["parse error"]
                raise InputError(f"{key} is not a readable matrix ({reason[-1]})", path=path, hint=_HINT) from None
            if m is None:
                raise InputError(f"{key} is not a matrix (!!opencv-matrix)", path=path, hint=_HINT)
            return m

        matrix = matrix_of(node("camera_matrix"), "camera_matrix")
        d = fs.getNode("distortion_coefficients")  # (the top level is a map: camera_matrix was found in it)
        dist = np.zeros(0) if d.empty() or d.isNone() else matrix_of(d, "distortion_coefficients")
        size = []
        for key in ("image_width", "image_height"):
            n = node(key)
            if not n.isReal() and not n.isInt():
                raise InputError(f"{key} is not a number", path=path, hint=_HINT)
            size.append(n.real())
    finally:
        fs.release()
    return np.asarray(matrix, dtype=np.float64), np.asarray(dist, dtype=np.float64), size[0], size[1]


def _check_matrix_node(n, key: str, path: Path) -> None:
    """That an ``!!opencv-matrix`` node has one ``rows``, ``cols`` and ``dt`` and as many ``data``
    numbers as they say: OpenCV 5.1 reads a node without ``cols``, or with fewer numbers than
    ``rows × cols``, past its buffer, and the process dies later in ``malloc``."""
    if not n.isMap():
        return  # not a matrix at all: .mat() says None, reported by the caller
    sizes = []
    for part in ("rows", "cols"):
        v = n.getNode(part)
        if v.empty() or v.isNone() or not v.isInt() or v.real() < 0:
            raise InputError(f"{key} has no whole number {part!r}", path=path, hint=_HINT)
        sizes.append(int(v.real()))
    dt = n.getNode("dt")
    match = re.fullmatch(r"(\d*)([ucwsifdh])", dt.string().strip()) if dt.isString() else None
    if match is None:
        raise InputError(f"{key} has no element type 'dt' (d for 64-bit floats)", path=path, hint=_HINT)
    channels = int(match.group(1) or 1)
    data = n.getNode("data")
    if not data.isSeq() or data.size() != sizes[0] * sizes[1] * channels:
        count = data.size() if data.isSeq() else 0
        raise InputError(f"{key} says {sizes[0]} × {sizes[1]} but its data holds {count} numbers", path=path,
                         hint=_HINT)


def _checked(path: Path, matrix, dist, width, height) -> Camera:
    if matrix.shape != (3, 3):
        raise InputError(f"camera_matrix has shape {matrix.shape}, a camera matrix is 3 × 3", path=path,
                         hint="give [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels")
    if not np.isfinite(matrix).all() or not np.allclose(matrix[2], [0, 0, 1]) or matrix[1, 0] != 0:
        raise InputError(f"camera_matrix {matrix.tolist()} is not a pinhole camera matrix", path=path,
                         hint="its last row must be 0 0 1 and the entry below fx 0: [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    if not (matrix[0, 0] > 0 and matrix[1, 1] > 0):
        raise InputError(f"focal lengths fx = {matrix[0, 0]:g}, fy = {matrix[1, 1]:g} must be positive pixels",
                         path=path, hint="check the calibration")
    dist = dist.reshape(-1)
    if dist.size not in _DISTORTION_SIZES:
        raise InputError(f"{dist.size} distortion coefficients: OpenCV's model has "
                         f"{', '.join(map(str, _DISTORTION_SIZES))}", path=path,
                         hint="give k1 k2 p1 p2 [k3 ...] as the calibration wrote them")
    if not np.isfinite(dist).all():
        raise InputError("a distortion coefficient is not finite", path=path, hint="check the calibration")
    try:
        w, h = float(width), float(height)
    except (TypeError, ValueError):
        raise InputError("image_width and image_height must be numbers of pixels", path=path, hint=_HINT) from None
    if not (np.isfinite(w) and np.isfinite(h) and w >= 1 and h >= 1 and w == int(w) and h == int(h)):
        raise InputError(f"image size {width} × {height} is not a positive whole number of pixels", path=path,
                         hint="give the footage's resolution the calibration was made at")
    return Camera(matrix, dist, int(w), int(h), str(path))


def write_camera(path, camera: Camera) -> None:
    """Write a calibration as OpenCV FileStorage (``.yml``, ``.yaml``, ``.xml``) or JSON (``.json``)."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        path.write_text(json.dumps({"image_width": camera.width, "image_height": camera.height,
                                    "camera_matrix": camera.matrix.tolist(),
                                    "dist_coeffs": camera.distortion.reshape(-1).tolist()}, indent=1))
        return
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(camera.width))
    fs.write("image_height", int(camera.height))
    fs.write("camera_matrix", np.asarray(camera.matrix, dtype=np.float64))
    fs.write("distortion_coefficients", np.asarray(camera.distortion, dtype=np.float64).reshape(1, -1))
    fs.release()
