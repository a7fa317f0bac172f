"""A light tree: which light a hit point's shadow ray goes to, chosen in
O(log n) by bounds on what each group of lights can deliver there.

After pbrt-v4's `BVHLightSampler` (Conty & Kulla 2018): a binary tree over
every light, each node bounding its lights' positions (a box), their
emission directions (a cone: axis w, spread theta_o, and theta_e past it
where emission falls to zero) and their summed intensity phi. At a point p
with normal n a node's importance bounds phi cos(theta') / d^2 times the
bound on the surface cosine, where theta' is the smallest angle between
the cone and the directions toward p from the box. A light is sampled by
walking down from the root, choosing each child in proportion to its
importance; its probability is the product of those choices, and can be
evaluated for any light by walking up from its leaf (for MIS).

The bounds are conservative: a light that can light p (from the front of
its surface, inside its spot cone, above the hit point's surface) has a
positive importance at every node above it, so it keeps a positive
probability. Unlike pbrt, phi is an intensity for every kind (radiance x
area for a triangle, W/sr for point and spot lights), so that phi / d^2
compares kinds fairly, and d^2 is clamped to the node's squared half
diagonal (pbrt clamps it to a length). The surface cosine is one-sided:
hit points reflect only on the side their normal faces.

The tree is built by pbrt's bucketed cost (power x solid angle of the
cone x surface area of the box), 12 buckets on each axis. Lights of zero
power, and the infinite lights (directional, environment), are left out
(`leaf_of` -1, probability 0).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from dosppm_core.scene.model import LIGHT_DIRECTIONAL, LIGHT_ENV, LIGHT_POINT, LIGHT_PROJECTOR, LIGHT_TRIANGLE

BUCKETS = 12
_ONE_MINUS = 0.9999999999999999


class LightTree(NamedTuple):
    """Nodes in depth-first order: node k's first child is k + 1, its
    second `child[k]`; a leaf holds light -1 - child[k]. The kernels take
    it as a plain tuple (`tuple(tree)`), made inside a parallel loop's
    body: numba refuses a tuple nested in a parallel kernel's arguments."""
    box: np.ndarray       # float64 (N, 2, 3)
    cone: np.ndarray      # float64 (N, 5): axis w (3), cos theta_o, cos theta_e
    phi: np.ndarray       # float64 (N,)
    child: np.ndarray     # int32 (N,)
    parent: np.ndarray    # int32 (N,), -1 at the root
    leaf_of: np.ndarray   # int32 (L,): each light's leaf, -1 if not in the tree


def build_light_tree(lights) -> LightTree:
    """The tree over a `LightTable`'s rows."""
    box, cone, phi = _light_bounds(lights.kind, lights.p0, lights.p1, lights.p2, lights.value, lights.cone)
    return LightTree(*_build(box, cone, phi))


