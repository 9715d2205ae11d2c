"""Wheel–soil contact on deformable ground: Wong–Reece stresses with slip sinkage and ruts.

A rigid wheel of radius r and width b sinks into the soil by h. Along its contact arc, from the
entry angle ``theta_f`` in front to the exit angle ``theta_r`` behind (angles from the downward
vertical, positive toward the direction of travel), the soil presses on the rim with the
normal stress sigma(theta) and shears along it with tau(theta) (Wong and Reece 1967; Wong 2008,
Ch. 2; Ishigami et al. 2007):

    sigma(theta) = k z(theta)^n,  z(theta) = r (cos theta_e - cos theta_f)   (Bekker; k = k_c/b + k_phi)
    theta_e      = theta                                         theta_m <= theta <= theta_f
                 = theta_f - (theta - theta_r)/(theta_m - theta_r) (theta_f - theta_m)   behind it
    tau(theta)   = (c + sigma tan phi) (1 - exp(-j(theta)/K))   (Mohr–Coulomb, Janosi–Hanamoto)
    j(theta)     = r (theta_f - theta) - (v/omega) (sin theta_f - sin theta)   (driving)

The soil's forces on the wheel, in the wheel's travel frame (x along its heading, z up):

    F_x = r_s b  int (tau cos theta - sigma sin theta) d theta   (drawbar pull)
    F_z = r_s b  int (tau sin theta + sigma cos theta) d theta   (the load the soil carries)
    T   = r_s^2 b int tau d theta                                (the torque the wheel needs)

Slip sinkage comes from three places (Ding et al. 2011; Ishigami et al. 2007; Pavlov and
Johnson's single-wheel fits): the sinkage exponent rises with slip (``n_slip`` s driving,
``n_skid`` |s|^``n_skid_power`` braking), the
largest stress moves forward (``theta_m = (a0 + a1 s) theta_f``) and the rear contact changes
(``theta_r = -(b0 + b1 s) theta_f``, or where the rim rises above the soil's rebound).
Braking (the wheel turning slower than it travels)
follows Pavlov and Johnson: the soil under the front of the arc flows forward and the shear
there reverses about ``theta_0 = theta_f (1 + s/2)``; the stress shape keeps its zero-slip
coefficients.

Choices where the literature is silent, all documented in ``docs/terramechanics.md``:

- Grousers: stresses act at the shear radius ``r_s = r + h_g`` on the grousers' tips and at r
  between them, mixed by the tips' share of the rim (Pavlov and Johnson).
- Side slip: the shear displacement across the wheel is ``j_y = -(theta_f - theta) v_y / omega``
  and the shear stress points along the slip velocity of the rim point, its strength reached
  at ``sqrt((j_x/K)^2 + (j_y/K_y)^2)``; the side wall bulldozes soil (Ishigami et al. 2007).
- Ruts and a second pass: sinkage is measured from the original surface. Where a wheel has
  been before, down to ``z_p``, the soil rebounded to ``d = z_p - p(z_p)/k_u(z_p)`` and reloads
  along the stiff line ``k_u (z - d)`` until it reaches its earlier pressure, then along
  Bekker's curve again (Wong 2008, Sec. 2.4.4). The rut's surface is ``d``. The shear the
  earlier wheel left adds to this wheel's own where both go the same way (Wong's cumulative
  shear of multi-axle vehicles), reached along a line ``RELOAD`` times as stiff as fresh soil's
  from this wheel's own displacement: it is no force of its own.
- At rest the contact is symmetric: below ``rest_speed`` the stress shape blends to
  ``theta_m = 0, theta_r = -theta_f``, so a wheel standing on level soil feels no horizontal
  force and does not creep; and its shear displacement blends from the kinematic one of a
  rolling wheel to the one it has accumulated since it stopped (``hold_x``, ``hold_y``), which
  holds it on a slope as static friction would, without the chatter of a friction law that
  jumps at zero speed.

Every function is vectorised over wheels: arrays of one shape in, arrays of that shape out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.models._jit import compiled as _compiled
from rover_env.config.io import ConfigError, check_range
from rover_env.config.soil import SoilConfig
from rover_env.sim.geometry import GRAVITY

__all__ = [
    "WheelSpec",
    "ContactForces",
    "PullCurves",
    "contact_forces",
    "rut_surface",
    "steady_state",
    "SteadyState",
]

#: Largest ratio v / (r omega) of a braking wheel the shear displacement uses (s = -0.98).
MAX_SKID_RATIO = 50.0
#: Soil sheared before reloads this many times as stiffly as fresh soil (assumed; the normal
#: stress's unloading modulus is of that order against Bekker's at the ruts' depths).
RELOAD = 10.0
#: Speed below which a wheel counts as at rest [m/s] (the side wall's bulldozing fades in below
#: it in the stepped contact). These constants are compiled into the kernels: edit, not assign.
REST_SPEED = 0.005


@dataclass(frozen=True)
class WheelSpec:
    """A rigid wheel's geometry as the soil sees it.

    Attributes:
        radius: Rim radius r, to the base of the grousers [m].
        width: Width b [m].
        grousers: Number of grousers (0: a smooth rim).
        grouser_height: Height h_g of the grousers above the rim [m].
        grouser_thickness: Thickness of a grouser's tip along the rim [m] (assumed 3 mm unless
            given); sets the tips' share of the rim.
        tip_ratio: The tips' share of the rim, if known directly (overrides the grousers' count
            and thickness); 1 for a smooth rim.
    """

    radius: float
    width: float
    grousers: int = 0
    grouser_height: float = 0.0
    grouser_thickness: float = 0.003
    tip_ratio: float | None = None

    def __post_init__(self) -> None:
        check_range("wheel.radius", self.radius, 0.0, 10.0, lo_open=True)
        check_range("wheel.width", self.width, 0.0, 10.0, lo_open=True)
        if not isinstance(self.grousers, int | np.integer) or self.grousers < 0:
            raise ConfigError(f"wheel.grousers: {self.grousers!r}; give a whole number >= 0")
        check_range("wheel.grouser_height", self.grouser_height, 0.0, self.radius)
        check_range("wheel.grouser_thickness", self.grouser_thickness, 0.0, self.radius, lo_open=True)
        if self.tip_ratio is not None:
            check_range("wheel.tip_ratio", self.tip_ratio, 0.0, 1.0, lo_open=True)

    @property
    def shear_radius(self) -> float:
        """r_s = r + h_g: the radius at which the grousers' tips shear the soil [m]."""
        return self.radius + self.grouser_height

    @property
    def tips(self) -> float:
        """The share of the rim on the grousers' tips (1 for a smooth wheel) [-]."""
        if self.tip_ratio is not None:
            return float(self.tip_ratio)
        if self.grousers == 0 or self.grouser_height == 0.0:
            return 1.0
        return min(1.0, self.grousers * self.grouser_thickness / (2.0 * math.pi * self.shear_radius))


