"""Vectorised ray casting of a spinning LiDAR against the synthetic scene.

The rays of one sweep form a regular grid: beam elevations x firing azimuths in
the sensor frame. Two kernels (numba, compiled once and cached on disk) find the
nearest hit of every ray:

1. the ground: a height-field march along each ray, only over the stretch where
   the ray is within the residual-height band above the scene plane (found in
   closed form, so rays far above the ground cost nothing), skipping a tile at a
   time wherever the ray is above the tile's maximum height;
2. the primitives, object-order: each primitive's oriented bounding box is
   projected into the sensor frame to an azimuth interval (a slice of columns)
   and an elevation interval (a run of beams), and only those rays are tested
   (a z-buffer keeps the nearest hit). Most primitives cover a few hundred rays,
   so the cost is the sum of their angular footprints, not rays x primitives.

Ray array layout is column-major, ``index = column * num_beams + beam``, which is
the sensor's firing order (for each azimuth step, all beams).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from omnilidar.data.synthetic.primitives import BOX, CYLINDER, Primitives

NO_HIT = -2  # hit id of rays that return nothing
GROUND_HIT = -1  # hit id of ground returns; >= 0: primitive index

_T_MIN = 1e-3  # ignore intersections closer than this (the ray origin itself)


@dataclass(frozen=True)
class RayHits:
    """Nearest hit per ray, in ray order (column-major)."""

    t: np.ndarray  # (N,) float64 range along the unit ray; inf where no hit
    hit: np.ndarray  # (N,) int32: NO_HIT, GROUND_HIT or primitive index
    cell: np.ndarray  # (N,) int64 flat ground cell of ground hits (-1 outside / not ground)
    normal: np.ndarray  # (N, 3) float64 unit surface normal (world frame)


@numba.njit(cache=True, nogil=True)
def _ground_kernel(origin, dirs, t_max, a, b, c, residual, tile_max, tile, x0, y0, res, rmin, rmax, t_out, cell_out,
                   n_out):
    ny, nx = residual.shape
    ty, tx = tile_max.shape
    ox, oy, oz = origin[0], origin[1], origin[2]
    f0 = oz - (a * ox + b * oy + c)  # height of the origin above the plane
    for k in range(dirs.shape[0]):
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        f1 = dz - a * dx - b * dy  # rate of change of (ray z - plane z) along t
        # Stretch of t where the ray lies inside the band [rmin, rmax] above the plane.
        if f1 < -1e-12:
            t0 = (f0 - rmax) / (-f1)
            t1 = (f0 - rmin) / (-f1)
        elif f0 >= rmin and f0 <= rmax:
            t0 = 0.0
            t1 = t_max
        else:
            continue
        if t0 < 0.0:
            t0 = 0.0
        if t1 > t_max:
            t1 = t_max
        if t0 >= t1:
            continue
        h = np.sqrt(dx * dx + dy * dy)
        dt = 0.5 * res / h if h > 1e-9 else t1 - t0
        if dt > t1 - t0:
            dt = t1 - t0
        t = t0
        x = ox + t * dx
        y = oy + t * dy
        j = int(np.floor((x - x0) / res))
        i = int(np.floor((y - y0) / res))
        hcur = residual[i, j] if (0 <= i < ny and 0 <= j < nx) else 0.0
        g = f0 + t * f1 - hcur
        if g <= 0.0:  # starts below the surface (only at the band entry): hit right there
            t_out[k] = t
            cell_out[k] = i * nx + j if (0 <= i < ny and 0 <= j < nx) else -1
            n_out[k, 0] = -a
            n_out[k, 1] = -b
            n_out[k, 2] = 1.0
            continue
        dt_big = tile * res / h if h > 1e-9 else t1 - t0
        while t < t1:
            # Coarse skip: over the next tile-width of travel the ray stays inside the
            # 3x3 tiles around the current one, whose (dilated) max height is tile_max.
            ti, tj = i // tile, j // tile
            m = tile_max[ti, tj] if (0 <= ti < ty and 0 <= tj < tx) else rmax
            t_end = min(t + dt_big, t1)
            if f0 + t * f1 - m > 0.0 and f0 + t_end * f1 - m > 0.0 and t_end < t1:
                t = t_end
                x = ox + t * dx
                y = oy + t * dy
                j = int(np.floor((x - x0) / res))
                i = int(np.floor((y - y0) / res))
                hcur = residual[i, j] if (0 <= i < ny and 0 <= j < nx) else 0.0
                g = f0 + t * f1 - hcur
                continue
            tp, gp, ip, jp = t, g, i, j
            t = t + dt
            if t > t1:
                t = t1
            x = ox + t * dx
            y = oy + t * dy
            j = int(np.floor((x - x0) / res))
            i = int(np.floor((y - y0) / res))
            inside = 0 <= i < ny and 0 <= j < nx
            hcur = residual[i, j] if inside else 0.0
            g = f0 + t * f1 - hcur
            if g > 0.0:
                continue
            # Crossed the surface between tp and t.
            gstep = f0 + tp * f1 - hcur  # previous sample against the NEW cell height
            if gstep <= 0.0 and (i != ip or j != jp):
                # The ray was already below this cell's height: it hit the vertical
                # face (kerb) at the cell boundary.
                tb = tp
                nx_, ny_ = 0.0, 0.0
                if j != jp and abs(dx) > 1e-12:
                    xb = x0 + res * max(j, jp)
                    tcand = (xb - ox) / dx
                    if tcand > tb:
                        tb = tcand
                        nx_, ny_ = -np.sign(dx), 0.0
                if i != ip and abs(dy) > 1e-12:
                    yb = y0 + res * max(i, ip)
                    tcand = (yb - oy) / dy
                    if tcand > tb:
                        tb = tcand
                        nx_, ny_ = 0.0, -np.sign(dy)
                if nx_ == 0.0 and ny_ == 0.0:
                    nx_, ny_ = -dx / h, -dy / h
                t_hit = min(max(tb, tp), t)
                n_out[k, 0] = nx_
                n_out[k, 1] = ny_
                n_out[k, 2] = 0.0
            else:
                t_hit = tp + (t - tp) * gp / (gp - g) if gp > g else t
                # Normal from the plane and the residual's central differences.
                gx, gy = 0.0, 0.0
                if inside and 0 < j < nx - 1:
                    gx = (residual[i, j + 1] - residual[i, j - 1]) / (2.0 * res)
                if inside and 0 < i < ny - 1:
                    gy = (residual[i + 1, j] - residual[i - 1, j]) / (2.0 * res)
                n_out[k, 0] = -(a + gx)
                n_out[k, 1] = -(b + gy)
                n_out[k, 2] = 1.0
            t_out[k] = t_hit
            cell_out[k] = i * nx + j if inside else -1
            break


@numba.njit(cache=True, nogil=True)
def _primitive_kernel(origin, dirs, num_beams, num_cols, kind, center, half, yaw, col0, ncol, beam0, beam1,
                      t_best, hit, n_out):
    for p in range(kind.shape[0]):
        if ncol[p] <= 0 or beam1[p] < beam0[p]:
            continue
        cy, sy = np.cos(yaw[p]), np.sin(yaw[p])
        hx, hy, hz = half[p, 0], half[p, 1], half[p, 2]
        # Ray origin in the primitive's frame (shared by all its rays).
        px, py = origin[0] - center[p, 0], origin[1] - center[p, 1]
        olx = cy * px + sy * py
        oly = -sy * px + cy * py
        olz = origin[2] - center[p, 2]
        kp = kind[p]
        for m in range(ncol[p]):
            col = (col0[p] + m) % num_cols
            for beam in range(beam0[p], beam1[p] + 1):
                r = col * num_beams + beam
                wx, wy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
                dx = cy * wx + sy * wy
                dy = -sy * wx + cy * wy
                t_near = -1.0
                nlx, nly, nlz = 0.0, 0.0, 0.0
                if kp == BOX:
                    tn, tf = -1e30, 1e30
                    axis = -1
                    miss = False
                    for ax in range(3):
                        if ax == 0:
                            o, d, hh = olx, dx, hx
                        elif ax == 1:
                            o, d, hh = oly, dy, hy
                        else:
                            o, d, hh = olz, dz, hz
                        if abs(d) < 1e-12:
                            if o < -hh or o > hh:
                                miss = True
                                break
                            continue
                        ta = (-hh - o) / d
                        tb = (hh - o) / d
                        if ta > tb:
                            ta, tb = tb, ta
                        if ta > tn:
                            tn = ta
                            axis = ax
                        if tb < tf:
                            tf = tb
                    if miss or tn > tf or axis < 0:
                        continue
                    t_near = tn
                    if axis == 0:
                        nlx = -np.sign(dx)
                    elif axis == 1:
                        nly = -np.sign(dy)
                    else:
                        nlz = -np.sign(dz)
                elif kp == CYLINDER:
                    qa = dx * dx + dy * dy
                    qb = olx * dx + oly * dy
                    qc = olx * olx + oly * oly - hx * hx
                    if qa < 1e-12:
                        if qc > 0.0:
                            continue
                        tn, tf = -1e30, 1e30
                    else:
                        disc = qb * qb - qa * qc
                        if disc < 0.0:
                            continue
                        sq = np.sqrt(disc)
                        tn = (-qb - sq) / qa
                        tf = (-qb + sq) / qa
                    cap = False
                    if abs(dz) > 1e-12:
                        ta = (-hz - olz) / dz
                        tb = (hz - olz) / dz
                        if ta > tb:
                            ta, tb = tb, ta
                        if ta > tn:
                            tn = ta
                            cap = True
                        if tb < tf:
                            tf = tb
                    elif olz < -hz or olz > hz:
                        continue
                    if tn > tf:
                        continue
                    t_near = tn
                    if cap:
                        nlz = -np.sign(dz)
                    else:
                        nlx = (olx + tn * dx) / hx
                        nly = (oly + tn * dy) / hx
                else:  # ellipsoid: unit sphere after scaling by the semi-axes
                    ex, ey, ez = olx / hx, oly / hy, olz / hz
                    fx, fy, fz = dx / hx, dy / hy, dz / hz
                    qa = fx * fx + fy * fy + fz * fz
                    qb = ex * fx + ey * fy + ez * fz
                    qc = ex * ex + ey * ey + ez * ez - 1.0
                    disc = qb * qb - qa * qc
                    if disc < 0.0:
                        continue
                    t_near = (-qb - np.sqrt(disc)) / qa
                    nlx = (ex + t_near * fx) / hx
                    nly = (ey + t_near * fy) / hy
                    nlz = (ez + t_near * fz) / hz
                if t_near <= _T_MIN or t_near >= t_best[r]:
                    continue
                t_best[r] = t_near
                hit[r] = p
                nn = np.sqrt(nlx * nlx + nly * nly + nlz * nlz)
                if nn > 0.0:
                    nlx, nly, nlz = nlx / nn, nly / nn, nlz / nn
                n_out[r, 0] = cy * nlx - sy * nly
                n_out[r, 1] = sy * nlx + cy * nly
                n_out[r, 2] = nlz


def cull(prims: Primitives, origin: np.ndarray, rotation: np.ndarray, elevations: np.ndarray,
         num_cols: int, max_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rays each primitive can hit: a column slice (start, count) and a beam run.

    Conservative bounds from the 8 corners of each primitive's bounding box in
    the sensor frame (``rotation`` maps sensor to world). ``elevations`` are the
    beam elevations (rad), descending. Columns follow the firing azimuths
    ``pi - (c + 0.5) * 2 pi / num_cols``.
    """
    P = len(prims)
    if P == 0:
        z = np.zeros(0, np.int64)
        return z, z, z, z
    corners = (prims.aabb_corners() - origin) @ rotation  # (P, 8, 3) sensor frame
    centre = corners.mean(axis=1)
    rho_c = np.hypot(centre[:, 0], centre[:, 1])
    r_xy = np.max(np.hypot(corners[..., 0] - centre[:, None, 0], corners[..., 1] - centre[:, None, 1]), axis=1)
    r_3d = np.max(np.linalg.norm(corners - centre[:, None], axis=2), axis=1)
    dist = np.linalg.norm(centre, axis=1)
    # Azimuth interval: corners' azimuths relative to the centre's (valid when the
    # sensor is outside the disc around the footprint, so the span is < pi).
    az_c = np.arctan2(centre[:, 1], centre[:, 0])
    rel = np.angle(np.exp(1j * (np.arctan2(corners[..., 1], corners[..., 0]) - az_c[:, None])))
    full = rho_c <= r_xy * 1.001
    az_lo = np.where(full, -np.pi, az_c + rel.min(axis=1))
    az_hi = np.where(full, np.pi, az_c + rel.max(axis=1))
    step = 2.0 * np.pi / num_cols
    # Columns with az in [az_lo, az_hi]: az_c = pi - (c + 0.5) step  =>  c = (pi - az)/step - 0.5
    c_first = np.floor((np.pi - az_hi) / step - 0.5).astype(np.int64) - 1
    c_last = np.ceil((np.pi - az_lo) / step - 0.5).astype(np.int64) + 1
    ncol = np.where(full, num_cols, np.minimum(c_last - c_first + 1, num_cols))
    col0 = np.where(full, 0, np.mod(c_first, num_cols))
    # Elevation interval from z and horizontal-distance bounds.
    zmin, zmax = corners[..., 2].min(axis=1), corners[..., 2].max(axis=1)
    rho_min = np.maximum(rho_c - r_xy, 0.0)
    rho_max = rho_c + r_xy
    tiny = 1e-9
    el_hi = np.arctan2(zmax, np.where(zmax > 0, np.maximum(rho_min, tiny), rho_max))
    el_lo = np.arctan2(zmin, np.where(zmin < 0, np.maximum(rho_min, tiny), rho_max))
    margin = 1e-3
    neg = -elevations  # ascending
    beam0 = np.searchsorted(neg, -(el_hi + margin), side="left")
    beam1 = np.searchsorted(neg, -(el_lo - margin), side="right") - 1
    out_of_range = dist - r_3d > max_range
    ncol = np.where(out_of_range, 0, ncol)
    return col0.astype(np.int64), ncol.astype(np.int64), beam0.astype(np.int64), beam1.astype(np.int64)


