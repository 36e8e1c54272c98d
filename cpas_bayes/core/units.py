"""Unit systems of a bundle and their conversion to the internal system (SI).

Everything inside the package is SI (N, m, m², m/s, Pa, kg/m³, s); angles are
degrees in tables and radians inside formulas. A bundle says ``units = "US"``
or ``"SI"``; values are converted on reading and converted back for a user's
outputs, so a US bundle gives US results.

The two systems' factors follow from three exact definitions — the
international foot (0.3048 m) and pound (0.45359237 kg) of 1959, and standard
gravity (9.80665 m/s², so 1 lbf = 0.45359237·9.80665 N) — so they are written
from those, and a test checks that pint derives the same to 1e-14. pint
parses the free-form units of a logger's columns (:func:`column_factor`, the
import maps), where it does a job hand-written code would not; it and its
registry (0.4 s to import and parse) load only then.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

STANDARD_GRAVITY = 9.80665  # m/s², the g that converts a load factor to acceleration
FOOT = 0.3048               # m, exact (international yard and pound, 1959)
POUND_MASS = 0.45359237     # kg, exact (the same agreement)
POUND_FORCE = POUND_MASS * STANDARD_GRAVITY     # N
SLUG = POUND_FORCE / FOOT                       # kg: the mass 1 lbf accelerates at 1 ft/s²


@functools.cache
def _registry():
    import pint

    return pint.UnitRegistry()


# Physical quantity -> unit name in each system (pint's spelling, for the test that checks the factors).
_US = {"force": "lbf", "length": "ft", "area": "ft**2", "speed": "ft/s",
       "pressure": "lbf/ft**2", "density": "slug/ft**3", "mass": "slug", "time": "s"}
_SI = {"force": "N", "length": "m", "area": "m**2", "speed": "m/s",
       "pressure": "Pa", "density": "kg/m**3", "mass": "kg", "time": "s"}
_US_TO_SI = {"force": POUND_FORCE, "length": FOOT, "area": FOOT**2, "speed": FOOT,
             "pressure": POUND_FORCE / FOOT**2, "density": SLUG / FOOT**3, "mass": SLUG, "time": 1.0}

_LABELS = {
    "US": {"force": "lbf", "length": "ft", "area": "ft²", "speed": "ft/s",
           "pressure": "lbf/ft²", "density": "slug/ft³", "mass": "slug", "time": "s"},
    "SI": {"force": "N", "length": "m", "area": "m²", "speed": "m/s",
           "pressure": "Pa", "density": "kg/m³", "mass": "kg", "time": "s"},
}


def pint_factors(system):
    """The factors of ``"US"`` or ``"SI"`` as pint derives them from its unit definitions (for the check)."""
    ureg = _registry()
    names = {"US": _US, "SI": _SI}[system]
    return {q: float(ureg.Quantity(1.0, u).to(_SI[q]).magnitude) for q, u in names.items()}


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


UNIT_SYSTEMS = {"US": UnitSystem("US", dict(_US_TO_SI)), "SI": UnitSystem("SI", dict.fromkeys(_SI, 1.0))}


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
