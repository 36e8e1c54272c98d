"""A campaign's options: :class:`CampaignConfig` and its TOML file (``cpas-bayes campaign --config``).

Every key is checked when the file is read — unknown keys refused with the
nearest valid one, numbers against the ranges of :mod:`cpas_bayes.app.options`,
the priors file loaded — so a bad option stops the campaign before any step.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.inputs import did_you_mean, read_toml
from cpas_bayes.inference.coordinates import COORDINATES
from cpas_bayes.inference.fit import PROPOSALS, SamplerOptions
from cpas_bayes.inference.stopping import ESS_TARGET, STOP_RULES
from cpas_bayes.physics.inflation import BELOW_PREVIOUS_RULES, DECAY_SHAPES
from cpas_bayes.stats.model_terms import EXTENSIONS

CONFIG_NAME = "campaign.toml"


@dataclass(frozen=True)
class CampaignConfig:
    """Options of a campaign; a TOML file (``--config``) sets any of them."""

    name: str | None = None               # report title; default the folder name
    seed: int = 0
    priors: str | None = None             # TOML replacing default priors (path relative to the config file)
    decay: str = "linear"                 # post-peak decay shape (inflation.DECAY_SHAPES)
    below_previous: str = "drop"          # a stage not above the held drag area: "drop" or "hold" (NASA CML)
    fit_ensembles: int = 4
    fit_max_steps: int = 20000
    fit_stop: str = "ess"                 # when a fit stops: "ess" (ESS and R-hat targets) or "tau" (tau_factor·τ)
    fit_ess_target: int = ESS_TARGET
    fit_tau_factor: float = 50.0
    fit_check_every: int = 500
    fit_proposal: str = "adaptive"        # ESS rule: "adaptive" (independence move after a warm-up) or "de"
    fit_coordinates: str = "grown"        # where the walkers move (inference.coordinates); "model": θ as written
    workers: int = 2
    diagnose: str = "screen"              # "screen", "full" or "off"
    candidates: tuple = ("added_mass", "friction_drift", "sensor_lag", "canopy_breathing")
    model_forms: bool = True              # composite cluster and the other decay, by ΔELPD, in each diagnosis
    montecarlo_runs: int = 10000
    compare_runs: int = 2000
    pool_draws: int = 10000

    def sampler(self) -> SamplerOptions:
        return SamplerOptions(seed=self.seed, n_ensembles=self.fit_ensembles, max_steps=self.fit_max_steps,
                              stop=self.fit_stop, ess_target=self.fit_ess_target, tau_factor=self.fit_tau_factor,
                              check_every=self.fit_check_every, workers=self.workers, proposal=self.fit_proposal,
                              coordinates=self.fit_coordinates)


# TOML layout: top-level keys and tables mapping onto CampaignConfig fields.
_TOML_KEYS = {
    (): {"name": "name", "seed": "seed", "priors": "priors", "decay": "decay", "below_previous": "below_previous",
         "workers": "workers"},
    ("fit",): {"ensembles": "fit_ensembles", "max_steps": "fit_max_steps", "stop": "fit_stop",
               "ess_target": "fit_ess_target", "tau_factor": "fit_tau_factor", "check_every": "fit_check_every",
               "proposal": "fit_proposal", "coordinates": "fit_coordinates"},
    ("diagnose",): {"mode": "diagnose", "candidates": "candidates", "model_forms": "model_forms"},
    ("montecarlo",): {"runs": "montecarlo_runs"},
    ("compare",): {"runs": "compare_runs"},
    ("pool",): {"draws": "pool_draws"},
}

CONFIG_EXAMPLE = """\
# campaign.toml: every key optional
name = "EDU Drogue and Main campaign"
seed = 0
# priors = "my_priors.toml"   # replaces tables of priors/*.toml
decay = "linear"              # or "exponential" (DCLDYN), "cml_linear" (NASA CML: jump to the peak at t_f)
below_previous = "drop"       # a stage below the held drag area drops to its own; "hold" keeps it (NASA CML)
workers = 2                   # local processes: 1 to max(4, 2 × cores)

[fit]
ensembles = 4                 # 1–16 (2 or more with stop = "ess")
max_steps = 20000             # 100–100,000 steps per ensemble
stop = "ess"                  # converged when every parameter's bulk and tail ESS ≥ ess_target and R-hat ≤ 1.01
ess_target = 1000             # 100–100,000
# stop = "tau"                # or: converged when longer than tau_factor·τ
# tau_factor = 50             # only with stop = "tau"
check_every = 500             # steps between convergence checks and checkpoints (10–10,000)
proposal = "adaptive"         # with stop = "ess": an independence move fitted after a warm-up; "de": DE alone
coordinates = "model"         # walkers move in θ as written; "drag_area": reefed drag areas ε·CDS_o in place of ε

[diagnose]
mode = "screen"               # "screen" (MAP screen, then sample), "full", "off"
candidates = ["added_mass", "friction_drift", "sensor_lag", "canopy_breathing"]   # catalogued terms to try ("correlated_noise" adds the AR(1) alternative, reported only)
model_forms = true            # also compare composite vs individual cluster and the decay shapes (2 more fits)

[montecarlo]
runs = 10000                  # 1–10,000,000, and what fits in half the available memory

[compare]
runs = 2000

