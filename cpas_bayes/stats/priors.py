"""Prior distributions read from readable TOML files (``priors/<kind>.toml``).

A prior is a frozen distribution of :mod:`cpas_bayes.stats.distributions`
(vectorised ``logpdf``, ``ppf`` and ``sample``, support ``(low, high)``) written
as a TOML inline table ``{ family = ..., <numbers> }``. Prior families (their
numbers and densities are tabled in :mod:`cpas_bayes.stats.distributions`):
``uniform`` (low, high), ``normal`` (mu, sigma), ``truncnormal`` (mu, sigma,
low, high) and ``lognormal`` (median, sigma_log [, low, high]).

A kind file holds one table per stage role, plus ``[parachute]`` for per-canopy
quantities::

    kind = "drogue"
    [parachute]
    cd_o = { family = "truncnormal", mu = 0.6, sigma = 0.12, low = 0.3, high = 1.0 }
    [first]        # the stage that starts at bag strip
    n_p = { family = "lognormal", median = 10.0, sigma_log = 0.5, low = 2, high = 40 }
    [reefed]       # a later reefed stage, after a disreef
    [full_open]    # the last stage

Stage roles: a parachute's first stage is ``first``; its last is ``full_open``;
stages between are ``reefed``. A one-stage parachute uses ``full_open``.
Values that a stage does not have (``eps`` of the full-open stage, which is 1;
``ck``/``tk`` of a finite-mass stage) are not sampled.

``priors/nuisance.toml`` holds the per-test nuisances (load-cell friction
factor, error multipliers). Start times, vehicle weight and vehicle drag area
get normal priors from the bundle's own stated values and sigmas.

A user's ``--priors FILE`` has the same layout; every table it gives replaces
the default entry of the same name (other entries stay).

Every prior file is read through :func:`cpas_bayes.core.inputs.read_toml` and
checked whole before any prior is used: only the tables above (``kind``,
``description``, ``parachute``, the roles, ``nuisance``) and their parameters,
an unknown name refused with the nearest valid one; ``kind`` one of the bundle
format's kinds; every number finite, scales > 0, ``low < high``, a lognormal's
``low ≥ 0``, and bounds that hold a usable share of the distribution; each
prior inside its parameter's physical domain, with a spread neither at rounding
level nor absurdly wide (:data:`DOMAINS`). For a test, :func:`priors_of_test`
also refuses a prior file that changes none of the test's priors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.inputs import check_keys, did_you_mean, inside, nearest, read_toml, shown
from cpas_bayes.data.bundle import KINDS, check_kind
from cpas_bayes.stats.distributions import TABLE_FORMS, LogNormal, Normal, TruncNormal, Uniform

PRIORS_DIR = Path(__file__).parent.parent / "data" / "priors"
ROLES = ("first", "reefed", "full_open")
STAGE_PARAMETERS = ("n_p", "expopen", "ck", "tk", "eps")   # sampled per stage (see the kind files)
PARACHUTE_PARAMETERS = ("cd_o",)
NUISANCE_PARAMETERS = ("load_scale", "noise_acc", "noise_lc", "noise_gnss")   # what the model reads from [nuisance]
PRIOR_FAMILIES = ("uniform", "normal", "truncnormal", "lognormal")   # those PriorSet evaluates in one pass
# The tables of a prior file and the parameters each may hold (None: a string, not a table).
FILE_TABLES = {"kind": None, "description": None, "finite_mass_ck": bool, "parachute": PARACHUTE_PARAMETERS,
               **{role: STAGE_PARAMETERS for role in ROLES}, "nuisance": NUISANCE_PARAMETERS}
MIN_MASS = 1e-6   # share of a truncated prior's parent distribution its bounds must hold


@dataclass(frozen=True)
class Domain:
    """Where a prior-file parameter can physically lie, and the size its values take (its scale)."""

    low: float
    high: float
    text: str     # the interval as a message shows it
    scale: float  # typical magnitude, in the parameter's unit
    unit: str
    reason: str

    @property
    def open_low(self):
        """True when ``low`` itself is outside the domain: its interval, as written, opens with '('."""
        return self.text.startswith("(")


_POSITIVE = (0.0, math.inf, "(0, inf)")
# Each prior-file parameter's physical domain, scale (shipped priors spread 0.1-1x it) and unit, with why.
DOMAINS = {
    "cd_o": Domain(*_POSITIVE, 1.0, "", "a drag coefficient is positive"),
    "n_p": Domain(*_POSITIVE, 10.0, " diameters", "a fill distance is positive"),
    "expopen": Domain(*_POSITIVE, 1.0, "", "an opening exponent ≤ 0 shrinks or jumps the canopy as it fills"),
    "ck": Domain(1.0, math.inf, "[1, inf)", 1.0, "", "C_k·CDS_i is the peak: below 1 a dip, not an over-inflation"),
    "tk": Domain(*_POSITIVE, 1.0, " s", "a ramp-down time is positive"),
    "eps": Domain(0.0, 1.0, "(0, 1]", 1.0, "", "CDS_i/CDS_o: a reefed stage holds part of the full-open drag area"),
    "load_scale": Domain(*_POSITIVE, 1.0, "", "true load / load-cell reading: ≤ 0 flips or erases the load"),
    "noise_acc": Domain(*_POSITIVE, 1.0, "", "it multiplies a 1-sigma, which is positive"),
    "noise_lc": Domain(*_POSITIVE, 1.0, "", "it multiplies a 1-sigma, which is positive"),
    "noise_gnss": Domain(*_POSITIVE, 1.0, "", "it multiplies a 1-sigma, which is positive"),
}
# A prior may put at most this share outside its parameter's domain: a normal 6 sigma from the edge (n_p of
# normal(12, 1) puts 1e-33 below 0). No fit draws that many points, so the stage law never sees such a value.
MAX_OUTSIDE = 1e-9
# Limits of a prior's spread W (half its central 68 % interval, the width find_map jitters its starts by).
# Narrow: W ≥ 1e-4 of max(|median|, scale). Fitted reefing ratios are known to ~1e-3, so such a prior already
# fixes a parameter; narrower ones break the start (measured on the Drogue example): emcee refused the walkers,
# collinear on the bounds, for tk uniform on [0.5, 0.50001] s (W 3.4e-6) and on [0, 1e-9] s, and sigma = 1e-300
# left the MAP search no finite start. Wide: W ≤ 1e3 × scale, on the scale and not the median, so that
# uniform [1e-300, 1e300] (median 5e299) is refused: no canopy parameter is that unknown.
MIN_SPREAD, MAX_SPREAD = 1e-4, 1e3


def prior_from_table(table, file, key):
    """Build a prior (a frozen :class:`~cpas_bayes.stats.distributions.Distribution`) from a TOML inline
    table; refuse with file, key and fix."""
    if not isinstance(table, dict) or "family" not in table:
        raise InputError(file, f"key '{key}'", "a prior must be a table with a 'family'",
                         'write e.g. { family = "normal", mu = 1.0, sigma = 0.1 }')
    family = table["family"]
    if family not in PRIOR_FAMILIES:
        near = nearest(family, PRIOR_FAMILIES)
        raise InputError(file, f"key '{key}.family'", f"unknown family {shown(family)}",
                         (f"did you mean '{near}'? " if near else "") + f"use one of {', '.join(PRIOR_FAMILIES)}")
    cls, required, optional = TABLE_FORMS[family]
    extra = [name for name in table if name not in required + optional + ("family",)]
    if extra:
        near = nearest(extra[0], required + optional)
        raise InputError(file, f"key '{key}.{shown(extra[0], quote=False)}'",
                         f"unexpected numbers {[shown(e, 20, quote=False) for e in extra]} for a {family} prior",
                         (f"did you mean '{near}'? " if near else "") + f"give exactly {', '.join(required)}"
                         + (f" (optional {', '.join(optional)})" if optional else ""))
    values = {}
    for name in required + optional:
        if name not in table:
            if name in required:
                raise InputError(file, f"key '{key}.{name}'", f"missing for a {family} prior", f"add {name} = <number>")
            continue
        v = table[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputError(file, f"key '{key}.{name}'", f"must be a number, got {shown(v)}",
                             f"write {name} = <number>")
        if not math.isfinite(v):
            raise InputError(file, f"key '{key}.{name}'", f"must be a finite number, got {v}",
                             f"give a finite {name}" + ("; leave out high for an unbounded lognormal"
                                                        if family == "lognormal" and name == "high" else ""))
        values[name] = float(v)
    for scale in ("sigma", "sigma_log", "median"):
        if scale in values and values[scale] <= 0:
            raise InputError(file, f"key '{key}.{scale}'", f"must be positive, got {values[scale]}",
                             f"give {scale} > 0")
    if "low" in values and "high" in values and not values["low"] < values["high"]:
        raise InputError(file, f"key '{key}'", f"low ({values['low']}) must be below high ({values['high']})",
                         "swap or correct the bounds")
    if family == "lognormal" and values.get("low", 0.0) < 0:
        raise InputError(file, f"key '{key}.low'", f"a lognormal lives on x > 0, got low = {values['low']}",
                         "give low ≥ 0 or leave it out")
    prior = cls(**values)
    with np.errstate(divide="ignore", invalid="ignore"):   # log 0: no mass at all, refused below
        mass = math.exp(prior.log_mass) if hasattr(prior, "log_mass") else 1.0
    if not mass >= MIN_MASS:
        raise InputError(file, f"key '{key}'", f"the bounds [{prior.low:g}, {prior.high:g}] hold {mass:.2g} of the "
                         f"{family} distribution (less than {MIN_MASS:g}): its centre lies far outside them",
                         "move mu (or median) inside the bounds, or widen them")
    table_name, _, parameter = key.rpartition(".")
    if table_name in FILE_TABLES and parameter in DOMAINS:   # a prior file's, not a fit folder's "priors.<name>"
        _check_physical(prior, family, file, key, DOMAINS[parameter])
    return prior


def _check_physical(prior, family, file, key, domain):
    """Refuse a prior reaching outside its parameter's physical domain, or of an absurd spread."""
    with np.errstate(all="ignore"):   # extreme numbers: a NaN spread is refused below
        below, upto = (float(c) for c in prior.cdf(np.array([domain.low, domain.high])))
        q16, q50, q84 = (float(q) for q in prior.ppf(np.array([0.16, 0.5, 0.84])))
    outside = below + (1.0 - upto)
    if not outside <= MAX_OUTSIDE:
        leaks = ([f"low ≥ {domain.low:g}"] if below > MAX_OUTSIDE / 2 else []) + \
                ([f"high ≤ {domain.high:g}"] if 1.0 - upto > MAX_OUTSIDE / 2 else [])
        share = "all" if outside > 1 - 1e-9 else f"{outside:.2g}"
        fix = (f"a normal has no bounds: use a truncnormal with {' and '.join(leaks)}"
               + (" or a lognormal" if domain.low == 0 and domain.high == math.inf else "")
               if family == "normal" else f"keep it inside {domain.text}: give {' and '.join(leaks)}")
        raise InputError(file, f"key '{key}'", f"{share} of this {family} prior lies outside the physical domain "
                         f"{domain.text} of {key.rpartition('.')[2]} ({domain.reason})", fix)
    spread, size = (q84 - q16) / 2, max(abs(q50), domain.scale)
    if not spread >= MIN_SPREAD * size:
        raise InputError(file, f"key '{key}'", f"too narrow to fit: its central 68 % interval is ±{spread:.2g}"
                         f"{domain.unit}, below {MIN_SPREAD:g} × {size:g}{domain.unit} (the larger of its median "
                         f"and the parameter's scale {domain.scale:g}{domain.unit})",
                         f"widen it (sigma, sigma_log or the bounds) to at least ±{MIN_SPREAD * size:.2g}"
                         f"{domain.unit}")
    if not spread <= MAX_SPREAD * domain.scale:
        raise InputError(file, f"key '{key}'", f"too wide to mean anything: its central 68 % interval is "
                         f"±{spread:.2g}{domain.unit}, over {MAX_SPREAD:g} × the parameter's scale "
                         f"{domain.scale:g}{domain.unit}",
                         f"narrow it (sigma, sigma_log or the bounds) to at most ±{MAX_SPREAD * domain.scale:g}"
                         f"{domain.unit}")
    if (domain.open_low and prior.support[0] == domain.low
            and np.isfinite(prior.logpdf(np.array([domain.low]))[0])):
        # an open edge where the prior's support ends with a density: the MAP search's bounded optimizer reaches
        # it exactly, where the stage law divides by expopen (or t_k, C_D,o); uniform(0, 8) on expopen ended a
        # search in a ZeroDivisionError
        raise InputError(file, f"key '{key}'", f"this {family} prior includes {domain.low:g}, outside the physical "
                         f"domain {domain.text} of {key.rpartition('.')[2]} ({domain.reason})",
                         f"give low > {domain.low:g} (for example the smallest value you would believe)")


