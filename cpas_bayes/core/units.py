"""Unit systems of a bundle and their conversion to the internal system (SI).

Everything inside the package is SI (N, m, m², m/s, Pa, kg/m³, s); angles are
degrees in tables and radians inside formulas. A bundle says ``units = "US"``
or ``"SI"``; values are converted on reading and converted back for a user's
outputs, so a US bundle gives US results.

The factors come from pint's unit definitions rather than hand-typed numbers;
no pint quantity is carried through numerical code. pint and its registry
(0.4 s to import and parse, in every process) are loaded on the first
conversion that needs them: SI's factors are 1 by definition, so a run on an
SI bundle never loads them.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field


@functools.cache
def _registry():
    import pint

    return pint.UnitRegistry()

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
    if names == _SI:
        return dict.fromkeys(_SI, 1.0)
    ureg = _registry()
    return {q: float(ureg.Quantity(1.0, u).to(_SI[q]).magnitude) for q, u in names.items()}


@dataclass(frozen=True)
class UnitSystem:
    """A bundle's unit system: factors that multiply its values into SI (``to_si``, computed on first use)."""

    name: str
    units: dict = field(repr=False)

    @functools.cached_property
    def to_si(self):
        return _factors(self.units)

    def si(self, value, quantity):
        """Convert ``value`` in this system's ``quantity`` unit to SI."""
        return value * self.to_si[quantity]

    def from_si(self, value, quantity):
        """Convert an SI ``value`` back to this system."""
        return value / self.to_si[quantity]

    def label(self, quantity):
        """Unit label for axis titles and tables, e.g. ``'lbf'``."""
        return _LABELS[self.name][quantity]


UNIT_SYSTEMS = {"US": UnitSystem("US", _US), "SI": UnitSystem("SI", _SI)}


def unit_system(name):
    """The :class:`UnitSystem` called ``name`` (``"US"`` or ``"SI"``); KeyError otherwise."""
    return UNIT_SYSTEMS[name]


# Quantities a logger's column may carry (cpas-bayes import) and the SI unit each is converted to; angles go to
# degrees, the unit of the bundle's angle columns.
_COLUMN_SI = {**_SI, "acceleration": "m/s**2", "angle": "degree"}
# Spellings pint reads otherwise: "g" is the gram to pint, but a load factor to a logger.
_ALIASES = {("acceleration", "g"): "standard_gravity", ("acceleration", "G"): "standard_gravity",
            ("pressure", "psf"): "lbf/ft**2"}
_NAME = r"[A-Za-zµ°_]+(\s*(\^|\*\*)\s*-?\d+)?"
_UNIT_TEXT = re.compile(rf"{_NAME}(\s*[*/]\s*{_NAME})*")


def column_factor(unit, quantity):
    """The factor that multiplies a value in ``unit`` (pint's spelling, e.g. ``"ft/s^2"``, ``"kn"``) into SI.

    ``quantity`` is one of :data:`_COLUMN_SI`'s keys; acceleration accepts
    ``"g"`` (standard gravity, 9.80665 m/s²) and angles convert to degrees.
    ``unit`` is unit names with integer powers joined by ``*`` or ``/``, no
    numbers (``"1000*m"`` is not a unit). A ValueError says why a unit is
    refused: not of that form, unknown to pint, or of another dimension than
    ``quantity`` (``"m"`` for a speed).
    """
    if quantity not in _COLUMN_SI:
        raise ValueError(f"unknown quantity {quantity!r}")
    text = unit.strip() if isinstance(unit, str) else ""
    if not _UNIT_TEXT.fullmatch(text):
        raise ValueError(f"{unit!r} is not a unit (unit names with integer powers joined by '*' or '/', "
                         "e.g. 'm/s^2')")
    name = _ALIASES.get((quantity, text), text)
    ureg = _registry()
    import pint

    try:
        return float(ureg.Quantity(1.0, name).to(_COLUMN_SI[quantity]).magnitude)
    except pint.errors.DimensionalityError:
        raise ValueError(f"{unit!r} is not a unit of {quantity}") from None
    except (pint.errors.PintError, AttributeError, TypeError, ValueError, ZeroDivisionError):
        raise ValueError(f"{unit!r} is not a unit pint knows") from None
