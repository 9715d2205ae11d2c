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
Johnson's single-wheel fits): the sinkage exponent rises with slip (``n_slip``, ``n_skid``), the
largest stress moves forward (``theta_m = (a0 + a1 s) theta_f``) and the rear contact changes
(``theta_r = -(b0 + b1 s) theta_f``, or where the rim rises above the soil's rebound).
Braking (the wheel turning slower than it travels)
follows Pavlov and Johnson: the soil under the front of the arc flows forward and the shear
there reverses about ``theta_0 = theta_f (1 + s/2)``; the stress shape keeps its zero-slip
coefficients.

Choices where the literature is silent, all documented in ``docs/terramechanics.md``:

- Grousers: stresses act at the shear radius ``r_s = r + h_g`` on the grousers' tips and at r
  between them, mixed by the tips' share of the rim (Pavlov and Johnson).
- Side slip: the shear displacement across the wheel is ``j_y = (theta_f - theta) v_jy / omega``
  and the shear stress points along the slip velocity of the rim point, its strength reached
  at ``sqrt((j_x/K)^2 + (j_y/K_y)^2)``; the side wall bulldozes soil (Ishigami et al. 2007).
- Ruts and a second pass: sinkage is measured from the original surface. Where a wheel has
  been before, down to ``z_p``, the soil rebounded to ``d = z_p - p(z_p)/k_u(z_p)`` and reloads
  along the stiff line ``k_u (z - d)`` until it reaches its earlier pressure, then along
  Bekker's curve again (Wong 2008, Sec. 2.4.4). The rut's surface is ``d``.
- At rest the contact is symmetric: below ``rest_speed`` the stress shape blends to
  ``theta_m = 0, theta_r = -theta_f``, so a wheel standing on level soil feels no horizontal
  force and does not creep.

Every function is vectorised over wheels: arrays of one shape in, arrays of that shape out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rover_env.config.io import ConfigError, check_range
from rover_env.config.soil import SoilConfig

__all__ = ["WheelSpec", "ContactForces", "contact_forces", "rut_surface", "steady_state", "SteadyState"]

GRAVITY = 9.81
#: Largest ratio v / (r omega) of a braking wheel the shear displacement uses (s = -0.98).
_MAX_SKID_RATIO = 50.0


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


def _pressure(soil, wheel, depth, n, prior, surface):
    """Normal stress [Pa] at ``depth`` below the original surface, with earlier loading."""
    k = soil.modulus(wheel.width)
    virgin = k * np.maximum(depth, 0.0) ** n
    if prior is None:
        return virgin
    ku = soil.unload_k0 + soil.unload_au * prior
    reload = ku * np.maximum(depth - surface, 0.0)
    return np.where(depth <= prior, np.minimum(reload, virgin), virgin)


def contact_forces(
    soil: SoilConfig,
    wheel: WheelSpec,
    sinkage,
    v_x,
    omega,
    v_y=0.0,
    *,
    prior=None,
    prior_shear=0.0,
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
        prior: The largest earlier sinkage at the place [m] (a rut; None or 0: virgin soil).
        prior_shear: The shear displacement earlier passes left in the soil there, along this
            wheel's heading [m] (Wong's cumulative shear of multi-axle vehicles): a wheel in a
            rut starts from it.
        rest_speed: Below this speed of the centre and the rim [m/s] the contact blends to the
            symmetric shape of a wheel at rest.
        n_theta: Integration nodes along the contact arc.

    Returns:
        :class:`ContactForces`, arrays of the inputs' broadcast shape.
    """
    h, vx, w, vy = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (sinkage, v_x, omega, v_y)))
    shape = h.shape
    h, vx, w, vy = (a.reshape(-1) for a in (h, vx, w, vy))
    r, rs, b = wheel.radius, wheel.shear_radius, wheel.width
    # travel direction: mirror a wheel rolling backward onto one rolling forward
    d = np.where(r * w + vx < 0.0, -1.0, 1.0)
    vx, w = vx * d, w * d
    j_prev = np.broadcast_to(np.asarray(prior_shear, dtype=np.float64), shape).reshape(-1) * d
    rim = r * w
    driving = rim >= vx
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(driving, np.where(rim > 0, (rim - vx) / rim, 0.0), (rim - vx) / np.maximum(vx, 1e-12))
    s = np.clip(s, -1.0, 1.0)
    n = soil.n + np.where(s >= 0.0, soil.n_slip * s, -soil.n_skid * s)
    if prior is None:
        zp = None
        surf = np.zeros_like(h)
    else:
        zp = np.broadcast_to(np.asarray(prior, dtype=np.float64), shape).reshape(-1)
        surf = rut_surface(soil, wheel, zp)
    depth_in = h - surf  # how far the rim reaches below the rut's surface
    touch = depth_in > 0.0
    tf = np.arccos(np.clip(1.0 - np.maximum(depth_in, 0.0) / rs, -1.0, 1.0))
    moving = np.clip(np.maximum(np.abs(vx), np.abs(rim)) / max(rest_speed, 1e-9), 0.0, 1.0)
    sd = np.maximum(s, 0.0)
    tm = moving * (soil.peak_a0 + soil.peak_a1 * sd) * tf
    if soil.rear_b0 is not None:
        rear = (soil.rear_b0 + soil.rear_b1 * sd) * tf
    else:  # the rim leaves the soil where it rises above the rut's rebounded surface
        bottom = _pressure(soil, wheel, h, n, zp, surf)
        ku = soil.unload_k0 + soil.unload_au * np.maximum(h, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            rebound = np.where(ku > 0.0, bottom / ku, 0.0)
        rear = np.arccos(np.clip(1.0 - np.maximum(depth_in - rebound, 0.0) / rs, -1.0, 1.0))
    tr = -((1.0 - moving) * tf + moving * rear)
    # nodes along the arc
    u = np.linspace(0.0, 1.0, n_theta)[None, :]
    th = tr[:, None] + (tf - tr)[:, None] * u
    tf_, tm_, tr_ = tf[:, None], tm[:, None], tr[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(tm_ > tr_, (th - tr_) / (tm_ - tr_), 1.0)
    te = np.where(th >= tm_, th, tf_ - frac * (tf_ - tm_))
    cos_gap = np.maximum(np.cos(te) - np.cos(tf_), 0.0)
    n_ = n[:, None]
    zp_ = None if zp is None else zp[:, None]
    surf_ = surf[:, None]
    sig_tips = _pressure(soil, wheel, rs * cos_gap + surf_, n_, zp_, surf_)
    mu = wheel.tips
    if mu < 1.0:
        sig_rim = _pressure(soil, wheel, r * cos_gap + surf_, n_, zp_, surf_)
        sig = mu * sig_tips + (1.0 - mu) * sig_rim
    else:
        sig = sig_tips
    # shear displacement and the slip velocity's direction at each node
    sin_t, cos_t = np.sin(th), np.cos(th)
    sin_f = np.sin(tf_)
    vx_, w_, rim_ = vx[:, None], w[:, None], rim[:, None]
    w_drive = np.where(w_ > 0.0, w_, 1.0)
    jx_drive = np.where(w_ > 0.0, r * (tf_ - th) - (vx_ / w_drive) * (sin_f - sin_t), 0.0)
    vj_drive = rim_ - vx_ * cos_t
    # braking: v/omega capped (a locked wheel shears the soil fully anyway)
    vw = np.minimum(vx_ / np.maximum(w_, vx_ / (r * _MAX_SKID_RATIO) + 1e-300), r * _MAX_SKID_RATIO)
    s_ = s[:, None]
    t0 = tf_ * (1.0 + 0.5 * np.minimum(s_, 0.0))
    sin_0 = np.sin(t0)
    with np.errstate(divide="ignore", invalid="ignore"):
        chord = np.where(tf_ > t0, (sin_f - sin_0) / (tf_ - t0), np.cos(tf_))
    front = th > t0
    jx_skid = np.where(
        front, vw * ((tf_ - th) * chord - (sin_f - sin_t)), r * (t0 - th) - vw * (sin_0 - sin_t)
    )
    vj_skid = np.where(front, vx_ * (chord - cos_t), rim_ - vx_ * cos_t)
    drive_ = driving[:, None]
    vjx = np.where(drive_, vj_drive, vj_skid)
    vjy = -vy[:, None] * np.ones_like(th)
    w_lat = np.maximum(np.maximum(np.abs(w_), np.abs(vx_) / r), 1e-9)
    # signed shear displacements along and across the wheel; earlier passes' shear stays in the soil
    jx = np.sign(vjx) * np.abs(np.where(drive_, jx_drive, jx_skid)) + j_prev[:, None]
    jy = np.sign(vjy) * np.abs((tf_ - th) * vjy / w_lat)
    phi = math.radians(soil.friction_deg)
    strength = soil.cohesion + sig * math.tan(phi)
    mobilised = 1.0 - np.exp(-np.hypot(jx / soil.shear_modulus, jy / soil.shear_modulus_lateral))
    jn = np.hypot(jx, jy)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = np.where(jn > 0.0, jx / jn, 0.0)
        uy = np.where(jn > 0.0, jy / jn, 0.0)
    tau_x = strength * mobilised * ux
    tau_y = strength * mobilised * uy
    span = (tf - tr)[:, None] / (n_theta - 1)
    wts = np.full(n_theta, 1.0)
    wts[0] = wts[-1] = 0.5
    integ = lambda f: np.sum(f * wts[None, :] * span, axis=1)  # noqa: E731
    fx = rs * b * integ(tau_x * cos_t - sig * sin_t)
    fz = rs * b * integ(tau_x * sin_t + sig * cos_t)
    torque = rs * rs * b * integ(tau_x)
    # side wall bulldozing (Ishigami et al. 2007), against the side slip
    xc = math.radians(soil.destructive_deg)
    d1 = 1.0 / math.tan(xc) + math.tan(xc + phi)
    d2 = 1.0 / math.tan(xc) + (1.0 / math.tan(xc)) ** 2 * math.tan(phi)
    hh = rs * np.maximum(cos_t - np.cos(tf_), 0.0)
    rb = d1 * (soil.cohesion * hh + d2 * soil.density * GRAVITY * hh * hh / 2.0)
    speed = np.hypot(vx, vy)
    with np.errstate(divide="ignore", invalid="ignore"):
        sin_beta = np.where(speed > 0.0, vy / speed, 0.0)
    fy = rs * b * integ(tau_y) - sin_beta * integ(rb * (rs - hh * cos_t))
    zero = ~touch
    out = []
    for a in (fx * d, fz, fy, torque * d):
        a = np.where(zero, 0.0, a)
        out.append(a.reshape(shape))
    return ContactForces(
        drawbar_pull=out[0],
        normal=out[1],
        lateral=out[2],
        torque=out[3],
        slip=s.reshape(shape),
        theta_f=np.where(zero, 0.0, tf).reshape(shape),
        theta_r=np.where(zero, 0.0, tr).reshape(shape),
        theta_m=np.where(zero, 0.0, tm).reshape(shape),
        shear_exit=np.where(zero, 0.0, jx[:, 0] * d).reshape(shape),
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
    prior=None,
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