@dataclass(frozen=True)
class ContactForces:
    """The soil's action on each wheel, in the wheel's travel frame (x: heading, z: up).

    Attributes:
        drawbar_pull: F_x, the net forward force [N] (negative: resistance).
        normal: F_z, the load the soil carries [N].
        lateral: F_y, the side force [N] (along the wheel's left).
        torque: T, the torque about the axle the soil's shear resists, i.e. the torque the
            wheel must apply to keep turning forward [N m].
        slip: The slip ratio [-1, 1]: (r omega - v)/(r omega) driving, (r omega - v)/v braking.
        theta_f, theta_r, theta_m: Entry, exit and peak-stress angles [rad] (0 out of contact).
        shear_exit: The shear displacement the wheel leaves in the soil at its exit, along its
            heading [m]: the ``prior_shear`` of the next wheel on this track.
    """

    drawbar_pull: np.ndarray
    normal: np.ndarray
    lateral: np.ndarray
    torque: np.ndarray
    slip: np.ndarray
    theta_f: np.ndarray
    theta_r: np.ndarray
    theta_m: np.ndarray
    shear_exit: np.ndarray


def rut_surface(soil: SoilConfig, wheel: WheelSpec, prior) -> np.ndarray:
    """Depth below the original surface [m] that soil pressed down to ``prior`` [m] rebounds to.

    A wheel's largest sinkage ``prior`` at a place leaves its rut there ``p/k_u`` shallower
    (Wong 2008, Sec. 2.4.4): p the pressure it reached, ``k_u = k0 + A_u prior`` the soil's
    unloading stiffness.
    """
    z = np.maximum(np.asarray(prior, dtype=np.float64), 0.0)
    p = soil.modulus(wheel.width) * z**soil.n
    ku = soil.unload_k0 + soil.unload_au * z
    with np.errstate(divide="ignore", invalid="ignore"):
        back = np.where(ku > 0.0, p / ku, 0.0)
    return np.maximum(z - back, 0.0)


@_compiled
def _pressure(kb, n, k0, au, depth, prior, surface):  # pragma: no cover (compiled)
    """Normal stress [Pa] at ``depth`` below the original surface, soil earlier pressed to ``prior``."""
    virgin = kb * max(depth, 0.0) ** n
    if depth <= prior:
        return min((k0 + au * prior) * max(depth - surface, 0.0), virgin)
    return virgin


