"""Ray casting and closest points on triangles in plain torch (CPU or CUDA).

Stands in for Open3D's ``RaycastingScene`` where Open3D cannot be installed (the GPU
machine: its wheel is too large to travel) and runs the camera on a GPU where there is one.

The caster tests every ray against every triangle it could possibly hit, in float32 and in
chunks of bounded size:

* The hit test is Möller–Trumbore's: the ray meets the triangle where its three barycentric
  numerators share a sign, at distance ``(a . n) / (d . n)``. All rays of a camera leave one
  point, so with the corners a, b, c taken relative to it each numerator is the dot product
  of the ray direction with a per-triangle vector, one per edge. Unlike the textbook form (u
  and v from the triangle's first corner, the third as 1 - u - v), each numerator comes from
  its own edge's two corners in a fixed order, so two triangles sharing an edge decide it
  with the same number and no ray slips through the seam between them (the textbook form in
  float32 let one through on a kettle, which then saw the wall 3.8 cm behind).
* Rays go in groups (a 16 x 16 pixel tile when the camera orders them so), and a group is
  only tested against the triangles whose projection onto the image plane overlaps the
  group's. The test is conservative, so the answer is the every-pair answer, computed in a
  few per cent of the time; ``cull=False`` tests every pair and is kept to show exactly that.
* The nearest hit per ray is one ``scatter_reduce`` (amin) of an int64 key: the bits of the
  positive float32 distance above the triangle index, so equal distances resolve to the lower
  triangle index, the same way on every device.
"""

from __future__ import annotations

import torch

GROUP = 256  # rays per culling group: a 16 x 16 tile
_MISS = torch.iinfo(torch.int64).max


def resolve_device(device: str = "auto") -> torch.device:
    """``auto``: CUDA when torch sees a GPU, else the CPU; otherwise the named device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def default_chunk(device: torch.device) -> int:
    """Ray-triangle pairs tested at once: cache-sized on the CPU, larger on a GPU (each pair
    costs ~40 bytes of temporaries, so 2**20 is ~40 MB and 2**24 ~0.7 GB)."""
    return 1 << 24 if device.type == "cuda" else 1 << 18


def _edge(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """(T, 3) ``p x (q - p)`` for the edge from corner p to q, always computed from the
    corner that sorts first (x, then y, then z) and negated when that is q: the two triangles
    sharing an edge get exactly opposite numbers, so they agree on which side a ray passes."""
    swap = (q[:, 0] < p[:, 0]) | ((q[:, 0] == p[:, 0]) & (
        (q[:, 1] < p[:, 1]) | ((q[:, 1] == p[:, 1]) & (q[:, 2] < p[:, 2]))))
    first = torch.where(swap[:, None], q, p)
    e = torch.linalg.cross(first, torch.where(swap[:, None], p, q) - first)
    return torch.where(swap[:, None], -e, e)


def _triangle_terms(tris: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(T, 3, 3) corners a, b, c relative to the ray origin -> the per-ray coefficients of the
    barycentric numerators (T, 3, 3), one column per edge (b c, c a, a b), the normals
    ``(b - a) x (c - a)`` (T, 3) and the distance numerators ``a . normal`` (T,). Each
    coefficient is a corner times an edge: as small as Möller–Trumbore's, so as accurate."""
    a, b, c = tris.unbind(1)
    coef = torch.stack([_edge(b, c), _edge(c, a), _edge(a, b)], dim=2)
    normal = torch.linalg.cross(b - a, c - a)
    return coef, normal, (a * normal).sum(-1)


