"""The elastic foundation's per-cell arithmetic (foundation.py), compiled with Numba.

The foundation runs every plant step (1-2 ms of simulated time). Written with NumPy on the
~150 cells near the wall, each step was ~150 array operations whose cost is their call, not
their arithmetic (~0.5 ms a step, most of the compliant wall's cost:
docs/results/performance.md, "The compliant wall's cost"). These loops do the same
arithmetic once per cell. `foundation.py` keeps the model: what is picked, stored and
returned; its docstring says what each quantity means.

Each kernel's first call compiles it (a few seconds); the machine code is cached beside this
file (`cache=True`), so later processes load it.
"""

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _newton_step(steps, j, p):
    """(the point p's step in stations from station j, unclamped; its squared distance from
    station j's point): (d . T') / (1 - d . B'), d = p - P (WallTable._steps: P, T', B')."""
    dx = p[0] - steps[j, 0, 0]
    dy = p[1] - steps[j, 0, 1]
    dz = p[2] - steps[j, 0, 2]
    along = dx * steps[j, 1, 0] + dy * steps[j, 1, 1] + dz * steps[j, 1, 2]
    bend = dx * steps[j, 2, 0] + dy * steps[j, 2, 1] + dz * steps[j, 2, 2]
    return int(np.rint(along / (1.0 - bend))), dx * dx + dy * dy + dz * dz


@njit(cache=True)
def follow_station(steps, p, station, reach) -> int:
    """The station of the point p on the stretch of tube around `station` (WallTable.follow):
    Newton steps along the centreline until one is zero; -1 when that takes more than 8 or
    ends farther than `reach` from p."""
    last = steps.shape[0] - 1
    j = min(max(station, 0), last)
    for _ in range(8):
        step, distance2 = _newton_step(steps, j, p)
        j = min(max(j + step, 0), last)
        if step == 0:
            return j if distance2 <= reach * reach else -1
    return -1


@njit(cache=True)
def place_cells(p_B, R, p_WB):
    """The cells' centres placed at the capsule's pose: (their offsets from the body origin
    (N, 3, world), their world points (N, 3)), offsets = R p_B."""
    count = p_B.shape[0]
    offsets = np.empty((count, 3))
    points = np.empty((count, 3))
    for n in range(count):
        x, y, z = p_B[n, 0], p_B[n, 1], p_B[n, 2]
        for a in range(3):
            o = R[a, 0] * x + R[a, 1] * y + R[a, 2] * z
            offsets[n, a] = o
            points[n, a] = o + p_WB[a]
    return offsets, points


@njit(cache=True)
def near_wall(points, frame, lowest, bend, slack, dtheta, around, start_cap, end_cap,
              first, last):
    """Indices of the points (N, 3) that may lie beyond the mucosa (WallTable.near_wall):
    measured in the station's `frame` (4, 3: point, tangent, normal, binormal), the distance
    from the centreline plus `slack` and what the bend `bend` (half the sharpest curvature)
    makes of the offset along it, against `lowest` (K,: the narrowest radius per sector);
    with `start_cap` / `end_cap`, also every point past (or within 1 mm of) that end's
    plane (`first`, `last`: the ends' frames)."""
    count = points.shape[0]
    out = np.empty(count, dtype=np.intp)
    m = 0
    inv = 1.0 / dtheta
    low, high = lowest.min(), lowest.max()   # the sector is read only between the two
    for n in range(count):
        dx = points[n, 0] - frame[0, 0]
        dy = points[n, 1] - frame[0, 1]
        dz = points[n, 2] - frame[0, 2]
        along = dx * frame[1, 0] + dy * frame[1, 1] + dz * frame[1, 2]
        u = dx * frame[2, 0] + dy * frame[2, 1] + dz * frame[2, 2]
        v = dx * frame[3, 0] + dy * frame[3, 1] + dz * frame[3, 2]
        a = abs(along) + slack
        reach = math.hypot(u, v) + (slack + bend * a * a)
        if reach <= low:
            near = False
        elif reach > high:
            near = True
        else:
            near = reach > lowest[int(math.atan2(v, u) * inv) % around]
        if not near and start_cap:
            near = -((points[n, 0] - first[0, 0]) * first[1, 0]
                     + (points[n, 1] - first[0, 1]) * first[1, 1]
                     + (points[n, 2] - first[0, 2]) * first[1, 2]) > -1e-3 - slack
        if not near and end_cap:
            near = ((points[n, 0] - last[0, 0]) * last[1, 0]
                    + (points[n, 1] - last[0, 1]) * last[1, 1]
                    + (points[n, 2] - last[0, 2]) * last[1, 2]) > -1e-3 - slack
        if near:
            out[m] = n
            m += 1
    return out[:m]