@_compiled
def _sign(x):  # pragma: no cover (compiled)
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@_compiled
def _contact_kernel(
    p, h, slip, side, sin_beta, moving_in, direction, zp, jprev, hold_x, hold_y, rise, n_theta, out
):  # pragma: no cover (compiled)
    """The contact integrals of every wheel; ``p`` (n, 22) its soil's and wheel's parameters (``_params``).

    Per wheel, in its travel frame (``direction`` -1 mirrors a wheel rolling backward): the
    slip ratio, the side slip ``side`` (j_y = r (theta_f - theta) side), sin of the slip angle
    (side-wall bulldozing), how far it is from rest (``moving``, 0..1), the rut (``zp``,
    ``jprev``) and the held shear (``hold_x``, ``hold_y``), the last three in the caller's frame;
    ``rise``, how far it has risen above the deepest it pressed the soil under it (which then
    unloads along its stiff line: :func:`_soil_step`).
    """
    for i in range(h.shape[0]):
        q = p[i]
        r, rs, b, mu, kb, n0, n_slip, n_skid = q[0], q[1], q[2], q[3], q[4], q[5], q[6], q[7]
        c, tan_phi, k_x, k_y, a0, a1, b0, b1 = q[8], q[9], q[10], q[11], q[12], q[13], q[14], q[15]
        k0, au, d1, d2, rho_g, skid_pow = q[16], q[17], q[18], q[19], q[20], q[21]
        for k in range(out.shape[1]):
            out[i, k] = 0.0
        d = direction[i]
        jp, hx = jprev[i] * d, hold_x[i] * d
        s = min(max(slip[i], -1.0), 1.0)
        driving = s >= 0.0
        moving = min(max(moving_in[i], 0.0), 1.0)
        out[i, 4] = s
        n = n0 + (n_slip * s if s >= 0.0 else n_skid * (-s) ** skid_pow)
        z_p = max(zp[i], 0.0)
        surf = 0.0
        if z_p > 0.0:
            ku = k0 + au * z_p
            if ku > 0.0:
                surf = max(z_p - kb * z_p**n0 / ku, 0.0)
        depth_in = h[i] - surf
        if depth_in <= 0.0:
            continue
        tf = math.acos(min(max(1.0 - depth_in / rs, -1.0), 1.0))
        sd = max(s, 0.0)
        tm = moving * (a0 + a1 * sd) * tf
        if b0 >= 0.0:
            rear = (b0 + b1 * sd) * tf
        else:  # the rim leaves the soil where it rises above the rut's rebounded surface
            ku = k0 + au * max(h[i], 0.0)
            rebound = _pressure(kb, n, k0, au, h[i], z_p, surf) / ku if ku > 0.0 else 0.0
            rear = math.acos(min(max(1.0 - max(depth_in - rebound, 0.0) / rs, -1.0), 1.0))
        tr = -((1.0 - moving) * tf + moving * rear)
        cos_f, sin_f = math.cos(tf), math.sin(tf)
        # braking: v / (r omega) capped (a locked wheel shears the soil fully anyway)
        vw = r * min(1.0 / max(1.0 + s, 1e-300), MAX_SKID_RATIO)
        t0 = tf * (1.0 + 0.5 * min(s, 0.0))
        sin_0 = math.sin(t0)
        chord = (sin_f - sin_0) / (tf - t0) if tf > t0 else cos_f
        span = (tf - tr) / (n_theta - 1)
        fx = fz = fy_t = fy_b = tq = 0.0
        for k in range(n_theta):
            th = tr + (tf - tr) * k / (n_theta - 1)
            frac = (th - tr) / (tm - tr) if tm > tr else 1.0
            te = th if th >= tm else tf - frac * (tf - tm)
            gap = max(math.cos(te) - cos_f, 0.0)
            sig = _pressure(kb, n, k0, au, rs * gap + surf, z_p, surf)
            if mu < 1.0:
                sig = mu * sig + (1.0 - mu) * _pressure(kb, n, k0, au, r * gap + surf, z_p, surf)
            if rise[i] > 0.0:  # pressed deeper a moment ago: unloading along the stiff line
                deep = rs * gap + surf + rise[i]
                sig = min(sig, max(kb * deep**n - (k0 + au * deep) * rise[i], 0.0))
            sin_t, cos_t = math.sin(th), math.cos(th)
            # shear displacement along the wheel, signed by the slip velocity there
            if driving:
                jx0 = r * ((tf - th) - (1.0 - s) * (sin_f - sin_t))
                vjx = 1.0 - (1.0 - s) * cos_t
            elif th > t0:
                jx0 = vw * ((tf - th) * chord - (sin_f - sin_t))
                vjx = chord - cos_t
            else:
                jx0 = r * (t0 - th) - vw * (sin_0 - sin_t)
                vjx = (1.0 + s) - cos_t
            # rolling: the kinematic displacement; at rest: the held one
            jx = moving * _sign(vjx) * abs(jx0) + (1.0 - moving) * hx
            jy = moving * r * (tf - th) * side[i] + (1.0 - moving) * hold_y[i]
            mob = 1.0 - math.exp(-math.hypot(jx / k_x, jy / k_y))
            if jx * jp > 0.0:
                # soil sheared the same way by an earlier pass reloads along a stiff line to
                # the strength it had reached, then goes on (Wong's repetitive shearing)
                own = mob
                jx += jp
                mob = min(
                    1.0 - math.exp(-math.hypot(jx / k_x, jy / k_y)), max(own, RELOAD * abs(jx - jp) / k_x)
                )
            jn = math.hypot(jx, jy)
            tau = (c + sig * tan_phi) * mob
            tau_x = tau * jx / jn if jn > 0.0 else 0.0
            tau_y = tau * jy / jn if jn > 0.0 else 0.0
            wt = 0.5 * span if (k == 0 or k == n_theta - 1) else span
            fx += wt * (tau_x * cos_t - sig * sin_t)
            fz += wt * (tau_x * sin_t + sig * cos_t)
            tq += wt * tau_x
            fy_t += wt * tau_y
            # side wall bulldozing (Ishigami et al. 2007)
            hh = rs * max(cos_t - cos_f, 0.0)
            fy_b += wt * d1 * (c * hh + d2 * rho_g * hh * hh / 2.0) * (rs - hh * cos_t)
            if k == 0:
                out[i, 8] = jx * d
        out[i, 0] = rs * b * fx * d
        out[i, 1] = rs * b * fz
        out[i, 2] = rs * b * fy_t - sin_beta[i] * fy_b
        out[i, 3] = rs * rs * b * tq * d
        out[i, 5] = tf
        out[i, 6] = tr
        out[i, 7] = tm


