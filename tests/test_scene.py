"""Tests for the extended-OBJ scene parser (jaxplush.scene.parse): every documented error names
file, line and problem; every accepted form parses to the intended geometry and parameters;
the shipped scenes round-trip through jaxplush.scene.write.format_scene."""

from __future__ import annotations

import glob
import os
import re
import warnings

import numpy as np
import pytest
import trimesh

import jaxplush
from jaxplush.errors import SceneError
from jaxplush.scene.parse import DEFAULT_GRAVITY, DEFAULT_TEMPERATURE, DEFAULTS
from jaxplush.scene.write import format_scene

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = sorted(glob.glob(os.path.join(REPO, "scenes", "*.obj")))

_ICO = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
SV = np.asarray(_ICO.vertices, np.float64)   # (42, 3)
SF = np.asarray(_ICO.faces, np.int64)        # (80, 3), outward
NV, NF = len(SV), len(SF)

HERE = "# <- HERE"  # marks the line an error must name (comments are ignored by the parser)


# ----------------------------------------------------------------------------------- helpers

def v_lines(vertices):
    return [f"v {a!r} {b!r} {c!r}" for a, b, c in np.asarray(vertices, np.float64).tolist()]


def f_lines(faces, offset=0):
    """1-based global face lines for 0-based faces of an object whose vertices start at ``offset``."""
    return [f"f {a} {b} {c}" for a, b, c in (np.asarray(faces) + offset + 1).tolist()]


def sphere(name="ball", keys=(), offset=0, faces=None, vertices=None, end=True, fixed=()):
    """Lines of one icosphere object; ``offset`` = number of vertices defined before it."""
    out = [f"o {name}"] if name else []
    out += list(keys)
    out += v_lines(SV if vertices is None else vertices)
    out += f_lines(SF if faces is None else faces, offset)
    out += [f"fixed {i + offset + 1}" for i in fixed]
    if end:
        out.append("END_OBJECT")
    return out


def write(tmp_path, content, name="scene.obj"):
    path = tmp_path / name
    if isinstance(content, (list, tuple)):
        content = "\n".join(content) + "\n"
    if isinstance(content, str):
        path.write_text(content, encoding="utf-8", newline="")
    else:
        path.write_bytes(content)
    return path


def load(tmp_path, content, name="scene.obj"):
    return jaxplush.load_scene(write(tmp_path, content, name))


def marked_line(lines):
    """1-based number of the line carrying the HERE marker."""
    hits = [i + 1 for i, ln in enumerate(lines) if ln.endswith(HERE)]
    assert len(hits) == 1, hits
    return hits[0]


def mark(lines, i):
    lines = list(lines)
    lines[i] = lines[i] + "  " + HERE
    return lines


def marked_face(lines, face_index, first_f=None):
    """Mark the line of the face_index-th 'f' line (counting from ``first_f``, default the first)."""
    f_idx = [i for i, ln in enumerate(lines) if ln.startswith("f ")]
    start = 0 if first_f is None else f_idx.index(first_f)
    return mark(lines, f_idx[start + face_index])


def edges_of(face):
    a, b, c = (int(t) for t in face)
    return {frozenset((a, b)), frozenset((b, c)), frozenset((c, a))}


# ------------------------------------------------------------------------------ bad inputs
# Each builder returns (content, expected_line, phrase). expected_line: an int, None (no line
# applies), "marked" (the line carrying HERE) or a set of admissible lines.

def _in_sphere(extra, at=None):
    """A valid sphere scene with extra lines inserted after the 'o' line (or at index ``at``)."""
    lines = sphere()
    at = 1 if at is None else at
    return lines[:at] + list(extra) + lines[at:]


def case_unknown_keyword():
    return _in_sphere(["frobnicate 3 " + HERE]), "marked", "unknown keyword 'frobnicate'"


def case_unknown_keyword_case():
    return _in_sphere(["END_object " + HERE], at=len(sphere()) - 1), "marked", "unknown keyword"


def case_missing_value():
    return _in_sphere(["k_structural " + HERE]), "marked", "expects 1 value(s), got 0"


def case_missing_coordinate():
    lines = sphere()
    lines = lines[:1] + ["v 1.0 2.0  " + HERE] + lines[1:]
    return lines, "marked", "'v' expects 3 coordinates, got 2"


def case_non_numeric_vertex():
    lines = sphere()
    lines[3] = "v 0.1 abc 0.2  " + HERE
    return lines, "marked", "expects a number, got 'abc'"


def case_non_numeric_param():
    return _in_sphere(["total_weight heavy  " + HERE]), "marked", "expects a number, got 'heavy'"


def case_nan_vertex():
    lines = sphere()
    lines[5] = "v nan 0 0  " + HERE
    return lines, "marked", "not finite"


def case_inf_vertex():
    lines = sphere()
    lines[5] = "v 0 -inf 0  " + HERE
    return lines, "marked", "not finite"


def case_overflowing_vertex():
    lines = sphere()
    lines[5] = "v 1e999 0 0  " + HERE  # parses to inf
    return lines, "marked", "not finite"


def case_inf_param():
    return _in_sphere(["k_structural inf  " + HERE]), "marked", "not finite"


def case_nan_gravity():
    return ["gravity 0 nan 0  " + HERE] + sphere(), "marked", "not finite"