@njit(cache=True)
def wall_depth(points, station, refinements, steps, frames, flat, step, dtheta, around,
               depth, inward):
    """Each point's depth beyond the mucosa and the wall's inward normal there, into
    `depth` (N,) and `inward` (N, 3) (WallTable.depth)."""
    last = frames.shape[0] - 1
    row = around + 1
    for n in range(points.shape[0]):
        p = points[n]
        j = station
        for _ in range(1 + refinements):   # from the capsule's station, then its own
            j = min(max(j + _newton_step(steps, j, p)[0], 0), last)
        f = frames[j]
        dx, dy, dz = p[0] - f[0, 0], p[1] - f[0, 1], p[2] - f[0, 2]
        s_local = dx * f[1, 0] + dy * f[1, 1] + dz * f[1, 2]
        x = dx * f[2, 0] + dy * f[2, 1] + dz * f[2, 2]
        y = dx * f[3, 0] + dy * f[3, 1] + dz * f[3, 2]
        rho = math.hypot(x, y)
        # Bilinear in (s, theta) over the flattened table.
        u = min(max(j + s_local / step, 0.0), last - 1e-6)
        ju = int(u)
        fu = u - ju
        v = (math.atan2(y, x) * (1.0 / dtheta)) % around
        kv = int(v)
        fv = v - kv
        base = ju * row + kv
        w00, w01 = (1.0 - fu) * (1.0 - fv), (1.0 - fu) * fv
        w10, w11 = fu * (1.0 - fv), fu * fv
        radius = (w00 * flat[base, 0] + w01 * flat[base + 1, 0] + w10 * flat[base + row, 0]
                  + w11 * flat[base + row + 1, 0])
        slope_s = (w00 * flat[base, 1] + w01 * flat[base + 1, 1] + w10 * flat[base + row, 1]
                   + w11 * flat[base + row + 1, 1])
        slope_theta = (w00 * flat[base, 2] + w01 * flat[base + 1, 2]
                       + w10 * flat[base + row, 2] + w11 * flat[base + row + 1, 2])
        inv = 1.0 / max(rho, 1e-9)
        tilt = slope_theta / max(radius, 1e-9)
        norm = math.sqrt(1.0 + slope_s * slope_s + tilt * tilt)
        a = slope_s
        b = -(x + tilt * y) * inv
        c = -(y - tilt * x) * inv
        for i in range(3):
            inward[n, i] = (f[1, i] * a + f[2, i] * b + f[3, i] * c) / norm
        d = (rho - radius) / norm
        # The flat caps closing the tube at its two ends: a point whose station is an end
        # and that lies past the end's plane (its tangent, outward) is that far into it.
        for end, sign in ((0, -1.0), (last, 1.0)):
            if j == end:
                e = frames[end]
                past = sign * ((p[0] - e[0, 0]) * e[1, 0] + (p[1] - e[0, 1]) * e[1, 1]
                               + (p[2] - e[0, 2]) * e[1, 2])
                if past > d:
                    d = past
                    for i in range(3):
                        inward[n, i] = -sign * e[1, i]
        depth[n] = d


