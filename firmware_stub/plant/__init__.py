"""Physics model ("plant") of the emulated gimbal: two DC torque-motor axes on a hexapod, gyro, encoders, camera.

Model (docs/emulator.md, "The plant"; seed 000 = Wang et al. 2023, seed 001 = Zhang & Shi, seed 004 = Zhang et al.):

* each axis (az, el): armature ``L di/dt = V - R i - K_e w_rel`` (seed 000 eq 35), torque ``K_t i`` (eq 36), rigid
  load ``J dw/dt = K_t i - T_f(w_rel) + T_imb`` (eqs 33-34 with ``theta_m = theta_L``); ``w`` is the axis' inertial
  rate about its own axis, ``w_rel = w - c`` its rate relative to the carrier (``c`` = carrier rate projected on the
  axis; seed 004 eqs 4-9 style), what friction, back-EMF and the encoder see. ``k_m = K_t V_count / (J R)`` (eq 38);
* friction ``T_f = T_c tanh(w_rel / w_s) + D w_rel``; mass imbalance ``T = -m rho x f`` (seed 001 eq 4), ``f`` the
  carrier's specific force in the elevation frame;
* gyro (seed 000 eq 3): ``k_a w_c / (s + w_c) e^{-T_d s}`` on the elevation-frame inertial rates, + white noise,
  bias, quantisation, sampled each 1 ms tick; encoders quantised; camera miss distance in pixels.

Optional mechanisms ("plant v2"), each off unless its YAML key is present (docs/emulator.md, "Mechanisms"):

* ``structure.<axis>``: two-mass compliance (seed 000 eqs 33-34 with a finite shaft stiffness). The axis' inertia J
  is split into a motor side ``J_m = f J`` and a load side ``J_l = (1 - f) J`` joined by a torsion spring ``k`` and
  damper ``c_s``; from the free-free mode ``w_r = 2 pi mode_hz = sqrt(k / mu)``, ``mu = J_m J_l / J``:
  ``k = w_r^2 mu``, ``c_s = 2 zeta w_r mu``::

      J_m dw_m/dt = K_t i (1 + ripple) - T_f(w_m - c) - k_c theta_m - c_c (w_m - c) - k (theta_m - theta_l)
                    - c_s (w_m - w_l)
      J_l dw_l/dt = k (theta_m - theta_l) + c_s (w_m - w_l) + T_imb
      d theta_m/dt = w_m - c,   d theta_l/dt = w_l - c

  Motor side (collocated with the motor): motor torque and its ripple, back-EMF (``K_e (w_m - c)``), bearing
  friction (tanh or LuGre), the cable harness and the **encoder**. Load side: the mass imbalance, the **gyro** and
  the **camera** (the LOS is the load's). Without ``structure`` both sides are one rigid body (``theta_m = theta_l``).
* ``friction.<axis>.model: lugre``: LuGre friction (Canudas de Wit et al., IEEE TAC 40(3), 1995) on the motor-side
  relative rate ``v``: ``dz/dt = v - sigma_0 |v| z / g(v)``, ``g(v) = T_c + (T_s - T_c) exp(-(v / v_s)^2)``,
  ``T_f = sigma_0 z + sigma_1 dz/dt + D v``; z is updated implicitly (``z' = (z + h v) / (1 + h sigma_0 |v| / g)``),
  stable for any step: true stiction (no creep below breakaway), bounded presliding.
* ``drive.<axis>.current_limit_a``: the driver's current limit, ``|i| <= I_max`` (torque authority ``K_t I_max``).
* ``cable.<axis>``: harness spring and damper on the motor-side relative angle, ``-k_c theta_m - c_c (w_m - c)``
  (neutral at encoder zero).
* ``mount.pivot_offset_m``: the gimbal's pivot at ``r`` (body frame) from the hexapod's rotation centre; the
  imbalance feels ``f_pivot = f_centre + alpha x r + omega x (omega x r)`` (seed 001 eqs 2-4).
* ``gyro.noise_psd``: coloured gyro noise, each ``{centre_hz, bandwidth_hz, std_dps}`` a second-order digital
  band-pass (the bilinear peak filter of ``scipy.signal.iirpeak``) of its own white noise, per axis;
  ``gyro.random_walk``: rate random walk of the bias (deg/s per sqrt(s)).
* ``ripple.<axis>``: motor torque ripple ``K_t i (1 + a sin(N theta_m))`` (current-proportional ripple at N periods
  per revolution of the motor-side relative angle; cogging proper, a torque independent of the current, is not
  modelled).

Frames: carrier body x forward, y right, z down; gimbal at ``az = el = 0`` aligned with the body; ``az`` about
``z_b``, ``el`` about ``y_o``; the LOS is ``x_e``. Positive az turns the LOS right, positive el raises it.

Integration: exact zero-order-hold discretisation of the linear part (current, motor and load rates and angles,
back-EMF, viscous friction, shaft, cable) at the internal step, by the matrix exponential at construction; drive,
carrier rate and imbalance torque held over the tick (the carrier is given at mid-tick), friction (tanh or LuGre) and
ripple over each sub-step; the current limit as a fast current loop (a sub-step whose update would exceed the limit
is redone with the voltage that holds ``di/dt = 0`` at the limit). The gyro filter is discretised exactly at the tick
for an input linear between tick ends (first-order hold), the delay evaluated exactly inside the tick plus whole
ticks from a ring.

The hot path is a numba kernel (``@numba.njit(cache=True)``: compiled once, cached in
``firmware_stub/plant/__pycache__``) over float64 arrays of parameters and state (``_kernel``); :class:`Plant`
(``_plant``) is the readable API around it, the YAML's models are ``_config``, the math done once at construction
``_math``. ``Plant.step_tick`` makes one compiled call per tick; :meth:`Plant.run` loops many ticks inside one
compiled call (offline use: fitting, benchmarks).

Randomness (reproducible across platforms): the bytes of ``random.Random(seed).randbytes``, drawn in blocks of 1000
ticks (by numpy's MT19937 put in that generator's state: the same 32-bit words, ~10x faster); each Gaussian is one of
2^16 normal quantiles picked by 16 little-endian random bits. The white gyro and camera noise sequence is the one of
the pure-Python plant before the kernel. The coloured noise and random walk draw from a second stream,
``random.Random(f"{seed}/gyro-extra")``, so switching them on leaves the white noise unchanged.

This package imports nothing from ``hil`` (``firmware_stub`` may only use ``hil.protocol``).
"""