# -- bounds of single lights and unions ----------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def _light_bounds(kind, p0, p1, p2, value, cone):
    L = kind.shape[0]
    box, cones, phi = np.zeros((L, 2, 3)), np.zeros((L, 5)), np.zeros(L)
    for i in range(L):
        intensity = (value[i, 0] + value[i, 1] + value[i, 2]) / 3.0
        cones[i, 2] = 1.0                       # w = +z unless set below
        if kind[i] == LIGHT_DIRECTIONAL or kind[i] == LIGHT_ENV:
            continue                            # infinitely far: chosen apart (`direct`), not in the tree
        if kind[i] == LIGHT_TRIANGLE:
            for k in range(3):
                box[i, 0, k] = min(p0[i, k], p1[i, k], p2[i, k])
                box[i, 1, k] = max(p0[i, k], p1[i, k], p2[i, k])
            e1, e2 = p1[i] - p0[i], p2[i] - p0[i]
            nx = e1[1] * e2[2] - e1[2] * e2[1]
            ny = e1[2] * e2[0] - e1[0] * e2[2]
            nz = e1[0] * e2[1] - e1[1] * e2[0]
            nl = math.sqrt(nx * nx + ny * ny + nz * nz)
            if not nl > 0.0:
                continue                        # degenerate: no power, not in the tree
            cones[i, 0], cones[i, 1], cones[i, 2] = nx / nl, ny / nl, nz / nl
            cones[i, 3], cones[i, 4] = 1.0, 0.0     # one-sided: the front hemisphere
            phi[i] = intensity * 0.5 * nl
        else:
            for k in range(3):
                box[i, 0, k] = box[i, 1, k] = p0[i, k]
            phi[i] = intensity
            if kind[i] == LIGHT_POINT:
                cones[i, 3], cones[i, 4] = -1.0, 0.0
            elif kind[i] == LIGHT_PROJECTOR:        # the frustum's cone; phi bounds pi E / cos^3
                cos_o = 1.0 / math.sqrt(1.0 + cone[i, 0] ** 2 + cone[i, 1] ** 2)
                cones[i, 0], cones[i, 1], cones[i, 2] = p1[i, 0], p1[i, 1], p1[i, 2]
                cones[i, 3], cones[i, 4] = cos_o, math.cos(0.01)
                phi[i] = math.pi * intensity / cos_o ** 3
            else:                               # spot: full to the beam, falling off to the cutoff
                cones[i, 0], cones[i, 1], cones[i, 2] = p1[i, 0], p1[i, 1], p1[i, 2]
                cones[i, 3] = math.cos(cone[i, 3])
                cones[i, 4] = math.cos(min(math.pi, cone[i, 2] - cone[i, 3]))
    return box, cones, phi


@nb.njit(inline="always", cache=True, error_model="numpy")
def _angle_between(a0, a1, a2, b0, b1, b2):
    """Robust angle between unit vectors (pbrt's AngleBetween)."""
    if a0 * b0 + a1 * b1 + a2 * b2 < 0.0:
        s0, s1, s2 = a0 + b0, a1 + b1, a2 + b2
        return math.pi - 2.0 * math.asin(min(1.0, math.sqrt(s0 * s0 + s1 * s1 + s2 * s2) / 2.0))
    s0, s1, s2 = b0 - a0, b1 - a1, b2 - a2
    return 2.0 * math.asin(min(1.0, math.sqrt(s0 * s0 + s1 * s1 + s2 * s2) / 2.0))


@nb.njit(cache=True, error_model="numpy")
def _cone_union(wa, cos_a, wb, cos_b, out):
    """The smallest cone holding cones a and b (pbrt's DirectionCone
    Union), written to out[0:4] (axis, cos theta)."""
    theta_a, theta_b = math.acos(max(-1.0, min(1.0, cos_a))), math.acos(max(-1.0, min(1.0, cos_b)))
    theta_d = _angle_between(wa[0], wa[1], wa[2], wb[0], wb[1], wb[2])
    if min(theta_d + theta_b, math.pi) <= theta_a:
        out[0], out[1], out[2], out[3] = wa[0], wa[1], wa[2], cos_a
        return
    if min(theta_d + theta_a, math.pi) <= theta_b:
        out[0], out[1], out[2], out[3] = wb[0], wb[1], wb[2], cos_b
        return
    theta_o = 0.5 * (theta_a + theta_d + theta_b)
    r0 = wa[1] * wb[2] - wa[2] * wb[1]
    r1 = wa[2] * wb[0] - wa[0] * wb[2]
    r2 = wa[0] * wb[1] - wa[1] * wb[0]
    rl = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    if theta_o >= math.pi or not rl > 0.0:
        out[0], out[1], out[2], out[3] = wa[0], wa[1], wa[2], -1.0
        return
    # Rotate a's axis toward b's by theta_o - theta_a about a x b (Rodrigues).
    k0, k1, k2 = r0 / rl, r1 / rl, r2 / rl
    t = theta_o - theta_a
    c, s = math.cos(t), math.sin(t)
    kv = k0 * wa[0] + k1 * wa[1] + k2 * wa[2]
    x0 = wa[0] * c + (k1 * wa[2] - k2 * wa[1]) * s + k0 * kv * (1.0 - c)
    x1 = wa[1] * c + (k2 * wa[0] - k0 * wa[2]) * s + k1 * kv * (1.0 - c)
    x2 = wa[2] * c + (k0 * wa[1] - k1 * wa[0]) * s + k2 * kv * (1.0 - c)
    xl = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    out[0], out[1], out[2], out[3] = x0 / xl, x1 / xl, x2 / xl, math.cos(theta_o)