N_PARAMS = 22


# The stepped contact of rover_env.sim.soil_contact, compiled here beside the kernel it calls:
# numba's on-disk cache follows a function's own file only, so callers in another file would
# keep running an edited kernel's old code.

#: How far the held shear may grow, in shear moduli (the soil's strength is reached by then).
HOLD_CAP = 5.0


@_compiled
def _advance(track, i, step, length):  # pragma: no cover (compiled)
    """Move wheel ``i``'s ``track`` (position, front, back) by ``step``; the new ground reached."""
    pos = track[i, 0] + step
    front, back = track[i, 1], track[i, 2]
    fresh = max(pos - front, 0.0) + max(back - pos, 0.0)
    front = max(front, pos)
    back = min(back, pos)
    back = max(back, front - length)  # the worked stretch is at most a contact long
    front = min(front, back + length)
    track[i, 0], track[i, 1], track[i, 2] = pos, front, back
    return fresh


@_compiled
def _soil_step(
    p, h, vx, w, vy, sink_rate, zp, jprev, dt, damping, shear_damping, n_theta,
    hold, deflection, rolled, travel, turn, pressed, work, out,
):  # pragma: no cover (compiled)  # fmt: skip
    """One substep of :class:`SoilContact` for every wheel: its soil state, then its forces."""
    slip, side, sin_beta, moving, direction, rate_x, rate_y = (
        work[0], work[1], work[2], work[3], work[4], work[5], work[6]
    )  # fmt: skip
    for i in range(h.shape[0]):
        r, rs, k_x, k_y = p[i, 0], p[i, 1], p[i, 10], p[i, 11]
        rim = r * w[i]
        # the deflection relaxes over the contact's length (the last step's, or the sinkage's)
        arc = rs * (out[i, 5] - out[i, 6])
        if arc <= 0.0:
            arc = 2.0 * rs * math.acos(min(max(1.0 - max(h[i], 0.0) / rs, -1.0), 1.0))
        length = max(arc, 0.05 * r)
        # new soil: travel past the stretch of ground (and of rim) the contact has already
        # worked, at most a contact length; moving back and forth inside it brings none
        fresh_x = _advance(travel, i, vx[i] * dt, length)
        fresh = max(fresh_x, _advance(turn, i, rim * dt, length))
        keep = math.exp(-fresh_x / length)
        cap = 100.0 * length
        jx = min(max(deflection[0, i] * keep + (rim - vx[i]) * dt, -cap), cap)
        jy = min(max(deflection[1, i] * keep - vy[i] * dt, -cap), cap)
        rate_x[i] = (jx - deflection[0, i]) / dt
        rate_y[i] = (jy - deflection[1, i]) / dt
        deflection[0, i], deflection[1, i] = jx, jy
        # how much of the contact the wheel has rolled through, signed by the direction: the
        # kinematic shear of a rolling wheel builds over a contact length of travel and turns
        # round only when the wheel has rolled back as far (never at a jitter about zero speed)
        heading = -1.0 if rim + vx[i] < 0.0 else 1.0
        forget = math.exp(-fresh / length)
        rolled[i] = heading + (rolled[i] - heading) * forget
        d = -1.0 if rolled[i] < 0.0 else 1.0
        direction[i] = d
        moving[i] = abs(rolled[i])
        # the deepest this rolling wheel has pressed the soil under it: its contact's front
        # meets fresh soil at vx sin(theta_f), so it may rise that fast still carried; faster,
        # it leaves soil pressed deeper, which unloads along its stiff line, not back up
        # Bekker's curve (which a wheel at rest keeps, the model's rest state)
        if out[i, 5] > 0.0:
            deepest = max(h[i], pressed[i] - abs(vx[i]) * math.sin(out[i, 5]) * dt)
            pressed[i] = h[i] + moving[i] * (deepest - h[i])
        else:
            pressed[i] = h[i]
        work[7, i] = max(pressed[i] - h[i], 0.0)
        q = min(max(d * jx / length, -1.0), 99.0)
        s = q / (1.0 + abs(q)) if q >= 0.0 else q
        slip[i] = s
        side[i] = (jy / length) * ((1.0 - s) if s >= 0.0 else 1.0)
        speed = math.hypot(vx[i], vy[i])
        sin_beta[i] = vy[i] / max(speed, REST_SPEED)  # no jump in the side force at zero speed
        # the shear a wheel at rest holds: what it has slipped, forgotten as it rolls on
        held = HOLD_CAP * max(k_x, k_y)
        hold[0, i] = min(max(hold[0, i] * forget + (rim - vx[i]) * dt, -held), held)
        hold[1, i] = min(max(hold[1, i] * forget - vy[i] * dt, -held), held)
    _contact_kernel(
        p, h, slip, side, sin_beta, moving, direction, zp, jprev, hold[0], hold[1], work[7], n_theta, out
    )
    for i in range(h.shape[0]):
        area = p[i, 2] * p[i, 1] * (out[i, 5] - out[i, 6])
        out[i, 1] += damping * max(sink_rate[i], 0.0) * area
        drag = shear_damping * area  # the shear deflection's rate: zero in steady rolling
        out[i, 0] += drag * rate_x[i]
        out[i, 2] += drag * rate_y[i]
        out[i, 3] += p[i, 1] * drag * rate_x[i]


