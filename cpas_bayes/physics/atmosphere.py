"""U.S. Standard Atmosphere 1976, lower seven layers (0 to 84.852 km geopotential).

Pure numpy, vectorised over any array of altitudes. SI throughout.

Each layer b has a base geopotential altitude H_b, a base temperature T_b and a
lapse rate L_b (K/m). Inside the layer::

    T = T_b + L_b·(H − H_b)
    p = p_b · (T_b / T)^(g0/(R·L_b))              L_b ≠ 0
    p = p_b · exp(−g0·(H − H_b)/(R·T_b))          L_b = 0
    ρ = p / (R·T)

with g0 = 9.80665 m/s², R = 287.05287 J/(kg·K) (R*/M0 of the 1976 model),
T_0 = 288.15 K, p_0 = 101325 Pa. In the troposphere this is the familiar
T = 288.15 − 0.0065·H, p = 101325·(T/288.15)^5.25588.

Altitude convention. The 1976 tables are functions of geopotential altitude
H = r0·z/(r0 + z) (r0 = 6,356,766 m, z geometric). ``standard_atmosphere``
takes ``geopotential=True`` by default, i.e. it puts the given altitude
straight into the layer formulas. That is the convention of the simulator that
made the example bundles (their density column matches it to 3e-5, and misses
the geometric conversion by 7e-4) and of most trajectory codes at parachute
altitudes, where the two differ by less than 0.1 % in density below 10 km.
Pass ``geopotential=False`` to treat the input as geometric altitude, as in
the tables indexed by geometric height (e.g. ρ(z = 20 km) = 0.08891 kg/m³,
while ρ(H = 20 km) = 0.08803 kg/m³).
"""

from __future__ import annotations

import numpy as np

from cpas_bayes.core.units import STANDARD_GRAVITY

GAS_CONSTANT_AIR = 287.05287   # J/(kg·K), R*/M0 of the 1976 standard
EARTH_RADIUS = 6_356_766.0     # m, r0 used by the 1976 standard for geopotential altitude
SEA_LEVEL_TEMPERATURE = 288.15  # K
SEA_LEVEL_PRESSURE = 101_325.0  # Pa
SEA_LEVEL_DENSITY = SEA_LEVEL_PRESSURE / (GAS_CONSTANT_AIR * SEA_LEVEL_TEMPERATURE)  # 1.2250 kg/m³

# Base geopotential altitude (m) and lapse rate (K/m) of the seven layers.
_LAYER_BASE = np.array([0.0, 11_000.0, 20_000.0, 32_000.0, 47_000.0, 51_000.0, 71_000.0])
_LAYER_LAPSE = np.array([-0.0065, 0.0, 0.0010, 0.0028, 0.0, -0.0028, -0.0020])
TOP_GEOPOTENTIAL_ALTITUDE = 84_852.0  # m, where the lower atmosphere model ends


def _layer_pressure_ratio(dh, base_temperature, lapse):
    """p/p_b after climbing ``dh`` (≥ 0) within a layer, both lapse cases."""
    lapse = np.asarray(lapse, float)
    gradient = lapse != 0
    safe_lapse = np.where(gradient, lapse, 1.0)
    temperature = base_temperature + lapse * dh
    with_gradient = (base_temperature / temperature) ** (STANDARD_GRAVITY / (GAS_CONSTANT_AIR * safe_lapse))
    isothermal = np.exp(-STANDARD_GRAVITY * dh / (GAS_CONSTANT_AIR * base_temperature))
    return np.where(gradient, with_gradient, isothermal)


def _layer_bases():
    """Base temperatures and pressures of every layer, chained from sea level."""
    temperatures = [SEA_LEVEL_TEMPERATURE]
    pressures = [SEA_LEVEL_PRESSURE]
    for b in range(len(_LAYER_BASE) - 1):
        dh = _LAYER_BASE[b + 1] - _LAYER_BASE[b]
        temperatures.append(temperatures[-1] + _LAYER_LAPSE[b] * dh)
        pressures.append(pressures[-1] * float(_layer_pressure_ratio(dh, temperatures[-2], _LAYER_LAPSE[b])))
    return np.array(temperatures), np.array(pressures)


_LAYER_TEMPERATURE, _LAYER_PRESSURE = _layer_bases()
# The same constants as Python floats for the single-layer fast path.
_BASES, _LAPSES = _LAYER_BASE.tolist(), _LAYER_LAPSE.tolist()
_BASE_TEMPERATURES, _BASE_PRESSURES = _LAYER_TEMPERATURE.tolist(), _LAYER_PRESSURE.tolist()


def geopotential_altitude(z_m):
    """H = r0·z/(r0 + z): geopotential altitude of a geometric altitude ``z_m`` (m)."""
    z = np.asarray(z_m, float)
    return EARTH_RADIUS * z / (EARTH_RADIUS + z)


def standard_atmosphere(h_m, geopotential=True):
    """Density (kg/m³), pressure (Pa) and temperature (K) at altitude ``h_m`` (m).

    Vectorised over any shape. ``geopotential`` says whether ``h_m`` is
    geopotential altitude (default, see the module notes) or geometric.
    Altitudes below sea level extrapolate the troposphere (valid to about
    −5 km); above 84.852 km geopotential a ValueError is raised.
    """
    h = np.asarray(h_m, float)
    if not geopotential:
        h = geopotential_altitude(h)
    if h.size and h.max() > TOP_GEOPOTENTIAL_ALTITUDE:
        raise ValueError(f"altitude above {TOP_GEOPOTENTIAL_ALTITUDE:.0f} m geopotential is outside the "
                         "1976 lower-atmosphere layers")
    layer = np.searchsorted(_LAYER_BASE, h, side="right") - 1
    lowest, highest = int(layer.min(initial=0)), int(layer.max(initial=0))
    if lowest == highest or (lowest == -1 and highest == 0):
        # Whole array in one layer (the usual case along a trajectory): scalar
        # layer constants and one branch of the pressure law, much faster.
        b = max(highest, 0)
        base_temperature, lapse = _BASE_TEMPERATURES[b], _LAPSES[b]
        temperature = base_temperature + lapse * (h - _BASES[b])
        if lapse != 0.0:
            ratio = (base_temperature / temperature) ** (STANDARD_GRAVITY / (GAS_CONSTANT_AIR * lapse))
        else:
            ratio = np.exp(-STANDARD_GRAVITY * (h - _BASES[b]) / (GAS_CONSTANT_AIR * base_temperature))
        pressure = _BASE_PRESSURES[b] * ratio
    else:
        layer = np.clip(layer, 0, len(_LAYER_BASE) - 1)
        dh = h - _LAYER_BASE[layer]
        base_temperature = _LAYER_TEMPERATURE[layer]
        lapse = _LAYER_LAPSE[layer]
        temperature = base_temperature + lapse * dh
        pressure = _LAYER_PRESSURE[layer] * _layer_pressure_ratio(dh, base_temperature, lapse)
    density = pressure / (GAS_CONSTANT_AIR * temperature)
    return density, pressure, temperature


def standard_density(h_m, geopotential=True):
    """Density only (kg/m³); see :func:`standard_atmosphere`."""
    return standard_atmosphere(h_m, geopotential)[0]
