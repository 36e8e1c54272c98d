"""Unit systems of a bundle and their conversion to the internal system (SI).

Everything inside the package is SI (N, m, m², m/s, Pa, kg/m³, s); angles are
degrees in tables and radians inside formulas. A bundle says ``units = "US"``
or ``"SI"``; values are converted on reading and converted back for a user's
outputs, so a US bundle gives US results.

The factors come from pint's unit definitions rather than hand-typed numbers,
once at import; no pint quantity is carried through numerical code.
"""

from __future__ import annotations

from dataclasses import dataclass

import pint

_ureg = pint.UnitRegistry()

STANDARD_GRAVITY = 9.80665  # m/s², the g that converts a load factor to acceleration

# Physical quantity -> unit name in each system.
_US = {"force": "lbf", "length": "ft", "area": "ft**2", "speed": "ft/s",
       "pressure": "lbf/ft**2", "density": "slug/ft**3", "mass": "slug", "time": "s"}
_SI = {"force": "N", "length": "m", "area": "m**2", "speed": "m/s",
       "pressure": "Pa", "density": "kg/m**3", "mass": "kg", "time": "s"}

_LABELS = {
    "US": {"force": "lbf", "length": "ft", "area": "ft²", "speed": "ft/s",
           "pressure": "lbf/ft²", "density": "slug/ft³", "mass": "slug", "time": "s"},
    "SI": {"force": "N", "length": "m", "area": "m²", "speed": "m/s",
           "pressure": "Pa", "density": "kg/m³", "mass": "kg", "time": "s"},
}


def _factors(names):
    return {q: float(_ureg.Quantity(1.0, u).to(_SI[q]).magnitude) for q, u in names.items()}


@dataclass(frozen=True)
class UnitSystem:
    """A bundle's unit system: factors that multiply its values into SI."""

    name: str
    to_si: dict

    def si(self, value, quantity):
        """Convert ``value`` in this system's ``quantity`` unit to SI."""
        return value * self.to_si[quantity]

    def from_si(self, value, quantity):
        """Convert an SI ``value`` back to this system."""
        return value / self.to_si[quantity]

    def label(self, quantity):
        """Unit label for axis titles and tables, e.g. ``'lbf'``."""
        return _LABELS[self.name][quantity]


UNIT_SYSTEMS = {"US": UnitSystem("US", _factors(_US)), "SI": UnitSystem("SI", _factors(_SI))}


def unit_system(name):
    """The :class:`UnitSystem` called ``name`` (``"US"`` or ``"SI"``); KeyError otherwise."""
    return UNIT_SYSTEMS[name]