@_compiled
def _ground_step(
    p, index, wheels, ground, normal, prior, prior_shear, dt, damping, shear_damping, n_theta,
    hold, deflection, rolled, travel, turn, pressed, work, out, inputs, frames, force, torque, sinkage,
):  # pragma: no cover (compiled)  # fmt: skip
    """One substep of :class:`SoilGround`: world frames, the soil's step, world forces."""
    h, vx, w, vy, sink_rate = inputs[0], inputs[1], inputs[2], inputs[3], inputs[4]
    for i in range(index.shape[0]):
        n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
        # the axle: the y axis of the wheel's frame (quaternion x, y, z, w)
        qx, qy, qz, qw = wheels[i, 3], wheels[i, 4], wheels[i, 5], wheels[i, 6]
        a0, a1, a2 = 2.0 * (qx * qy - qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz + qw * qx)
        frames[i, 2, 0], frames[i, 2, 1], frames[i, 2, 2] = a0, a1, a2
        # heading = axle x normal (in the ground's plane), left = normal x heading
        x0, x1, x2 = a1 * n2 - a2 * n1, a2 * n0 - a0 * n2, a0 * n1 - a1 * n0
        norm = max(math.sqrt(x0 * x0 + x1 * x1 + x2 * x2), 1e-12)
        x0, x1, x2 = x0 / norm, x1 / norm, x2 / norm
        y0, y1, y2 = n1 * x2 - n2 * x1, n2 * x0 - n0 * x2, n0 * x1 - n1 * x0
        frames[i, 0, 0], frames[i, 0, 1], frames[i, 0, 2] = x0, x1, x2
        frames[i, 1, 0], frames[i, 1, 1], frames[i, 1, 2] = y0, y1, y2
        c0, c1, c2 = 0.0, 0.0, wheels[i, 2] - ground[i]  # from the ground point below the centre
        v0, v1, v2 = wheels[i, 7], wheels[i, 8], wheels[i, 9]
        h[i] = p[i, 1] - (c0 * n0 + c1 * n1 + c2 * n2) if index[i] >= 0 else -1.0
        vx[i] = v0 * x0 + v1 * x1 + v2 * x2
        vy[i] = v0 * y0 + v1 * y1 + v2 * y2
        sink_rate[i] = -(v0 * n0 + v1 * n1 + v2 * n2)
        w[i] = wheels[i, 10] * a0 + wheels[i, 11] * a1 + wheels[i, 12] * a2
    _soil_step(
        p, h, vx, w, vy, sink_rate, prior, prior_shear, dt, damping, shear_damping, n_theta,
        hold, deflection, rolled, travel, turn, pressed, work, out,
    )  # fmt: skip
    for i in range(index.shape[0]):
        on = index[i] >= 0
        sinkage[i] = max(h[i], 0.0) if on else 0.0
        for k in range(3):
            if on:
                force[i, k] = (
                    out[i, 0] * frames[i, 0, k] + out[i, 2] * frames[i, 1, k] + out[i, 1] * normal[i, k]
                )
                torque[i, k] = -out[i, 3] * frames[i, 2, k]
            else:
                force[i, k] = 0.0
                torque[i, k] = 0.0


