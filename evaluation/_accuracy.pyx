# cython: language_level=3
"""Beam-model classification of reconstruction points against laser scans (ETH3D accuracy).

A scan point is a laser beam from the scanner (the scan frame's origin) to the point. The beam
is a cone: radius ``beam_start + distance * tan(divergence)``. A reconstruction point inside
some beam is *accurate* for a tolerance if it lies within the tolerance of that beam's scan
point; it is *inaccurate* if it lies inside a beam in front of the beam's scan point (the laser
saw through that space, so nothing can be there); otherwise it is *unobserved*, and ignored.

Scan points are bucketed by azimuth and inclination (the scan frame's z axis is the pole) so a
reconstruction point only visits the buckets its beam search cone can touch. Arithmetic is in
float32, as in the official program, so that borderline points classify the same way.
"""

import numpy as np
cimport numpy as cnp
from cython.parallel cimport prange
from libc.math cimport sqrtf, atan2f, acosf, asinf, floorf, M_PI

cnp.import_array()

from dvpmvs._digest cimport DVPMVS_SOURCE_DIGEST

# Checked against this file on import (dvpmvs._kernel_sources.require_current).
SOURCE_DIGEST = (<bytes>DVPMVS_SOURCE_DIGEST).decode("ascii")


cdef inline int _mod(int k, int n) noexcept nogil:
    k = k % n
    return k + n if k < 0 else k


cdef inline int _cell(float angle, float extent) noexcept nogil:
    return <int>floorf(angle / extent)


def classify(
    const float[:, ::1] points,        # (N, 3) reconstruction points, global frame
    const float[:, :, ::1] scan_from_global,  # (S, 3, 4)
    const float[:, ::1] scan_points,   # (M, 3) all scans' points, scan frames, bucket order
    const float[:, ::1] scan_dirs,     # (M, 3) unit directions of scan_points
    const float[::1] scan_radii,       # (M,) distances of scan_points from their scanner
    const long long[:, ::1] cell_start,  # (S, cells + 1) first index of each bucket, into scan_points
    int cells_azimuth,
    int cells_inclination,
    const float[::1] tolerances_squared,  # increasing
    float beam_start_radius,
    float tan_beam_divergence,
):
    """Return ``(first_accurate, inaccurate)`` per reconstruction point.

    ``first_accurate[i]`` is the index of the smallest tolerance for which point ``i`` is
    accurate (the number of tolerances if none); ``inaccurate[i]`` is 1 if some beam passes
    through the point in front of its scan point, which makes every tolerance below
    ``first_accurate[i]`` inaccurate instead of unobserved.
    """
    cdef Py_ssize_t n = points.shape[0]
    cdef int num_scans = scan_from_global.shape[0]
    cdef int num_tol = tolerances_squared.shape[0]
    first_np = np.full(n, num_tol, dtype=np.int32)
    inaccurate_np = np.zeros(n, dtype=np.uint8)
    cdef int[::1] first = first_np
    cdef unsigned char[::1] inaccurate = inaccurate_np
    cdef float extent_az = <float>(2.0 * M_PI / cells_azimuth)
    cdef float extent_inc = <float>(M_PI / cells_inclination)
    cdef Py_ssize_t i
    cdef int s, ti, best, flag, ca, ci, a_lo, a_hi, i_lo, i_hi, cell
    cdef long long k, k_end
    cdef float qx, qy, qz, r, rh, beam, beam2, rel_v, rel_h, az, inc
    cdef float dx, dy, dz, along, ex, ey, ez, d2
    with nogil:
        for i in prange(n, schedule="dynamic", chunksize=256):
            best = num_tol
            flag = 0
            for s in range(num_scans):
                qx = (scan_from_global[s, 0, 0] * points[i, 0] + scan_from_global[s, 0, 1] * points[i, 1]
                      + scan_from_global[s, 0, 2] * points[i, 2] + scan_from_global[s, 0, 3])
                qy = (scan_from_global[s, 1, 0] * points[i, 0] + scan_from_global[s, 1, 1] * points[i, 1]
                      + scan_from_global[s, 1, 2] * points[i, 2] + scan_from_global[s, 1, 3])
                qz = (scan_from_global[s, 2, 0] * points[i, 0] + scan_from_global[s, 2, 1] * points[i, 1]
                      + scan_from_global[s, 2, 2] * points[i, 2] + scan_from_global[s, 2, 3])
                r = sqrtf(qx * qx + qy * qy + qz * qz)
                rh = sqrtf(qx * qx + qy * qy)
                beam = beam_start_radius + r * tan_beam_divergence
                beam2 = beam * beam
                # Angular half-widths of the region whose beams can reach the point.
                if beam >= r:
                    rel_v = <float>M_PI
                    rel_h = <float>M_PI
                else:
                    rel_v = asinf(beam / r)
                    rel_h = <float>M_PI if beam >= rh else asinf(beam / rh)
                az = atan2f(qy, qx)
                inc = acosf(qz / r) if r > 0 else 0
                a_lo = _cell(az - rel_h, extent_az)
                a_hi = _cell(az + rel_h, extent_az)
                i_lo = max(0, min(cells_inclination - 1, _cell(inc - rel_v, extent_inc)))
                i_hi = max(0, min(cells_inclination - 1, _cell(inc + rel_v, extent_inc)))
                if a_hi - a_lo >= cells_azimuth:  # the whole circle: visit each bucket once
                    a_lo = 0
                    a_hi = cells_azimuth - 1
                for ci in range(i_lo, i_hi + 1):
                    for ca in range(a_lo, a_hi + 1):
                        cell = _mod(ca, cells_azimuth) + cells_azimuth * ci
                        k_end = cell_start[s, cell + 1]
                        k = cell_start[s, cell]
                        while k < k_end:
                            along = scan_dirs[k, 0] * qx + scan_dirs[k, 1] * qy + scan_dirs[k, 2] * qz
                            if along >= 0:
                                ex = qx - along * scan_dirs[k, 0]
                                ey = qy - along * scan_dirs[k, 1]
                                ez = qz - along * scan_dirs[k, 2]
                                if ex * ex + ey * ey + ez * ez <= beam2:
                                    dx = scan_points[k, 0] - qx
                                    dy = scan_points[k, 1] - qy
                                    dz = scan_points[k, 2] - qz
                                    d2 = dx * dx + dy * dy + dz * dz
                                    for ti in range(best):
                                        if d2 <= tolerances_squared[ti]:
                                            best = ti
                                            break
                                    if along < scan_radii[k]:
                                        flag = 1
                                    if best == 0:
                                        break
                            k = k + 1
                        if best == 0:
                            break
                    if best == 0:
                        break
                if best == 0:
                    break
            first[i] = best
            inaccurate[i] = flag
    return first_np, inaccurate_np