[pool]
draws = 10000                 # 100–1,000,000
"""


def _quoted(names):
    """``"a", "b" or "c"``: the valid values of a key, as the messages say them."""
    quoted = [f'"{n}"' for n in names]
    return ", ".join(quoted[:-1]) + " or " + quoted[-1]


def load_config(path) -> CampaignConfig:
    """Read a campaign TOML; refuse unknown keys (naming the nearest valid one) and bad values, naming the
    file, the key and the fix, before any work (limits: :data:`cpas_bayes.app.options.CONFIG_LIMITS`)."""
    from cpas_bayes.app.options import CONFIG_LIMITS, value_problem

    path = Path(path)
    doc = read_toml(path, fix_syntax="fix the syntax; see 'cpas-bayes campaign --help'")
    keys = {(f"{t[0]}.{k}" if t else k): field for t, table in _TOML_KEYS.items() for k, field in table.items()}
    fix_key = "use the keys of the example in 'cpas-bayes campaign --help'"
    values, where = {}, {}
    for key, value in doc.items():
        if (key,) in _TOML_KEYS:
            if not isinstance(value, dict):
                raise InputError(path, f"key '{key}'", f"must be a table ([{key}]), got {value!r:.40}", fix_key)
            items = [(f"{key}.{sub}", v) for sub, v in value.items()]
        else:
            items = [(key, value)]
        for name, v in items:
            if name not in keys:
                raise InputError(path, f"key '{name}'", f"unknown{did_you_mean(name, keys)}",
                                 f"use one of {', '.join(keys)}")
            values[keys[name]], where[keys[name]] = v, f"key '{name}'"
    defaults = CampaignConfig()
    for name, value in values.items():
        problem = None
        if name in CONFIG_LIMITS:
            problem = value_problem(value, *CONFIG_LIMITS[name])
        elif name == "candidates":
            known = [isinstance(v, str) and v in EXTENSIONS for v in value] if isinstance(value, list) else [False]
            if not value or not all(known):
                bad = value[known.index(False)] if isinstance(value, list) and value else None
                problem = (f"{value!r:.80} is not a non-empty list of extensions"
                           + (did_you_mean(bad, EXTENSIONS) if isinstance(bad, str) else ""))
            elif len(set(value)) < len(value):
                problem = "an extension is listed twice"
        elif name == "diagnose" and value not in ("screen", "full", "off"):
            problem = (f"{value!r:.40}{did_you_mean(str(value), ('screen', 'full', 'off'))} is not \"screen\", "
                       "\"full\" or \"off\"")
        elif name == "model_forms" and not isinstance(value, bool):
            problem = f"{value!r:.40} is not true or false"
        elif name == "decay" and value not in DECAY_SHAPES:
            problem = f"{value!r:.40}{did_you_mean(str(value), DECAY_SHAPES)} is not one of {_quoted(DECAY_SHAPES)}"
        elif name == "fit_proposal" and value not in PROPOSALS:
            problem = f"{value!r:.40}{did_you_mean(str(value), PROPOSALS)} is not one of {_quoted(PROPOSALS)}"
        elif name == "fit_coordinates" and value not in COORDINATES:
            problem = f"{value!r:.40}{did_you_mean(str(value), COORDINATES)} is not one of {_quoted(COORDINATES)}"
        elif name == "fit_stop" and value not in STOP_RULES:
            problem = f"{value!r:.40}{did_you_mean(str(value), STOP_RULES)} is not one of {_quoted(STOP_RULES)}"
        elif name == "below_previous" and value not in BELOW_PREVIOUS_RULES:
            problem = (f"{value!r:.40}{did_you_mean(str(value), BELOW_PREVIOUS_RULES)} is not one of "
                       f"{_quoted(BELOW_PREVIOUS_RULES)}")
        elif name in ("name", "priors") and (not isinstance(value, str) or not value.strip()):
            problem = f"{value!r:.40} is not a text"
        if problem:
            raise InputError(path, where[name], problem,
                             "write a value as in the example of 'cpas-bayes campaign --help'")
        if name == "candidates":
            values[name] = tuple(value)
        elif name == "fit_tau_factor":
            values[name] = float(value)
    config = replace(defaults, **values)
    if config.fit_stop == "ess" and config.fit_ensembles < 2:
        raise InputError(path, where.get("fit_ensembles", where.get("fit_stop", "key 'fit.stop'")),
                         f"stop \"ess\" needs 2 or more ensembles (its R-hat compares them), not {config.fit_ensembles}",
                         "set fit.ensembles = 2 or more, or fit.stop = \"tau\"")
    for name, other in (("fit_tau_factor", "tau"), ("fit_ess_target", "ess")):
        if name in values and config.fit_stop != other:
            raise InputError(path, where[name], f"applies only with fit.stop = \"{other}\", and stop is "
                             f"\"{config.fit_stop}\"", f"set fit.stop = \"{other}\" or remove the key")
    if config.fit_check_every > config.fit_max_steps:
        raise InputError(path, where.get("fit_check_every", where.get("fit_max_steps", "key 'fit.max_steps'")),
                         f"check_every {config.fit_check_every} is more than max_steps {config.fit_max_steps}",
                         "make fit.check_every at most fit.max_steps")
    if config.priors:
        priors = (path.parent / config.priors).resolve()
        try:
            read_toml(priors)
        except InputError as exc:
            raise InputError(path, where["priors"], f"{exc.file}: {exc.problem}", exc.fix) from None
        config = replace(config, priors=str(priors))
    return config