def _params(soil: SoilConfig, wheel: WheelSpec) -> np.ndarray:
    """The kernel's parameter row of a soil and a wheel."""
    phi = math.radians(soil.friction_deg)
    xc = math.radians(soil.destructive_deg)
    d1 = 1.0 / math.tan(xc) + math.tan(xc + phi)
    d2 = 1.0 / math.tan(xc) + (1.0 / math.tan(xc)) ** 2 * math.tan(phi)
    b0 = -1.0 if soil.rear_b0 is None else soil.rear_b0
    return np.array(
        [
            wheel.radius,
            wheel.shear_radius,
            wheel.width,
            wheel.tips,
            soil.modulus(wheel.width),
            soil.n,
            soil.n_slip,
            soil.n_skid,
            soil.cohesion,
            math.tan(phi),
            soil.shear_modulus,
            soil.shear_modulus_lateral,
            soil.peak_a0,
            soil.peak_a1,
            b0,
            soil.rear_b1,
            soil.unload_k0,
            soil.unload_au,
            d1,
            d2,
            soil.density * GRAVITY,
            soil.n_skid_power,
        ]
    )


def slip_state(radius: float, v_x, omega, v_y, rest_speed: float):
    """A wheel's slip from its velocities (vectorised), as the contact integrals take it.

    Returns:
        ``(slip, side, sin_beta, moving, direction)``: the slip ratio in [-1, 1] (driving
        (r omega - v)/(r omega), braking (r omega - v)/v, in the travel direction); the side
        slip ``-v_y / max(|r omega|, |v_x|)``; sin of the slip angle; how far from rest, 0..1
        (``max(|v_x|, |r omega|) / rest_speed``); the travel direction, +1 or -1 (-1: rolling
        backward, mirrored).
    """
    vx = np.asarray(v_x, dtype=np.float64)
    w = np.asarray(omega, dtype=np.float64)
    vy = np.asarray(v_y, dtype=np.float64)
    d = np.where(radius * w + vx < 0.0, -1.0, 1.0)
    fwd, rim = vx * d, radius * w * d
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(
            rim >= fwd, np.where(rim > 0.0, (rim - fwd) / rim, 0.0), (rim - fwd) / np.maximum(fwd, 1e-12)
        )
        side = -vy / np.maximum(np.maximum(np.abs(rim), np.abs(fwd)), 1e-9 * radius)
        sin_beta = vy / np.maximum(np.hypot(vx, vy), max(rest_speed, 1e-9))
    moving = np.clip(np.maximum(np.abs(fwd), np.abs(rim)) / max(rest_speed, 1e-9), 0.0, 1.0)
    return np.clip(s, -1.0, 1.0), side, sin_beta, moving, d


