"""Mocap takes: one reader and writer per file format behind one registry, and gap filling.

``from facepipe.mocap import read_take, write_take, fill_gaps, Take, write_take_csv``.

Formats (see :data:`FORMATS`): the facepipe CSV, C3D (through ezc3d), TRC, Vicon Nexus CSV
(the Trajectories block) and OptiTrack Motive CSV. :func:`read_take` finds the format from
the file's first bytes and suffix, matches the file's marker names to the rig's (subject
prefixes stripped), converts units to the rig's and checks frame order and values.
"""

from facepipe.mocap import c3d, facepipe_csv, motive_csv, trc, vicon_csv# noqa: F401  (register the formats)
from facepipe.mocap import landmarks2d  # noqa: F401  (2D landmark takes; after the 3D formats, tried before them)
from facepipe.mocap import mesh_cache  # noqa: F401  (point caches of a rigged face: USD, MDD, PC2, OBJ sequences)
from facepipe.mocap.facepipe_csv import read_csv_take, write_take_csv
from facepipe.mocap.gaps import fill_gaps
from facepipe.mocap.markers import MarkerMatch, match_markers, normalise_units, split_subject, unit_factor
from facepipe.mocap.registry import (FORMATS, MESH_CACHES, READERS, WRITERS, Format, available_memory, detect_format,
                                     mesh_cache_format, read_take, register, write_take)
from facepipe.mocap.take import Take, parse_frame_slice

__all__ = [
    "FORMATS",
    "READERS",
    "WRITERS",
    "Format",
    "MESH_CACHES",
    "MarkerMatch",
    "Take",
    "available_memory",
    "detect_format",
    "fill_gaps",
    "match_markers",
    "mesh_cache_format",
    "normalise_units",
    "parse_frame_slice",
    "read_csv_take",
    "read_take",
    "register",
    "split_subject",
    "unit_factor",
    "write_take",
    "write_take_csv",
]