@njit(cache=True)
def response_gain(r, nu, normal_gain, beta):
    """The cells' response over a step mapped onto the capsule's spatial velocity [w; v]
    (6x6): sum over cells of J^T (beta I + (alpha - beta) nu nu^T) J, J = [-[r]x, I] (a
    cell's velocity v + w x r), alpha its normal gain and beta its bristle's."""
    gain = np.zeros((6, 6))
    u = np.empty(6)
    for q in range(r.shape[0]):
        # beta J^T J + (alpha - beta) u u^T, J = [-[r]x, I], u = J^T nu = [r x nu; nu].
        rx, ry, rz = r[q, 0], r[q, 1], r[q, 2]
        nx, ny, nz = nu[q, 0], nu[q, 1], nu[q, 2]
        u[0], u[1], u[2] = ry * nz - rz * ny, rz * nx - rx * nz, rx * ny - ry * nx
        u[3], u[4], u[5] = nx, ny, nz
        g = normal_gain[q] - beta[q]
        for a in range(6):
            ga = g * u[a]
            for b in range(6):
                gain[a, b] += ga * u[b]
        bq = beta[q]
        rr = rx * rx + ry * ry + rz * rz
        gain[0, 0] += bq * (rr - rx * rx)
        gain[1, 1] += bq * (rr - ry * ry)
        gain[2, 2] += bq * (rr - rz * rz)
        gain[0, 1] -= bq * rx * ry
        gain[1, 0] -= bq * rx * ry
        gain[0, 2] -= bq * rx * rz
        gain[2, 0] -= bq * rx * rz
        gain[1, 2] -= bq * ry * rz
        gain[2, 1] -= bq * ry * rz
        for a in range(3):
            gain[3 + a, 3 + a] += bq
        # beta [r]x in the upper right and its transpose, -beta [r]x, in the lower left.
        skew = ((0.0, -rz, ry), (rz, 0.0, -rx), (-ry, rx, 0.0))
        for a in range(3):
            for b in range(3):
                gain[a, 3 + b] += bq * skew[a][b]
                gain[3 + b, a] += bq * skew[a][b]
    return gain