def case_gravity_two_values():
    return ["gravity 0 -9.81  " + HERE] + sphere(), "marked", "expects 3 value(s), got 2"


def case_translate_four_values():
    return _in_sphere(["translate 1 2 3 4  " + HERE]), "marked", "expects 3 value(s), got 4"


def case_floor_two_values():
    return ["floor -1 0  " + HERE] + sphere(), "marked", "expects 1 value(s), got 2"


def case_face_two_vertices():
    return sphere() [:-1] + ["f 1 2  " + HERE, "END_OBJECT"], "marked", "at least 3 vertices"


def case_face_index_out_of_range():
    lines = sphere()
    lines = marked_face(lines, 10)
    f = [i for i, ln in enumerate(lines) if ln.endswith(HERE)][0]
    lines[f] = f"f 1 2 {NV + 57}  " + HERE
    return lines, "marked", f"face index {NV + 57} out of range"


def case_relative_index_out_of_range():
    lines = sphere()
    lines = lines[:-1] + [f"f -1 -2 -{NV + 5}  " + HERE, "END_OBJECT"]
    return lines, "marked", "points before the first vertex"


def case_zero_face_index():
    lines = sphere()
    lines = lines[:-1] + ["f 0 1 2  " + HERE, "END_OBJECT"]
    return lines, "marked", "vertex index 0 is invalid"


def case_non_integer_face_index():
    lines = sphere()
    lines = lines[:-1] + ["f 1 2 3.5  " + HERE, "END_OBJECT"]
    return lines, "marked", "expects a vertex index, got '3.5'"


def case_degenerate_repeated_vertex():
    lines = sphere()
    lines = lines[:-1] + ["f 1 1 2  " + HERE, "END_OBJECT"]
    return lines, "marked", "degenerate face"


def case_degenerate_zero_area():
    # A tetrahedron whose vertices 1, 2, 3 are collinear: face (1, 2, 3) has zero area.
    lines = ["v 0 0 0", "v 1 0 0", "v 2 0 0", "v 0 1 0.5",
             "f 1 2 4", "f 2 3 4", "f 3 1 4", "f 1 3 2  " + HERE]
    return lines, "marked", "degenerate face (zero area"


def case_open_mesh():
    removed = 7
    faces = np.delete(SF, removed, axis=0)
    lines = sphere(faces=faces)
    # The parser names the first face (in file order) that has a boundary edge.
    hole = edges_of(SF[removed])
    first = next(i for i, f in enumerate(faces) if edges_of(f) & hole)
    return marked_face(lines, first), "marked", "open mesh"


def case_non_manifold_edge():
    # A fin: a new vertex and two faces on edge (a, b) of face 0 -> edge (a, b) has 4 faces.
    a, b, _ = SF[0]
    lines = sphere(end=False)
    lines += ["v 0.5 0.5 0.5", f"f {a + 1} {b + 1} {NV + 1}", f"f {b + 1} {a + 1} {NV + 1}", "END_OBJECT"]
    return marked_face(lines, 0), "marked", "non-manifold edge"


def case_non_manifold_vertex_pinched():
    # Merge the vertex opposite vertex 1 into vertex 1: one connected surface whose faces around
    # vertex 1 form two fans (a pinched sphere).
    far = int(np.argmax(np.linalg.norm(SV - SV[0], axis=1)))
    faces = SF.copy()
    faces[faces == far] = 0
    lines = sphere(faces=faces)
    first = int(np.argmax((faces == 0).any(axis=1)))
    return marked_face(lines, first), "marked", "non-manifold vertex 1"


def case_two_tetrahedra_sharing_a_vertex():
    lines = ["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 0 0 1", "v -1 0 0", "v 0 -1 0", "v 0 0 -1",
             "f 1 3 2", "f 1 2 4", "f 1 4 3", "f 2 3 4",
             "f 1 5 6  " + HERE, "f 1 7 5", "f 1 6 7", "f 5 7 6"]
    return lines, "marked", "non-manifold vertex 1"


def case_non_orientable():
    # The 6-vertex real projective plane: closed (every edge in two faces) but non-orientable.
    rp2 = np.array([[1, 2, 3], [1, 3, 4], [1, 4, 5], [1, 5, 6], [1, 6, 2],
                    [2, 3, 5], [3, 4, 6], [4, 5, 2], [5, 6, 3], [6, 2, 4]]) - 1
    pts = np.random.default_rng(0).normal(size=(6, 3))
    lines = sphere(name="rp2", vertices=pts, faces=rp2)
    return lines, set(range(8, 18)), "non-orientable"


def case_two_spheres_in_one_object():
    lines = ["o twins"] + v_lines(SV) + v_lines(SV + 1.0) + f_lines(SF) + f_lines(SF, NV)
    return marked_face(lines, NF), "marked", "2 disconnected parts"


def case_vertex_shared_by_two_objects():
    lines = sphere("a")
    lines += ["o b"] + v_lines(SV + 1.0)
    faces_b = SF + NV
    faces_b[faces_b == NV + 3] = 5  # reuse vertex 6 of object a
    lines += f_lines(faces_b) + ["END_OBJECT"]
    first = int(np.argmax((faces_b == 5).any(axis=1)))
    return marked_face(lines, first, first_f=lines.index(f_lines(faces_b)[0])), "marked", \
        "uses vertex 6, which already belongs to object 'a'"