def _load_toml(path):
    """A prior file's document, checked whole (tables, parameters, every prior) before any use."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "", "prior file not found", "pass an existing TOML file to --priors")
    doc = read_toml(path, InputError)
    check_keys(doc, tuple(FILE_TABLES), path, "", InputError, what="table")
    for name, parameters in FILE_TABLES.items():
        if name not in doc:
            continue
        value = doc[name]
        if parameters is bool:
            if not isinstance(value, bool):
                raise InputError(path, f"key '{name}'", f"must be true or false, got {shown(value)}",
                                 f"write {name} = true")
            continue
        if parameters is None:
            if not isinstance(value, str):
                raise InputError(path, f"key '{name}'", f"must be a string, got {shown(value)}",
                                 f"write {name} = \"...\"")
            continue
        if not isinstance(value, dict):
            raise InputError(path, f"key '{name}'", f"must be a table, got {shown(value)}",
                             f"write [{name}] with one prior per line, e.g. {parameters[0]} = {{ family = ... }}")
        what = ("stage parameter" if name in ROLES else f"{name} parameter")
        check_keys(value, parameters, path, name, InputError, what=what)
        for parameter, table in value.items():
            prior_from_table(table, path, f"{name}.{parameter}")
    kind = doc.get("kind")
    if kind is not None:   # a kind of the package's, or one the user defines in this file
        check_kind(kind, path, "key 'kind'", InputError)
    return doc


@dataclass(frozen=True)
class KindPriors:
    """Priors of one parachute kind: per role and parameter, plus per-canopy ones."""

    kind: str
    stage: dict        # role -> {parameter -> Prior}
    parachute: dict    # parameter -> Prior
    source: tuple      # files read, in order
    finite_mass_ck: bool = False   # finite-mass stages also over-inflate (C_k, t_k sampled)

    def for_stage(self, role, parameter):
        return self.stage[role][parameter]


@dataclass(frozen=True)
class NuisancePriors:
    """Per-test nuisances: {name -> Prior}."""

    priors: dict
    source: tuple

    def __getitem__(self, name):
        return self.priors[name]


def _merge_kind(doc, file, base=None):
    stage = {r: dict(base.stage[r]) if base else {} for r in ROLES}
    chute = dict(base.parachute) if base else {}
    for role in ROLES:   # the document is checked whole by _load_toml
        for name, table in doc.get(role, {}).items():
            stage[role][name] = prior_from_table(table, file, f"{role}.{name}")
    for name, table in doc.get("parachute", {}).items():
        chute[name] = prior_from_table(table, file, f"parachute.{name}")
    return stage, chute


def _override_files(override):
    """``--priors`` as a tuple of files: None, one path, or several."""
    if override is None:
        return ()
    return (override,) if isinstance(override, (str, Path)) else tuple(override)


def load_kind_priors(kind, override=None, named_in=None):
    """Priors for parachute ``kind``: the package's ``priors/<kind>.toml`` if it ships one, then each file of
    ``override`` (one path or several, later ones win) whose ``kind`` is this one or absent.

    A kind the package does not ship needs a file with ``kind = "<kind>"`` holding every prior (see
    ``priors/template.toml``); without one the refusal names ``named_in`` (file, key), where a test asks
    for the kind, if given.
    """
    files = _override_files(override)
    check_kind(kind, files[-1] if files else PRIORS_DIR, "parachute kind", InputError)   # a name, never a path
    stage, chute, sources, finite_ck = {r: {} for r in ROLES}, {}, [], False
    base = None
    if kind in KINDS:
        path = inside(PRIORS_DIR, f"{kind}.toml")  # a kind is a name, never a way out of the priors folder
        doc = _load_toml(path)
        stage, chute = _merge_kind(doc, path)
        sources.append(str(path))
        finite_ck = bool(doc.get("finite_mass_ck", False))
        base = KindPriors(kind, stage, chute, tuple(sources), finite_ck)
    for file in files:
        odoc = _load_toml(file)
        okind = odoc.get("kind")
        if okind is not None and okind != kind:
            continue  # the file speaks of another kind
        if base is None and okind is None and not any(odoc.get(r) for r in ROLES):
            continue  # a nuisance-only or partial file cannot define a kind of its own
        stage, chute = _merge_kind(odoc, file, base)
        sources.append(str(file))
        finite_ck = bool(odoc.get("finite_mass_ck", finite_ck))
        base = KindPriors(kind, stage, chute, tuple(sources), finite_ck)
    if base is None:
        file, key = named_in or (files[-1] if files else "priors", f"kind '{kind}'")
        raise InputError(file, key,
                         f"no priors for parachute kind {shown(kind)}{did_you_mean(kind, KINDS)}: the package "
                         f"ships priors for {', '.join(KINDS)} only",
                         f'give a prior file with kind = "{kind}" (copy priors/template.toml) through --priors FILE '
                         'or priors = "FILE" in the bundle\'s test.toml')
    missing = [(r, p) for r in ROLES for p in ("n_p", "expopen") if p not in stage[r]]
    missing += [(r, "eps") for r in ("first", "reefed") if "eps" not in stage[r]]
    if "cd_o" not in chute:
        missing.append(("parachute", "cd_o"))
    if finite_ck:
        missing += [(r, p) for r in ROLES for p in ("ck", "tk") if p not in stage[r]]
    if missing:
        r, p = missing[0]
        raise InputError(sources[-1], f"key '{r}.{p}'", f"no prior for this parameter of kind {shown(kind)}",
                         f"add [{r}] {p} = {{...}}")
    return base


def load_test_priors(kinds, override=None, files=(), named_in=None):
    """Every prior a test of parachute ``kinds`` needs: what ``fit``, ``diagnose`` and ``validate`` load before
    any work. ``files`` are the test's own prior files (test.toml ``priors``), ``override`` the command's
    ``--priors`` (it wins); ``named_in`` {kind: (file, key)} where the test names each kind, for messages.
    Returns ({kind: KindPriors}, NuisancePriors)."""
    sources = tuple(files) + _override_files(override)
    named_in = named_in or {}
    return ({kind: load_kind_priors(kind, sources, named_in.get(kind)) for kind in dict.fromkeys(kinds)},
            load_nuisance_priors(sources))


def priors_of_test(test, override=None):
    """:func:`load_test_priors` for a flight test (a ``FlightTest``): its parachutes' kinds and its own
    prior files, a refusal naming the test.toml key of a kind without priors, and one naming a prior file
    of its own that changes no prior of this test (``override``, which may serve many tests, is checked
    against all their kinds at once: :func:`check_override_applies`)."""
    named_in = test.kind_keys()
    kinds = list(named_in)
    loaded = load_test_priors(kinds, override, test.priors_files, named_in)   # each file checked whole first
    for file in test.priors_files:
        _check_applies(file, kinds, "remove it from test.toml's key 'priors'")
    return loaded


def check_override_applies(override, kinds, or_else="leave out --priors"):
    """Refuse an override file (``--priors``, a campaign's ``priors``) that changes no prior of the tests,
    whose parachutes are of ``kinds`` (every test it serves)."""
    for file in _override_files(override):
        _check_applies(file, sorted(set(kinds)), or_else)


def _check_applies(file, kinds, or_else):
    """Refuse a prior file that changes nothing for a test of parachute ``kinds``: a silently ignored file
    would leave the user believing a fit used priors it never saw. Nuisance priors apply to every test; the
    other tables to the file's ``kind`` (every kind without one)."""
    doc = _load_toml(file)
    if doc.get("nuisance"):
        return
    kind = doc.get("kind")
    tables = [t for t in ("parachute",) + ROLES + ("finite_mass_ck",) if doc.get(t) not in (None, {})]
    if tables and (kind is None or kind in kinds):
        return
    fix = (f'give a file with kind = "{kinds[0]}" (or no kind) and the tables it replaces (layout: '
           f'priors/template.toml), or {or_else}')
    if tables:
        raise InputError(file, "key 'kind'", f"the file is for parachute kind {shown(kind)}, and the test's "
                         f"parachutes are of kind {', '.join(map(shown, kinds))}: it changes no prior of this test",
                         fix)
    raise InputError(file, "", "the file sets no prior: it has no [parachute], [first], [reefed], [full_open] or "
                     "[nuisance] table with a prior in it", fix)


def load_nuisance_priors(override=None):
    """Per-test nuisance priors from ``priors/nuisance.toml`` (and each override file's [nuisance] table)."""
    path = PRIORS_DIR / "nuisance.toml"
    doc = _load_toml(path).get("nuisance", {})
    priors = {k: prior_from_table(v, path, f"nuisance.{k}") for k, v in doc.items()}
    sources = [str(path)]
    for file in _override_files(override):
        odoc = _load_toml(file).get("nuisance", {})
        priors.update({k: prior_from_table(v, file, f"nuisance.{k}") for k, v in odoc.items()})
        if odoc:
            sources.append(str(file))
    return NuisancePriors(priors, tuple(sources))


class PriorSet:
    """Independent priors of a parameter vector, evaluated for a batch at once.

    ``logpdf(theta)`` with θ (B, D) returns (B,) in one compiled pass over the
    rows (the sampler's hot path: grouped numpy operations per family cost as
    much as a whole small likelihood). The sum of each prior's own ``logpdf``
    is the reference it is tested against.
    """

    # family codes of the compiled form
    _UNIFORM, _NORMAL, _LOGNORMAL = 0, 1, 2

    def __init__(self, priors):
        self.priors = list(priors)
        for p in self.priors:
            if not isinstance(p, (Uniform, Normal, TruncNormal, LogNormal)):
                raise TypeError(f"no batched form for {type(p).__name__}")
        self.family = np.array([self._UNIFORM if type(p) is Uniform else self._LOGNORMAL if type(p) is LogNormal
                                else self._NORMAL for p in self.priors], dtype=np.int64)
        # normal: (x − mu)/sigma; lognormal: (log x − log median)/sigma_log
        self.loc = np.array([0.0 if f == self._UNIFORM else math.log(p.median) if f == self._LOGNORMAL else p.mu
                             for f, p in zip(self.family, self.priors)])
        self.scale = np.array([1.0 if f == self._UNIFORM else p.sigma_log if f == self._LOGNORMAL else p.sigma
                               for f, p in zip(self.family, self.priors)])
        self.const = np.array([p.log_normaliser() for p in self.priors])
        self.low = np.array([p.support[0] for p in self.priors], dtype=float)
        self.high = np.array([p.support[1] for p in self.priors], dtype=float)

    def logpdf(self, theta):
        theta = np.ascontiguousarray(np.atleast_2d(np.asarray(theta, float)))
        out = np.empty(theta.shape[0])
        _prior_set_kernel(theta, self.family, self.loc, self.scale, self.low, self.high, self.const, out)
        return out


@numba.njit(cache=True)
def _prior_set_kernel(theta, family, loc, scale, low, high, const, out):
    """Σ_j log p_j(θ_bj) per row into ``out``, −inf outside any support (NaN is outside)."""
    B, D = theta.shape
    for b in range(B):
        total = 0.0
        for j in range(D):
            x = theta[b, j]
            if not (x >= low[j] and x <= high[j]):
                total = -np.inf
                break
            if family[j] == 1:
                z = (x - loc[j]) / scale[j]
                total += -0.5 * z * z + const[j]
            elif family[j] == 2:
                log_x = np.log(x) if x > 0.0 else 0.0
                z = (log_x - loc[j]) / scale[j]
                total += -0.5 * z * z - log_x + const[j]
            else:
                total += const[j]
        out[b] = total