def _candidate_pairs(dirs: torch.Tensor, tris: torch.Tensor) -> torch.Tensor:
    """(G, P, 3) grouped unit directions, (T, 3, 3) triangles -> (M, 2) (group, triangle)
    pairs a ray of the group may hit.

    Everything is projected from the origin onto the plane one unit along the mean ray (the
    camera's image plane): a ray of the group can only hit a triangle in front of the origin
    if the boxes around their projections overlap (the projection of a triangle is the
    triangle of its projected corners). A triangle reaching behind that plane's horizon, or a
    group leaning away from the axis, is kept for every group. In float64 with a margin far
    above float32's error, so no hit the test below would register is culled.
    """
    d, t = dirs.double(), tris.double()
    axis = torch.nn.functional.normalize(d.sum((0, 1)), dim=0)
    helper = torch.tensor([1.0, 0.0, 0.0] if abs(float(axis[0])) < 0.9 else [0.0, 1.0, 0.0],
                          dtype=d.dtype, device=d.device)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(axis, helper), dim=0)
    basis = torch.stack([axis, e1, torch.linalg.cross(axis, e1)], 1)  # (3, 3)

    def slopes(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        local = v @ basis  # (..., 3): along the axis, then the two image-plane directions
        ahead = local[..., 0] > 1e-3 * v.norm(dim=-1)
        return local[..., 1:] / local[..., :1].clamp_min(1e-12), ahead

    ray_s, ray_ahead = slopes(d)  # (G, P, 2)
    tri_s, tri_ahead = slopes(t)  # (T, 3, 2)
    margin = 1e-5
    lo_g, hi_g = ray_s.amin(1) - margin, ray_s.amax(1) + margin  # (G, 2)
    lo_t, hi_t = tri_s.amin(1), tri_s.amax(1)  # (T, 2)
    near = ((lo_g[:, None, 0] <= hi_t[None, :, 0]) & (lo_t[None, :, 0] <= hi_g[:, None, 0])
            & (lo_g[:, None, 1] <= hi_t[None, :, 1]) & (lo_t[None, :, 1] <= hi_g[:, None, 1]))
    near |= ~tri_ahead.all(1)[None] | ~ray_ahead.all(1)[:, None]
    return torch.nonzero(near)


def cast_rays(origin: torch.Tensor, dirs: torch.Tensor, triangles: torch.Tensor,
              group: int = GROUP, chunk: int | None = None,
              cull: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest hit of each ray from ``origin`` (3,) along unit ``dirs`` (N, 3) on
    ``triangles`` (T, 3, 3), both faces: (distance (N,), triangle index (N,), -1 and inf
    for a miss). float32 on the tensors' device; at most ``chunk`` ray-triangle pairs at a
    time. Consecutive ``group`` rays are culled together, so pass neighbouring rays together
    (:func:`sim_bridge.camera.tile_order`); ``cull=False`` tests every pair.
    """
    device = dirs.device
    n = len(dirs)
    t_out = torch.full((n,), float("inf"), device=device)
    i_out = torch.full((n,), -1, dtype=torch.long, device=device)
    if n == 0 or len(triangles) == 0:
        return t_out, i_out
    chunk = chunk or default_chunk(device)
    tris = (triangles.to(device, torch.float64) - origin.to(device, torch.float64)).float()
    coef, normal, tnum = _triangle_terms(tris)
    g = -(-n // group)
    padded = torch.cat([dirs.float(), dirs[-1:].float().expand(g * group - n, 3)])
    grouped = padded.view(g, group, 3)
    if cull:
        pairs = _candidate_pairs(grouped, tris)
    else:
        gi, ti = torch.meshgrid(torch.arange(g, device=device),
                                torch.arange(len(tris), device=device), indexing="ij")
        pairs = torch.stack([gi.reshape(-1), ti.reshape(-1)], 1)
    best = torch.full((g * group,), _MISS, dtype=torch.long, device=device)
    step = max(1, chunk // group)
    lanes = torch.arange(group, device=device)
    comp = grouped.permute(2, 0, 1).contiguous()  # (3, G, P): x, y, z of every ray
    for s in range(0, len(pairs), step):
        gk, tk = pairs[s:s + step].unbind(1)
        dx, dy, dz = comp[0][gk], comp[1][gk], comp[2][gk]  # (M, P) each
        k = coef[tk]  # (M, 3, 3)
        wa, wb, wc = (torch.addcmul(torch.addcmul(dx * k[:, 0, j, None], dy, k[:, 1, j, None]),
                                    dz, k[:, 2, j, None]) for j in range(3))  # (M, P) each
        lo = torch.minimum(torch.minimum(wa, wb), wc)
        hi = torch.maximum(torch.maximum(wa, wb), wc)
        m, p = torch.nonzero((lo >= 0) | (hi <= 0), as_tuple=True)  # all three on one side
        if len(m) == 0:
            continue
        det = (grouped[gk[m], p] * normal[tk[m]]).sum(-1)  # d . normal, on the hits only
        t = tnum[tk[m]] / det
        front = (t > 0) & torch.isfinite(t)  # drops 0 / 0 and x / 0: rays along the plane
        m, p, t = m[front], p[front], t[front]
        bits = t.view(torch.int32).long()  # positive floats order as their bits
        key = (bits << 32) | tk[m]
        best.scatter_reduce_(0, gk[m] * group + lanes[p], key, "amin")
    best = best[:n]
    found = best != _MISS
    i_out[found] = best[found] & 0xFFFFFFFF
    t_out[found] = (best[found] >> 32).int().view(torch.float32)
    return t_out, i_out


def triangle_normals(triangles: torch.Tensor) -> torch.Tensor:
    """(T, 3, 3) -> (T, 3) unit normals ``(v1 - v0) x (v2 - v0)`` (zero for degenerate)."""
    n = torch.linalg.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    return torch.nn.functional.normalize(n, dim=-1)


def closest_points(query: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """(Q, T, 3): the nearest point of each of ``triangles`` (T, 3, 3) to each ``query``
    (Q, 3), by the Voronoi region of the triangle the query projects into (a corner, an edge
    or the face). Every pair is computed, so keep Q x T modest; NaN for degenerate triangles."""
    a, b, c = (triangles[None, :, k] for k in range(3))  # (1, T, 3)
    p = query[:, None]  # (Q, 1, 3)
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    out = a + ab * (vb / denom)[..., None] + ac * (vc / denom)[..., None]  # inside the face
    # the other regions in reverse order of precedence, each overriding what came before
    bc_w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    out = torch.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None],
                      b + (c - b) * bc_w[..., None], out)
    out = torch.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None],
                      a + ac * (d2 / (d2 - d6))[..., None], out)
    out = torch.where(((d6 >= 0) & (d5 <= d6))[..., None], c.expand_as(out), out)
    out = torch.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None],
                      a + ab * (d1 / (d1 - d3))[..., None], out)
    out = torch.where(((d3 >= 0) & (d4 <= d3))[..., None], b.expand_as(out), out)
    return torch.where(((d1 <= 0) & (d2 <= 0))[..., None], a.expand_as(out), out)