def cast(ground, prims: Primitives, origin: np.ndarray, rotation: np.ndarray, elevations: np.ndarray,
         azimuths: np.ndarray, max_range: float) -> RayHits:
    """Nearest hit of every ray of one sweep.

    origin: (3,) sensor position (world). rotation: (3, 3) sensor-to-world.
    elevations: (B,) beam elevations (rad, descending); azimuths: (C,) firing
    azimuths (rad) as ``SensorSpec.azimuths_rad``. Rays beyond ``max_range`` miss.
    """
    origin = np.ascontiguousarray(origin, dtype=np.float64)
    B, Cn = len(elevations), len(azimuths)
    ce, se = np.cos(elevations), np.sin(elevations)
    ca, sa = np.cos(azimuths), np.sin(azimuths)
    d_sensor = np.stack([ca[:, None] * ce[None, :], sa[:, None] * ce[None, :],
                         np.broadcast_to(se[None, :], (Cn, B))], axis=-1).reshape(-1, 3)
    dirs = np.ascontiguousarray(d_sensor @ rotation.T)
    n = B * Cn
    t = np.full(n, np.inf)
    cell = np.full(n, -1, np.int64)
    normal = np.zeros((n, 3))
    a, b, c = ground.plane
    rmin, rmax = ground.residual_range
    _ground_kernel(origin, dirs, float(max_range), a, b, c, ground.residual, ground.tile_max, ground.TILE, ground.x0,
                   ground.y0, ground.res, rmin - 1e-4, rmax + 1e-4, t, cell, normal)
    hit = np.where(np.isfinite(t), GROUND_HIT, NO_HIT).astype(np.int32)
    t_best = np.where(np.isfinite(t), t, float(max_range))
    col0, ncol, beam0, beam1 = cull(prims, origin, rotation, elevations, Cn, max_range)
    _primitive_kernel(origin, dirs, B, Cn, prims.kind, prims.center, prims.half, prims.yaw,
                      col0, ncol, beam0, beam1, t_best, hit, normal)
    t_best[hit == NO_HIT] = np.inf
    cell[hit != GROUND_HIT] = -1
    nrm = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, nrm, out=np.zeros_like(normal), where=nrm > 0)
    return RayHits(t=t_best, hit=hit, cell=cell, normal=normal)
