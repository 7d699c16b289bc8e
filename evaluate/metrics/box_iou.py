"""Exact intersection-over-union of oriented 3D boxes (no sampling, no randomness, no Qhull).

A box is given by its full side lengths ``extents`` (3,) in metres along the object axes and a rigid
object-to-camera transform ``T`` (4, 4); the box is centred on the object origin.

Method (exact up to floating-point rounding).  The intersection A ∩ B of two boxes is a convex
polyhedron whose every face lies on one of the 12 box planes; the face on plane F is the convex
polygon ``plane F ∩ A ∩ B``.  Working in B's frame, the divergence theorem with the field (x, 0, 0)
gives its volume,

    V = sum_F  n_Fx * integral over face F of x dA,

where only faces with n_x != 0 contribute: A's 6 faces and B's two x faces (B's y and z faces have
n_x = 0 exactly).  Each face polygon is the intersection of 10 half-planes in its plane; a convex
polygon given by half-planes has its vertices among the 45 pairwise intersections of the 10 boundary
lines (40 once the parallel pairs are left out): we keep the feasible ones, sort them by angle about their mean and take the shoelace area and
first moments.  All of this is fixed-size arrays, vectorised across pairs (8 faces x 40 candidates x
10 lines per pair; faces whose own quad misses the other box are skipped).

Degenerate configurations are exact by construction, not by luck:

* Touching or coplanar faces with opposite normals produce two polygons that cancel in the sum.
* Coplanar faces with the same normal (e.g. shared top faces) would be counted twice.  Every face is
  therefore parametrised by the two coordinates of B's frame orthogonal to the B axis most aligned
  with its normal, so that the line where a face of A meets the face of B with the same normal
  direction is computed from bit-identical numbers for both faces; a shift ``tau`` assigns the strip
  between them to A's face and the rest to B's face, so the two faces tile the common plane without
  overlap however small the angle between them (tested down to 1e-13 rad, where independent clipping
  of the two faces would count a strip of width rounding/angle twice).
* Disjoint boxes give empty polygons (volume 0); contained boxes give the smaller box's faces.
* A box with zero volume has IoU 0 with every box, including an identical zero-volume box (0/0 is
  defined as 0 here: a flat box cannot overlap a volume).

Tolerances: ``_FEASIBLE`` (1e-14 of the pair's size scale) accepts polygon vertices that lie on a
boundary line up to rounding; ``_SHIFT`` (1e-13), used only for nearly parallel same-direction face
pairs (sine of their angle < 1e-3), is the strip width above.  Each changes the volume by at most about
its value times the boxes' area: relative errors ~1e-13, far below cpas_toolbox's Qhull (~1e-12).
"""

from __future__ import annotations

import math
import threading

import numpy as np

from evaluate.metrics import _validate