@njit(cache=True)
def contact_cells(points, offsets, normals_B, R, near, stuck, release, v_W, w_W, areas,
                  k, knee, k_stiff, dissipation, dt, mu, tangential_per_share, station,
                  refinements, steps, frames, flat, step, dtheta, around, inertia_B):
    """The cells in contact among `near` and what the step needs of each (FoundationContact
    ._geometry): (pressed (M,), r, nu (M, 3), area, pressure, normal_gain, bristle_gain,
    share, slip (M, 3), limit, floor (M,), system (6, 6): M + dt gain, M the capsule's
    spatial inertia `inertia_B` (about its body origin, [w; v], body frame) turned into
    world, gain the cells' response mapped onto its spatial velocity [w; v]). The wall's
    elastic pressure is bilinear in the depth d: k d up to `knee` (m), then k_stiff beyond
    it (knee = inf: linear)."""
    count = near.shape[0]
    pts = np.empty((count, 3))
    for n in range(count):
        pts[n] = points[near[n]]
    depth = np.empty(count)
    inward = np.empty((count, 3))
    wall_depth(pts, station, refinements, steps, frames, flat, step, dtheta, around,
               depth, inward)
    # Which cells touch: pressed beyond the mucosa (or, stuck, within the release
    # distance beyond it) and facing the wall.
    touching = np.empty(count, dtype=np.intp)
    facing = np.empty(count)
    m = 0
    for n in range(count):
        i = near[n]
        nb = normals_B[i]
        face = 0.0
        for a in range(3):
            face -= (R[a, 0] * nb[0] + R[a, 1] * nb[1] + R[a, 2] * nb[2]) * inward[n, a]
        held = release > 0.0 and stuck[i] > 0.5 and depth[n] > -release
        if (depth[n] > 0.0 or held) and face > 0.0:
            touching[m] = n
            facing[m] = face
            m += 1
    pressed = np.empty(m, dtype=np.intp)
    r = np.empty((m, 3))
    nu = np.empty((m, 3))
    area = np.empty(m)
    pressure = np.empty(m)
    normal_gain = np.empty(m)
    slip = np.empty((m, 3))
    floor = np.empty(m)
    total = 0.0
    for q in range(m):
        n = touching[q]
        i = near[n]
        pressed[q] = i
        for a in range(3):
            r[q, a] = offsets[i, a]
            nu[q, a] = inward[n, a]
        # v + w x r, its rate into the wall and its tangential part.
        vx = v_W[0] + w_W[1] * r[q, 2] - w_W[2] * r[q, 1]
        vy = v_W[1] + w_W[2] * r[q, 0] - w_W[0] * r[q, 2]
        vz = v_W[2] + w_W[0] * r[q, 1] - w_W[1] * r[q, 0]
        into = -(vx * nu[q, 0] + vy * nu[q, 1] + vz * nu[q, 2])
        slip[q, 0] = vx + into * nu[q, 0]
        slip[q, 1] = vy + into * nu[q, 1]
        slip[q, 2] = vz + into * nu[q, 2]
        area[q] = areas[i] * facing[q]
        total += area[q]
        d = depth[n]
        rate = 1.0 + dissipation * into
        if release > 0.0 and d <= 0.0:   # stuck beyond the mucosa: the spring alone
            pressure[q] = k * d
            normal_gain[q] = k * dt * area[q]
        else:
            elastic, stiffness = k * d, k
            if d > knee:   # past the knee of the wall's stretch: the stiffer modulus
                elastic, stiffness = k * knee + k_stiff * (d - knee), k_stiff
            pressure[q] = elastic * max(rate, 0.0)
            normal_gain[q] = (area[q] * (elastic * dissipation + stiffness * dt * rate)
                              if rate > 0.0 else 0.0)
        floor[q] = -k * release * area[q]
    share = area / max(total, 1e-300)
    beta = tangential_per_share * share
    limit = np.empty(m)
    for q in range(m):
        limit[q] = mu * max(pressure[q], 0.0) * area[q]
    gain = response_gain(r, nu, normal_gain, beta)
    # M + dt gain, M = diag(R, R) inertia_B diag(R, R)^T.
    system = np.empty((6, 6))
    for bi in range(2):
        for bj in range(2):
            for a in range(3):
                for b in range(3):
                    total = 0.0
                    for c in range(3):
                        for e in range(3):
                            total += R[a, c] * inertia_B[3 * bi + c, 3 * bj + e] * R[b, e]
                    system[3 * bi + a, 3 * bj + b] = total + dt * gain[3 * bi + a, 3 * bj + b]
    return pressed, r, nu, area, pressure, normal_gain, beta, share, slip, limit, floor, system


@njit(cache=True)
def _projected_bristle(bristles, i, nu, q, out):
    """Cell i's bristle, in its wall's tangent plane (nu[q]), into out (3,)."""
    zn = (bristles[3 * i] * nu[q, 0] + bristles[3 * i + 1] * nu[q, 1]
          + bristles[3 * i + 2] * nu[q, 2])
    for a in range(3):
        out[a] = bristles[3 * i + a] - zn * nu[q, a]


@njit(cache=True)
def _wrench(r, forces):
    """[sum r x f; sum f] of forces (M, 3) at offsets r (M, 3)."""
    w = np.zeros(6)
    for q in range(r.shape[0]):
        fx, fy, fz = forces[q, 0], forces[q, 1], forces[q, 2]
        w[0] += r[q, 1] * fz - r[q, 2] * fy
        w[1] += r[q, 2] * fx - r[q, 0] * fz
        w[2] += r[q, 0] * fy - r[q, 1] * fx
        w[3] += fx
        w[4] += fy
        w[5] += fz
    return w