from firmware_stub.plant._config import (
    DEFAULT_PLANT_CONFIG,
    RIGID_PLANT_CONFIG,
    CableAxisConfig,
    CableConfig,
    CameraConfig,
    DriveAxisConfig,
    DriveConfig,
    EncoderConfig,
    FrictionAxisConfig,
    FrictionConfig,
    GyroConfig,
    GyroNoiseBand,
    HexapodConfig,
    ImbalanceConfig,
    MotorConfig,
    MountConfig,
    PlantConfig,
    PlantConfigError,
    RippleAxisConfig,
    RippleConfig,
    StructureAxisConfig,
    StructureConfig,
    load_plant_config,
)
from firmware_stub.plant._kernel import RUN_COLUMNS, kernel
from firmware_stub.plant._math import (
    CarrierMotion,
    attitude_at_tick_end,
    axis_matrices,
    axis_zoh,
    band_pass,
    carrier_state,
)
from firmware_stub.plant._plant import Plant, imbalance_torques

__all__ = [
    "DEFAULT_PLANT_CONFIG",
    "RIGID_PLANT_CONFIG",
    "RUN_COLUMNS",
    "CableAxisConfig",
    "CableConfig",
    "CameraConfig",
    "CarrierMotion",
    "DriveAxisConfig",
    "DriveConfig",
    "EncoderConfig",
    "FrictionAxisConfig",
    "FrictionConfig",
    "GyroConfig",
    "GyroNoiseBand",
    "HexapodConfig",
    "ImbalanceConfig",
    "MotorConfig",
    "MountConfig",
    "Plant",
    "PlantConfig",
    "PlantConfigError",
    "RippleAxisConfig",
    "RippleConfig",
    "StructureAxisConfig",
    "StructureConfig",
    "attitude_at_tick_end",
    "axis_matrices",
    "axis_zoh",
    "band_pass",
    "carrier_state",
    "imbalance_torques",
    "kernel",
    "load_plant_config",
]