@nb.njit(cache=True, error_model="numpy")
def _union_into(acc_box, acc_cone, acc_phi, box, cone, phi, tmp):
    """acc (one node's bounds, acc_phi[0] 0 when empty) |= one light's or
    node's bounds."""
    if not phi > 0.0:
        return
    if not acc_phi[0] > 0.0:
        acc_box[:, :] = box
        acc_cone[:] = cone
        acc_phi[0] = phi
        return
    for k in range(3):
        acc_box[0, k] = min(acc_box[0, k], box[0, k])
        acc_box[1, k] = max(acc_box[1, k], box[1, k])
    _cone_union(acc_cone[0:3], acc_cone[3], cone[0:3], cone[3], tmp)
    acc_cone[0], acc_cone[1], acc_cone[2], acc_cone[3] = tmp[0], tmp[1], tmp[2], tmp[3]
    acc_cone[4] = min(acc_cone[4], cone[4])
    acc_phi[0] += phi


@nb.njit(cache=True, error_model="numpy")
def _cost(box, cone, phi, kr):
    """pbrt's EvaluateCost: power x the cone's solid-angle measure x the
    box's surface area, x kr (the parent's longest side over this axis')."""
    cos_o, cos_e = cone[3], cone[4]
    theta_o, theta_e = math.acos(max(-1.0, min(1.0, cos_o))), math.acos(max(-1.0, min(1.0, cos_e)))
    theta_w = min(theta_o + theta_e, math.pi)
    sin_o = math.sqrt(max(0.0, 1.0 - cos_o * cos_o))
    m_omega = 2.0 * math.pi * (1.0 - cos_o) + math.pi / 2.0 * (
        2.0 * theta_w * sin_o - math.cos(theta_o - 2.0 * theta_w) - 2.0 * theta_o * sin_o + cos_o)
    d0, d1, d2 = box[1, 0] - box[0, 0], box[1, 1] - box[0, 1], box[1, 2] - box[0, 2]
    area = 2.0 * (d0 * d1 + d1 * d2 + d2 * d0)
    return phi * m_omega * kr * area


# -- build -----------------------------------------------------------------------------------
@nb.njit(cache=True, error_model="numpy")
def _build(lbox, lcone, lphi):
    L = lphi.shape[0]
    idx = np.flatnonzero(lphi > 0.0)
    n = idx.shape[0]
    N = max(0, 2 * n - 1)
    box, cone, phi = np.zeros((N, 2, 3)), np.zeros((N, 5)), np.zeros(N)
    child, parent, leaf_of = np.zeros(N, np.int32), np.full(N, -1, np.int32), np.full(L, -1, np.int32)
    if n == 0:
        return box, cone, phi, child, parent, leaf_of
    tmp, acc_phi = np.zeros(4), np.zeros(1)
    # (start, end, parent, is the second child)
    stack = np.zeros((2 * n + 2, 4), np.int64)
    stack[0, 1], stack[0, 2] = n, -1
    top, node = 1, 0
    while top > 0:
        top -= 1
        s, e, par, second = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        parent[node] = par
        if second:
            child[par] = node
        acc_phi[0] = 0.0
        for j in range(s, e):
            _union_into(box[node], cone[node], acc_phi, lbox[idx[j]], lcone[idx[j]], lphi[idx[j]], tmp)
        phi[node] = acc_phi[0]
        if e - s == 1:
            child[node] = -1 - idx[s]
            leaf_of[idx[s]] = node
        else:
            mid = _split(idx, s, e, lbox, lcone, lphi, box[node], tmp)
            stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3] = mid, e, node, 1
            # Pushed last, popped next: the first child is node + 1.
            stack[top + 1, 0], stack[top + 1, 1], stack[top + 1, 2], stack[top + 1, 3] = s, mid, node, 0
            top += 2
        node += 1
    return box, cone, phi, child, parent, leaf_of


