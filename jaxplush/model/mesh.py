"""Mesh checks and static topology (numpy only; never traced).

Everything here runs once, before any JAX tracing: it validates that each object is a
closed, manifold, consistently oriented triangle mesh, orients it outward, and builds the
static index tables the compiled step closes over (unique edges, ordered one-rings).

Shape letters (also in :mod:`jaxplush.types`): V vertices, E edges, F faces, O objects,
K the maximum valence (one-ring width).
"""

from __future__ import annotations

from collections import deque

import numpy as np


class MeshProblem(ValueError):
    """A mesh defect. ``face`` is the index (into the faces given) of an offending face, if any."""

    def __init__(self, reason, face=None):
        super().__init__(reason)
        self.reason = reason
        self.face = face


def face_area_normals(vertices, faces):
    """(F, 3) cross products (b - a) x (c - a): twice the area times the unit normal."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return np.cross(b - a, c - a)


def signed_volume(vertices, faces):
    """Signed volume of a closed triangle mesh (divergence theorem, about the centroid)."""
    x = vertices - vertices.mean(axis=0)
    a, b, c = (x[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def check_and_orient(vertices, faces, labels=None):
    """Validate one object's mesh and return its faces wound outward.

    Args:
      vertices: (n, 3) float positions of this object's vertices.
      faces: (f, 3) int indices into ``vertices``.
      labels: optional (n,) numbers to name vertices by in messages (e.g. the 1-based
        indices of the scene file); default: the indices into ``vertices``.

    Returns:
      (faces_out, flipped): faces consistently wound so that the signed volume is
      positive, and the number of faces whose winding was reversed.

    Raises:
      MeshProblem: degenerate faces, open or non-manifold edges or vertices, several
      disconnected parts, a non-orientable surface, or zero volume.
    """
    faces = np.asarray(faces, dtype=np.int64)
    n = len(vertices)
    lab = np.arange(n) if labels is None else np.asarray(labels)
    if len(faces) == 0:
        raise MeshProblem("object has no faces")
    extent = _check_faces_not_degenerate(vertices, faces, lab)
    inverse = _check_edges_shared_by_two(faces, n, lab)
    out, flipped = _orient_consistently(faces, inverse, lab)

    used = np.unique(out)
    vol = signed_volume(vertices[used], np.searchsorted(used, out))
    if abs(vol) <= 1e-12 * extent ** 3:
        raise MeshProblem("mesh encloses zero volume")
    if vol < 0:  # wound inward as a whole: turn it outward, as the user meant
        out = out[:, ::-1].copy()
        flipped = len(out) - flipped

    # Vertex manifoldness: the faces around each vertex must form a single fan.
    one_rings(out, n, labels=lab)  # raises MeshProblem at a non-manifold vertex
    return out, flipped


def _check_faces_not_degenerate(vertices, faces, lab):
    """Raise MeshProblem at a face that repeats a vertex or has (numerically) zero area; return
    the mesh's extent (its largest bounding-box side)."""
    n = len(vertices)
    rep = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    if rep.any():
        i = int(np.argmax(rep))
        raise MeshProblem(f"degenerate face (repeats a vertex: {lab[faces[i]].tolist()})", face=i)
    extent = float(np.ptp(vertices, axis=0).max()) if n else 0.0
    area2 = np.linalg.norm(face_area_normals(vertices, faces), axis=1)
    tiny = (extent * extent) * 1e-12
    if (area2 <= tiny).any():
        i = int(np.argmax(area2 <= tiny))
        raise MeshProblem("degenerate face (zero area: its vertices are collinear or coincide)", face=i)
    return extent


