"""The method's mathematics as pure functions over arrays.

Mesh topology, cotangent operators and the thin shell, sparse solves, tangent frames, strain
features, PSD/WPSD and the novelty gate, the RBF volume morph, rigid fits. Nothing here reads
or writes files, starts processes or touches OpenCL: the layers above do.
"""