def contact_forces(
    soil: SoilConfig,
    wheel: WheelSpec,
    sinkage,
    v_x,
    omega,
    v_y=0.0,
    *,
    prior=0.0,
    prior_shear=0.0,
    hold_x=0.0,
    hold_y=0.0,
    rest_speed: float = 0.005,
    n_theta: int = 48,
) -> ContactForces:
    """The soil's forces on wheels sunk ``sinkage`` deep, moving at (v_x, v_y), turning at omega.

    Args:
        soil: The soil.
        wheel: The wheel.
        sinkage: Depth of the rim's lowest point below the original soil surface [m].
        v_x: The wheel centre's velocity along the wheel's heading [m/s].
        omega: The wheel's spin rate, positive rolling forward [rad/s].
        v_y: The wheel centre's velocity across the wheel, to its left [m/s].
        prior: The largest earlier sinkage at the place [m] (a rut; 0: virgin soil).
        prior_shear: The shear displacement earlier passes left in the soil there, along this
            wheel's heading [m] (Wong's cumulative shear of multi-axle vehicles): a wheel in a
            rut starts from it.
        hold_x: The shear displacement of a wheel at rest along it [m]: the slip it has
            accumulated since it stopped (:class:`rover_env.sim.soil_contact.SoilContact`
            integrates it), which holds it the way static friction would.
        hold_y: The same across the wheel [m].
        rest_speed: Below this speed of the centre and the rim [m/s] the contact blends to the
            symmetric shape of a wheel at rest, and the shear to the held one.
        n_theta: Integration nodes along the contact arc (at least 3).

    Returns:
        :class:`ContactForces`, arrays of the inputs' broadcast shape.
    """
    h, vx, w, vy, zp, jp, hx, hy = (
        np.ascontiguousarray(a.reshape(-1), dtype=np.float64)
        for a in np.broadcast_arrays(
            *(
                np.asarray(a, dtype=np.float64)
                for a in (sinkage, v_x, omega, v_y, prior, prior_shear, hold_x, hold_y)
            )
        )
    )
    shape = np.broadcast_shapes(
        *(np.shape(a) for a in (sinkage, v_x, omega, v_y, prior, prior_shear, hold_x, hold_y))
    )
    slip, side, sin_beta, moving, direction = slip_state(wheel.radius, vx, w, vy, rest_speed)
    out = np.empty((h.shape[0], 9))
    params = np.ascontiguousarray(np.broadcast_to(_params(soil, wheel), (h.shape[0], N_PARAMS)))
    _contact_kernel(
        params,
        h,
        slip,
        side,
        sin_beta,
        moving,
        direction,
        zp,
        jp,
        hx,
        hy,
        np.zeros(h.shape[0]),
        max(int(n_theta), 3),
        out,
    )
    o = [out[:, k].reshape(shape) for k in range(9)]
    return ContactForces(
        drawbar_pull=o[0],
        normal=o[1],
        lateral=o[2],
        torque=o[3],
        slip=o[4],
        theta_f=o[5],
        theta_r=o[6],
        theta_m=o[7],
        shear_exit=o[8],
    )


@dataclass(frozen=True)
class SteadyState:
    """A wheel's steady state at a slip under a load (see :func:`steady_state`).

    Attributes:
        slip: Slip ratio [-].
        sinkage: Depth of the rim's lowest point below the original surface [m].
        drawbar_pull: [N]. load: The vertical load carried [N]. torque: [N m]. lateral: [N].
        shear_exit: The shear displacement left in the soil behind the wheel [m].
        converged: The load was carried within 0.1 % (False: the wheel sank by more than its
            radius).
    """

    slip: np.ndarray
    sinkage: np.ndarray
    drawbar_pull: np.ndarray
    load: np.ndarray
    torque: np.ndarray
    lateral: np.ndarray
    shear_exit: np.ndarray
    converged: np.ndarray