def case_object_without_faces():
    lines = ["o empty", "k_structural 5", "END_OBJECT  " + HERE] + sphere(offset=0)
    return lines, "marked", "object has no faces ('empty'"


def case_object_without_faces_before_next_o():
    lines = ["o empty  " + HERE, "total_weight 2"] + sphere()
    return lines, "marked", "object has no faces ('empty'"


def case_object_with_vertices_but_no_faces():
    return ["o lonely  " + HERE] + v_lines(SV), "marked", "object has no faces ('lonely'"


def case_vertices_but_no_faces():
    return ["# just points"] + v_lines(SV), None, "no faces"


def case_end_object_without_object():
    return sphere() + ["END_OBJECT  " + HERE], "marked", "without an open object"


def case_end_object_with_values():
    return sphere()[:-1] + ["END_OBJECT now  " + HERE], "marked", "takes no values"


def case_keywords_after_last_object():
    return sphere() + ["k_structural 5  " + HERE], "marked", "belong to no object"


def case_total_weight_zero():
    return _in_sphere(["total_weight 0  " + HERE]), "marked", "must be > 0"


def case_total_weight_negative():
    return _in_sphere(["total_weight -1  " + HERE]), "marked", "must be > 0"


def case_nmol_zero():
    return _in_sphere(["nmol 0  " + HERE]), "marked", "must be > 0"


def case_nmol_negative():
    return _in_sphere(["nmol -1e-3  " + HERE]), "marked", "must be > 0"


def case_k_negative():
    return _in_sphere(["k_structural -1  " + HERE]), "marked", "must be >= 0"


def case_dashpot_negative():
    return _in_sphere(["dashpot -0.1  " + HERE]), "marked", "must be >= 0"


def case_drag_negative():
    return _in_sphere(["drag -2  " + HERE]), "marked", "must be >= 0"


def case_damping_between_0_and_1():
    return _in_sphere(["damping 0.5  " + HERE]), "marked", "must be 0 (off) or >= 1"


def case_damping_negative():
    return _in_sphere(["damping -3  " + HERE]), "marked", "must be 0 (off) or >= 1"


def case_scale_zero():
    return _in_sphere(["scale 0  " + HERE]), "marked", "must be > 0"


def case_scale_overflow():
    return _in_sphere(["scale 1e300  " + HERE]), "marked", "too large"


def case_temperature_zero():
    return ["temperature 0  " + HERE] + sphere(), "marked", "must be > 0"


def case_fixed_index_beyond_file():
    return sphere(end=False) + [f"fixed {NV + 10}  " + HERE, "END_OBJECT"], "marked", "is not a vertex of object 'ball'"


def case_fixed_vertex_of_other_object():
    lines = sphere("a") + sphere("b", offset=NV, end=False) + ["fixed 3  " + HERE, "END_OBJECT"]
    return lines, "marked", "'fixed' vertex 3 is not a vertex of object 'b'"


def case_fixed_unused_vertex():
    lines = ["o ball", "v 9 9 9"] + v_lines(SV) + f_lines(SF, 1) + ["fixed 1  " + HERE, "END_OBJECT"]
    return lines, "marked", "is not a vertex of object 'ball'"


def case_fixed_zero():
    return sphere(end=False) + ["fixed 0  " + HERE, "END_OBJECT"], "marked", "vertex index 0 is invalid"


def case_fixed_two_values():
    return sphere(end=False) + ["fixed 1 2  " + HERE, "END_OBJECT"], "marked", "expects 1 vertex index, got 2"


def case_object_key_twice():
    return _in_sphere(["k_structural 5", "k_structural 6  " + HERE]), "marked", "given twice"


def case_scene_key_twice():
    return ["floor -1", "gravity 0 -1 0", "floor -2  " + HERE] + sphere(), "marked", "given twice"


def case_duplicate_object_names():
    return sphere("ball") + ["o ball  " + HERE] + sphere(None, offset=NV)[0:], "marked", "used by more than one object"


def case_below_floor():
    return ["floor 0  " + HERE] + sphere(), "marked", "starts below the floor"


def case_zero_volume():
    return ["v 0 0 0", "v 1 0 0", "v 0 1 0", "f 1 2 3", "f 1 3 2"], {4, 5}, "zero volume"


def case_binary_png():
    return b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00", 3, "binary data"


def case_binary_after_text():
    text = ("\n".join(sphere()) + "\n").encode()
    return text + b"\xff\xfe\x00\x01garbage", text.count(b"\n") + 1, "binary data"


def case_not_utf8():
    text = ("\n".join(sphere()[:5]) + "\n").encode()
    return text + b"v 1 2 \xe9\xff 3\n", 6, "not UTF-8"


def case_empty_file():
    return b"", None, "empty scene"


def case_only_comments_and_blanks():
    return "# nothing here\n\n   \n# still nothing\n", None, "empty scene"


