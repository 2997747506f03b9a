"""OpenEXR files through the OpenEXR Python bindings (3.x): atomic writing, reading back.

Maps are single-part scanline images with ZIP compression (lossless, per 16 scanlines),
channels ``R, G, B`` (a vector) or ``Y`` (a scalar), half or float pixels, and ``facepipe/…``
string/number attributes that say what the pixels mean.
"""

from __future__ import annotations

import os

import numpy as np

from facepipe.io.atomic import atomic_path


def write_exr(path: str | os.PathLike, image: np.ndarray, half: bool = True, attributes: dict | None = None) -> int:
    """Write a map as an EXR file, atomically (temporary name, then rename).

    Parameters
    ----------
    path : destination ``.exr``.
    image : (H, W) scalar map → channel ``Y``; (H, W, 3) vector map → channels ``R, G, B``.
    half : 16-bit half floats (the usual for displacement; about 3 significant digits);
        False for 32-bit floats.
    attributes : extra header attributes (str, int or float values), e.g. ``{"facepipe/space": "local"}``.

    Returns
    -------
    int, the file's size in bytes.

    Example
    -------
    >>> write_exr("disp.exr", np.zeros((256, 256, 3)))  # doctest: +SKIP
    """
    import OpenEXR  # lazily: only map exports need it (start-up)

    image = np.asarray(image)
    dtype = np.float16 if half else np.float32
    if image.ndim == 2:
        channels = {"Y": np.ascontiguousarray(image, dtype=dtype)}
    elif image.ndim == 3 and image.shape[2] == 3:
        channels = {c: np.ascontiguousarray(image[..., k], dtype=dtype) for k, c in enumerate("RGB")}
    else:
        raise ValueError(f"a map is (H, W) or (H, W, 3), not {image.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (attributes or {}).items():
        header[key] = value if isinstance(value, (str, int)) else float(value)
    with atomic_path(path) as tmp:
        OpenEXR.File(header, channels).write(str(tmp))
        size = os.path.getsize(tmp)
    return size


def read_exr(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Read a map written by :func:`write_exr` (or any single-part Y or RGB EXR).

    Returns
    -------
    image : (H, W) for a ``Y`` file, (H, W, 3) for ``R, G, B``; in the stored pixel type.
    header : dict of the header attributes.
    """
    import OpenEXR  # lazily: only map exports need it (start-up)

    f = OpenEXR.File(str(path), separate_channels=True)
    ch = f.channels()
    header = dict(f.header())
    if "Y" in ch:
        return ch["Y"].pixels, header
    return np.stack([ch[c].pixels for c in "RGB"], axis=-1), header
