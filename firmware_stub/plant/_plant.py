"""The plant object: the readable API over the compiled kernel (firmware_stub.plant._kernel); its randomness.

The model, its integration and its random streams: the package docstring (firmware_stub/plant/__init__.py)."""

from __future__ import annotations

import math
import random
from collections.abc import Iterable
from typing import Any

import numpy as np

from firmware_stub.plant._config import (
    D2R,
    R2D,
    TICK_S,
    ImbalanceConfig,
    PlantConfig,
    Vec3f,
)
from firmware_stub.plant._kernel import (
    MAX_BANDS,
    NOISE_BLOCK_TICKS,
    NOISE_WHITE,
    P_DELAY,
    P_LEN,
    P_STRIDE,
    PA_LEN,
    PA_RIPN,
    RUN_COLUMNS,
    RUN_INDEX,
    S_CAMN,
    S_M,
    S_REFILL,
    S_RING,
    S_RIP,
    S_SC,
    S_TICK,
    S_X,
    TRUTH_KEYS,
    kernel,
    pack_params,
)
from firmware_stub.plant._math import CarrierMotion, normal_table

__all__ = [
    "Plant",
    "imbalance_torques",
]


# --- configuration -------------------------------------------------------------------------------------------------


# --- carrier input -------------------------------------------------------------------------------------------------


# --- discretisation (construction only) ----------------------------------------------------------------------------


# --- Gaussian noise by table lookup --------------------------------------------------------------------------------


# --- the compiled kernel ---------------------------------------------------------------------------------------------
# Plain functions over float64 arrays (p: parameters, s: state, nz: the current noise block); numba compiles them on
# first use and caches the machine code (cache=True) next to this file. No Python objects inside.


# --- the plant -----------------------------------------------------------------------------------------------------


def _python_mt(seed: int | str) -> np.random.MT19937:
    """numpy's MT19937 in the state of ``random.Random(seed)``: its 32-bit words are those ``random.Random(seed)``
    would give, so ``random_raw(n)`` as little-endian uint32 bytes is ``random.Random(seed).randbytes(4 n)`` (a test
    checks this), ~10x faster."""
    state = random.Random(seed).getstate()[1]
    bg = np.random.MT19937()
    bg.state = {"bit_generator": "MT19937", "state": {"key": np.array(state[:624], dtype=np.uint32),
                                                      "pos": state[624]}}
    return bg