BAD = {name[5:]: fn for name, fn in sorted(globals().items()) if name.startswith("case_")}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_scene(tmp_path, case):
    content, expected, phrase = BAD[case]()
    path = write(tmp_path, content, f"{case}.obj")
    if expected == "marked":
        expected = marked_line(content)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warnings or stray warnings must not stand in for errors
        with pytest.raises(SceneError) as info:
            jaxplush.load_scene(path)
    err = info.value
    assert err.path == str(path)
    if isinstance(expected, set):
        assert err.line in expected, (err.line, str(err))
    else:
        assert err.line == expected, str(err)
    assert phrase in err.reason, str(err)
    where = f"{path}:{err.line}" if err.line is not None else str(path)
    assert str(err).startswith(where + ": "), str(err)


def test_missing_file(tmp_path):
    with pytest.raises(SceneError, match="no such file") as info:
        jaxplush.load_scene(tmp_path / "nope.obj")
    assert info.value.line is None


def test_directory_is_not_a_scene(tmp_path):
    with pytest.raises(SceneError, match="is a directory"):
        jaxplush.load_scene(tmp_path)


def test_line_numbers_ignore_form_feeds_and_odd_separators(tmp_path):
    # Only \n, \r\n and \r end lines; a form feed or U+2028 inside a comment must not shift them.
    lines = ["# page\x0cbreak \u2028 in a comment", "# \x1c"] + _in_sphere(["bogus 1  " + HERE])
    with pytest.raises(SceneError, match="unknown keyword 'bogus'") as info:
        load(tmp_path, lines)
    assert info.value.line == marked_line(lines)


def test_line_numbers_with_crlf(tmp_path):
    lines = _in_sphere(["bogus 1  " + HERE])
    with pytest.raises(SceneError) as info:
        load(tmp_path, "\r\n".join(lines) + "\r\n")
    assert info.value.line == marked_line(lines)


# ----------------------------------------------------------------------------- good inputs

def _faces_as_sets(faces):
    return sorted(tuple(sorted(f)) for f in np.asarray(faces).tolist())


def _assert_consistent_outward(scene):
    """Every object: positive volume, and every interior edge runs both ways exactly once."""
    assert (scene.volumes() > 0).all()
    for o in scene.objects:
        f = scene.faces[o.face_slice[0]:o.face_slice[1]]
        directed = [(int(a), int(b)) for tri in f for a, b in zip(tri, np.roll(tri, -1))]
        assert len(set(directed)) == len(directed)
        assert set(directed) == {(b, a) for a, b in directed}


def test_plain_sphere_defaults(tmp_path):
    scene = load(tmp_path, sphere())
    assert scene.n_objects == 1 and scene.object_names == ("ball",)
    assert scene.n_vertices == NV and scene.faces.shape == (NF, 3)
    assert scene.faces.dtype == np.int32
    np.testing.assert_array_equal(scene.vertices, SV)
    np.testing.assert_array_equal(scene.faces, SF)  # already outward: kept as written
    np.testing.assert_allclose(scene.volumes(), [trimesh.Trimesh(SV, SF).volume], rtol=1e-12)
    for k, d in DEFAULTS.items():
        np.testing.assert_array_equal(getattr(scene.params, k), [d])
    assert not scene.has_gas and not scene.objects[0].has_gas
    np.testing.assert_array_equal(scene.gravity, DEFAULT_GRAVITY)
    np.testing.assert_array_equal(scene.gravity, [0.0, -9.81, 0.0])
    assert scene.floor is None
    assert scene.temperature == DEFAULT_TEMPERATURE == 293.15
    assert scene.fixed.shape == (0,)
    assert scene.text == "\n".join(sphere()) + "\n"
    np.testing.assert_array_equal(scene.rest_pressure(), [0.0])


def test_params_and_scene_keywords(tmp_path):
    keys = ["k_structural 250", "damping 1.5", "dashpot 0.03", "drag 0.7", "total_weight 0.2", "nmol 0.002"]
    lines = ["gravity 0.5 -3 1.25", "floor -0.25", "temperature 300"] + sphere(keys=keys)
    scene = load(tmp_path, lines)
    p = scene.params
    assert p.k_structural.tolist() == [250.0] and p.damping.tolist() == [1.5]
    assert p.dashpot.tolist() == [0.03] and p.drag.tolist() == [0.7]
    assert p.total_weight.tolist() == [0.2] and p.nmol.tolist() == [0.002]
    assert scene.has_gas
    np.testing.assert_array_equal(scene.gravity, [0.5, -3.0, 1.25])
    assert scene.floor == -0.25 and scene.temperature == 300.0
    np.testing.assert_allclose(scene.rest_pressure(), 0.002 * 8.314 * 300.0 / scene.volumes())


def test_scene_keywords_anywhere(tmp_path):
    lines = sphere("a", end=False) + ["temperature 250"] + ["END_OBJECT", "gravity 0 0 -9.81"] \
        + sphere("b", offset=NV, vertices=SV + 1.0) + ["floor -5"]
    scene = load(tmp_path, lines)
    assert scene.temperature == 250.0 and scene.floor == -5.0
    np.testing.assert_array_equal(scene.gravity, [0, 0, -9.81])
    assert scene.n_objects == 2


def test_damping_zero_means_off(tmp_path):
    assert load(tmp_path, sphere(keys=["damping 0"])).params.damping.tolist() == [0.0]
    assert load(tmp_path, sphere(keys=["damping 1"])).params.damping.tolist() == [1.0]


