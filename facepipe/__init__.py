"""facepipe: facial motion capture to high-resolution, wrinkled face animation.

Large-scale motion from a linear thin shell driven by marker handles, fine-scale details from
pose-space deformation over strain features (Bickel et al. 2008).

The Python API (see :mod:`facepipe.api`)::

    import facepipe

    model = facepipe.load_model("model.npz")
    take = facepipe.read_take("take.c3d", model)
    result = facepipe.replay_take(model, take)     # result.positions: (T, V, 3)
    faces = facepipe.evaluate(model, handles)       # (T, H, 3) head-space handles -> (T, V, 3)
    wrinkled = facepipe.add_details(model, frames)  # a rig's own animation (T, V, 3) -> with details
"""

__version__ = "0.1.0"

__all__ = ["InputError", "Model", "ReplayedTake", "Take", "add_details", "evaluate", "load_model", "read_take", "replay_take"]


def __getattr__(name):
    # the API is imported on first use: `import facepipe` (and the command line's start) stays
    # free of SciPy and the readers until a function is called
    if name in __all__:
        from facepipe import api, errors

        return getattr(errors if name == "InputError" else api, name)
    raise AttributeError(f"module 'facepipe' has no attribute {name!r}")


def __dir__():
    # tab completion (IPython, dir()) shows the API, which __getattr__ imports on first use
    return sorted(set(globals()) | set(__all__))
