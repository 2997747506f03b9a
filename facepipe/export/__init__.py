"""Exports of a replay folder: OBJ sequences, point caches, EXR displacement and wrinkle maps."""