def test_vt_vn_face_forms(tmp_path):
    def fmt(i, k):
        return (f"{i}/{i}/{i}", f"{i}//{i}", f"{i}/{i}")[k % 3]
    lines = ["o ball", "mtllib plush.mtl", "usemtl felt", "s 1"] + v_lines(SV)
    lines += [f"vt {u:.3f} {w:.3f}" for u, w in np.random.default_rng(1).random((NV, 2)).tolist()]
    lines += [f"vn {a!r} {b!r} {c!r}" for a, b, c in (SV / 0.1).tolist()] + ["vp 0.5"]
    lines += ["f " + " ".join(fmt(int(i) + 1, n) for i in face) for n, face in enumerate(SF)]
    scene = load(tmp_path, lines)
    np.testing.assert_array_equal(scene.faces, SF)
    np.testing.assert_array_equal(scene.vertices, SV)


def test_negative_relative_indices(tmp_path):
    # Faces after all vertices: index i (0-based) is written as i - NV.
    lines = ["o ball"] + v_lines(SV) + [f"f {a} {b} {c}" for a, b, c in (SF - NV).tolist()]
    scene = load(tmp_path, lines)
    np.testing.assert_array_equal(scene.faces, SF)
    # Two objects, the second's faces relative to the vertices defined so far (2 NV).
    lines += ["END_OBJECT", "o second"] + v_lines(SV + 1.0)
    lines += [f"f {a} {b} {c}" for a, b, c in (SF - NV).tolist()] + ["fixed -1", "END_OBJECT"]
    scene = load(tmp_path, lines)
    np.testing.assert_array_equal(scene.faces, np.concatenate([SF, SF + NV]))
    assert scene.fixed.tolist() == [2 * NV - 1]


def test_mixed_absolute_and_relative(tmp_path):
    lines = ["o ball"] + v_lines(SV) + [f"f {a + 1} {b - NV} {c + 1}" for a, b, c in SF.tolist()]
    np.testing.assert_array_equal(load(tmp_path, lines).faces, SF)


def test_polygons_are_triangulated(tmp_path):
    # Unit cube of quads (outward), and an octagonal prism with octagon caps.
    cube = ["o cube", "v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "v 0 0 1", "v 1 0 1", "v 1 1 1", "v 0 1 1",
            "f 1 4 3 2", "f 5 6 7 8", "f 1 2 6 5", "f 2 3 7 6", "f 3 4 8 7", "f 4 1 5 8", "END_OBJECT"]
    scene = load(tmp_path, cube)
    assert scene.n_vertices == 8 and scene.faces.shape == (12, 3)
    np.testing.assert_allclose(scene.volumes(), [1.0], rtol=1e-12)
    _assert_consistent_outward(scene)

    n = 8
    ang = 2 * np.pi * np.arange(n) / n
    ring = np.stack([np.cos(ang), np.zeros(n), np.sin(ang)], 1)
    verts = np.concatenate([ring, ring + [0, 1, 0]])
    lines = ["o prism"] + v_lines(verts)
    lines.append("f " + " ".join(str(i + 1) for i in range(n)))            # bottom (winding either way)
    lines.append("f " + " ".join(str(n + i + 1) for i in range(n)[::-1]))  # top
    lines += [f"f {i + 1} {(i + 1) % n + 1} {n + (i + 1) % n + 1} {n + i + 1}" for i in range(n)]
    scene = load(tmp_path, lines)
    assert scene.faces.shape == (2 * (n - 2) + 2 * n, 3)
    area = 0.5 * n * np.sin(2 * np.pi / n)
    np.testing.assert_allclose(scene.volumes(), [area * 1.0], rtol=1e-12)
    _assert_consistent_outward(scene)


def test_inward_mesh_is_reoriented(tmp_path):
    scene = load(tmp_path, sphere(faces=SF[:, ::-1]))
    assert scene.volumes()[0] > 0
    np.testing.assert_allclose(scene.volumes(), [trimesh.Trimesh(SV, SF).volume], rtol=1e-12)
    _assert_consistent_outward(scene)
    assert _faces_as_sets(scene.faces) == _faces_as_sets(SF)
    # Every face flipped back to the outward winding (a cyclic rotation of the original).
    for got, want in zip(scene.faces.tolist(), SF.tolist()):
        assert any(got == want[r:] + want[:r] for r in range(3))


def test_a_few_flipped_faces_are_made_consistent(tmp_path):
    faces = SF.copy()
    for i in (0, 3, 17, 40, 79):  # face 0 included: orientation propagates from it
        faces[i] = faces[i][::-1]
    scene = load(tmp_path, sphere(faces=faces))
    _assert_consistent_outward(scene)
    np.testing.assert_allclose(scene.volumes(), [trimesh.Trimesh(SV, SF).volume], rtol=1e-12)
    for got, want in zip(scene.faces.tolist(), SF.tolist()):
        assert any(got == want[r:] + want[:r] for r in range(3))


def test_scale_then_translate(tmp_path):
    scene = load(tmp_path, sphere(keys=["translate 1 2 -3", "scale 2.5"]))  # order in file irrelevant
    np.testing.assert_allclose(scene.vertices, SV * 2.5 + [1, 2, -3], rtol=0, atol=1e-14)
    np.testing.assert_allclose(scene.volumes(), [2.5 ** 3 * trimesh.Trimesh(SV, SF).volume], rtol=1e-12)