def _random_u16(bg: np.random.MT19937, n: int) -> np.ndarray:
    """``n`` 16-bit numbers (n even): ``randbytes(2 n)`` read as little-endian uint16, on any platform."""
    return bg.random_raw(n // 2).astype("<u4").view("<u2").astype(np.uint16)


class Plant:
    """The emulated gimbal on its hexapod. See the module docstring and docs/emulator.md.

    ``step_tick(u_az_counts, u_el_counts, carrier)`` advances 1 ms (one compiled call); the outputs (``gyro_dps``,
    ``encoders_deg``, ``currents_a``, ``miss_px``, ``truth``) describe the instant ``t_s`` reached, as plain Python
    floats. :meth:`run` advances many ticks in one compiled call and returns arrays. All randomness comes from
    ``random.Random(seed)`` (and ``random.Random(f"{seed}/gyro-extra")`` for coloured noise and random walk): every
    tick uses five 16-bit random numbers (3 gyro, 2 camera), each an index into a table of normal quantiles, drawn in
    blocks of 1000 ticks; the sequence does not depend on which outputs are read.
    """

    TICK_S = TICK_S

    def __init__(self, config: PlantConfig, seed: int) -> None:
        self.config = config
        self.seed = seed
        self.n_sub = round(TICK_S / config.internal_step_s)
        p = pack_params(config)
        self._delay_ticks = int(p[P_DELAY])
        self._stride = int(p[P_STRIDE])
        # one buffer: parameters, state, noise block (views of it; the per-tick kernel call takes the buffer)
        ns = S_RING + 3 * self._delay_ticks
        self._buf = np.zeros(P_LEN + ns + NOISE_BLOCK_TICKS * self._stride)
        self._p, self._s, self._nz = np.split(self._buf, [P_LEN, P_LEN + ns])
        self._p[:] = p
        self._table = np.frombuffer(normal_table(), dtype=np.float64)
        g = config.gyro
        unit = g.quantisation_lsb_dps or 1.0  # the kernel works in gyro LSBs (see pack_params)
        sn = config.camera.centroid_noise_std_px
        self._offsets = np.array([*(b / unit for b in g.bias_dps), 0.0, 0.0])
        self._scales = np.array([*(x / unit for x in g.noise_std_dps), sn, sn])
        self._ones, self._zeros = np.ones(3 * MAX_BANDS + 3), np.zeros(3 * MAX_BANDS + 3)
        self._tick = kernel("tick")
        self._out: tuple[float, ...] = ()
        self.reset()

    def reset(self) -> None:
        """Back to the initial state: angles from the config, at rest, the random sequences restarted."""
        cfg = self.config
        self._rng = _python_mt(self.seed)
        self._rng_extra = _python_mt(f"{self.seed}/gyro-extra")
        s = self._s
        s[:] = 0.0
        az, el = cfg.initial_az_deg * D2R, cfg.initial_el_deg * D2R
        s[S_X + 2] = s[S_X + 4] = az
        s[S_X + 7] = s[S_X + 9] = el
        s[S_SC], s[S_SC + 1], s[S_SC + 2], s[S_SC + 3] = math.sin(az), math.cos(az), math.sin(el), math.cos(el)
        na, ne = self._p[PA_RIPN], self._p[PA_LEN + PA_RIPN]
        s[S_RIP: S_RIP + 4] = (math.sin(na * az), math.cos(na * az), math.sin(ne * el), math.cos(ne * el))
        s[S_M: S_M + 3] = [self._quantise(b) for b in cfg.gyro.bias_dps]
        self._refill_noise()
        self._out = kernel("outputs")(self._p, s, 0.0)

    @property
    def t_s(self) -> float:
        """Simulated time reached, s."""
        return int(self._s[S_TICK]) * TICK_S

    def _refill_noise(self) -> None:
        """The next block of noise, per tick: gyro x, y, z (bias + std * N(0, 1), output units) and camera x, y
        (std * N(0, 1), px), then the unit normals of the coloured bands and the random walk. Each N(0, 1) is a
        normal quantile picked by 16 random bits (little-endian pairs of bytes, so any platform draws the same)."""
        n = NOISE_BLOCK_TICKS
        fill = kernel("fill")
        fill(self._nz, self._stride, 0, NOISE_WHITE, _random_u16(self._rng, NOISE_WHITE * n), self._table,
             self._scales, self._offsets)
        extra = self._stride - NOISE_WHITE
        if extra:
            fill(self._nz, self._stride, NOISE_WHITE, extra, _random_u16(self._rng_extra, extra * n), self._table,
                 self._ones[:extra], self._zeros[:extra])
        self._s[S_REFILL] = 0.0

    def _quantise(self, x: float) -> float:
        lsb = self.config.gyro.quantisation_lsb_dps
        return round(x / lsb) * lsb if lsb > 0 else x

    def step_tick(self, u_az_counts: float, u_el_counts: float, carrier: CarrierMotion,
                  drive_delay_s: float = 0.0) -> None:
        """Advance one 1 ms tick; ``carrier`` is evaluated at mid-tick. The drive (DAC counts) takes over from the last
        tick's ``drive_delay_s`` after the tick's start (0: over the whole tick; the wire's and the host's delay,
        docs/emulator.md "The wire"; clipped to the tick) and holds until the next tick's drive takes over."""
        at = drive_delay_s / TICK_S
        try:
            pose, rate, accel = carrier
            out = self._tick(self._buf, u_az_counts, u_el_counts, at, pose, rate, accel)
        except (TypeError, ValueError):  # not floats / tuples of 6 (nothing was stepped): convert, or say why
            out = self._tick(self._buf, float(u_az_counts), float(u_el_counts), float(at), *_carrier_tuples(carrier))
        self._out = out
        if out[7]:
            self._refill_noise()

    def run(self, u_az_counts: Any, u_el_counts: Any, carrier: Any,
            outputs: Iterable[str] | None = None, drive_delay_s: float = 0.0) -> dict[str, np.ndarray]:
        """Advance ``n`` ticks in one compiled loop (offline use: fitting, benchmarks): the same physics, noise and
        final state as ``n`` calls of :meth:`step_tick` (bit for bit; tested), so the two can be mixed.

        ``u_az_counts``, ``u_el_counts``: arrays ``(n,)`` of drive counts, held over each tick; ``carrier``: array
        ``(n, 18)``, per tick the CarrierMotion's ``pose + rate + accel`` at mid-tick (mm, deg, mm/s, deg/s, mm/s^2,
        deg/s^2). Returns arrays ``(n,)`` at each tick end: ``t_s`` and :data:`RUN_COLUMNS` (gyro x/y/z in deg/s,
        encoders in deg, currents in A, LOS error in deg, miss x/y in px with centroid noise, ``track_valid``
        (bool), true LOS rates in deg/s, load angles az/el in deg, armature voltages in V). ``outputs``: the names of
        the columns to compute and return (default: all); the physics, the noise and the state do not depend on it,
        only the time spent (without the LOS error and camera columns: no atan2, hypot, sin / cos of the yaw).
        ``drive_delay_s``: each tick's drive takes over from the last one's this long after the tick's start, as in
        :meth:`step_tick`.
        """
        u_a = np.ascontiguousarray(u_az_counts, dtype=np.float64)
        u_e = np.ascontiguousarray(u_el_counts, dtype=np.float64)
        car = np.ascontiguousarray(carrier, dtype=np.float64)
        n = u_a.shape[0]
        if u_a.shape != (n,) or u_e.shape != (n,) or car.shape != (n, 18):
            raise ValueError(f"run: need u_az_counts (n,), u_el_counts (n,), carrier (n, 18); got {u_a.shape}, "
                             f"{u_e.shape}, {car.shape}")
        if not (np.all(np.isfinite(u_a)) and np.all(np.isfinite(u_e)) and np.all(np.isfinite(car))):
            raise ValueError("run: inputs must be finite")
        if not 0.0 <= drive_delay_s <= TICK_S:
            raise ValueError(f"run: drive_delay_s must be within the tick, 0 to {TICK_S} s; got {drive_delay_s!r}")
        names = RUN_COLUMNS if outputs is None else tuple(dict.fromkeys(outputs))
        rows = np.full(len(RUN_COLUMNS), -1, dtype=np.int64)
        for i, name in enumerate(names):
            if name not in RUN_INDEX:
                raise ValueError(f"run: unknown output {name!r}; the outputs are {', '.join(RUN_COLUMNS)}")
            rows[RUN_INDEX[name]] = i
        out = np.empty((len(names), n))
        tick0 = int(self._s[S_TICK])
        step = kernel("run")
        k = 0
        while k < n:
            k = step(self._p, self._s, self._nz, u_a, u_e, drive_delay_s / TICK_S, car, out, rows, k)
            if self._s[S_REFILL]:
                self._refill_noise()
        self._out = kernel("outputs")(self._p, self._s, 0.0)
        res = {"t_s": (tick0 + np.arange(1, n + 1)) * TICK_S}
        for i, name in enumerate(names):
            res[name] = out[i] > 0.5 if name == "track_valid" else out[i]  # contiguous rows of one array
        return res

    # -- outputs --

    def gyro_dps(self) -> tuple[float, float, float]:
        """Measured rates (x about the LOS, y elevation axis, z cross-elevation) at ``t_s``: filtered, delayed,
        noisy, biased, quantised. The noise is drawn once per tick."""
        o = self._out
        return (o[0], o[1], o[2])

    def encoders_deg(self) -> tuple[float, float]:
        """Azimuth (wrapped to [-180, 180)) and elevation angles of the motor side relative to the carrier (the load
        side without ``structure``), quantised to the encoder."""
        o = self._out
        return (o[3], o[4])

    def currents_a(self) -> tuple[float, float]:
        """Armature currents (A), azimuth and elevation."""
        o = self._out
        return (o[5], o[6])

    def los_error_deg(self) -> tuple[float, float, float]:
        """Exact LOS error ``(x, y, in_front)`` at ``t_s``: the angles (deg) the LOS must turn about z_e (+ = target
        right) and about y_e (sign flipped, so + = target up) to reach the target, and the target direction's
        x_e component (> 0: in front of the camera)."""
        return kernel("los")(self._buf)

    def miss_px(self) -> tuple[float, float, bool]:
        """Miss distance (px, + = target right / up) with centroid noise, and track_valid, at ``t_s``."""
        cam = self.config.camera
        ex, ey, front = self.los_error_deg()
        x = ex / cam.ifov_deg_per_px + self._s.item(S_CAMN)
        y = ey / cam.ifov_deg_per_px + self._s.item(S_CAMN + 1)
        valid = front > 0.0 and abs(x) <= cam.half_width_px and abs(y) <= cam.half_height_px
        return (x, y, valid)

    def los_rate_dps(self) -> tuple[float, float, float]:
        """The true (noise-free, unfiltered, undelayed) LOS rates x, y, z (deg/s) at ``t_s``: :meth:`truth`'s first
        three values without building its dict (a per-tick recorder's cost)."""
        v = kernel("truth")(self._p, self._s)
        return (v[0] * R2D, v[1] * R2D, v[2] * R2D)

    def truth(self) -> dict[str, float]:
        """True (noise-free) values at ``t_s``. Torques (N m) are those acting on the axis; rates in deg/s. ``az_deg``,
        ``el_deg`` and the rates without ``motor`` are the load's (what the LOS, the gyro and the imbalance see);
        ``*_motor_*`` the motor side's (the encoder's); they are equal without ``structure``."""
        values = kernel("truth")(self._p, self._s)
        out = {"t_s": self.t_s}
        for (key, scale), v in zip(TRUTH_KEYS, values, strict=True):
            out[key] = v * scale if scale != 1.0 else v
        return out


def _carrier_tuples(carrier: Any) -> tuple[tuple[float, ...], ...]:
    """The carrier as three tuples of 6 floats, or ValueError naming what is wrong."""
    try:
        parts = tuple(tuple(float(x) for x in part) for part in carrier)
    except (TypeError, ValueError):
        raise ValueError("carrier: need (pose, rate, accel), each 6 numbers") from None
    if len(parts) != 3 or any(len(part) != 6 for part in parts):
        raise ValueError("carrier: need (pose, rate, accel), each 6 numbers")
    return parts


def imbalance_torques(imb: ImbalanceConfig, f_body: Vec3f, az_rad: float, el_rad: float) -> tuple[float, float]:
    """Imbalance torques (N m) acting on the azimuth (about z_o) and elevation (about y_e) axes: ``-m rho x f`` with
    ``f`` the specific force (m/s^2, body frame) expressed in the elevation frame (seed 001 eqs 3-4)."""
    rx, ry, rz = (x * 1e-3 for x in imb.eccentricity_mm)
    m = imb.mass_kg
    ca, sa = math.cos(az_rad), math.sin(az_rad)
    ce, se = math.cos(el_rad), math.sin(el_rad)
    fbx, fby, fbz = f_body
    hxy = ca * fbx + sa * fby
    fx, fy, fz = hxy * ce - fbz * se, ca * fby - sa * fbx, hxy * se + fbz * ce
    tx, ty, tz = -m * (ry * fz - rz * fy), -m * (rz * fx - rx * fz), -m * (rx * fy - ry * fx)
    return ce * tz - se * tx, ty