@nb.njit(cache=True, error_model="numpy")
def _split(idx, s, e, lbox, lcone, lphi, node_box, tmp):
    """Partition idx[s:e] at the cheapest bucket boundary (pbrt's bucketed
    cost); returns the first index of the second half."""
    cmin, cmax = np.full(3, np.inf), np.full(3, -np.inf)
    for j in range(s, e):
        for k in range(3):
            c = 0.5 * (lbox[idx[j], 0, k] + lbox[idx[j], 1, k])
            cmin[k], cmax[k] = min(cmin[k], c), max(cmax[k], c)
    diag = node_box[1] - node_box[0]
    longest = max(diag[0], diag[1], diag[2])
    best, best_dim, best_b = np.inf, -1, -1
    bbox, bcone, bphi = np.zeros((BUCKETS, 2, 3)), np.zeros((BUCKETS, 5)), np.zeros((BUCKETS, 1))
    abox, acone, aphi = np.zeros((2, 3)), np.zeros(5), np.zeros(1)
    below = np.zeros(BUCKETS)       # cost of buckets [0, b] together
    for dim in range(3):
        if not cmax[dim] > cmin[dim] or not diag[dim] > 0.0:
            continue
        bphi[:] = 0.0
        for j in range(s, e):
            b = _bucket(lbox[idx[j]], dim, cmin[dim], cmax[dim])
            _union_into(bbox[b], bcone[b], bphi[b], lbox[idx[j]], lcone[idx[j]], lphi[idx[j]], tmp)
        kr = longest / diag[dim]
        # One sweep up and one down, so each cut costs two unions' worth.
        aphi[0] = 0.0
        for b in range(BUCKETS - 1):
            _union_into(abox, acone, aphi, bbox[b], bcone[b], bphi[b, 0], tmp)
            below[b] = _cost(abox, acone, aphi[0], kr) if aphi[0] > 0.0 else 0.0
        aphi[0] = 0.0
        for cut in range(BUCKETS - 2, -1, -1):
            _union_into(abox, acone, aphi, bbox[cut + 1], bcone[cut + 1], bphi[cut + 1, 0], tmp)
            cost = below[cut] + (_cost(abox, acone, aphi[0], kr) if aphi[0] > 0.0 else 0.0)
            if cost > 0.0 and cost < best:
                best, best_dim, best_b = cost, dim, cut
    mid = (s + e) // 2
    if best_dim >= 0:
        lo, hi = s, e - 1
        while lo <= hi:         # bucket <= best_b to the front
            if _bucket(lbox[idx[lo]], best_dim, cmin[best_dim], cmax[best_dim]) <= best_b:
                lo += 1
            else:
                idx[lo], idx[hi] = idx[hi], idx[lo]
                hi -= 1
        if s < lo < e:
            mid = lo
    return mid


@nb.njit(inline="always", cache=True, error_model="numpy")
def _bucket(lbox, dim, lo, hi):
    c = 0.5 * (lbox[0, dim] + lbox[1, dim])
    return min(BUCKETS - 1, int(BUCKETS * (c - lo) / (hi - lo)))


# -- importance, sampling, probability ----------------------------------------------------
@nb.njit(inline="always", cache=True, error_model="numpy")
def _cos_sub(sin_a, cos_a, sin_b, cos_b):
    """cos(max(0, a - b)) for angles in [0, pi]."""
    if cos_a > cos_b:
        return 1.0
    return cos_a * cos_b + sin_a * sin_b


@nb.njit(inline="always", cache=True, error_model="numpy")
def _sin_sub(sin_a, cos_a, sin_b, cos_b):
    """sin(max(0, a - b)) for angles in [0, pi]."""
    if cos_a > cos_b:
        return 0.0
    return sin_a * cos_b - cos_a * sin_b


