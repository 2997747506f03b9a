"""Mesh reading/writing and the topology and input checks of facepipe.core.mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facepipe.errors import InputError
from facepipe.core.mesh import (Mesh, check_components, check_marker_vertices, check_mesh, check_pose, triangulate, unique_edges)
from facepipe.io.mesh_write import _format_rows, format_obj_faces, save_obj
from facepipe.io.mesh_read import load_mesh, load_vertices

SHARED = Path(__file__).parents[1] / ".." / "shared"
ICT = SHARED / "data" / "ict"


def needs_ict():
    if not (ICT / "neutral.obj").is_file():
        pytest.skip(f"the ICT kit is not there ({ICT}): /work/shared is absent in this checkout")


# ---------------------------------------------------------------------------------------------
# small meshes built in the tests

def grid(nx: int = 4, ny: int = 3, quads: bool = True, z=None) -> Mesh:
    """A flat nx x ny vertex grid in the xy plane, quads or triangles, with per-corner UVs."""
    u, v = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="ij")
    V = np.c_[u.ravel(), v.ravel(), np.zeros(nx * ny) if z is None else z]
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    if quads:
        polys = np.c_[a, b, c, d]
    else:
        polys = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    size = polys.shape[1]
    offsets = np.arange(0, size * len(polys) + 1, size)
    pv = polys.ravel()
    return Mesh(V, offsets, pv, uvs=V[:, :2] / max(nx, ny), polygon_uvs=pv.copy(), path="grid.obj")


def tri_mesh(V, F, path="test.obj") -> Mesh:
    F = np.asarray(F, dtype=np.int64)
    return Mesh(np.asarray(V, dtype=float), np.arange(0, 3 * len(F) + 1, 3), F.ravel(), path=path)


def message(exc_info) -> str:
    return str(exc_info.value)


# ---------------------------------------------------------------------------------------------
# triangulation and edges

def test_triangulate_ngon_fans_from_first_corner():
    offsets = np.array([0, 3, 7, 12])  # triangle, quad, pentagon
    corners = np.array([0, 1, 2, 2, 1, 3, 4, 4, 3, 5, 6, 7])
    tris, poly = triangulate(offsets, corners)
    assert tris.tolist() == [[0, 1, 2], [2, 1, 3], [2, 3, 4], [4, 3, 5], [4, 5, 6], [4, 6, 7]]
    assert poly.tolist() == [0, 1, 1, 2, 2, 2]


def test_mesh_faces_and_face_uvs_follow_polygons():
    m = grid(3, 3)
    assert m.faces.shape == (8, 3)
    assert m.face_polygon.tolist() == [0, 0, 1, 1, 2, 2, 3, 3]
    assert np.array_equal(m.face_uvs, m.faces)  # the grid's UV index is its vertex index


def test_unique_edges_of_two_triangles():
    assert unique_edges(np.array([[0, 1, 2], [0, 2, 3]])).tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]


# ---------------------------------------------------------------------------------------------
# check_mesh

def test_clean_grids_pass_check_mesh():
    check_mesh(grid())
    check_mesh(grid(5, 4, quads=False))


def test_nan_coordinates_name_the_vertex():
    m = grid()
    m.vertices[5, 1] = np.nan
    with pytest.raises(InputError) as e:
        check_mesh(m)
    assert "NaN" in message(e) and "vertex 5" in message(e) and "grid.obj" in message(e)


def test_non_manifold_edge_names_edge_and_face_count():
    # three triangles hinge on edge (0, 1): a fin, not a surface
    V = [[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]]
    F = [[0, 1, 2], [1, 0, 3], [0, 1, 4]]
    with pytest.raises(InputError) as e:
        check_mesh(tri_mesh(V, F))
    text = message(e)
    assert "non-manifold" in text and "edge (0, 1)" in text and "3 triangles" in text


def test_zero_area_triangle_names_polygon_and_vertices():
    # polygon 1 has three collinear corners
    V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0]]
    F = [[0, 1, 2], [1, 3, 4]]
    with pytest.raises(InputError) as e:
        check_mesh(tri_mesh(V, F))
    text = message(e)
    assert "zero-area" in text and "polygon 1" in text and "[1, 3, 4]" in text


def test_area_tolerance_is_relative_to_edge_length():
    # a sliver of relative area 1e-6: fine by default, degenerate for a stricter tolerance
    V = np.array([[0, 0, 0], [1, 0, 0], [0.5, 2e-6, 0]]) * 1000.0
    m = tri_mesh(V, [[0, 1, 2]])
    check_mesh(m)
    with pytest.raises(InputError, match="zero-area"):
        check_mesh(m, area_tolerance=1e-5)


def test_unreferenced_vertex_is_named_with_count_and_fix():
    m = grid()
    m.vertices = np.r_[m.vertices, [[9.0, 9.0, 9.0], [8.0, 8.0, 8.0]]]
    with pytest.raises(InputError) as e:
        check_mesh(m)
    text = message(e)
    assert "2 vertices are used by no face" in text and "vertex 12, 13" in text
    assert "remove them" in text and "reference them" in text


def test_repeated_vertex_in_polygon():
    m = grid()
    pv = m.polygon_vertices.copy()
    pv[4 * 2 + 3] = pv[4 * 2 + 1]  # polygon 2 lists a vertex twice
    m.polygon_vertices = pv
    with pytest.raises(InputError) as e:
        check_mesh(m)
    assert "use a vertex twice" in message(e) and "polygon 2" in message(e)


@pytest.mark.parametrize("sizes", [[3], [4], [3, 4, 5], [3, 9]])
def test_polygons_listing_a_vertex_twice_are_found_whatever_their_sizes(sizes):
    """Uniform sizes (a table), mixed small ones (corner pairs) and large ones (a sort) against a
    plain per-polygon count."""
    from facepipe.core.mesh import _polygons_with_repeats

    rng = np.random.default_rng(len(sizes))
    size = rng.choice(sizes, size=400)
    offsets = np.r_[0, np.cumsum(size)]
    pv = rng.integers(0, 40, size=offsets[-1])
    expected = [len(set(pv[a:b])) < b - a for a, b in zip(offsets[:-1], offsets[1:])]
    assert 0 < sum(expected) < 400
    assert _polygons_with_repeats(offsets, pv, size).tolist() == expected


def test_the_checked_mesh_gives_its_edges_once_each():
    m = grid()
    check_mesh(m)  # (it sorts the edges' keys, which the edges then reuse)
    expected = sorted({tuple(sorted((int(t[i]), int(t[(i + 1) % 3])))) for t in m.faces for i in range(3)})
    assert m.edges.tolist() == [list(e) for e in expected] and m.edges.dtype == np.int64
    assert unique_edges(m.faces).tolist() == m.edges.tolist()
    assert grid().edges.tolist() == m.edges.tolist()  # unchecked: the same


def test_repeated_vertex_in_large_ngon():
    # polygons bigger than the pairwise-comparison path go through the sorting path
    n = 12
    ring = np.c_[np.cos(np.arange(n) * 2 * np.pi / n), np.sin(np.arange(n) * 2 * np.pi / n), np.zeros(n)]
    corners = np.r_[np.arange(n - 1), 3]
    m = Mesh(ring, np.array([0, n]), corners, path="ngon.obj")
    with pytest.raises(InputError, match="polygon 0"):
        check_mesh(m)


def test_duplicated_triangle_at_a_border():
    V = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    with pytest.raises(InputError) as e:
        check_mesh(tri_mesh(V, [[0, 1, 2], [0, 2, 1]]))
    assert "duplicated" in message(e) and "polygons 0 and 1" in message(e)


def test_corner_out_of_range_and_short_polygon():
    m = tri_mesh(np.eye(3), [[0, 1, 7]])
    with pytest.raises(InputError, match="polygon 0 uses vertex 7"):
        check_mesh(m)
    m = Mesh(np.eye(3), np.array([0, 3, 5]), np.array([0, 1, 2, 0, 1]))
    with pytest.raises(InputError, match="polygon 1 has 2"):
        check_mesh(m)


def test_all_problems_are_listed_together():
    m = grid()
    m.vertices = np.r_[m.vertices, [[9.0, 9.0, 9.0]]]
    m.vertices[0, 0] = np.inf
    with pytest.raises(InputError) as e:
        check_mesh(m)
    assert "infinite" in message(e) and "used by no face" in message(e)


# ---------------------------------------------------------------------------------------------
# check_components

def two_grids() -> Mesh:
    a, b = grid(3, 3), grid(4, 3)
    V = np.r_[a.vertices, b.vertices + [10.0, 0, 0]]
    pv = np.r_[a.polygon_vertices, b.polygon_vertices + a.n_vertices]
    offsets = np.r_[a.polygon_offsets, b.polygon_offsets[1:] + a.polygon_offsets[-1]]
    return Mesh(V, offsets, pv, path="two.obj")


def test_component_without_handle_is_named():
    m = two_grids()
    with pytest.raises(InputError) as e:
        check_components(m, [0, 4], what="handle")
    text = message(e)
    assert "1 of the mesh's 2 connected parts have no handle" in text
    assert "12 vertices containing vertex 9" in text and "singular" in text


def test_components_each_constrained_pass():
    n, labels = check_components(two_grids(), [0, 10])
    assert n == 2 and labels.shape == (21,) and labels[0] != labels[20]


def test_isolated_vertex_is_its_own_component():
    m = grid(3, 3)
    m.vertices = np.r_[m.vertices, [[5.0, 5.0, 5.0]]]
    with pytest.raises(InputError, match=r"vertex 9 \(used by no face\)"):
        check_components(m, [0])


def test_constrained_vertex_out_of_range():
    with pytest.raises(InputError, match="anchor vertex 99"):
        check_components(grid(3, 3), [0, 99], what="anchor")


# ---------------------------------------------------------------------------------------------
# check_pose

def bumpy_grid(n: int = 12) -> Mesh:
    rng = np.random.default_rng(1)
    return grid(n, n, z=rng.normal(scale=0.2, size=n * n))


def test_pose_with_other_vertex_count():
    m = bumpy_grid()
    with pytest.raises(InputError) as e:
        check_pose(m, m.vertices[:-3], "smile.obj")
    text = message(e)
    assert "smile.obj" in text and "141 vertices" in text and "144" in text


def test_pose_with_permuted_vertices():
    m = bumpy_grid()
    rng = np.random.default_rng(0)
    with pytest.raises(InputError) as e:
        check_pose(m, m.vertices[rng.permutation(m.n_vertices)], "smile.obj")
    text = message(e)
    assert "vertex order differs" in text and "% of the" in text and "first offending vertex" in text


def test_pose_in_other_units():
    m = bumpy_grid()
    with pytest.raises(InputError, match="10 times the size"):
        check_pose(m, m.vertices * 10.0, "mm.obj")


def test_strong_expression_passes():
    # half of the grid stretched 1.9x (a jaw opening stretches edges by less), moved and rotated
    m = bumpy_grid()
    P = m.vertices.copy()
    P[:, 1] = np.where(P[:, 1] > 5, 5 + (P[:, 1] - 5) * 1.9, P[:, 1])
    c, s = np.cos(0.4), np.sin(0.4)
    P = P @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [3.0, -2.0, 1.0]
    check_pose(m, P, "jaw_open.obj")


def test_large_pose_checked_on_an_edge_sample_with_the_same_verdicts():
    """Past 400k edges a sample passes clearly good poses; anything else gets the exact check."""
    from facepipe.core import mesh as mesh_module

    m = bumpy_grid(400)  # 160k vertices, ~479k edges
    assert m.edges.shape[0] > 2 * mesh_module._CHECK_EDGES
    P = m.vertices.copy()
    y = float(np.median(P[:, 1]))
    P[:, 1] = np.where(P[:, 1] > y, y + (P[:, 1] - y) * 1.9, P[:, 1])
    check_pose(m, P, "jaw_open.obj")
    assert hasattr(m, "_sample_edge_lengths") and not hasattr(m, "_edge_lengths")  # passed on the sample
    rng = np.random.default_rng(0)
    # 3 % of the vertices swapped among themselves: near the limit, so every edge is measured
    swap = rng.choice(m.n_vertices, m.n_vertices * 3 // 100, replace=False)
    Q = m.vertices.copy()
    Q[swap] = Q[rng.permutation(swap)]
    with pytest.raises(InputError, match="vertex order differs"):
        check_pose(m, Q, "smile.obj")
    assert hasattr(m, "_edge_lengths")
    with pytest.raises(InputError, match="10 times the size"):
        check_pose(m, m.vertices * 10.0, "mm.obj")


def test_pose_with_nan():
    m = bumpy_grid()
    P = m.vertices.copy()
    P[7] = np.nan
    with pytest.raises(InputError, match="vertex 7"):
        check_pose(m, P, "bad.obj")


# ---------------------------------------------------------------------------------------------
# check_marker_vertices

def test_marker_out_of_range_names_marker_and_line():
    with pytest.raises(InputError) as e:
        check_marker_vertices([3, 120, 5], 100, ["M1", "M2", "M3"], "markers.csv", lines=[2, 3, 4])
    text = message(e)
    assert "markers.csv" in text and "'M2' (line 3)" in text and "120" in text and "100 vertices" in text


def test_marker_negative_without_lines_names_entry():
    with pytest.raises(InputError, match=r"'chin' \(entry 2\): vertex -1"):
        check_marker_vertices([3, -1], 10, ["nose", "chin"], "markers.csv")


def test_duplicate_marker_vertex_names_both_markers():
    with pytest.raises(InputError) as e:
        check_marker_vertices([3, 7, 3], 10, ["a", "b", "c"], "markers.csv", lines=[2, 3, 4])
    text = message(e)
    assert "'a' (line 2)" in text and "'c' (line 4)" in text and "vertex 3" in text


def test_duplicate_marker_name():
    with pytest.raises(InputError, match="'a' \\(line 3\\): the name is used before"):
        check_marker_vertices([3, 7], 10, ["a", "a"], "markers.csv", lines=[2, 3])


def test_fractional_marker_vertex():
    with pytest.raises(InputError, match="not a whole number"):
        check_marker_vertices(np.array([1.0, 2.5]), 10, ["a", "b"], "markers.csv")


def test_good_markers_pass():
    check_marker_vertices(np.array([0, 9, 4]), 10, ["a", "b", "c"], "markers.csv")


# ---------------------------------------------------------------------------------------------
# OBJ reading

MIXED_OBJ = """# a triangle, a quad and a pentagon in two groups
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0 0
v 2 1 0
v 3 0.5 0
v 0.5 -1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 0.5
vn 0 0 1
g cheek
f 1/1 2/2 3/3 4/4
f 2/2 5/1 6/3 3/3
g lip
usemtl skin
s 1
f 5/1 7/5 6/2
f 1/1 8/2 2/3
"""


def write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    p = tmp_path / name
    if isinstance(text, str):
        p.write_text(text)
    else:
        p.write_bytes(text)
    return p


def test_obj_polygons_uvs_and_groups(tmp_path):
    m = load_mesh(write(tmp_path, "mixed.obj", MIXED_OBJ))
    assert m.n_vertices == 8 and m.n_polygons == 4
    assert m.polygon_sizes.tolist() == [4, 4, 3, 3]
    assert m.polygon_vertices.tolist() == [0, 1, 2, 3, 1, 4, 5, 2, 4, 6, 5, 0, 7, 1]
    assert m.polygon_uvs.tolist() == [0, 1, 2, 3, 1, 0, 2, 2, 0, 4, 1, 0, 1, 2]
    assert m.uvs.shape == (5, 2) and m.uvs[4].tolist() == [0.5, 0.5]
    assert [m.group_names[g] for g in m.polygon_groups] == ["cheek", "cheek", "lip", "lip"]
    check_mesh(m)


def test_obj_negative_indices_and_normals(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf -3//1 -2//1 -1//1\nv 1 1 0\nf 2//1 4//1 3//1\n"
    m = load_mesh(write(tmp_path, "neg.obj", text))
    assert m.polygon_vertices.tolist() == [0, 1, 2, 1, 3, 2]
    assert m.uvs is None and m.polygon_uvs is None


def test_obj_v_vt_vn_and_ngon(tmp_path):
    text = ("v 0 0 0\nv 1 0 0\nv 2 1 0\nv 1 2 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt .5 .5\n"
            "vn 0 0 1\nf 1/1/1 2/2/1 3/3/1 4/4/1 5/5/1\n")
    m = load_mesh(write(tmp_path, "ngon.obj", text))
    assert m.polygon_sizes.tolist() == [5]
    assert m.polygon_uvs.tolist() == [0, 1, 2, 3, 4]
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 3, 4]]


def test_obj_mixed_corner_layouts_and_continuation(tmp_path):
    text = "v 0 0 0\nv 1 0 0 # origin + x\nv 0 1 0\nv 1 1 0 0.5 0.5 0.5\nf 1 2 3\nf 2 \\\n 4 3\n"
    m = load_mesh(write(tmp_path, "plain.obj", text))
    assert m.polygon_vertices.tolist() == [0, 1, 2, 1, 3, 2]
    assert m.vertices[3].tolist() == [1, 1, 0]  # vertex colours after x y z are ignored


@pytest.mark.parametrize(
    "text, expected",
    [
        ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", r"line 2: a vertex needs three numbers"),
        ("v 0 0 0\nv 1 0 zero\nv 0 1 0\nf 1 2 3\n", r"line 2: a vertex needs three numbers"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", r"line 4: bad vertex index 'x'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", r"line 4: vertex index 9 is out of range: the file has 3"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"line 4: vertex index 0 is out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -4 1 2\n", r"line 4: vertex index -4 is out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n",
         r"line 4: vertex index 99999999999999999999999 is out of range: the file has 3"),  # past int64
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r"line 4: a face needs at least three corners"),
        ("v 0 0 0\nhello world\n", r"line 2: unknown OBJ statement 'hello world'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\nf 1 2 3\n", r"line 6: this face has corners without"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/5 3/1\n", r"line 5: texture index 5 is out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt zero 0\nf 1/1 2/1 3/1\n", r"line 4: bad texture coordinate"),
        ("# nothing\n", r"no vertices"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"3 vertices but no faces"),
        ("", r"the file is empty"),
        ("  \n\n", r"the file is empty"),
        ("\t \r\n\x0b\x0c", r"the file is empty"),  # every byte that strip() takes for blank
    ],
)
def test_obj_garbage_is_an_input_error_naming_the_line(tmp_path, text, expected):
    p = write(tmp_path, "bad.obj", text)
    with pytest.raises(InputError, match=expected) as e:
        load_mesh(p)
    assert str(p) in message(e)


def test_truncated_obj_says_so(tmp_path):
    p = write(tmp_path, "cut.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\nf 1/1 2/1 3/")
    with pytest.raises(InputError) as e:
        load_mesh(p)
    assert "line 6" in message(e) and "truncated" in message(e)


def test_binary_file_with_obj_name(tmp_path):
    p = write(tmp_path, "model.obj", b"ply\nformat binary_little_endian 1.0\n\x00\x01\x02")
    with pytest.raises(InputError, match="not a text OBJ file"):
        load_mesh(p)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "nope.obj")


# ---------------------------------------------------------------------------------------------
# OBJ writing

def test_obj_round_trip_keeps_everything(tmp_path):
    m = load_mesh(write(tmp_path, "mixed.obj", MIXED_OBJ))
    rng = np.random.default_rng(3)
    moved = m.vertices + rng.normal(size=m.vertices.shape)
    save_obj(tmp_path / "out.obj", m, moved)
    back = load_mesh(tmp_path / "out.obj")
    np.testing.assert_allclose(back.vertices, moved, rtol=1e-8, atol=1e-12)
    assert np.array_equal(back.polygon_offsets, m.polygon_offsets)
    assert np.array_equal(back.polygon_vertices, m.polygon_vertices)
    assert np.array_equal(back.polygon_uvs, m.polygon_uvs)
    np.testing.assert_allclose(back.uvs, m.uvs)
    assert [back.group_names[g] for g in back.polygon_groups] == [m.group_names[g] for g in m.polygon_groups]


def test_obj_round_trip_triangles_without_uvs(tmp_path):
    m = grid(5, 4, quads=False)
    m = Mesh(m.vertices, m.polygon_offsets, m.polygon_vertices)
    save_obj(tmp_path / "tri.obj", m)
    back = load_mesh(tmp_path / "tri.obj")
    assert back.polygon_uvs is None and np.array_equal(back.faces, m.faces)
    assert "g " not in (tmp_path / "tri.obj").read_text()  # no groups: no g lines


def naive_faces(m: Mesh) -> bytes:
    out = []
    last = None
    named = any(m.group_names[g] != "default" for g in np.unique(m.polygon_groups))
    for k in range(m.n_polygons):
        if named and m.polygon_groups[k] != last:
            out.append(f"g {m.group_names[m.polygon_groups[k]]}")
            last = m.polygon_groups[k]
        s, e = m.polygon_offsets[k], m.polygon_offsets[k + 1]
        if m.polygon_uvs is None:
            out.append("f " + " ".join(str(v + 1) for v in m.polygon_vertices[s:e]))
        else:
            out.append("f " + " ".join(f"{v + 1}/{t + 1}" for v, t in
                                        zip(m.polygon_vertices[s:e], m.polygon_uvs[s:e], strict=True)))
    return ("\n".join(out) + "\n").encode()


def test_format_obj_faces_matches_a_line_by_line_writer(tmp_path):
    m = load_mesh(write(tmp_path, "mixed.obj", MIXED_OBJ))
    assert format_obj_faces(m) == naive_faces(m)
    # interleaved sizes and group runs, indices with different digit counts
    rng = np.random.default_rng(5)
    sizes = rng.integers(3, 7, size=300)
    offsets = np.r_[0, np.cumsum(sizes)]
    pv = rng.integers(0, 12345, size=offsets[-1])
    groups = np.repeat(np.arange(6) % 3, 50).astype(np.int32)
    m2 = Mesh(np.zeros((12345, 3)), offsets, pv, np.zeros((99, 2)), rng.integers(0, 99, size=offsets[-1]),
              groups, ["default", "a", "b c"])
    assert format_obj_faces(m2) == naive_faces(m2)


def test_format_rows_text():
    assert _format_rows(b"v", np.array([[1.5, -2.0, 0.0], [-0.0, 1e-3, 123.25]])) == \
        b"v 1.5 -2 0\nv 0 0.001 123.25\n"
    assert _format_rows(b"vt", np.array([[0.5, 1.0]])) == b"vt 0.5 1\n"
    assert _format_rows(b"v", np.array([[9.9999999996, -0.99999999996, 0.125]])) == b"v 10 -1 0.125\n"
    assert _format_rows(b"v", np.array([[np.nan, 1.0, 2.0]])) == b"v nan 1 2\n"  # printf fallback


def test_format_rows_gives_float32_back_exactly():
    # face-mesh-like values: cm around the origin, some near zero
    rng = np.random.default_rng(7)
    x = (rng.normal(scale=8.0, size=(5000, 3)) * 10.0 ** rng.integers(-3, 1, size=(5000, 3))).astype(np.float32)
    x[:10] = 0
    text = _format_rows(b"v", x).decode()
    back = np.array(text.replace("v", " ").split(), dtype=np.float64).reshape(-1, 3)
    assert np.array_equal(back.astype(np.float32), x)


def test_format_rows_agrees_with_printf():
    rng = np.random.default_rng(8)
    x = rng.normal(size=(2000, 3)) * 10.0 ** rng.integers(-2, 4, size=(2000, 3))
    text = _format_rows(b"v", x).decode()
    back = np.array(text.replace("v", " ").split(), dtype=np.float64).reshape(-1, 3)
    ref = np.array([float("%.9g" % v) for v in x.ravel()]).reshape(-1, 3)
    # 9 significant digits, down to an absolute floor of ~1e-16 x the block's largest value
    np.testing.assert_allclose(back, ref, rtol=1e-9, atol=1e-15 * np.abs(x).max())
    np.testing.assert_allclose(back, x, rtol=5.1e-9, atol=1e-15 * np.abs(x).max())
    assert "e" not in text


# ---------------------------------------------------------------------------------------------
# PLY through trimesh

def test_ply_round_trip_keeps_vertex_order(tmp_path):
    import trimesh

    rng = np.random.default_rng(2)
    m = grid(6, 5, quads=False)
    V = m.vertices + rng.normal(scale=0.01, size=m.vertices.shape)
    F = m.faces
    # scramble the vertex order so that a re-ordering reader would be caught
    perm = rng.permutation(len(V))
    inv = np.argsort(perm)
    V, F = V[perm], inv[F]
    for encoding in ("binary", "ascii"):
        data = trimesh.exchange.ply.export_ply(trimesh.Trimesh(V, F, process=False), encoding=encoding)
        p = write(tmp_path, f"m_{encoding}.ply", data)
        back = load_mesh(p)
        np.testing.assert_allclose(back.vertices, V, rtol=1e-6, atol=1e-6)
        assert np.array_equal(back.faces, F)
        assert np.array_equal(load_vertices(p), back.vertices)
        check_mesh(back)


def test_ply_garbage_and_empty(tmp_path):
    with pytest.raises(InputError, match="cannot read mesh"):
        load_mesh(write(tmp_path, "junk.ply", b"this is no ply\n\x00\x01"))
    with pytest.raises(InputError, match="empty"):
        load_mesh(write(tmp_path, "empty.ply", b""))


def test_ply_point_cloud_has_no_faces(tmp_path):
    text = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n" \
           "end_header\n0 0 0\n1 0 0\n0 1 0\n"
    with pytest.raises(InputError, match="3 vertices but no faces"):
        load_mesh(write(tmp_path, "cloud.ply", text))


# ---------------------------------------------------------------------------------------------
# the ICT kit

@pytest.mark.ict
def test_ict_neutral_passes_the_checks():
    needs_ict()
    m = load_mesh(ICT / "neutral.obj")
    assert m.n_vertices == 11248 and m.n_polygons == 11144
    assert set(m.polygon_sizes.tolist()) == {4} and m.polygon_uvs is not None
    check_mesh(m)
    rows = [line.split(",") for line in (ICT / "markers.csv").read_text().splitlines()[1:] if line.strip()]
    names = [r[0] for r in rows]
    markers = np.array([int(r[1]) for r in rows])
    check_marker_vertices(markers, m.n_vertices, names, ICT / "markers.csv", lines=list(range(2, len(rows) + 2)))
    anchors = np.loadtxt(ICT / "anchors.txt", dtype=np.int64)
    check_components(m, np.r_[markers, anchors])


@pytest.mark.ict
def test_ict_expressions_pass_check_pose_and_permutation_is_caught():
    needs_ict()
    m = load_mesh(ICT / "neutral.obj")
    for name in ("jawOpen", "mouthClose", "mouthRollLower", "eyeBlink_L"):
        path = ICT / "expressions" / f"{name}.obj"
        check_pose(m, load_vertices(path), path)
    P = load_vertices(ICT / "expressions" / "jawOpen.obj")
    perm = np.random.default_rng(0).permutation(len(P))
    with pytest.raises(InputError, match="vertex order differs"):
        check_pose(m, P[perm], "jawOpen_reordered.obj")


# ---------------------------------------------------------------------------------------------
# the fast (numpy) OBJ reader against a plain line-by-line reference

def reference_obj(text: str):
    """A minimal OBJ reader written for the tests: one statement at a time, no shortcuts."""
    verts, uvs, offsets, corners_v, corners_t, groups, names = [], [], [0], [], [], [], ["default"]
    group = 0
    for raw in text.splitlines():
        parts = raw.split("#")[0].split()
        if not parts:
            continue
        tag, args = parts[0], parts[1:]
        if tag == "v":
            verts.append([float(x) for x in args[:3]])
        elif tag == "vt":
            uvs.append([float(args[0]), float(args[1]) if len(args) > 1 else 0.0])
        elif tag in ("f", "fo"):
            for c in args:
                fields = c.split("/")
                v = int(fields[0])
                corners_v.append(v - 1 if v > 0 else len(verts) + v)
                if len(fields) > 1 and fields[1]:
                    t = int(fields[1])
                    corners_t.append(t - 1 if t > 0 else len(uvs) + t)
            offsets.append(len(corners_v))
            groups.append(group)
        elif tag in ("g", "o"):
            name = " ".join(args) or "default"
            if name not in names:
                names.append(name)
            group = names.index(name)
    return (np.array(verts), np.array(offsets), np.array(corners_v), np.array(uvs).reshape(-1, 2),
            np.array(corners_t) if corners_t else None, np.array(groups), names)


TRICKY_OBJS = {
    "crlf_comments_tabs": (
        "# header\r\nv 0 0 0 # a comment after a statement\r\nv\t1.5e0  0 -0\r\n  v 0 1 0\r\n"
        "v -1E-1 +2 3.25 0.5 0.5 0.5\r\nvt 0 0 0\r\nvt 1\r\nvt .5 .25\r\nvn 0 0 1\r\ns 1\r\n"
        "usemtl skin\r\ng cheek  left\r\nf 1/1/1 2/2/1 3/3/1 4/1/1\r\no lip\r\nfo 2/2/1 3/3/1 4/1/1\r\n"
        "g cheek left\r\nf 4/3/1 1/2/1 2/1/1 3/3/1 4/2/1"),  # no line end at the end
    "negative_and_forward": (
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nf 1 2 5\nv 1 1 0\nv 2 2 0\nf -1 -2 -3 1\n"),
    "v_double_slash_vn": "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\nf 2//1 4//1 3//1\n",
    "v_vt_negative": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf -3/-3 -2/-2 -1/-1\n"
                      "vt 1 1\nv 1 1 0\nf 2/2 -1/-1 3/3\ng\nf 1/1 2/2 3/3\n"),
    "ngons_and_groups": ("v 0 0 0\nv 1 0 0\nv 2 1 0\nv 1 2 0\nv 0 1 0\nv 3 3 3\n"
                         "g a\nf 1 2 3 4 5\ng b\nf 1 2 6\ng a\nf 2 3 6 4\nf 1 2 3\n"),
    "long_numbers": ("v 0.123456789012345678 -123456.5 1e-300\nv 12345678901234567890 0.5 -.5\n"
                     "v 1. 2 3\nf 1 2 3\n"),
}


@pytest.mark.parametrize("name", sorted(TRICKY_OBJS))
def test_fast_obj_reader_matches_a_line_by_line_reference(tmp_path, name):
    from facepipe.io.mesh_read import _fast_obj, _parse_obj_lists

    text = TRICKY_OBJS[name]
    p = write(tmp_path, f"{name}.obj", text.encode())
    fast = _fast_obj(p.read_bytes(), p)
    assert fast is not None  # the fast path reads these itself
    V, offsets, cv, uvs, ct, groups, names = reference_obj(text)
    assert np.array_equal(fast.vertices, V)
    assert np.array_equal(fast.polygon_offsets, offsets)
    assert np.array_equal(fast.polygon_vertices, cv)
    if ct is None:
        assert fast.polygon_uvs is None and fast.uvs is None
    else:
        assert np.array_equal(fast.polygon_uvs, ct) and np.array_equal(fast.uvs, uvs)
    assert [fast.group_names[g] for g in fast.polygon_groups] == [names[g] for g in groups]
    # and the list-based reader (the fallback) reads the same
    slow = _parse_obj_lists(p, p.read_bytes())
    for key in ("vertices", "polygon_offsets", "polygon_vertices", "uvs", "polygon_uvs", "polygon_groups"):
        a, b = getattr(fast, key), getattr(slow, key)
        assert (a is None and b is None) or (a.dtype == b.dtype and np.array_equal(a, b)), key
    assert fast.group_names == slow.group_names
    assert np.array_equal(load_vertices(p), V)


def test_fast_obj_reader_on_a_large_random_mesh(tmp_path):
    from facepipe.io.mesh_read import _fast_obj, _parse_obj_lists

    rng = np.random.default_rng(11)
    V = rng.normal(size=(3000, 3)) * 10.0 ** rng.integers(-4, 4, size=(3000, 3))
    sizes = rng.integers(3, 6, size=2000)
    lines = [f"v {float(x)!r} {y:.6f} {z:.9g}" for x, y, z in V]
    lines += [f"vt {u:.5f} {v:.5f}" for u, v in rng.random((500, 2))]
    for k, n in enumerate(sizes):
        if k % 500 == 0:
            lines.append(f"g part{k // 500 % 3}")
        lines.append("f " + " ".join(f"{a}/{b}" for a, b in zip(rng.integers(1, 3001, n), rng.integers(1, 501, n))))
    p = write(tmp_path, "big.obj", "\n".join(lines) + "\n")
    fast = _fast_obj(p.read_bytes(), p)
    slow = _parse_obj_lists(p, p.read_bytes())
    assert fast is not None
    for key in ("vertices", "polygon_offsets", "polygon_vertices", "uvs", "polygon_uvs", "polygon_groups"):
        assert np.array_equal(getattr(fast, key), getattr(slow, key)), key
    assert fast.group_names == slow.group_names
    assert np.array_equal(fast.vertices[:, 0], V[:, 0])  # repr: exact
    assert np.array_equal(load_vertices(p), slow.vertices)  # the positions-only path
    for text in (b"v 1 2 3\nv 4 5 6\nv", b"v 1 2 3\r\nv 4 5 6 1\r\n", b"v 1 2 3\nv 4  5 6\n", b"v 1 2 3\n  v 4 5 6\n",
                 # vertices after the faces, plain or indented (the faces after the last vertex are skipped)
                 b"v 1 2 3\nf 1 1 1\nv 4 5 6\nf 1 2 2\n", b"v 1 2 3\nf 1 1 1\n v 4 5 6\nf 1 2 2\n",
                 b"v 1 2 3\nvt 0 0\nf 1/1 1/1 1/1\n\tv 4 5 6\n", b"v 1 2 3\r\nv 4 5 6\r\nf 1 2 2\r\n"):
        p = write(tmp_path, "pts.obj", text)
        if text.endswith(b"v"):
            with pytest.raises(InputError, match="line 3"):
                load_vertices(p)
        else:
            assert load_vertices(p).tolist() == [[1, 2, 3], [4, 5, 6]]


@pytest.mark.parametrize("text", [b"v 1 2\nv 4 5 6 7\nf 1 2 2\n",                # one block of vertex lines
                                  b"v 1 2\nvn 0 0 1\nv 4 5 6 7\nf 1 2 2\n"])   # two blocks
def test_positions_of_lines_with_two_and_four_numbers_are_not_shifted(tmp_path, text):
    """Six numbers in two vertex lines are not two vertices when one line has two of them: the
    positions-only reader names the short line as the full reader does."""
    p = write(tmp_path, "short.obj", text)
    for read in (load_vertices, load_mesh):
        with pytest.raises(InputError, match="line 1: a vertex needs three numbers"):
            read(p)


def _plain_mesh_text(rng, corners: int, layout: str) -> str:
    V = rng.normal(size=(400, 3)) * 10.0 ** rng.integers(-3, 3, size=(400, 3))
    lines = [f"v {float(x)!r} {y:.6f} {z:.9g}" for x, y, z in V]
    lines += [f"vt {u:.5f} {v:.5f}" for u, v in rng.random((90, 2))]
    lines += ["vn 0 0 1", "vn 0 1 0"]
    for _ in range(300):
        vs, ts = rng.integers(1, 401, corners), rng.integers(1, 91, corners)
        vs = np.where(rng.random(corners) < 0.1, vs - 401, vs)  # some relative (negative) indices
        fields = {"v": [f"{a}" for a in vs], "v/vt": [f"{a}/{b}" for a, b in zip(vs, ts)],
                  "v/vt/vn": [f"{a}/{b}/{1 + a % 2}" for a, b in zip(vs, ts)]}[layout]
        lines.append("f " + " ".join(fields))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("corners", [3, 4])
@pytest.mark.parametrize("layout", ["v", "v/vt", "v/vt/vn"])
def test_plain_obj_reader_matches_the_reference(tmp_path, corners, layout):
    """The plain layout's reader (line starts only) reads exactly what the list reader reads."""
    from facepipe.io.mesh_read import _parse_obj_lists, _plain_obj

    p = write(tmp_path, "plain.obj", _plain_mesh_text(np.random.default_rng(corners), corners, layout))
    plain = _plain_obj(p.read_bytes(), p)
    assert plain is not None
    slow = _parse_obj_lists(p, p.read_bytes())
    for key in ("vertices", "polygon_offsets", "polygon_vertices", "uvs", "polygon_uvs", "polygon_groups"):
        a, b = getattr(plain, key), getattr(slow, key)
        assert (a is None and b is None) or (a.dtype == b.dtype and np.array_equal(a, b)), key
    assert plain.group_names == slow.group_names