def test_floor_exactly_touching_is_allowed(tmp_path):
    low = float(SV[:, 1].min())
    scene = load(tmp_path, ["floor 0"] + sphere(keys=[f"translate 0 {-low!r} 0"]))
    assert scene.floor == 0.0
    assert scene.vertices[:, 1].min() >= 0.0


def test_names_comments_blank_lines_crlf_bom(tmp_path):
    lines = ["# a scene", "", "   # indented comment", "g my group  # trailing comment", "",
             "k_structural 7  # stiffness"] + v_lines(SV) + [""] + f_lines(SF) + ["", "# the end"]
    text = "\ufeff" + "\r\n".join(lines) + "\r\n"
    scene = load(tmp_path, text.encode("utf-8"))
    assert scene.object_names == ("my group",)
    assert scene.params.k_structural.tolist() == [7.0]
    assert scene.n_vertices == NV and len(scene.faces) == NF


def test_object_names(tmp_path):
    # 'o' names an object; a later 'g' does not rename it; 'g' alone names it; none: objectN.
    lines = sphere("first", end=False) + ["g part", "END_OBJECT"]
    lines += ["g grouped"] + v_lines(SV + 1) + f_lines(SF, NV) + ["END_OBJECT"]
    lines += v_lines(SV + 2) + f_lines(SF, 2 * NV) + ["END_OBJECT"]
    scene = load(tmp_path, lines)
    assert scene.object_names == ("first", "grouped", "object2")


def test_several_objects(tmp_path):
    lines = sphere("a", keys=["k_structural 10", "fixed 2"])
    lines += sphere("b", keys=["k_structural 20", "nmol 0.001", "translate 1 0 0"], offset=NV)
    lines += sphere("c", offset=2 * NV, fixed=(0, 5))
    scene = load(tmp_path, lines)
    assert scene.object_names == ("a", "b", "c")
    assert [o.vertex_slice for o in scene.objects] == [(0, NV), (NV, 2 * NV), (2 * NV, 3 * NV)]
    assert [o.face_slice for o in scene.objects] == [(0, NF), (NF, 2 * NF), (2 * NF, 3 * NF)]
    assert scene.params.k_structural.tolist() == [10.0, 20.0, 100.0]
    assert scene.params.nmol.tolist() == [0.0, 0.001, 0.0]
    assert [o.has_gas for o in scene.objects] == [False, True, False]
    np.testing.assert_array_equal(scene.object_id, np.repeat([0, 1, 2], NV))
    np.testing.assert_allclose(scene.vertices[NV:2 * NV], SV + [1, 0, 0], atol=1e-15)
    assert scene.fixed.tolist() == [1, 2 * NV, 2 * NV + 5]
    assert [o.fixed for o in scene.objects] == [(1,), (), (2 * NV, 2 * NV + 5)]
    _assert_consistent_outward(scene)


def test_objects_separated_by_o_without_end_object(tmp_path):
    lines = sphere("a", end=False) + sphere("b", offset=NV, vertices=SV + 1, end=False)
    scene = load(tmp_path, lines)
    assert scene.object_names == ("a", "b") and scene.n_vertices == 2 * NV


def test_single_object_may_omit_end_object(tmp_path):
    scene = load(tmp_path, sphere(end=False, keys=["nmol 0.001"]))
    assert scene.n_objects == 1 and scene.params.nmol.tolist() == [0.001]


def test_fixed_indices_are_compacted(tmp_path):
    # Unused vertices (a warning) are dropped; fixed indices refer to the compacted arrays.
    lines = ["v 5 5 5", "o a"] + v_lines(SV) + f_lines(SF, 1) + ["fixed 2", "fixed 2", "END_OBJECT",
                                                                    "v 6 6 6", "o b"]
    lines += v_lines(SV + 1) + f_lines(SF, NV + 2) + [f"fixed {NV + 3}", "fixed -1", "END_OBJECT"]
    with pytest.warns(UserWarning, match=r"scene\.obj:1: 2 vertex/vertices not used"):
        scene = load(tmp_path, lines)
    assert scene.n_vertices == 2 * NV
    assert scene.fixed.dtype == np.int32
    assert scene.fixed.tolist() == [0, NV, 2 * NV - 1]
    assert scene.objects[0].fixed == (0,)  # duplicates collapse
    np.testing.assert_array_equal(scene.vertices[scene.fixed], [SV[0], SV[0] + 1, SV[-1] + 1])


def test_fixed_before_its_vertices(tmp_path):
    # 'fixed' may come before the vertex it names (indices are resolved when the object closes).
    lines = ["o ball", "fixed 3"] + v_lines(SV) + f_lines(SF)
    assert load(tmp_path, lines).fixed.tolist() == [2]


def test_parse_scene_accepts_str_and_bytes():
    text = "\n".join(sphere()) + "\n"
    a = jaxplush.parse_scene(text)
    b = jaxplush.parse_scene(text.encode(), "mem.obj")
    assert a.path == "<string>" and b.path == "mem.obj"
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


# ------------------------------------------------------------------------------ round trip