@nb.njit(cache=True, error_model="numpy")
def importance(tree, k, p0, p1, p2, n0, n1, n2):
    """Node k's importance at point p with normal n (n = 0: no surface
    cosine, as for a point in a medium or a ray origin)."""
    box, cone = tree[0][k], tree[1][k]
    c0, c1, c2 = 0.5 * (box[0, 0] + box[1, 0]), 0.5 * (box[0, 1] + box[1, 1]), 0.5 * (box[0, 2] + box[1, 2])
    h0, h1, h2 = 0.5 * (box[1, 0] - box[0, 0]), 0.5 * (box[1, 1] - box[0, 1]), 0.5 * (box[1, 2] - box[0, 2])
    r2 = h0 * h0 + h1 * h1 + h2 * h2              # the box's bounding sphere, squared radius
    d0, d1, d2 = p0 - c0, p1 - c1, p2 - c2
    dist2 = d0 * d0 + d1 * d1 + d2 * d2
    phi = tree[2][k]
    inside = box[0, 0] <= p0 <= box[1, 0] and box[0, 1] <= p1 <= box[1, 1] and box[0, 2] <= p2 <= box[1, 2]
    if inside or not dist2 > r2:
        return phi / max(dist2, r2)     # every direction possible: bound the distance alone
    cos_b = math.sqrt(1.0 - r2 / dist2)
    sin_b = math.sqrt(r2 / dist2)
    dl = math.sqrt(dist2)
    w0, w1, w2 = d0 / dl, d1 / dl, d2 / dl        # from the box toward p
    cos_w = cone[0] * w0 + cone[1] * w1 + cone[2] * w2
    sin_w = math.sqrt(max(0.0, 1.0 - cos_w * cos_w))
    sin_o = math.sqrt(max(0.0, 1.0 - cone[3] * cone[3]))
    cos_x = _cos_sub(sin_w, cos_w, sin_o, cone[3])
    sin_x = _sin_sub(sin_w, cos_w, sin_o, cone[3])
    cos_p = _cos_sub(sin_x, cos_x, sin_b, cos_b)
    if not cos_p > cone[4]:
        return 0.0
    imp = phi * cos_p / dist2
    if n0 != 0.0 or n1 != 0.0 or n2 != 0.0:
        cos_i = -(n0 * w0 + n1 * w1 + n2 * w2)    # toward the light, one-sided
        sin_i = math.sqrt(max(0.0, 1.0 - cos_i * cos_i))
        cos_pi = _cos_sub(sin_i, cos_i, sin_b, cos_b)
        if not cos_pi > 0.0:
            return 0.0
        imp *= cos_pi
    return imp


@nb.njit(cache=True, error_model="numpy")
def sample_tree(tree, p0, p1, p2, n0, n1, n2, u):
    """(light, its probability) chosen by importance at p, n; (-1, 0) if
    no light can light p."""
    child = tree[3]
    if child.shape[0] == 0 or not importance(tree, 0, p0, p1, p2, n0, n1, n2) > 0.0:
        return -1, 0.0
    node, pmf = 0, 1.0
    while child[node] >= 0:
        a, b = node + 1, child[node]
        ia = importance(tree, a, p0, p1, p2, n0, n1, n2)
        ib = importance(tree, b, p0, p1, p2, n0, n1, n2)
        if not ia + ib > 0.0:
            return -1, 0.0
        q = ia / (ia + ib)
        if u < q:
            node, pmf, u = a, pmf * q, min(u / q, _ONE_MINUS)
        else:
            node, pmf, u = b, pmf * (1.0 - q), min((u - q) / (1.0 - q), _ONE_MINUS)
    return -1 - child[node], pmf


@nb.njit(cache=True, error_model="numpy")
def tree_pmf(tree, light, p0, p1, p2, n0, n1, n2):
    """The probability that `sample_tree` at p, n returns `light`."""
    child, parent = tree[3], tree[4]
    node = tree[5][light]
    if node < 0 or not importance(tree, 0, p0, p1, p2, n0, n1, n2) > 0.0:
        return 0.0
    pmf = 1.0
    while node > 0:
        par = parent[node]
        sib = child[par] if node == par + 1 else par + 1
        a = importance(tree, node, p0, p1, p2, n0, n1, n2)
        if not a > 0.0:
            return 0.0
        pmf *= a / (a + importance(tree, sib, p0, p1, p2, n0, n1, n2))
        node = par
    return pmf