@pytest.mark.parametrize("text", [
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 1 2 4 3\n",        # triangles and quads
    "v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\nf 1 2 3\n",                  # a vertex after a face
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2  3\n",                          # a doubled space
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3 \n",                          # a trailing space
    "v 0 0 0 1\nv 1 0 0 1\nv 0 1 0 1\nf 1 2 3\n",                      # a fourth coordinate
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0 0\nvt 1 0 0\nvt 0 1 0\nf 1/1 2/2 3/3\n",  # a third texture coordinate
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\n",      # v//vn
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nf 1/1/1 2/1/1 3/1/1\nf 1/1 2/1 3/1\n",  # two corner layouts
    "v 0 0 0\nv 1 0 0\nv 0 1 0\ng part\nf 1 2 3\n",                  # a group
    "v 0 0 0\nvt 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",                  # vertices in two blocks
    "v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 3\n",                        # a blank line
])
def test_other_obj_layouts_leave_the_plain_reader(tmp_path, text):
    """Files off the plain layout are declined by its reader and read as the list reader reads them."""
    from facepipe.io.mesh_read import _parse_obj_lists, _plain_obj

    p = write(tmp_path, "odd.obj", text.encode())
    assert _plain_obj(p.read_bytes(), p) is None
    m, ref = load_mesh(p), _parse_obj_lists(p, p.read_bytes())
    assert np.array_equal(m.polygon_vertices, ref.polygon_vertices) and np.array_equal(m.vertices, ref.vertices)
    assert np.array_equal(m.polygon_offsets, ref.polygon_offsets)