def _check_edges_shared_by_two(faces, n, lab):
    """Raise MeshProblem unless every undirected edge is shared by exactly two faces; return the
    (3 F,) undirected-edge number of each half-edge (face f's edges are 3 f .. 3 f + 2)."""
    und = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1).reshape(-1, 2), axis=1)
    keys = und[:, 0] * n + und[:, 1]
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    if (counts == 1).any():
        j = int(np.argmax(counts[inverse] == 1))
        nb = int((counts == 1).sum())
        e = und[j]
        raise MeshProblem(
            f"open mesh: {nb} boundary edge(s), e.g. the edge between vertices {lab[e[0]]} and {lab[e[1]]} "
            "belongs to only one face (pressure needs a closed surface)", face=j // 3)
    if (counts > 2).any():
        j = int(np.argmax(counts[inverse] > 2))
        e = und[j]
        raise MeshProblem(
            f"non-manifold edge between vertices {lab[e[0]]} and {lab[e[1]]}: shared by "
            f"{int(counts[inverse[j]])} faces", face=j // 3)
    return inverse


def _orient_consistently(faces, inverse, lab):
    """Consistent orientation by breadth-first propagation over shared edges, from face 0.

    Returns (faces wound consistently, number flipped); raises MeshProblem for a non-orientable
    surface, parts touching at a vertex, or several disconnected parts."""
    edge_faces = np.argsort(inverse, kind="stable").reshape(-1, 2) // 3  # the two faces of each edge
    nbrs = [[] for _ in range(len(faces))]
    for f0, f1 in edge_faces:
        nbrs[f0].append(f1)
        nbrs[f1].append(f0)
    out = faces.copy()
    seen = np.zeros(len(faces), bool)
    seen[0] = True
    queue = deque([0])
    flipped = 0

    def directed(f):
        a, b, c = out[f]
        return {(a, b), (b, c), (c, a)}

    while queue:
        f = queue.popleft()
        df = directed(f)
        for g in nbrs[f]:
            dg = directed(g)
            consistent = not (df & dg)  # a shared edge must run in opposite directions
            if seen[g]:
                if not consistent:
                    raise MeshProblem("non-orientable surface: faces cannot be wound consistently", face=g)
                continue
            if not consistent:
                out[g] = out[g][::-1]
                flipped += 1
            seen[g] = True
            queue.append(g)
    if not seen.all():
        # Parts that touch only at a vertex are one non-manifold surface, not separate objects.
        touch = np.intersect1d(np.unique(faces[seen]), np.unique(faces[~seen]))
        if len(touch):
            v = int(touch[0])
            raise MeshProblem(f"non-manifold vertex {lab[v]}: two parts of the surface touch only at "
                              "this vertex (its faces do not form a single fan)",
                              face=int(np.argmax((faces == v).any(axis=1) & ~seen)))
        raise MeshProblem(
            f"object has {1 + _count_parts(nbrs, seen)} disconnected parts; give each closed part its "
            "own object (END_OBJECT between them)", face=int(np.argmin(seen)))
    return out, flipped


def _count_parts(nbrs, seen):
    seen = seen.copy()
    parts = 0
    for s in range(len(seen)):
        if seen[s]:
            continue
        parts += 1
        seen[s] = True
        q = deque([s])
        while q:
            f = q.popleft()
            for g in nbrs[f]:
                if not seen[g]:
                    seen[g] = True
                    q.append(g)
    return parts


def unique_edges(faces):
    """(E, 2) sorted unique undirected edges (i < j) of a triangle mesh, in lexicographic order."""
    faces = np.asarray(faces, np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lo, hi = np.minimum(e[:, 0], e[:, 1]), np.maximum(e[:, 0], e[:, 1])
    n = int(hi.max()) + 1 if len(hi) else 1
    keys = np.unique(lo * n + hi)                     # one 1-D sort (np.unique(axis=0) is far slower)
    return np.stack([keys // n, keys % n], axis=1).astype(faces.dtype)


def edge_index(edges, a, b):
    """Index into ``edges`` ((E, 2) sorted unique edges, :func:`unique_edges`) of the edges (a, b)
    (arrays of vertex indices, either order), or -1 where (a, b) is not an edge."""
    edges = np.asarray(edges, np.int64)
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    n = max(int(edges.max()) + 1 if edges.size else 1, int(hi.max()) + 1 if hi.size else 1)
    keys = edges[:, 0] * n + edges[:, 1]
    q = lo * n + hi
    if not len(keys):
        return np.full(q.shape, -1, np.int64)
    i = np.clip(np.searchsorted(keys, q), 0, len(keys) - 1)
    return np.where(keys[i] == q, i, -1)


def edge_face_mean(faces, face_values, edges=None):
    """(E,) the mean over each edge's adjacent faces of a per-face value (F,): on a closed mesh
    (each edge in two faces) half the sum of its two faces' values, in the order of
    :func:`unique_edges` (or of ``edges``). The scene's stiffness field is built with it
    (``k_region``: docs/formats.md §2.4)."""
    faces = np.asarray(faces, np.int64)
    edges = unique_edges(faces) if edges is None else np.asarray(edges, np.int64)
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    idx = edge_index(edges, half[:, 0], half[:, 1])
    vals = np.tile(np.asarray(face_values, np.float64), 3)
    total = np.bincount(idx, weights=vals, minlength=len(edges))
    count = np.bincount(idx, minlength=len(edges))
    return total / np.maximum(count, 1)


def ring_edges(edges, nbr):
    """(V, K) int32: the index into ``edges`` ((E, 2), :func:`unique_edges`) of the edge from each
    vertex to each of its ring neighbours ``nbr`` ((V, K), :func:`ring_tables`; padded slots repeat
    a real neighbour, so they name a real edge too, and empty rows name edge 0)."""
    v = np.broadcast_to(np.arange(len(nbr))[:, None], nbr.shape)
    idx = edge_index(edges, v, nbr)
    return np.where(idx >= 0, idx, 0).astype(np.int32)


def one_rings(faces, n_vertices, labels=None):
    """Ordered one-rings: for each vertex, its neighbours counter-clockwise seen from outside.

    For an outward-wound face (a, b, c) the ring of ``a`` steps from ``b`` to ``c``. Returns a
    list of integer arrays. Raises MeshProblem at a non-manifold vertex (a fan that is not a
    single closed cycle, e.g. two surfaces touching at one vertex), naming the vertex by
    ``labels[v]`` if given, with ``face`` one of its faces.
    """
    nxt = [dict() for _ in range(n_vertices)]
    for a, b, c in faces:
        nxt[a][b] = c
        nxt[b][c] = a
        nxt[c][a] = b
    rings = []
    for v in range(n_vertices):
        m = nxt[v]
        if not m:
            rings.append(np.zeros(0, np.int64))
            continue
        start = next(iter(m))
        ring = [start]
        cur = m[start]
        while cur != start and len(ring) <= len(m):
            ring.append(cur)
            cur = m.get(cur, -1)
            if cur == -1:
                break
        if cur != start or len(ring) != len(m):
            name = v if labels is None else labels[v]
            raise MeshProblem(f"non-manifold vertex {name}: its faces do not form a single fan",
                              face=int(np.argmax((np.asarray(faces) == v).any(axis=1))))
        rings.append(np.asarray(ring, np.int64))
    return rings


def ring_table(rings):
    """Pad ordered rings into an (V, K) table.

    Padding repeats each ring's last neighbour, which keeps the fan's cross-product sum exact
    (a repeated neighbour contributes a zero cross product and the wrap-around pair is the true
    closing pair). Returns (nbr (V, K) int32, mask (V, K) bool: real neighbours).
    """
    k = max(len(r) for r in rings)
    nbr = np.zeros((len(rings), k), np.int32)
    mask = np.zeros((len(rings), k), bool)
    for v, r in enumerate(rings):
        nbr[v, : len(r)] = r
        nbr[v, len(r):] = r[-1]
        mask[v, : len(r)] = True
    return nbr, mask


def superellipsoid(a, c, exponent, subdivisions=3):
    """A cushion mesh: the superellipsoid |x/a|^p + |y/c|^p + |z/a|^p = 1 (p = ``exponent``).

    Each unit direction d of a trimesh icosphere is moved to the surface along its ray,
    r(d) = (sum |d_i / a_i|^p)^(-1/p): a star-shaped, closed, outward-wound mesh with the
    icosphere's topology, flat on top and bottom for p > 2. Returns (vertices (N, 3), faces (F, 3)).
    """
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    d = np.asarray(m.vertices, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    r = (np.abs(d[:, 0] / a) ** exponent + np.abs(d[:, 1] / c) ** exponent
         + np.abs(d[:, 2] / a) ** exponent) ** (-1.0 / exponent)
    return d * r[:, None], np.asarray(m.faces, np.int64)


# --------------------------------------------------------------------------- vectorised checks

def orient_all(vertices, faces, face_object, n_objects):
    """Validate and orient every object of a scene at once (numpy only, no Python loop over faces
    or objects); the fast path of :func:`check_and_orient`.

    Args:
      vertices: (V, 3) positions (all objects); faces: (F, 3) global indices; face_object: (F,)
        object of each face (objects own disjoint vertex sets); n_objects: O.

    Returns:
      (faces_out (F, 3) wound outward, object by object; bad: (O,) bool, objects with any defect).
      A defective object's faces are returned unchanged; :func:`check_and_orient` on it names the
      defect (the same checks, one object at a time, with the exact face and message).
    """
    faces = np.asarray(faces, np.int64)
    fo = np.asarray(face_object, np.int64)
    n_f, n_v = len(faces), len(vertices)
    bad = np.zeros(n_objects, bool)
    if n_f == 0:
        return faces, np.ones(n_objects, bool)
    vo, used, extent = _vertex_objects(vertices, faces, fo, n_objects)
    # degenerate faces: a repeated vertex, or zero area against the object's size
    rep = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    area2 = np.linalg.norm(face_area_normals(vertices, faces), axis=1)
    bad[fo[rep | (area2 <= (extent[fo] ** 2) * 1e-12)]] = True
    # every undirected edge in exactly two faces
    f0, f1, same, not_two = _edge_face_pairs(faces, n_v)
    bad[fo[not_two]] = True
    # one connected piece per object
    first_of, flip = _pieces(f0, f1, same, n_f)
    per_obj = np.bincount(fo[first_of], minlength=n_objects)
    bad[per_obj != 1] = True
    bad[fo[f1[same ^ flip[f0] ^ flip[f1]]]] = True           # not orientable
    out = np.where(flip[:, None], faces[:, ::-1], faces)
    # outward: the signed volume of each object positive (about its vertices' mean)
    vol = _object_volumes(vertices, out, fo, vo, used, n_objects)
    bad[np.abs(vol) <= 1e-12 * extent ** 3] = True
    out = np.where((vol[fo] < 0)[:, None], out[:, ::-1], out)
    # every vertex's faces one fan (ring_tables checks it)
    _, _, fan_bad = ring_tables(out, n_v)
    bad[vo[fan_bad & used]] = True
    keep = bad[fo]
    out[keep] = faces[keep]
    return out, bad


def _vertex_objects(vertices, faces, fo, n_objects):
    """(vo (V,) object of each vertex, -1 where no face uses it; used (V,) bool, vo >= 0;
    extent (O,) each object's largest bounding-box side)."""
    lo = np.full((n_objects, 3), np.inf)
    hi = np.full((n_objects, 3), -np.inf)
    vo = np.full(len(vertices), -1)
    vo[faces.ravel()] = np.repeat(fo, 3)
    used = vo >= 0
    np.minimum.at(lo, vo[used], vertices[used])
    np.maximum.at(hi, vo[used], vertices[used])
    return vo, used, np.max(hi - lo, axis=1)


def _edge_face_pairs(faces, n_v):
    """The faces on either side of every undirected edge shared by exactly two faces: (f0, f1,
    same: the edge runs the same way in both, not_two: the faces of the half-edges whose edge is
    in one face or more than two)."""
    de = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1).reshape(-1, 2)
    und = np.sort(de, axis=1)
    keys = und[:, 0] * n_v + und[:, 1]
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    start = np.concatenate([[True], sk[1:] != sk[:-1]])
    counts = np.diff(np.append(np.nonzero(start)[0], len(sk)))
    grp = np.cumsum(start) - 1
    cnt = counts[grp]
    pair = order[cnt == 2].reshape(-1, 2)                    # the two half-edges of each edge
    f0, f1 = pair[:, 0] // 3, pair[:, 1] // 3
    same = de[pair[:, 0], 0] == de[pair[:, 1], 0]            # the edge runs the same way in both
    return f0, f1, same, order[cnt != 2] // 3


def _pieces(f0, f1, same, n_f):
    """The connected pieces of the face graph (edges f0[i]-f1[i]) and a winding for each face.

    Union-find with parity, vectorised (numpy only, so parsing a scene imports no scipy): each
    round hooks every piece's root to the smallest root it shares an edge with, then compresses
    every path to its root, until no edge joins two pieces. ``same[i]`` (the edge runs the same
    way in both faces) asks for flip[f0[i]] != flip[f1[i]]; every face's flip is its winding
    parity relative to the root of its piece along the edges that joined them.

    Returns (first_of: the lowest face index of every piece, which is its root, ascending;
    flip (F,) bool: the faces to reverse for a consistent winding, the first face of each piece
    kept). A piece that cannot be wound consistently (not orientable) gets a winding that breaks
    at some edge, which the caller finds; an orientable piece's winding is the only one that
    keeps its first face.
    """
    root = np.arange(n_f)
    par = np.zeros(n_f, bool)                                # winding relative to root[f]
    same = np.asarray(same, bool)
    while len(f0):
        r0, r1 = root[f0], root[f1]
        cross = r0 != r1
        if not cross.any():
            break
        hi = np.maximum(r0, r1)[cross]
        lo = np.minimum(r0, r1)[cross]
        rel = (par[f0] ^ par[f1] ^ same)[cross]              # flip[hi] ^ flip[lo] the edge asks for
        order = np.lexsort((lo, hi))                         # each root hooks to its smallest neighbour
        hi, lo, rel = hi[order], lo[order], rel[order]
        first = np.concatenate([[True], hi[1:] != hi[:-1]])
        root[hi[first]] = lo[first]
        par[hi[first]] = rel[first]
        while True:                                          # pointer jumping, parity along
            up = root[root]
            if np.array_equal(up, root):
                break
            par = par ^ par[root]
            root = up
    return np.nonzero(root == np.arange(n_f))[0], par


def _object_volumes(vertices, faces, fo, vo, used, n_objects):
    """(O,) signed volume of each object, about the mean of its vertices."""
    centre = np.zeros((n_objects, 3))
    np.add.at(centre, vo[used], vertices[used])
    centre /= np.maximum(np.bincount(vo[used], minlength=n_objects), 1)[:, None]
    a, b, c = (vertices[faces[:, i]] - centre[fo] for i in range(3))
    return np.bincount(fo, weights=np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0, minlength=n_objects)


def ring_tables(faces, n_vertices):
    """Ordered one-rings of an outward-wound mesh as a padded table, vectorised (the fast
    equivalent of ``ring_table(one_rings(...))``).

    Returns:
      (nbr (V, K) int32 padded by repeating each ring's last neighbour, mask (V, K) bool,
      bad (V,) bool: vertices whose faces do not form a single fan). Vertices in no face get an
      empty (all-masked) row.
    """
    faces = np.asarray(faces, np.int64)
    v = faces.ravel()                                         # (v, from, to) for each corner
    frm = faces[:, [1, 2, 0]].ravel()
    to = faces[:, [2, 0, 1]].ravel()
    # each ring starts where one_rings starts it: at the first corner of the vertex in face order
    seen, first_corner = np.unique(v, return_index=True)
    ring_start = np.zeros(n_vertices, np.int64)
    ring_start[seen] = frm[first_corner]
    key = v * n_vertices + frm
    order = np.argsort(key, kind="stable")
    key, v, frm, to = key[order], v[order], frm[order], to[order]
    deg = np.bincount(v, minlength=n_vertices)
    dup = np.zeros(n_vertices, bool)
    if len(key) > 1:
        dup[v[1:][key[1:] == key[:-1]]] = True                 # two faces leave v towards one neighbour
    k = int(deg.max()) if len(deg) else 0
    has = deg > 0
    nbr = np.zeros((n_vertices, max(k, 1)), np.int64)
    mask = np.zeros((n_vertices, max(k, 1)), bool)
    start = ring_start
    cur = start.copy()
    closed_at = np.where(has, k + 1, 0)
    rows = np.nonzero(has)[0]
    for j in range(k):
        live = rows[deg[rows] > j]
        nbr[live, j] = cur[live]
        mask[live, j] = True
        q = live * n_vertices + cur[live]
        i = np.clip(np.searchsorted(key, q), 0, len(key) - 1)
        found = key[i] == q
        nxt = np.where(found, to[i], -1)
        lost = live[~found]
        closed_at[lost] = np.minimum(closed_at[lost], 0)      # the fan breaks: not a cycle
        cur[live] = np.where(found, nxt, cur[live])
        back = live[found & (nxt == start[live])]
        closed_at[back] = np.minimum(closed_at[back], j + 1)
    bad = dup | (has & (closed_at != deg))
    last = np.where(has, nbr[np.arange(n_vertices), np.maximum(deg - 1, 0)], 0)
    nbr = np.where(mask, nbr, last[:, None])
    return nbr.astype(np.int32), mask, bad