def scene_to_objects(scene):
    """Object dicts for :func:`jaxplush.scene.write.format_scene` that reproduce ``scene``.

    The geometry is written as loaded (already scaled and translated), so no scale/translate;
    faces and fixed indices become 0-based local; nmol 0 (no gas) is left out.
    """
    objs = []
    for i, o in enumerate(scene.objects):
        v0, v1 = o.vertex_slice
        f0, f1 = o.face_slice
        d = dict(name=o.name, vertices=scene.vertices[v0:v1], faces=scene.faces[f0:f1].astype(np.int64) - v0,
                 fixed=[j - v0 for j in o.fixed] or None,
                 driven=[dict(path=p.file, vertices=[j - v0 for j in p.vertices], until=p.until)
                         for p in o.driven] or None)
        for k in ("k_structural", "damping", "dashpot", "drag", "total_weight"):
            d[k] = float(getattr(scene.params, k)[i])
        if o.has_gas:
            d["nmol"] = float(scene.params.nmol[i])
        objs.append(d)
    return objs


def _assert_same_scene(a, b):
    np.testing.assert_allclose(b.vertices, a.vertices, rtol=0, atol=0)  # repr floats: bit-identical
    np.testing.assert_array_equal(b.faces, a.faces)
    assert b.object_names == a.object_names
    assert [o.vertex_slice for o in b.objects] == [o.vertex_slice for o in a.objects]
    assert [o.face_slice for o in b.objects] == [o.face_slice for o in a.objects]
    assert [o.has_gas for o in b.objects] == [o.has_gas for o in a.objects]
    for k in a.params._fields:
        np.testing.assert_array_equal(getattr(b.params, k), getattr(a.params, k), err_msg=k)
    np.testing.assert_array_equal(b.gravity, a.gravity)
    assert b.floor == a.floor
    assert b.temperature == a.temperature
    np.testing.assert_array_equal(b.fixed, a.fixed)
    assert [(d.file, d.vertices, d.until) for d in b.driven] == [(d.file, d.vertices, d.until) for d in a.driven]
    for p, q in zip(a.driven, b.driven):
        np.testing.assert_array_equal(q.times, p.times)
        np.testing.assert_array_equal(q.positions, p.positions)


def _round_trip(scene):
    text = format_scene(scene_to_objects(scene), gravity=scene.gravity, floor=scene.floor,
                        temperature=scene.temperature, header="round trip")
    back = jaxplush.parse_scene(text, "roundtrip.obj")
    _assert_same_scene(scene, back)
    return back


def test_round_trip_synthetic(tmp_path):
    lines = ["gravity 0 -1.5 0.25", "floor -2", "temperature 310.5"]
    lines += sphere("a", keys=["k_structural 12.5", "damping 2", "total_weight 0.3", "scale 1.7",
                               "translate 0.1 0.2 0.3"], faces=SF[:, ::-1], fixed=(3, 9))
    lines += sphere("b", keys=["nmol 0.004", "dashpot 0.05", "drag 0.1"], offset=NV, vertices=SV + 5)
    _round_trip(load(tmp_path, lines))
    # and a scene with every default
    back = _round_trip(load(tmp_path, sphere()))
    assert back.floor is None


