"""Write one of the ICT kit's other faces (identities/face_a.obj, face_b.obj) as a complete rig, so
the whole pipeline can be run on a face that is not the kit's:

    python bench/ict_identity_rig.py face_a /tmp/face_a_rig
    cd /tmp/face_a_rig && facepipe fit rig.toml -o fit.npz && facepipe bake fit.npz -o model.npz
    facepipe replay train_mocap.csv -m model.npz -o out && facepipe eval out --truth train_truth.npz --vertices 0:9409

The kit's README defines the other faces' truth: an ICT expression's displacement does not depend
on the identity, so face X making expression e is X + (e − neutral), and a frame of a take is the
face plus that frame's displacement from the neutral (its head motion, where the take has one,
taken out first and put back after). Written: ``expressions/*.obj`` (the kit's 26 on this face),
``rig.toml`` (configs/ict.toml with this face's mesh and expressions), and per take with truth
(``train``, ``noisy``): ``NAME_truth.npz`` and ``NAME_mocap.csv``, the markers at their vertices
(the noisy take's marker noise, gaps and head motion are the kit's own, carried over as its
markers' offsets from their truth vertices).
"""

from __future__ import annotations

import argparse
import csv
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's facepipe, however it is run

from facepipe.io.mesh_read import load_mesh, load_vertices  # noqa: E402
from facepipe.io.mesh_write import save_obj  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KIT = ROOT.parent / "shared" / "data" / "ict"
TAKES = {"train": ("train_truth.npz", "train_mocap.csv"), "noisy": ("noisy_truth.npz", "noisy_mocap.csv")}


def moved_frames(positions: np.ndarray, offset: np.ndarray, truth) -> np.ndarray:
    """A take's frames (T, V, 3) on another face: ``offset`` (V, 3) = face − neutral added in head
    space (world = head · Rᵀ + t where the truth has ``rotation``/``translation``)."""
    if "rotation" in truth and "translation" in truth:
        return positions + np.einsum("vj,tij->tvi", offset, np.asarray(truth["rotation"]))
    return positions + offset


def write_identity_rig(face: str, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "expressions").mkdir(exist_ok=True)
    neutral = load_mesh(KIT / "neutral.obj")
    mesh = load_mesh(KIT / "identities" / f"{face}.obj")
    if mesh.n_vertices != neutral.n_vertices:
        raise SystemExit(f"{face}: {mesh.n_vertices} vertices, the kit's neutral has {neutral.n_vertices}")
    offset = mesh.vertices - neutral.vertices
    for path in sorted((KIT / "expressions").glob("*.obj")):
        save_obj(out / "expressions" / path.name, mesh, mesh.vertices + (load_vertices(path) - neutral.vertices))
    marker_vertex = {row["name"]: int(row["vertex"]) for row in csv.DictReader(open(KIT / "markers.csv"))}
    for truth_name, mocap_name in TAKES.values():
        truth = dict(np.load(KIT / truth_name))
        moved = moved_frames(truth["positions"], offset, truth)
        # each marker keeps its offset from its vertex in the kit's take (noise, gaps as NaN):
        # the truth vertex's move onto this face is added to the file's own samples
        shift = moved - truth["positions"]
        np.savez(out / truth_name, **{**truth, "positions": moved.astype(truth["positions"].dtype)})
        with open(KIT / mocap_name, newline="") as fh:
            rows = list(csv.reader(fh))
        header = rows[0]
        row_of = {int(f): k for k, f in enumerate(np.asarray(truth["frame"]))}
        with open(out / mocap_name, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            for row in rows[1:]:
                k = row_of[int(row[0])]
                for j, column in enumerate(header[2:], start=2):
                    name, axis = re.fullmatch(r"(.+)_([xyz])", column).groups()
                    if row[j].strip():
                        row[j] = f"{float(row[j]) + shift[k, marker_vertex[name], 'xyz'.index(axis)]:.5f}"
                writer.writerow(row)
    config = (ROOT / "configs" / "ict.toml").read_text()
    config = config.replace("../../shared/data/ict/neutral.obj", str(KIT / "identities" / f"{face}.obj"))
    config = config.replace("../../shared/data/ict/expressions/*.obj", "expressions/*.obj")
    config = config.replace("../../shared/data/ict/", str(KIT) + "/")
    (out / "rig.toml").write_text(f"# the ICT kit's {face} as a rig (bench/ict_identity_rig.py)\n" + config)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("face", choices=["face_a", "face_b"])
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    write_identity_rig(args.face, args.out)
    print(f"wrote {args.out}/rig.toml, expressions/, " + ", ".join(f"{t}, {m}" for t, m in TAKES.values()))


if __name__ == "__main__":
    main()