_FEASIBLE = 1e-14
_SHIFT = 1e-13
_PARALLEL = 1e-3
#: For face F (0-5: A's planes +x,-x,+y,-y,+z,-z; 6-11: B's), the 10 planes that bound it: all but F
#: and its parallel opposite.
_OTHER = np.array([[k for k in range(12) if k // 2 != f // 2] for f in range(12)])
# The line pairs of a face that can meet: in _OTHER's order, positions (0,1), (2,3), ... (8,9) are the
# two parallel planes of one box axis, for A's faces and B's alike; the other 40 pairs remain.
_PAIR_K, _PAIR_L = np.triu_indices(10, k=1)
_PAIR_K, _PAIR_L = _PAIR_K[_PAIR_K // 2 != _PAIR_L // 2], _PAIR_L[_PAIR_K // 2 != _PAIR_L // 2]
_CANDIDATES = len(_PAIR_K)  # 40
_VERTICES = 10  # a convex polygon bounded by 10 lines has at most 10 distinct vertices
_SIGNS = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
# Positions in _OTHER[f] of a face's own box's 4 neighbouring planes (first 4 for A's faces, last 4 for
# B's) and of the other box's 6 planes; the own quad's corners are the pairs of non-parallel neighbours.
_OWN_A = np.array([[0, 2], [0, 3], [1, 2], [1, 3]])
_OWN_B = _OWN_A + 6
_FOREIGN_A = np.arange(4, 10)
_FOREIGN_B = np.arange(0, 6)
# The same for the 8 faces at once, as indices into a pair's (8 faces x 10 lines) flattened rows.
_FACE_ROW = 10 * np.arange(8)[:, None]
_QUAD_K = np.concatenate([np.tile(_OWN_A[:, 0], (6, 1)), np.tile(_OWN_B[:, 0], (2, 1))]) + _FACE_ROW  # (8, 4)
_QUAD_L = np.concatenate([np.tile(_OWN_A[:, 1], (6, 1)), np.tile(_OWN_B[:, 1], (2, 1))]) + _FACE_ROW
_QUAD_FOREIGN = np.concatenate([np.tile(_FOREIGN_A, (6, 1)), np.tile(_FOREIGN_B, (2, 1))]) + _FACE_ROW  # (8, 6)
_CHUNK = 1024
_CORNERS = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=np.float64) * 2 - 1
_FACES = 8  # A's 6 faces and B's +x, -x faces: the others have n_x = 0 in V = integral of x n_x dA


def box_volume(extents) -> np.ndarray:
    """Volume (m^3) of boxes with full side lengths ``extents`` (..., 3)."""
    return np.prod(np.asarray(extents, dtype=np.float64), axis=-1)


def _intersection_volume(half_a: np.ndarray, half_b: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Volume of A ∩ B for M pairs, in B's frame.

    half_a, half_b: (M, 3) half extents; R: (M, 3, 3) A's axes (columns) in B's frame; t: (M, 3) A's
    centre in B's frame.
    """
    M = len(half_a)
    scale = half_a.max(axis=1) + half_b.max(axis=1) + np.linalg.norm(t, axis=1)  # (M,) size of the numbers
    tol = _FEASIBLE * scale
    tau = _SHIFT * scale

    # The 12 planes n·x <= o, in B's frame.
    axes_a = np.swapaxes(R, 1, 2)  # row j = A's axis j
    normals_a = axes_a[:, [0, 0, 1, 1, 2, 2]] * _SIGNS[None, :, None]
    offsets_a = np.einsum("mfd,md->mf", normals_a, t) + np.repeat(half_a, 2, axis=1)
    normals_b = np.broadcast_to((np.eye(3)[[0, 0, 1, 1, 2, 2]] * _SIGNS[:, None])[None], (M, 6, 3))
    offsets_b = np.repeat(half_b, 2, axis=1)
    normals = np.concatenate([normals_a, normals_b], axis=1)  # (M, 12, 3)
    offsets = np.concatenate([offsets_a, offsets_b], axis=1)  # (M, 12)

    # Faces that can contribute to V = integral of x n_x dA (x: B's first axis): A's 6 and B's +-x.
    # Parametrise face F by B's coordinates (s, r) orthogonal to the B axis p most aligned with n_F.
    nf, of = normals[:, :_FACES], offsets[:, :_FACES]
    proj = np.argmax(np.abs(normals), axis=2)  # (M, 12): also needed for the planes as constraints
    s_axis, r_axis = (proj[:, :_FACES] + 1) % 3, (proj[:, :_FACES] + 2) % 3
    n_fp, n_fs, n_fr = _pick(nf, proj[:, :_FACES]), _pick(nf, s_axis), _pick(nf, r_axis)
    abs_fp, sign_fp = np.abs(n_fp), np.sign(n_fp)

    other = _OTHER[:_FACES]
    ok = offsets[:, other]  # (M, 8, 10)
    # Component ``axis`` (M, 8) of the 10 bounding planes' normals of each face, gathered from the flat
    # normals in one take each (no (M, 8, 10, 3) copy).
    plane_start = (36 * np.arange(M))[:, None, None] + 3 * other[None]  # (M, 8, 10)
    flat_normals = normals.reshape(-1)
    n_kp, n_ks, n_kr = (flat_normals.take(plane_start + a[..., None]) for a in (proj[:, :_FACES], s_axis, r_axis))
    # Constraint n_k·x <= o_k for x on face F, x_p eliminated, scaled by |n_Fp| > 0.  The operation order
    # matters: for a face of A and the B plane with the same normal direction it yields exactly the
    # negation of the B face's constraint from that A plane (see the module docstring).
    sk = sign_fp[..., None] * n_kp
    a_s = abs_fp[..., None] * n_ks - sk * n_fs[..., None]
    a_r = abs_fp[..., None] * n_kr - sk * n_fr[..., None]
    b = abs_fp[..., None] * ok - sk * of[..., None]

    # Same-direction pairs sharing the projection axis: give the strip to A's face.
    same_dir = (proj[:, other] == proj[:, :_FACES, None]) & (np.sign(n_kp) == sign_fp[..., None])
    face_is_a = (np.arange(_FACES) < 6)[None, :, None]
    other_is_a = (other < 6)[None]
    # Only nearly parallel pairs need it (|a| ~ sine of the angle between the planes); elsewhere a shift
    # would open a gap of width tau along the seam for nothing.
    same_dir &= a_s * a_s + a_r * a_r < _PARALLEL**2
    shift = np.where(same_dir & face_is_a & ~other_is_a, tau[:, None, None], 0.0)
    shift = np.where(same_dir & ~face_is_a & other_is_a, -tau[:, None, None], shift)
    b = b + shift

    # Faces whose own quad lies wholly outside one of the other box's planes are empty: skip them.
    F = M * _FACES
    tol_f = np.repeat(tol, _FACES)
    active = _quad_meets_other_box(a_s, a_r, b, tol).reshape(F)
    a_s, a_r, b = a_s.reshape(F, 10), a_r.reshape(F, 10), b.reshape(F, 10)
    moments = np.zeros((3, F))  # area, integral of s, integral of r, in the (s, r) plane
    rows = np.flatnonzero(active)
    for start in range(0, len(rows), _CHUNK):  # chunks keep the (faces, 10, 40) arrays in cache
        sel = rows[start:start + _CHUNK]
        moments[:, sel] = _polygon_moments(a_s[sel], a_r[sel], b[sel], tol_f[sel])
    area, ms, mr = (m.reshape(M, _FACES) for m in moments)
    # integral of x n_x dA over each face polygon (dA = dA_sr / |n_Fp|)
    n_fx = nf[..., 0]
    x_is_p = proj[:, :_FACES] == 0
    integral_x = np.where(x_is_p, (of * area - n_fs * ms - n_fr * mr) / abs_fp,
                          n_fx / abs_fp * np.where(s_axis == 0, ms, mr))
    return integral_x.sum(axis=1)


def _pick(x: np.ndarray, index: np.ndarray) -> np.ndarray:
    """x[..., index] with one index per leading position (x: (..., 3), index: x.shape[:-1])."""
    flat = x.reshape(-1, x.shape[-1])
    return flat[np.arange(len(flat)), index.reshape(-1)].reshape(index.shape)


def _line_intersections(a_s, a_r, b, k, l):
    """Intersections of lines k and l (column indices) of a_s s + a_r r = b; also whether they exist."""
    as1, ar1, b1 = a_s[..., k], a_r[..., k], b[..., k]
    as2, ar2, b2 = a_s[..., l], a_r[..., l], b[..., l]
    det = as1 * ar2 - ar1 * as2
    valid = np.abs(det) > 1e-20  # fails only for parallel lines (or two rounding-noise lines)
    det = np.where(valid, det, 1.0)
    return (b1 * ar2 - b2 * ar1) / det, (as1 * b2 - as2 * b1) / det, valid


def _quad_meets_other_box(a_s, a_r, b, tol):
    """(M, 8) False where a face's own quad lies wholly outside one of the other box's planes (empty face).

    a_s, a_r, b: (M, 8, 10) the faces' bounding lines; tol: (M,)."""
    M = len(a_s)
    s_, r_, b_ = a_s.reshape(M, -1), a_r.reshape(M, -1), b.reshape(M, -1)
    k, l = _QUAD_K, _QUAD_L  # (8, 4) the lines meeting at each corner of each face's own quad
    cs, cr, _ = _line_intersections(s_, r_, b_, k, l)  # (M, 8, 4) quad corners
    fs, fr, fb = (x[:, _QUAD_FOREIGN][:, :, None, :] for x in (s_, r_, b_))  # (M, 8, 1, 6) the other box's lines
    r = fs * cs[..., None] + fr * cr[..., None] - fb
    return ~np.any(np.all(r > tol[:, None, None, None], axis=2), axis=2)


class _Workspace(threading.local):
    """Scratch arrays of :func:`_polygon_moments`, kept per thread and reused from call to call.

    Why: a call's temporaries come to several MB; glibc hands freed heap tops back to the kernel
    (trimming) and page-faults them in again on the next call, which cost 40-80% of a call in
    about half of all processes (0 vs ~1500 minor faults per 200-pair batch, depending on the
    heap's layout).  Writing the large temporaries into these buffers makes the time of a call
    independent of the allocator's state.  Their sizes are bounded by ``_CHUNK`` rows (~8 MB).
    """

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        """A contiguous array of ``shape`` in the buffer ``name`` (contents undefined; valid until the
        next ``get`` of that name)."""
        size = math.prod(shape)
        array = self._arrays.get(name)
        if array is None or array.size < size or array.dtype != dtype:
            array = self._arrays[name] = np.empty(max(size, 2 * (0 if array is None else array.size)), dtype=dtype)
        return array[:size].reshape(shape)


_WORKSPACE = _Workspace()


def _polygon_moments(a_s, a_r, b, tol):
    """Area and first moments (integral of s, of r) of the convex polygons {p : a_s p_s + a_r p_r <= b (+tol)},
    one per row (rows are (10,) lines, at most ``_CHUNK`` of them); shape (3, rows).

    Every (rows, 40) and larger temporary lives in :data:`_WORKSPACE` (``out=`` throughout), see there.
    """
    n = len(a_s)
    ws = _WORKSPACE
    f = lambda name: ws.get(name, (n, _CANDIDATES))  # noqa: E731  an (n, 40) float scratch array
    # Candidate vertices: the intersections of the 40 non-parallel line pairs, written straight into the
    # (n, 3, 40) right-hand side of the residual product below (rows s, r, -1).
    ps, pr = f("ps"), f("pr")
    as1, ar1, b1 = (np.take(x, _PAIR_K, axis=1, out=f(name), mode="clip") for x, name in ((a_s, "as1"), (a_r, "ar1"), (b, "b1")))
    as2, ar2, b2 = (np.take(x, _PAIR_L, axis=1, out=f(name), mode="clip") for x, name in ((a_s, "as2"), (a_r, "ar2"), (b, "b2")))
    det, tmp = f("det"), f("tmp")
    np.subtract(np.multiply(as1, ar2, out=det), np.multiply(ar1, as2, out=tmp), out=det)
    valid = np.greater(np.abs(det, out=tmp), 1e-20, out=ws.get("valid", (n, _CANDIDATES), dtype=bool))  # False: parallel lines
    np.copyto(det, 1.0, where=np.logical_not(valid, out=ws.get("invalid", (n, _CANDIDATES), dtype=bool)))
    np.subtract(np.multiply(b1, ar2, out=ps), np.multiply(b2, ar1, out=tmp), out=ps)
    np.divide(ps, det, out=ps)
    np.subtract(np.multiply(as1, b2, out=pr), np.multiply(as2, b1, out=tmp), out=pr)
    np.divide(pr, det, out=pr)
    # Residuals of all candidates against all 10 lines as one batched matrix product (n, 10, 40), stored
    # line-major (10, n, 40) so that the max over lines is an elementwise max of 10 contiguous slabs.
    points = ws.get("points", (n, 3, _CANDIDATES))
    points[:, 0], points[:, 1], points[:, 2] = ps, pr, -1.0
    lines = ws.get("lines", (n, 10, 3))
    lines[..., 0], lines[..., 1], lines[..., 2] = a_s, a_r, b
    residual = ws.get("residual", (10, n, _CANDIDATES))
    np.matmul(lines, points, out=residual.transpose(1, 0, 2))
    worst = np.max(residual, axis=0, out=f("worst"))
    feasible = np.logical_and(valid, np.less_equal(worst, tol[:, None], out=ws.get("feasible", (n, _CANDIDATES), dtype=bool)),
                              out=ws.get("feasible", (n, _CANDIDATES), dtype=bool))
    count = feasible.sum(axis=1)
    moments = np.zeros((3, n))
    # Rows with fewer than 3 vertices have no area.  A polygon bounded by 10 lines has at most 10
    # vertices, but where more lines meet in one point (touching boxes) it gets that vertex several
    # times: such rows take the full width.  The width depends on the row alone, so a pair's IoU does not
    # depend on the other pairs in its batch.
    for width, rows in ((_VERTICES, (count >= 3) & (count <= _VERTICES)), (_CANDIDATES, count > _VERTICES)):
        if rows.any():
            _shoelace_moments(ps, pr, feasible, count, rows, width, moments)
    return moments


def _shoelace_moments(ps, pr, feasible, count, rows, width, moments) -> None:
    """Area and first moments of the polygons of the selected ``rows`` (n,) bool, written into
    ``moments`` (3, n); their vertices are the ``feasible`` (n, 40) candidates (ps, pr), at most ``width``.

    The vertices are compacted to the left of (m, width) arrays, sorted by angle about their mean
    and summed by the shoelace formula (scratch arrays from :data:`_WORKSPACE`).
    """
    ws = _WORKSPACE
    selected = np.flatnonzero(rows)
    m = len(selected)
    count = np.where(rows, count, 0)
    # Scatter the vertices: the k-th vertex of the i-th selected row goes to slot (i, k) of (m, width).
    flat = np.flatnonzero(feasible & rows[:, None])  # row-major: each row's vertices in a run
    row = flat // _CANDIDATES
    before = np.cumsum(count) - count  # vertices of the rows before each row
    dest = np.arange(len(flat)) - before[row] + (np.cumsum(rows) - 1)[row] * width
    g = lambda name, w=width: ws.get(f"{name}{w}", (m, w))  # noqa: E731  an (m, w) float scratch array
    vs, vr = g("vs"), g("vr")
    vs[...], vr[...] = 0.0, 0.0  # slots past a row's last vertex stay 0
    vs.reshape(-1)[dest], vr.reshape(-1)[dest] = ps.reshape(-1)[flat], pr.reshape(-1)[flat]
    count = count[selected]
    cs, cr = vs.sum(axis=1) / count, vr.sum(axis=1) / count  # the vertices' mean, inside the polygon
    qs, qr = np.subtract(vs, cs[:, None], out=g("qs")), np.subtract(vr, cr[:, None], out=g("qr"))
    # Sort by a pseudo-angle (monotone in the true angle, cheaper than arctan2): qr / (|qs| + |qr|) for
    # qs >= 0, 2 minus that for qs < 0, 0 at the mean; slots past the last vertex last.
    d = np.add(np.abs(qs, out=g("d")), np.abs(qr, out=g("t")), out=g("d"))
    pseudo = g("pseudo")
    pseudo[...] = 0.0
    np.divide(qr, d, out=pseudo, where=d > 0)
    np.copyto(pseudo, np.subtract(2.0, pseudo, out=g("t")), where=qs < 0)
    np.copyto(pseudo, np.inf, where=np.arange(width)[None, :] >= count[:, None])
    order = np.argsort(pseudo, axis=1)
    # Slots past the last vertex repeat it, which adds nothing to the shoelace sums; a last slot repeats
    # the first vertex, so that slots 1..width are the next vertex round the polygon.
    slot = np.minimum(np.append(np.arange(width), 0)[None, :], (count - 1)[:, None],
                      out=ws.get(f"slot{width}", (m, width + 1), dtype=np.intp))
    row_start = (width * np.arange(m))[:, None]
    idx = np.take(order, np.add(slot, row_start, out=slot), out=ws.get(f"idx{width}", (m, width + 1), dtype=np.intp))
    np.add(idx, row_start, out=idx)
    sorted_s = np.take(qs.reshape(-1), idx, out=g("sorted_s", width + 1))
    sorted_r = np.take(qr.reshape(-1), idx, out=g("sorted_r", width + 1))
    qs, qs2, qr, qr2 = sorted_s[:, :-1], sorted_s[:, 1:], sorted_r[:, :-1], sorted_r[:, 1:]
    cross = np.subtract(np.multiply(qs, qr2, out=g("cross")), np.multiply(qs2, qr, out=g("t")), out=g("cross"))
    t = g("t")
    area = 0.5 * cross.sum(axis=1)
    m_s = np.multiply(np.add(qs, qs2, out=t), cross, out=t).sum(axis=1) / 6.0
    m_r = np.multiply(np.add(qr, qr2, out=t), cross, out=t).sum(axis=1) / 6.0
    sign = np.sign(area)  # vertices sorted either way round
    area, m_s, m_r = sign * area, sign * m_s, sign * m_r
    moments[:, selected] = area, m_s + cs * area, m_r + cr * area  # moments about the (s, r) origin


def _iou_from_volumes(inter: np.ndarray, vol_a: np.ndarray, vol_b: np.ndarray, a_in_b: np.ndarray,
                      b_in_a: np.ndarray) -> np.ndarray:
    inter = np.clip(inter, 0.0, np.minimum(vol_a, vol_b))
    # A inside B: the union is B itself, so the IoU is exactly vol_a / vol_b (1.0 for identical boxes,
    # where vol_a + vol_b - inter would leave a rounding error in the last bit).
    union = np.where(a_in_b, vol_b, np.where(b_in_a, vol_a, vol_a + vol_b - inter))
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
    return np.clip(iou, 0.0, 1.0)


def _box_iou_arrays(extents_a, T_a, extents_b, T_b) -> np.ndarray:
    """IoU for validated arrays (M, 3), (M, 4, 4), (M, 3), (M, 4, 4)."""
    vol_a, vol_b = box_volume(extents_a), box_volume(extents_b)
    half_a, half_b = extents_a / 2.0, extents_b / 2.0
    Ra, Rb = T_a[:, :3, :3], T_b[:, :3, :3]
    R = np.einsum("mji,mjk->mik", Rb, Ra)
    t = np.einsum("mji,mj->mi", Rb, T_a[:, :3, 3] - T_b[:, :3, 3])
    # A box inside the other (up to the _FEASIBLE tolerance) is the intersection itself.
    tol = _FEASIBLE * (half_a.max(axis=1) + half_b.max(axis=1) + np.linalg.norm(t, axis=1))
    corners_a = t[:, None, :] + np.einsum("mij,mkj->mki", R, _CORNERS * half_a[:, None, :])  # in B's frame
    a_in_b = np.all(np.abs(corners_a) <= half_b[:, None, :] + tol[:, None, None], axis=(1, 2))
    corners_b = np.einsum("mji,mkj->mki", R, _CORNERS * half_b[:, None, :] - t[:, None, :])  # in A's frame
    b_in_a = np.all(np.abs(corners_b) <= half_a[:, None, :] + tol[:, None, None], axis=(1, 2))
    inter = np.where(a_in_b, vol_a, np.where(b_in_a, vol_b, 0.0))
    # Only other pairs that have volume and whose bounding spheres meet need the polygon work.
    reach = np.linalg.norm(half_a, axis=1) + np.linalg.norm(half_b, axis=1)
    work = (vol_a > 0) & (vol_b > 0) & (np.linalg.norm(t, axis=1) < reach) & ~a_in_b & ~b_in_a
    if np.any(work):
        inter[work] = _intersection_volume(half_a[work], half_b[work], R[work], t[work])
    iou = _iou_from_volumes(inter, vol_a, vol_b, a_in_b, b_in_a)
    return np.where((vol_a > 0) & (vol_b > 0), iou, 0.0)


def box_iou_batch(extents_a, T_a, extents_b, T_b) -> np.ndarray:
    """Exact IoU of N pairs of oriented boxes: extents (N, 3) m, object-to-camera transforms (N, 4, 4).

    Returns (N,).  Raises ValueError on NaN/inf, negative extents or non-rigid transforms (the evaluation
    code screens predictions first and reports malformed ones as failed).
    """
    ea = _validate.extents(extents_a, "extents_a").reshape(-1, 3)
    eb = _validate.extents(extents_b, "extents_b").reshape(-1, 3)
    Ta = _validate.rigid_transforms(T_a, "T_a").reshape(-1, 4, 4)
    Tb = _validate.rigid_transforms(T_b, "T_b").reshape(-1, 4, 4)
    n = max(len(ea), len(eb), len(Ta), len(Tb))
    try:
        ea, Ta, eb, Tb = (np.broadcast_to(x, (n,) + x.shape[1:]) for x in (ea, Ta, eb, Tb))
    except ValueError:
        raise ValueError("box_iou_batch: inputs do not have matching lengths") from None
    return _box_iou_arrays(ea, Ta, eb, Tb)


def box_iou(extents_a, T_a, extents_b, T_b) -> float:
    """Exact IoU of two oriented boxes: extents (3,) m, object-to-camera transforms (4, 4)."""
    if np.shape(extents_a) != (3,) or np.shape(extents_b) != (3,):
        raise ValueError("box_iou: extents must have shape (3,)")
    if np.shape(T_a) != (4, 4) or np.shape(T_b) != (4, 4):
        raise ValueError("box_iou: transforms must have shape (4, 4)")
    return float(box_iou_batch(extents_a, T_a, extents_b, T_b)[0])


# --- symmetric IoU -------------------------------------------------------------------------------

_BISECT = 3  # rounds of halving the intervals that may hold the maximum (to 1/8 of the grid spacing)
_REFINE = 3  # brackets refined per pair: its highest local maxima
_ZOOM = 8  # points per bracket and refinement step (the bracket shrinks ~4.5x per step)


def _rotated_about_y(T: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """T (M, 4, 4) composed with rotations by ``angles`` (M,) radians about the object's own y axis."""
    c, s = np.cos(angles), np.sin(angles)
    Ry = np.zeros((len(angles), 3, 3))
    Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 1, 1], Ry[:, 2, 0], Ry[:, 2, 2] = c, s, 1.0, -s, c
    out = np.array(T, copy=True)
    out[:, :3, :3] = np.einsum("mij,mjk->mik", T[:, :3, :3], Ry)
    return out


def _aligned_angles(T_gt: np.ndarray, T_pred: np.ndarray) -> np.ndarray:
    """(N, 6) angles in [0, pi) about the prediction's y axis that make its x axis parallel to the
    projection of one of the ground truth's axes onto the prediction's xz plane (NaN where undefined).

    At these angles faces of the two boxes become parallel, where the IoU curve has its kinks.
    """
    M = np.einsum("nji,njk->nik", T_pred[:, :3, :3], T_gt[:, :3, :3])  # gt axes in the prediction's frame
    gx, gz = M[:, 0, :], M[:, 2, :]  # (N, 3)
    # R_y(phi) maps x to (cos phi, 0, -sin phi): parallel to (gx, gz) when phi = atan2(-gz, gx) mod pi/2.
    base = np.mod(np.arctan2(-gz, gx), np.pi / 2)
    base = np.where(np.hypot(gx, gz) > 1e-9, base, np.nan)
    return np.concatenate([base, base + np.pi / 2], axis=1)


def symmetric_box_iou_batch(extents_gt, T_gt, extents_pred, T_pred, grid: int = 90, xtol: float = 1e-9,
                            return_angle: bool = False):
    """Exact max over rotations of the prediction about its own y axis of the box IoU, for N pairs.

    For objects rotationally symmetric about y (bottle, bowl, can) the box's rotation about y is
    arbitrary, so the prediction is rotated to fit the ground truth best.  The IoU is a continuous,
    piecewise-smooth function of the angle phi with period pi (a box maps onto itself under a half turn).
    The maximum is found as follows, and why it is the maximum:

    1. ``grid`` equally spaced angles in [0, pi) (spacing h) bracket it: by the bound below, on an
       interval of width w between samples f_l and f_r the IoU is at most (f_l + f_r + L w) / 2, so
       only intervals whose bound reaches the best value found so far can hold the maximum; those
       are halved (branch and bound, three rounds), the others are provably lower.
       L = e_y (e_x^2 + e_z^2) / max(V_gt, V_pred) bounds |dIoU/dphi|: rotating about y, only the four
       side faces sweep volume, at normal speed at most |z| (x faces) or |x| (z faces), so
       |dV_inter/dphi| <= e_y (e_x^2 + e_z^2) / 2 and dIoU/dV_inter <= 2 / union.
    2. Each bracket is refined by a bounded zooming search (a generalised golden-section search: 8
       interior points per step, the bracket shrinking to the best point's neighbours, ~4.5x per step)
       to ``xtol`` radians, vectorised over all brackets and pairs.  Inside a bracket of width 2h = 1 degree the
       IoU has at most one local maximum in practice (its pieces are ratios of low-order
       trigonometric polynomials, and the pieces change only where edges cross faces).
    3. The IoU is non-smooth exactly where faces of the two boxes turn parallel; the maximum often sits
       on such a kink (e.g. identical boxes at phi = 0).  Those angles are computed in closed form
       (:func:`_aligned_angles`) and evaluated directly.

    The result is the largest IoU over all evaluated angles: a value attained by an actual rotation
    (never an overestimate) and at least the value of any grid, refined or aligned angle.  Returns (N,)
    IoUs, and the best angles (N,) in radians when ``return_angle``.
    """
    ea = _validate.extents(extents_gt, "extents_gt").reshape(-1, 3)
    eb = _validate.extents(extents_pred, "extents_pred").reshape(-1, 3)
    Ta = _validate.rigid_transforms(T_gt, "T_gt").reshape(-1, 4, 4)
    Tb = _validate.rigid_transforms(T_pred, "T_pred").reshape(-1, 4, 4)
    n = max(len(ea), len(eb), len(Ta), len(Tb))
    ea, Ta, eb, Tb = (np.broadcast_to(x, (n,) + x.shape[1:]) for x in (ea, Ta, eb, Tb))

    def iou_at(rows: np.ndarray, angles: np.ndarray) -> np.ndarray:
        return _box_iou_arrays(ea[rows], Ta[rows], eb[rows], _rotated_about_y(Tb[rows], angles))

    h = np.pi / grid
    rows = np.repeat(np.arange(n), grid)
    grid_angles = np.tile(np.arange(grid) * h, n)
    # 3. aligned angles, evaluated in the same batch as the grid
    aligned = _aligned_angles(Ta, Tb)
    ok = np.isfinite(aligned)
    a_rows, a_angles = np.nonzero(ok)[0], aligned[ok]
    values = iou_at(np.concatenate([rows, a_rows]), np.concatenate([grid_angles, a_angles]))
    grid_iou, a_values = values[: len(rows)].reshape(n, grid), values[len(rows):]
    best = grid_iou.max(axis=1)
    best_angle = grid_angles.reshape(n, grid)[np.arange(n), grid_iou.argmax(axis=1)]
    samples_rows, samples_angles, samples_values = [rows], [grid_angles], [grid_iou.ravel()]

    def consider(rows: np.ndarray, angles: np.ndarray, values: np.ndarray) -> None:
        order = np.lexsort((values, rows))  # per row, the largest value last
        rows, angles, values = rows[order], angles[order], values[order]
        last = np.r_[rows[1:] != rows[:-1], True]
        r, a, v = rows[last], angles[last], values[last]
        better = v > best[r]
        best[r[better]], best_angle[r[better]] = v[better], a[better]

    if len(a_rows):
        consider(a_rows, a_angles, a_values)

    # 1. branch and bound: intervals [phi_l, phi_r] whose Lipschitz bound (f_l + f_r + L w) / 2 reaches
    # the best value so far are halved, _BISECT times; the bound, tightening as w halves, prunes the
    # others (they provably stay below the best value).
    vol_a, vol_b = box_volume(ea), box_volume(eb)
    lipschitz = eb[:, 1] * (eb[:, 0] ** 2 + eb[:, 2] ** 2) / np.maximum(np.maximum(vol_a, vol_b), 1e-300)
    i_rows = np.repeat(np.arange(n), grid)
    i_lo = grid_angles
    i_f_lo, i_f_hi = grid_iou.ravel(), np.roll(grid_iou, -1, axis=1).ravel()
    width = h
    for _ in range(_BISECT):
        keep = (i_f_lo + i_f_hi + lipschitz[i_rows] * width) / 2 >= best[i_rows]
        i_rows, i_lo, i_f_lo, i_f_hi = i_rows[keep], i_lo[keep], i_f_lo[keep], i_f_hi[keep]
        if not len(i_rows):
            break
        width /= 2
        mid = i_lo + width
        f_mid = iou_at(i_rows, mid)
        consider(i_rows, mid, f_mid)
        samples_rows.append(i_rows), samples_angles.append(mid), samples_values.append(f_mid)
        i_rows = np.concatenate([i_rows, i_rows])
        i_lo = np.concatenate([i_lo, mid])
        i_f_lo, i_f_hi = np.concatenate([i_f_lo, f_mid]), np.concatenate([f_mid, i_f_hi])
    # 2. zooming search, maximising, on brackets around the local maxima of each pair's samples (in
    # angle order; a local maximum's bracket runs from its left to its right neighbour), at most
    # _REFINE per pair, the highest first, skipping those the Lipschitz bound rules out.
    s_rows, s_angles, s_values = np.concatenate(samples_rows), np.concatenate(samples_angles), np.concatenate(samples_values)
    order = np.lexsort((s_angles, s_rows))
    s_rows, s_angles, s_values = s_rows[order], s_angles[order], s_values[order]
    same_prev = np.r_[False, s_rows[1:] == s_rows[:-1]]
    same_next = np.r_[s_rows[:-1] == s_rows[1:], False]
    prev_v = np.where(same_prev, np.roll(s_values, 1), -np.inf)
    next_v = np.where(same_next, np.roll(s_values, -1), -np.inf)
    prev_a = np.where(same_prev, np.roll(s_angles, 1), s_angles - h)
    next_a = np.where(same_next, np.roll(s_angles, -1), s_angles + h)
    reach = lipschitz[s_rows] * np.maximum(s_angles - prev_a, next_a - s_angles)
    peak = (s_values >= prev_v) & (s_values >= next_v) & (s_values > 0) & (s_values + reach >= best[s_rows])
    k_rows, k_values, k_lo, k_hi = s_rows[peak], s_values[peak], prev_a[peak], next_a[peak]
    order = np.lexsort((-k_values, k_rows))
    k_rows, k_lo, k_hi = k_rows[order], k_lo[order], k_hi[order]
    rank = np.arange(len(k_rows)) - np.searchsorted(k_rows, k_rows)
    pick = rank < _REFINE
    b_rows = k_rows[pick]
    if len(b_rows):
        lo, hi = k_lo[pick], k_hi[pick]
        steps = np.arange(1, _ZOOM + 1) / (_ZOOM + 1)
        while np.max(hi - lo) > xtol:
            x = lo[:, None] + (hi - lo)[:, None] * steps[None, :]  # (brackets, _ZOOM) interior points
            f = iou_at(np.repeat(b_rows, _ZOOM), x.ravel()).reshape(-1, _ZOOM)
            consider(np.repeat(b_rows, _ZOOM), x.ravel(), f.ravel())
            j = np.argmax(f, axis=1)
            # for a unimodal function the maximum lies between the neighbours of the best point
            k = np.arange(len(j))
            lo = np.where(j == 0, lo, x[k, np.maximum(j - 1, 0)])
            hi = np.where(j == _ZOOM - 1, hi, x[k, np.minimum(j + 1, _ZOOM - 1)])
    best_angle = np.mod(best_angle, np.pi)
    return (best, best_angle) if return_angle else best


def symmetric_box_iou(extents_gt, T_gt, extents_pred, T_pred) -> float:
    """Exact max IoU over rotations of the prediction about its y axis (see :func:`symmetric_box_iou_batch`)."""
    if np.shape(extents_gt) != (3,) or np.shape(extents_pred) != (3,):
        raise ValueError("symmetric_box_iou: extents must have shape (3,)")
    if np.shape(T_gt) != (4, 4) or np.shape(T_pred) != (4, 4):
        raise ValueError("symmetric_box_iou: transforms must have shape (4, 4)")
    return float(symmetric_box_iou_batch(extents_gt, T_gt, extents_pred, T_pred)[0])


# --- NOCS-style axis-aligned IoU (for comparison only) --------------------------------------------

def axis_aligned_iou(extents_gt, T_gt, extents_pred, T_pred, symmetry: str | None = "none", n_angles: int = 20) -> float:
    """IoU of the camera-axis-aligned bounding boxes of the two boxes, as NOCS's ``compute_3d_iou_new``.

    For comparison with published NOCS/REAL275 numbers only: it is not the overlap of the oriented
    boxes and depends on the camera's orientation.  Convention implemented (NOCS_CVPR2019 utils.py):
    the 8 corners of each box (full side lengths ``extents``) are mapped to the camera frame by its
    pose, each box is replaced by the axis-aligned box of its corners, and the IoU of those is returned
    (0 when they do not overlap).  With ``symmetry="y"`` the prediction is rotated about its own y axis
    by 2 pi i / n_angles, i = 0..n_angles-1 (NOCS: n = 20, rotating ``RT_1``, the prediction), and the
    largest IoU is returned.  NOCS's original code takes the min/max over the wrong array axis
    (``axis=0`` of a (3, 8) array, i.e. over x, y, z per corner); we implement the intended per-axis
    bounding box, as the later corrected versions of that file do.
    """
    mode = _validate.symmetry(symmetry)
    eg, ep = _validate.extents(extents_gt, "extents_gt"), _validate.extents(extents_pred, "extents_pred")
    Tg, Tp = _validate.rigid_transforms(T_gt, "T_gt"), _validate.rigid_transforms(T_pred, "T_pred")
    if eg.shape != (3,) or ep.shape != (3,) or Tg.shape != (4, 4) or Tp.shape != (4, 4):
        raise ValueError("axis_aligned_iou: expected extents (3,) and transforms (4, 4)")
    signs = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=np.float64) * 2 - 1
    corners_g = (signs * eg / 2) @ Tg[:3, :3].T + Tg[:3, 3]
    angles = 2 * np.pi * np.arange(n_angles) / n_angles if mode == "y" else np.zeros(1)
    Tps = _rotated_about_y(np.broadcast_to(Tp, (len(angles), 4, 4)), angles)
    corners_p = np.einsum("kd,mjd->mkj", signs * ep / 2, Tps[:, :3, :3]) + Tps[:, None, :3, 3]  # (m, 8, 3)
    lo_g, hi_g = corners_g.min(axis=0), corners_g.max(axis=0)
    lo_p, hi_p = corners_p.min(axis=1), corners_p.max(axis=1)
    overlap = np.minimum(hi_g, hi_p) - np.maximum(lo_g, lo_p)
    inter = np.where(np.all(overlap >= 0, axis=1), np.prod(np.maximum(overlap, 0), axis=1), 0.0)
    union = np.prod(hi_g - lo_g) + np.prod(hi_p - lo_p, axis=1) - inter
    iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
    return float(iou.max())