@pytest.mark.skipif(not SCENES, reason="no scenes/*.obj in the repository yet (made by scenes/make_scenes.py)")
@pytest.mark.parametrize("path", SCENES, ids=[os.path.basename(p) for p in SCENES])
def test_round_trip_shipped_scenes(path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # shipped scenes must load cleanly (no unused vertices, ...)
        scene = jaxplush.load_scene(path)
    assert (scene.volumes() > 0).all()
    if scene.floor is not None:
        assert scene.vertices[:, 1].min() >= scene.floor
    _round_trip(scene)


def test_scenes_readme_describes_every_shipped_scene():
    """scenes/README.md has a row for every bundled scene with its vertex counts, and the number of
    scenes it says the script writes is the number of files (the README had drifted)."""
    root = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scenes")
    text = open(os.path.join(root, "README.md")).read()
    rows = {m.group(1): m.group(2) for m in re.finditer(r"^\| `([\w.]+\.obj)` \|[^|]*\| ([^|]+) \|", text, re.M)}
    files = sorted(os.path.basename(p) for p in SCENES)
    assert sorted(rows) == files
    words = {3: "three", 4: "four", 5: "five", 6: "six", 7: "seven", 8: "eight"}
    assert f"writes the {words[len(files)]} scenes" in text
    for name, cell in rows.items():
        counts = [o.n_vertices for o in jaxplush.load_scene(os.path.join(root, name)).objects]
        m = re.fullmatch(r"\s*(\d+) × (\d+)\s*", cell)
        expect = [int(m.group(2))] * int(m.group(1)) if m else [int(c) for c in cell.split("+")]
        assert counts == expect, (name, cell)


@pytest.mark.slow
def test_make_scenes_is_deterministic(tmp_path):
    """scenes/make_scenes.py (run on a copy of scenes/) rewrites every bundled scene: the same lines,
    and the same numbers to 1e-9 relative (the meshes are relaxed and nmol calibrated by iterative
    float code, whose last digits depend on the CPU's vector instructions and BLAS kernels)."""
    import shutil
    import subprocess
    import sys
    root = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scenes")
    copy = tmp_path / "scenes"
    shutil.copytree(root, copy)
    for p in copy.glob("*.obj"):
        p.unlink()
    proc = subprocess.run([sys.executable, str(copy / "make_scenes.py")], cwd=tmp_path, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    number = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
    for name in sorted(os.listdir(root)):
        if name.endswith(".obj"):
            new, old = (copy / name).read_text(), open(os.path.join(root, name)).read()
            assert number.sub("#", new) == number.sub("#", old), name
            a = np.array([float(x) for x in number.findall(new)])
            b = np.array([float(x) for x in number.findall(old)])
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12, err_msg=name)


def _two_sphere_text():
    out = []
    for i, (sub, off) in enumerate(((2, 0), (1, 162))):
        m = trimesh.creation.icosphere(subdivisions=sub, radius=0.1)
        out += [f"o s{i}", "k_structural 100", "total_weight 1", "nmol 0.001", f"translate {0.5 * i} 0 0"]
        out += ["v %r %r %r" % tuple(map(float, v)) for v in m.vertices]
        out += ["f %d %d %d" % tuple(f + 1 + off) for f in m.faces]
        out.append("END_OBJECT")
    return out


@pytest.mark.parametrize("edit", [None, (20, "v 0.1 0.2"), (30, "v 0.1 0.2 nan"), (40, "v 1 2 3 # comment"),
                                  (50, "v 1_0 2 3"), (400, "f 1 2"), (420, "f 1 -2 3"), (440, "f 1/1 2/2 3/3"),
                                  (460, "f 1 2 99999999999999999999"), (470, "f 1 2 3 4"), (480, "f 0 1 2")])
def test_blocks_of_v_and_f_lines_read_as_line_by_line(monkeypatch, edit):
    """Long runs of 'v'/'f' lines are read in bulk (jaxplush.scene.parse._Parser.bulk); the scene, or the
    error with its line, is exactly what the line-by-line reading gives, for good input and for any
    odd or bad line inside a block."""
    from jaxplush.scene import parse as S
    lines = _two_sphere_text()
    if edit is not None:
        i, text = edit
        assert lines[i][0] == text[0]                       # the edit lands inside a block of its kind
        lines[i] = text
    text = "\n".join(lines) + "\n"

    def parse():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                return jaxplush.parse_scene(text, "blocks.obj")
            except SceneError as e:
                return str(e)

    fast = parse()
    monkeypatch.setattr(S._Parser, "BULK_MIN", 10 ** 9)
    slow = parse()
    if isinstance(slow, str):
        assert fast == slow
    else:
        assert not isinstance(fast, str)
        np.testing.assert_array_equal(fast.vertices, slow.vertices)
        np.testing.assert_array_equal(fast.faces, slow.faces)
        assert fast.objects == slow.objects and fast.n_vertices == 162 + 42


def _test_meshes():
    from jaxplush.model import mesh
    out = []
    for sub in (0, 1, 2):
        m = trimesh.creation.icosphere(subdivisions=sub, radius=0.1)
        out.append((np.asarray(m.vertices), np.asarray(m.faces, np.int64)))
    t = trimesh.creation.torus(major_radius=0.1, minor_radius=0.03)
    out.append((np.asarray(t.vertices), np.asarray(t.faces, np.int64)))
    out.append(mesh.superellipsoid(0.12, 0.05, 4.0, subdivisions=2))
    return out


def test_vectorised_rings_and_orientation_match_the_reference_checks():
    """The scene parser's vectorised mesh code (jaxplush.model.mesh.ring_tables, orient_all) gives what the
    per-vertex / per-object reference code gives (ring_table(one_rings(...)), check_and_orient): the
    same ordered one-rings, the same outward winding of randomly flipped faces, several objects at
    once; and it flags an object with a hole, leaving the others oriented."""
    from jaxplush.model import mesh
    rng = np.random.default_rng(0)
    xs, fs, fo, expect, off = [], [], [], [], 0
    for i, (x, f) in enumerate(_test_meshes()):
        nbr, mask, bad = mesh.ring_tables(f, len(x))
        ref_nbr, ref_mask = mesh.ring_table(mesh.one_rings(f, len(x)))
        np.testing.assert_array_equal(nbr, ref_nbr)
        np.testing.assert_array_equal(mask, ref_mask)
        assert not bad.any()
        flipped = f.copy()
        sel = rng.random(len(f)) < 0.3
        flipped[sel] = flipped[sel][:, ::-1]
        expect.append(mesh.check_and_orient(x, flipped)[0] + off)
        xs.append(x + np.array([0.5 * i, 0.0, 0.0]))
        fs.append(flipped + off)
        fo.append(np.full(len(f), i))
        off += len(x)
    x, f, fo = np.concatenate(xs), np.concatenate(fs), np.concatenate(fo)
    out, bad = mesh.orient_all(x, f, fo, len(xs))
    assert not bad.any()
    np.testing.assert_array_equal(out, np.concatenate(expect))
    holed = np.delete(f, int(np.argmax(fo == 1)), axis=0)          # object 1 loses a face
    out, bad = mesh.orient_all(x, holed, np.delete(fo, int(np.argmax(fo == 1))), len(xs))
    assert bad.tolist() == [i == 1 for i in range(len(xs))]
    with pytest.raises(mesh.MeshProblem, match="open mesh"):
        mesh.check_and_orient(x, holed[np.delete(fo, int(np.argmax(fo == 1))) == 1])