def slip_velocities(slip, speed: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The carriage speed [m/s] and wheel rate [rad/s] that make ``slip`` at ``speed``.

    Driving (s >= 0): omega = v / (r (1 - s)); s = 1 is a wheel spinning in place at the rate
    it would roll at ``speed``. Braking (s < 0): omega = v (1 + s) / r.
    """
    s = np.asarray(slip, dtype=np.float64)
    v = np.full_like(s, speed)
    with np.errstate(divide="ignore"):
        w = np.where(s >= 0.0, speed / (radius * np.maximum(1.0 - s, 1e-12)), speed * (1.0 + s) / radius)
    spinning = s >= 1.0
    w = np.where(spinning, speed / radius, w)
    v = np.where(spinning, 0.0, v)
    return v, w


def steady_state(
    soil: SoilConfig,
    wheel: WheelSpec,
    load,
    slip,
    *,
    speed: float = 0.01,
    slip_angle_deg=0.0,
    prior=0.0,
    prior_shear=0.0,
    n_theta: int = 96,
) -> SteadyState:
    """Solve for the sinkage at which the soil carries ``load`` at ``slip`` (vectorised).

    The single-wheel test bed's steady state: the carriage moves at ``speed`` [m/s], the wheel
    turns at the rate that makes ``slip``, and it sinks until the soil's vertical force equals
    the load [N] (bisection on the sinkage, 60 halvings).
    """
    load = np.asarray(load, dtype=np.float64)
    s = np.asarray(slip, dtype=np.float64)
    if np.any(load <= 0.0) or not np.all(np.isfinite(load)):
        raise ConfigError(f"load: {load!r}; give a positive, finite load [N]")
    if np.any(np.abs(s) > 1.0) or not np.all(np.isfinite(s)):
        raise ConfigError(f"slip: {s!r}; give slips in [-1, 1]")
    if not (math.isfinite(speed) and speed >= 2 * REST_SPEED):
        raise ConfigError(
            f"speed: {speed!r} m/s; give at least {2 * REST_SPEED} m/s (slower is a wheel at rest)"
        )
    if np.any(np.asarray(prior, dtype=np.float64) < 0.0) or not np.all(np.isfinite(np.asarray(prior, float))):
        raise ConfigError(f"prior: {prior!r}; give earlier sinkages >= 0 [m]")
    load, s, beta = np.broadcast_arrays(load, s, np.radians(np.asarray(slip_angle_deg, dtype=np.float64)))
    v, w = slip_velocities(s, speed, wheel.radius)
    vx, vy = v * np.cos(beta), -v * np.sin(beta)
    lo = np.zeros(load.shape)
    hi = np.full(load.shape, 1.5 * wheel.shear_radius)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        fz = contact_forces(
            soil, wheel, mid, vx, w, vy, prior=prior, prior_shear=prior_shear, n_theta=n_theta
        ).normal
        below = fz < load
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    h = 0.5 * (lo + hi)
    f = contact_forces(soil, wheel, h, vx, w, vy, prior=prior, prior_shear=prior_shear, n_theta=n_theta)
    return SteadyState(
        slip=s,
        sinkage=h,
        drawbar_pull=f.drawbar_pull,
        load=f.normal,
        torque=f.torque,
        lateral=f.lateral,
        shear_exit=f.shear_exit,
        converged=np.abs(f.normal - load) <= 1e-3 * load,
    )


class PullCurves:
    """A soil's steady-state drawbar pull over load against slip, tabulated over loads (virgin soil).

    What the truth reports of each wheel on soil: its steady-state DP/W at its slip and load,
    and the slips of largest DP/W and of largest tractive efficiency
    ``eta = DP (1 - s) / (T / r)`` (driving: the drawbar power over the axle's) at its load.
    The table (:data:`LOADS` x :data:`SLIPS`: 25 x 146 steady states, the contact arc on 48
    nodes) is solved once per soil at first use (about a second, with the compilation); a load
    outside the table's 10-1000 N reads its nearest row.

    Args:
        soil: The soil.
        wheel: The wheel.
    """

    #: Loads of the table [N], geometrically spaced.
    LOADS = np.geomspace(10.0, 1000.0, 25)
    #: Slips of the table [-]: braking to -0.5, driving to 0.95.
    SLIPS = np.linspace(-0.5, 0.95, 146)

    def __init__(self, soil: SoilConfig, wheel: WheelSpec) -> None:
        self.soil, self.wheel = soil, wheel
        self._table: tuple[np.ndarray, np.ndarray] | None = None

    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """(DP/W, tractive efficiency), each (len(LOADS), len(SLIPS)); NaN where no steady state."""
        if self._table is None:
            load, slip = np.meshgrid(self.LOADS, self.SLIPS, indexing="ij")
            ss = steady_state(self.soil, self.wheel, load, slip, n_theta=48)
            dpw = ss.drawbar_pull / ss.load
            with np.errstate(divide="ignore", invalid="ignore"):
                eff = ss.drawbar_pull * (1.0 - slip) * self.wheel.radius / ss.torque
            dpw = np.where(ss.converged, dpw, np.nan)
            eff = np.where(ss.converged & (ss.torque > 0.0) & (slip >= 0.0), eff, np.nan)
            self._table = (dpw, eff)
        return self._table

    def curve(self, load: float) -> tuple[np.ndarray, np.ndarray]:
        """(DP/W, efficiency) over :data:`SLIPS` at ``load`` [N] (interpolated in log load)."""
        dpw, eff = self.table()
        x = np.log(self.LOADS)
        u = float(np.clip(np.log(max(load, 1e-9)), x[0], x[-1]))
        k = min(int(np.searchsorted(x, u, side="right")) - 1, len(x) - 2)
        a = (u - x[k]) / (x[k + 1] - x[k])
        return (1 - a) * dpw[k] + a * dpw[k + 1], (1 - a) * eff[k] + a * eff[k + 1]

    def at(self, load: float, slip: float) -> tuple[float, float, float]:
        """(DP/W at ``slip``, slip of largest DP/W, slip of largest efficiency) at ``load`` [N].

        The efficiency is a driving wheel's (s >= 0). A slip outside the table's reads NaN for
        the first.
        """
        dpw, eff = self.curve(load)
        s = self.SLIPS
        ratio = float(np.interp(slip, s, dpw)) if s[0] <= slip <= s[-1] else math.nan
        best_pull = float(s[np.nanargmax(dpw)]) if np.any(np.isfinite(dpw)) else math.nan
        best_eff = float(s[np.nanargmax(eff)]) if np.any(np.isfinite(eff)) else math.nan
        return ratio, best_pull, best_eff