@njit(cache=True)
def _solve6(A, b):
    """x with A x = b (6x6, Gaussian elimination with partial pivoting)."""
    M = A.copy()
    x = b.copy()
    n = 6
    for c in range(n):
        p = c
        for r_ in range(c + 1, n):
            if abs(M[r_, c]) > abs(M[p, c]):
                p = r_
        if p != c:
            for k in range(n):
                M[c, k], M[p, k] = M[p, k], M[c, k]
            x[c], x[p] = x[p], x[c]
        for r_ in range(c + 1, n):
            f = M[r_, c] / M[c, c]
            for k in range(c, n):
                M[r_, k] -= f * M[c, k]
            x[r_] -= f * x[c]
    for c in range(n - 1, -1, -1):
        s = x[c]
        for k in range(c + 1, n):
            s -= M[c, k] * x[k]
        x[c] = s / M[c, c]
    return x


@njit(cache=True)
def implicit_wrench(pressed, r, nu, normal_force, normal_gain, beta, share, slip, floor,
                    bristles, system, other, dt, mu, tangential_stiffness, tangential_damping):
    """(the wall's wrench at the step's start, the wrench it applies over the step), both
    [torque about the body origin; force], world (FoundationContact._solve): the velocity
    change over the step with every cell's force taken at its end, dt system^-1 (F + other),
    then each cell's force there: normal at least its floor, friction within mu times its
    pressing force (Coulomb's cone)."""
    m = pressed.shape[0]
    tangential = np.empty((m, 3))
    z = np.empty(3)
    for q in range(m):
        _projected_bristle(bristles, pressed[q], nu, q, z)
        for a in range(3):
            tangential[q, a] = (tangential_stiffness * z[a]
                                + tangential_damping * slip[q, a]) * share[q]
    forces = np.empty((m, 3))
    for q in range(m):
        for a in range(3):
            forces[q, a] = normal_force[q] * nu[q, a] - tangential[q, a]
    explicit = _wrench(r, forces)
    change = _solve6(system, explicit + other)
    for a in range(6):
        change[a] *= dt
    for q in range(m):
        # dv + dw x r, its normal part, and the cell's force at the step's end.
        dvx = change[3] + change[1] * r[q, 2] - change[2] * r[q, 1]
        dvy = change[4] + change[2] * r[q, 0] - change[0] * r[q, 2]
        dvz = change[5] + change[0] * r[q, 1] - change[1] * r[q, 0]
        dvn = dvx * nu[q, 0] + dvy * nu[q, 1] + dvz * nu[q, 2]
        normal = max(normal_force[q] - normal_gain[q] * dvn, floor[q])
        tx = tangential[q, 0] + beta[q] * (dvx - dvn * nu[q, 0])
        ty = tangential[q, 1] + beta[q] * (dvy - dvn * nu[q, 1])
        tz = tangential[q, 2] + beta[q] * (dvz - dvn * nu[q, 2])
        size = math.sqrt(tx * tx + ty * ty + tz * tz)
        limit = mu * max(normal, 0.0)
        if size > limit:
            scale = limit / max(size, 1e-300)
            tx, ty, tz = tx * scale, ty * scale, tz * scale
        forces[q, 0] = normal * nu[q, 0] - tx
        forces[q, 1] = normal * nu[q, 1] - ty
        forces[q, 2] = normal * nu[q, 2] - tz
    return explicit, _wrench(r, forces)


@njit(cache=True)
def next_bristles(count, pressed, nu, slip, share, limit, bristles, dt, tangential_stiffness):
    """The bristles after the step (3 count,): each pressed cell's follows its slip, held
    at mu times its normal force; the others let go."""
    out = np.zeros(3 * count)
    z = np.empty(3)
    for q in range(pressed.shape[0]):
        i = pressed[q]
        _projected_bristle(bristles, i, nu, q, z)
        for a in range(3):
            z[a] += dt * slip[q, a]
        size = math.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2]) * (
            tangential_stiffness * share[q])
        scale = limit[q] / size if size > limit[q] else 1.0
        for a in range(3):
            out[3 * i + a] = z[a] * scale
    return out