@pytest.mark.parametrize("text", [
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nvn 0 0 1\nf 1//1 2//1 3//1\n",  # mixed corner layouts
    "v 0 0 0\rv 1 0 0\rv 0 1 0\rf 1 2 3\r",                    # old Mac line ends
    "v 0 0 0\nv 1 0 \\\n 0\nv 0 1 0\nf 1 2 3\n",              # a continuation
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nf 1/1/1 2/2/1 3/1/1\nf 1/1 2/2 3/1\n",  # v/vt/vn and v/vt
    "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",                  # a number numpy would read differently
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\ng caf\u00e9\u00a0x\nf 1 2 3\n",  # non-ASCII space in a name
])
def test_unusual_obj_files_are_read_by_the_list_reader(tmp_path, text):
    from facepipe.io.mesh_read import _parse_obj_lists

    p = write(tmp_path, "odd.obj", text.encode())
    m = load_mesh(p)
    ref = _parse_obj_lists(p, p.read_bytes())
    assert np.array_equal(m.polygon_vertices, ref.polygon_vertices)
    assert np.array_equal(m.vertices, ref.vertices, equal_nan=True)
    assert m.group_names == ref.group_names


# ---------------------------------------------------------------------------------------------
# reading leaves the process as it found it

def test_reading_obj_leaves_garbage_collector_and_warning_filters_alone(tmp_path, monkeypatch):
    """Neither reader switches the garbage collector off nor changes the warning filters (both are
    process-wide: another thread would see them changed)."""
    import gc
    import warnings

    calls = []
    monkeypatch.setattr(gc, "disable", lambda: calls.append("gc.disable"))
    monkeypatch.setattr(warnings, "simplefilter", lambda *a, **k: calls.append("simplefilter"))
    monkeypatch.setattr(warnings, "catch_warnings", lambda *a, **k: calls.append("catch_warnings"))
    fast = tmp_path / "fast.obj"
    fast.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    slow = tmp_path / "slow.obj"  # a continuation line: only the line-by-line reader takes it
    slow.write_text("v 0 0 \\\n0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    bad = tmp_path / "bad.obj"  # the fast path's numbers parse, but not as plain numbers
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0-\nf 1 2 3\n")
    assert load_mesh(fast).n_vertices == 3 and load_mesh(slow).n_vertices == 3
    with pytest.raises(InputError, match="line 3"):
        load_mesh(bad)
    assert calls == []


@pytest.mark.parametrize("last", ["0-", "0e", "1.5.", "+-2"])
def test_a_last_coordinate_with_trailing_garbage_is_named(tmp_path, last):
    p = tmp_path / "m.obj"
    p.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 {last}\nf 1 2 3\n")
    with pytest.raises(InputError, match="line 3"):
        load_mesh(p)
