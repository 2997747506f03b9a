"""facepipe: facial motion capture to high-resolution, wrinkled face animation.

Large-scale motion from a linear thin shell driven by marker handles, fine-scale
details from pose-space deformation over strain features (Bickel et al. 2008).
"""

__version__ = "0.1.0"
