"""Priors: densities against scipy, batched evaluation, TOML files and their refusals."""

import math
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from cpas_bayes.core.errors import InputError
from cpas_bayes.stats.distributions import Beta, LogNormal, Normal, TruncNormal, Uniform, from_table
from cpas_bayes.stats.priors import (DOMAINS, NUISANCE_PARAMETERS, PARACHUTE_PARAMETERS, PRIOR_FAMILIES, PRIORS_DIR,
                                     STAGE_PARAMETERS, PriorSet, load_kind_priors, load_nuisance_priors,
                                     check_override_applies, load_test_priors, prior_from_table, priors_of_test)
from cpas_bayes.physics.inflation import stage_role

PRIORS = [
    (Uniform(0.1, 0.9), stats.uniform(0.1, 0.8)),
    (Normal(1.0, 0.2), stats.norm(1.0, 0.2)),
    (TruncNormal(1.25, 0.25, 1.0, 2.5), stats.truncnorm(-1.0, 5.0, loc=1.25, scale=0.25)),
    (LogNormal(10.0, 0.5), stats.lognorm(0.5, scale=10.0)),
]


@pytest.mark.parametrize("prior,reference", PRIORS)
def test_logpdf_and_ppf_match_scipy(prior, reference):
    x = reference.ppf(np.linspace(0.01, 0.99, 41))
    np.testing.assert_allclose(prior.logpdf(x), reference.logpdf(x), rtol=1e-10, atol=1e-10)
    u = np.linspace(0.02, 0.98, 17)
    np.testing.assert_allclose(prior.ppf(u), reference.ppf(u), rtol=1e-9)


@pytest.mark.parametrize("dist,reference", PRIORS + [(Beta(2.0, 5.0, 0.1, 0.9), stats.beta(2.0, 5.0, 0.1, 0.8))])
def test_distribution_layer_matches_scipy_and_its_table_round_trips(dist, reference):
    """Every family of cpas_bayes.stats.distributions (the one layer priors, pooling and the memo share):
    cdf, logpdf and ppf against scipy; ``from_table(describe())`` rebuilds the same distribution."""
    x = reference.ppf(np.linspace(0.01, 0.99, 41))
    np.testing.assert_allclose(dist.cdf(x), reference.cdf(x), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(dist.logpdf(x), reference.logpdf(x), rtol=1e-10, atol=1e-10)
    u = np.linspace(0.02, 0.98, 17)
    np.testing.assert_allclose(dist.ppf(u), reference.ppf(u), rtol=1e-9)
    assert from_table(dist.describe()) == dist


def test_truncated_lognormal_cdf_inverts_its_ppf_and_prior_set_refuses_a_beta():
    prior = LogNormal(10.0, 0.5, low=2.0, high=50.0)
    u = np.linspace(0.0, 1.0, 11)
    np.testing.assert_allclose(prior.cdf(prior.ppf(u)), u, atol=1e-12)
    assert prior.cdf(np.array([1.0, 60.0])).tolist() == [0.0, 1.0]
    with pytest.raises(TypeError, match="no batched form"):
        PriorSet([Beta(2.0, 3.0)])


def test_truncated_lognormal_is_normalised_on_its_bounds():
    prior = LogNormal(10.0, 0.5, low=2.0, high=50.0)
    grid = np.linspace(2.0, 50.0, 200001)
    mass = np.trapezoid(np.exp(prior.logpdf(grid)), grid)
    assert mass == pytest.approx(1.0, abs=1e-6)
    assert prior.logpdf(np.array([1.9, 50.1])).tolist() == [-np.inf, -np.inf]
    draws = prior.sample(np.random.default_rng(0), 5000)
    assert draws.min() >= 2.0 and draws.max() <= 50.0


def test_scaled_prior_is_the_density_of_the_scaled_variable():
    cd = TruncNormal(0.6, 0.1, 0.3, 1.0)
    area = 38.6
    cds = cd.scaled(area)
    x = np.linspace(0.35, 0.95, 13)
    # p_cds(a·x) = p_cd(x) / a
    np.testing.assert_allclose(cds.logpdf(area * x), cd.logpdf(x) - math.log(area), rtol=1e-12)


def test_prior_set_equals_sum_of_priors_and_refuses_outside_support():
    priors = [p for p, _ in PRIORS] + [LogNormal(0.5, 0.7, 0.02, 5.0), TruncNormal(5.0, 1.0, 0.0, 20.0)]
    rng = np.random.default_rng(1)
    theta = np.column_stack([p.sample(rng, 50) for p in priors])
    expected = sum(p.logpdf(theta[:, i]) for i, p in enumerate(priors))
    np.testing.assert_allclose(PriorSet(priors).logpdf(theta), expected, rtol=1e-12)
    theta[3, 0] = 0.95   # outside Uniform(0.1, 0.9)
    theta[7, 3] = -1.0   # negative for a lognormal
    out = PriorSet(priors).logpdf(theta)
    assert out[3] == -np.inf and out[7] == -np.inf
    assert np.isfinite(np.delete(out, [3, 7])).all()


@pytest.mark.parametrize("kind", ["drogue", "main", "pilot", "fbcp"])
def test_every_kind_file_loads_with_all_roles(kind):
    kp = load_kind_priors(kind)
    for role in ("first", "reefed", "full_open"):
        assert {"n_p", "expopen", "ck", "tk"} <= set(kp.stage[role])
    assert "eps" in kp.stage["first"] and "eps" in kp.stage["reefed"]
    assert "cd_o" in kp.parachute
    assert (PRIORS_DIR / f"{kind}.toml").is_file()


def test_stage_roles():
    assert [stage_role(k, 3) for k in range(3)] == ["first", "reefed", "full_open"]
    assert [stage_role(k, 2) for k in range(2)] == ["first", "full_open"]
    assert stage_role(0, 1) == "full_open"


def test_override_file_replaces_only_the_tables_it_gives(tmp_path):
    override = tmp_path / "mine.toml"
    override.write_text('kind = "drogue"\n[first]\nn_p = { family = "normal", mu = 12.0, sigma = 1.0 }\n'
                        '[nuisance]\nload_scale = { family = "uniform", low = 1.0, high = 1.3 }\n')
    base, mine = load_kind_priors("drogue"), load_kind_priors("drogue", override)
    assert mine.stage["first"]["n_p"] == Normal(12.0, 1.0)
    assert mine.stage["first"]["expopen"] == base.stage["first"]["expopen"]
    assert mine.stage["full_open"]["n_p"] == base.stage["full_open"]["n_p"]
    assert str(override) in mine.source
    # An override for another kind leaves this kind alone.
    assert load_kind_priors("main", override).stage["first"]["n_p"] == load_kind_priors("main").stage["first"]["n_p"]
    assert load_nuisance_priors(override)["load_scale"] == Uniform(1.0, 1.3)


@pytest.mark.parametrize("table,fragment", [
    ({"family": "gamma", "a": 1.0}, "unknown family"),
    ({"family": "normal", "mu": 1.0}, "sigma"),
    ({"family": "normal", "mu": 1.0, "sigma": -2.0}, "must be positive"),
    ({"family": "uniform", "low": 2.0, "high": 1.0}, "must be below high"),
    ({"family": "normal", "mu": "one", "sigma": 1.0}, "must be a number"),
    ({"family": "lognormal", "median": 1.0, "sigma_log": 0.5, "mode": 2.0}, "unexpected numbers"),
    ({"mu": 1.0}, "family"),
])
def test_bad_prior_tables_are_refused_with_file_key_and_fix(table, fragment):
    with pytest.raises(InputError) as err:
        prior_from_table(table, "priors/mine.toml", "first.n_p")
    message = str(err.value)
    assert message.startswith("priors/mine.toml, key 'first.n_p")
    assert fragment in message and "Fix:" in message


def test_unknown_parameter_in_a_file_is_refused(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('kind = "drogue"\n[first]\nfill_distance = { family = "normal", mu = 1.0, sigma = 1.0 }\n')
    with pytest.raises(InputError, match=r"key 'first.fill_distance'.*unknown stage parameter"):
        load_kind_priors("drogue", bad)
    with pytest.raises(InputError, match="prior file not found"):
        load_kind_priors("drogue", tmp_path / "missing.toml")


# ---------------------------------------------------------------------------
# issue #18: every prior file refused by name before any work

LOGNORMAL = '{ family = "lognormal", median = 10.0, sigma_log = 0.5'
PRIOR_FILE_REFUSALS = [
    # id, file text (bytes if not str), place named, problem named
    ("Latin-1 file", '# Priors de l\'équipe\nkind = "drogue"\n'.encode("latin-1"), "line 1 (byte 14)",
     "not UTF-8 text"),
    ("syntax", 'kind = "drogue\n', "", "not valid TOML"),
    ("400-digit integer", "[first]\nn_p = { family = \"uniform\", low = 1, high = " + "9" * 400 + " }\n",
     "key 'first.n_p.high'", "an integer beyond 64 bits"),
    ("unknown table", '[nuisanse]\nload_scale = { family = "uniform", low = 1.0, high = 1.3 }\n', "key 'nuisanse'",
     "unknown table 'nuisanse'. Fix: did you mean 'nuisance'?"),
    ("unknown nuisance", '[nuisance]\nload_scal = { family = "uniform", low = 1.0, high = 1.3 }\n',
     "key 'nuisance.load_scal'", "unknown nuisance parameter 'load_scal'. Fix: did you mean 'load_scale'?"),
    ("unknown stage parameter", f'[full_open]\nnp = {LOGNORMAL} }}\n', "key 'full_open.np'",
     "unknown stage parameter 'np'. Fix: did you mean 'n_p'?"),
    ("unknown parachute parameter", '[parachute]\ncd = { family = "uniform", low = 0.3, high = 1.0 }\n',
     "key 'parachute.cd'", "did you mean 'cd_o'?"),
    ("kind in capitals", 'kind = "Drogue"\n', "key 'kind'", "unknown kind 'Drogue'. Fix: did you mean 'drogue'?"),
    ("kind not a string", "kind = 3\n", "key 'kind'", "must be a string, got 3"),
    ("role not a table", "first = 3\n", "key 'first'", "must be a table, got 3"),
    ("high = inf", f"[first]\nn_p = {LOGNORMAL}, low = 2.0, high = inf }}\n", "key 'first.n_p.high'",
     "must be a finite number, got inf"),
    ("mu = nan", '[first]\nck = { family = "truncnormal", mu = nan, sigma = 0.2, low = 1.0, high = 2.0 }\n',
     "key 'first.ck.mu'", "must be a finite number, got nan"),
    ("low = -inf", '[first]\neps = { family = "uniform", low = -inf, high = 0.9 }\n', "key 'first.eps.low'",
     "must be a finite number"),
    ("low above high", '[first]\neps = { family = "uniform", low = 0.9, high = 0.1 }\n', "key 'first.eps'",
     "low (0.9) must be below high (0.1)"),
    ("low equal to high", '[first]\neps = { family = "uniform", low = 0.5, high = 0.5 }\n', "key 'first.eps'",
     "must be below high"),
    ("sigma zero", '[first]\nck = { family = "truncnormal", mu = 1.2, sigma = 0.0, low = 1.0, high = 2.0 }\n',
     "key 'first.ck.sigma'", "must be positive, got 0.0"),
    ("sigma negative", '[nuisance]\nload_scale = { family = "normal", mu = 1.1, sigma = -0.1 }\n',
     "key 'nuisance.load_scale.sigma'", "must be positive"),
    ("negative lognormal low", f"[reefed]\nn_p = {LOGNORMAL}, low = -2.0, high = 50.0 }}\n", "key 'reefed.n_p.low'",
     "a lognormal lives on x > 0"),
    ("bounds far from the centre", '[first]\nck = { family = "truncnormal", mu = 100.0, sigma = 0.1, low = 1.0, '
     'high = 2.0 }\n', "key 'first.ck'", "the bounds [1, 2] hold 0 of the truncnormal distribution"),
    ("misspelt number", '[first]\nck = { family = "truncnormal", mu = 1.2, sigm = 0.2, low = 1.0, high = 2.0 }\n',
     "key 'first.ck.sigm'", "did you mean 'sigma'?"),
    ("family in capitals", '[first]\neps = { family = "Uniform", low = 0.1, high = 0.9 }\n',
     "key 'first.eps.family'", "unknown family 'Uniform'. Fix: did you mean 'uniform'?"),
]


@pytest.mark.parametrize("text, place, problem", [c[1:] for c in PRIOR_FILE_REFUSALS],
                         ids=[c[0] for c in PRIOR_FILE_REFUSALS])
def test_prior_file_refusals_name_file_key_and_fix(tmp_path, text, place, problem):
    path = tmp_path / "mine.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    for load in (lambda: load_test_priors(["drogue"], path), lambda: load_nuisance_priors(path),
                 lambda: load_kind_priors("main", path)):   # whichever kind a test has: the whole file is checked
        with pytest.raises(InputError) as info:
            load()
        message = str(info.value)
        assert message.startswith(f"{path}{', ' + place if place else ''}: "), message
        assert problem in message and ". Fix: " in message, message


def test_a_prior_file_with_a_byte_order_mark_loads(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_bytes(b'\xef\xbb\xbfkind = "drogue"\n[first]\nn_p = { family = "normal", mu = 12.0, sigma = 1.0 }\n')
    kinds, _ = load_test_priors(["drogue", "main", "drogue"], path)
    assert list(kinds) == ["drogue", "main"]
    assert kinds["drogue"].stage["first"]["n_p"] == Normal(12.0, 1.0)


numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10, 10),
                    st.sampled_from([0.0, -0.0, 1e-300, 1e300]), st.text(max_size=3), st.booleans())


@st.composite
def prior_tables(draw):
    family = draw(st.sampled_from(PRIOR_FAMILIES + ("Normal", "gamma", 3)))
    names = ["mu", "sigma", "low", "high", "median", "sigma_log", "sigm"]
    table = {name: draw(numbers) for name in draw(st.lists(st.sampled_from(names), unique=True, max_size=5))}
    return {"family": family, **table}


@settings(max_examples=400, deadline=None, derandomize=True, database=None)
@given(table=prior_tables())
def test_a_prior_table_is_refused_by_key_or_is_a_usable_prior(table):
    """Any table: an InputError naming the file and the key, or a prior whose median, density and support
    are finite numbers (the MAP search and the sampler can use it)."""
    try:
        prior = prior_from_table(table, "p.toml", "first.n_p")
    except InputError as exc:
        assert str(exc).startswith("p.toml, key 'first.n_p") and ". Fix: " in str(exc)
        return
    low, high = prior.support
    assert low < high
    median = float(prior.ppf(np.array([0.5]))[0])
    assert math.isfinite(median) and low <= median <= high
    assert math.isfinite(float(prior.logpdf(np.array([median]))[0]))
    assert math.isfinite(PriorSet([prior]).logpdf(np.array([[median]]))[0])


def test_a_campaign_refuses_a_bad_prior_file_before_any_step(tmp_path):
    import shutil

    from cpas_bayes.app.campaign import CampaignConfig, run_campaign
    from cpas_bayes.core.executor import Executor
    from cpas_bayes.data.bundle import example_bundles

    folder = tmp_path / "tests"
    for bundle in example_bundles():
        shutil.copytree(bundle, folder / bundle.name)
    priors = tmp_path / "mine.toml"
    priors.write_text('[nuisance]\nload_scal = { family = "uniform", low = 1.0, high = 1.3 }\n')
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"key 'nuisance.load_scal': unknown nuisance parameter .*'load_scale'"):
        run_campaign(folder, out, CampaignConfig(priors=str(priors)), echo=lambda *a: None, executor=Executor())
    assert not out.exists()


# ---------------------------------------------------------------------------
# physical domains and sane spreads (a hang, an emcee crash and impossible ranges found by fuzzing)

TEMPLATE = Path(__file__).parent.parent / "priors" / "template.toml"
DROGUE_TEXT = (PRIORS_DIR / "drogue.toml").read_text(encoding="utf-8")


def _drogue_with(tmp_path, table, line):
    """A copy of the shipped drogue.toml whose [``table``] has ``line`` in place of its prior of the same name
    (a table the file lacks is added)."""
    name, section, out, done = line.split(" =")[0], None, [], False
    for old in DROGUE_TEXT.splitlines():
        section = old.strip("[]") if old.startswith("[") else section
        hit = section == table and old.startswith(name + " =")
        out.append(line if hit else old)
        done |= hit
    if not done:
        assert f"[{table}]" not in DROGUE_TEXT, f"drogue.toml's [{table}] has no {name}"
        out += [f"[{table}]", line]
    path = tmp_path / "mine.toml"
    path.write_text("\n".join(out) + "\n", encoding="utf-8")
    return path


def test_every_shipped_prior_file_and_the_template_pass_every_check():
    assert set(DOMAINS) == set(STAGE_PARAMETERS + PARACHUTE_PARAMETERS + NUISANCE_PARAMETERS)
    files = sorted(PRIORS_DIR.glob("*.toml")) + [TEMPLATE]
    assert len(files) == 6
    for path in files:
        kind = tomllib.loads(path.read_text(encoding="utf-8")).get("kind", "drogue")
        kinds, nuisance = load_test_priors([kind], path)   # every prior of the file built and checked
        assert kinds[kind].parachute["cd_o"] and nuisance["noise_acc"]


BAD_RANGES = [
    # id, table, line, key named, problem named, fix named
    ("W1 uniform 1e-300..1e300", "parachute", 'cd_o = { family = "uniform", low = 1e-300, high = 1e300 }',
     "parachute.cd_o", "too wide to mean anything: its central 68 % interval is ±3.4e+299", "at most ±1000"),
    ("W1 sigma 1e-300", "first", 'ck = { family = "truncnormal", mu = 1.25, sigma = 1e-300, low = 1.0, high = 2.5 }',
     "first.ck", "too narrow to fit", "widen it (sigma, sigma_log or the bounds) to at least ±0.00013"),
    ("W1 sigma_log 1e-300", "reefed", 'n_p = { family = "lognormal", median = 10.0, sigma_log = 1e-300 }',
     "reefed.n_p", "too narrow to fit", "at least ±0.001 diameters"),
    ("W1 nuisance sigma 1e-300", "nuisance", 'load_scale = { family = "normal", mu = 1.1, sigma = 1e-300 }',
     "nuisance.load_scale", "too narrow to fit", "widen it"),
    ("W1 lognormal sigma_log 30", "first", 'n_p = { family = "lognormal", median = 10.0, sigma_log = 30.0 }',
     "first.n_p", "too wide to mean anything", "at most ±10000 diameters"),
    ("W2 tk within 1e-9 s", "first", 'tk = { family = "uniform", low = 0.0, high = 1e-9 }',
     "first.tk", "too narrow to fit: its central 68 % interval is ±3.4e-10 s", "at least ±0.0001 s"),
    ("W6 eps beyond 0 and 1", "first", 'eps = { family = "uniform", low = -0.5, high = 3.0 }',
     "first.eps", "0.71 of this uniform prior lies outside the physical domain (0, 1] of eps",
     "give low ≥ 0 and high ≤ 1"),
    ("W6 n_p normal", "first", 'n_p = { family = "normal", mu = 1.0, sigma = 50.0 }',
     "first.n_p", "0.49 of this normal prior lies outside the physical domain (0, inf) of n_p",
     "use a truncnormal with low ≥ 0 or a lognormal"),
    ("W6 ck below 1", "reefed", 'ck = { family = "uniform", low = -5.0, high = 0.5 }',
     "reefed.ck", "all of this uniform prior lies outside the physical domain [1, inf) of ck", "give low ≥ 1"),
    ("W6 ck normal", "full_open", 'ck = { family = "normal", mu = 1.25, sigma = 0.25 }',
     "full_open.ck", "0.16 of this normal prior lies outside", "use a truncnormal with low ≥ 1"),
    ("W6 tk negative", "first", 'tk = { family = "uniform", low = -1.0, high = 2.0 }',
     "first.tk", "outside the physical domain (0, inf) of tk", "give low ≥ 0"),
    ("W6 expopen normal", "first", 'expopen = { family = "normal", mu = 0.5, sigma = 1.0 }',
     "first.expopen", "outside the physical domain (0, inf) of expopen", "truncnormal with low ≥ 0"),
    ("W6 cd_o truncated below 0", "parachute", 'cd_o = { family = "truncnormal", mu = 0.6, sigma = 0.3, '
     'low = -1.0, high = 1.0 }', "parachute.cd_o", "outside the physical domain (0, inf) of cd_o", "low ≥ 0"),
    # an open edge inside the prior's support: the MAP search's bounded optimizer reaches it exactly, where the
    # stage law divides by it (uniform(0, 8) on expopen ended the search in a ZeroDivisionError)
    ("W7 expopen from 0", "first", 'expopen = { family = "uniform", low = 0.0, high = 8.0 }',
     "first.expopen", "this uniform prior includes 0, outside the physical domain (0, inf) of expopen", "low > 0"),
    ("W7 tk from 0", "reefed", 'tk = { family = "uniform", low = 0.0, high = 2.0 }',
     "reefed.tk", "this uniform prior includes 0, outside the physical domain (0, inf) of tk", "low > 0"),
    ("W7 eps from 0", "first", 'eps = { family = "uniform", low = 0.0, high = 1.0 }',
     "first.eps", "this uniform prior includes 0, outside the physical domain (0, 1] of eps", "low > 0"),
    ("W7 cd_o truncated at 0", "parachute", 'cd_o = { family = "truncnormal", mu = 0.6, sigma = 0.3, '
     'low = 0.0, high = 1.0 }', "parachute.cd_o", "this truncnormal prior includes 0", "low > 0"),
    ("W6 noise multiplier", "nuisance", 'noise_lc = { family = "uniform", low = -1.0, high = 2.0 }',
     "nuisance.noise_lc", "outside the physical domain (0, inf) of noise_lc", "give low ≥ 0"),
]


@pytest.mark.parametrize("table, line, key, problem, fix", [c[1:] for c in BAD_RANGES], ids=[c[0] for c in BAD_RANGES])
def test_impossible_or_absurd_prior_ranges_are_refused_naming_file_key_and_fix(tmp_path, table, line, key, problem,
                                                                               fix):
    path = _drogue_with(tmp_path, table, line)
    with pytest.raises(InputError) as info:
        load_test_priors(["drogue"], path)
    message = str(info.value)
    assert message.startswith(f"{path}, key '{key}': "), message
    assert problem in message and ". Fix: " in message and fix in message.split(". Fix: ")[1], message


@pytest.mark.parametrize("table, line", [
    ("first", 'n_p = { family = "normal", mu = 12.0, sigma = 1.0 }'),       # 12 sigma above 0: never drawn there
    ("first", 'eps = { family = "uniform", low = 0.01, high = 1.0 }'),      # the domain's own closed edge
    ("full_open", 'ck = { family = "truncnormal", mu = 1.0, sigma = 0.2, low = 1.0, high = 2.0 }'),
    ("first", 'tk = { family = "uniform", low = 0.5, high = 0.501 }'),      # ±3.4e-4 s: narrow, still fits
    ("parachute", 'cd_o = { family = "uniform", low = 0.01, high = 2000.0 }'),  # ±680: wide, under 1000
])
def test_priors_inside_the_domain_and_the_spread_limits_load(tmp_path, table, line):
    path = _drogue_with(tmp_path, table, line)
    kinds, _ = load_test_priors(["drogue"], path)
    name = line.split(" =")[0]
    prior = kinds["drogue"].parachute[name] if table == "parachute" else kinds["drogue"].stage[table][name]
    assert prior == prior_from_table(tomllib.loads(line)[name], path, f"{table}.{name}")


def test_a_fit_folder_prior_is_not_held_to_the_file_limits():
    """Only a prior file's tables are checked against the domains; a fit folder's summary names its priors
    'priors.<parameter>' and is rebuilt as written."""
    narrow = {"family": "uniform", "low": 0.0, "high": 1e-9}
    assert prior_from_table(narrow, "summary.json", "priors.D3.s1.tk") == Uniform(0.0, 1e-9)
    with pytest.raises(InputError, match="too narrow"):
        prior_from_table(narrow, "mine.toml", "first.tk")


def _run(capsys, *args):
    """The command line's exit code and standard error."""
    from cpas_bayes.app.cli import main

    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err


def test_fit_refuses_the_w2_prior_before_any_work(example_dir, tmp_path, capsys):
    bundle, out = example_dir("drogue-clean"), tmp_path / "NEW"
    path = _drogue_with(tmp_path, "first", 'tk = { family = "uniform", low = 0.0, high = 1e-9 }')
    for args in (["validate", bundle, "--priors", path], ["fit", bundle, "--out", out, "--priors", path]):
        code, err = _run(capsys, *args)
        assert code == 2 and f"{path}, key 'first.tk': too narrow" in err, err
    assert not out.exists()


class _CountingModel:
    """A model whose calls are counted; a runaway search fails the test instead of hanging it."""

    def __init__(self, parameters, log_posterior):
        self.parameters, self.log_posterior, self.calls = parameters, log_posterior, 0
        self.test = SimpleNamespace(source=Path("bundles/T1"), label="T1")

    def __call__(self, theta):
        self.calls += 1
        assert self.calls < 10_000, "find_map keeps drawing starts: a hang"
        return self.log_posterior(np.atleast_2d(theta))


def test_find_map_gives_up_drawing_starts_and_names_the_priors_at_fault():
    from types import SimpleNamespace

    from cpas_bayes.inference.start import find_map

    params = [SimpleNamespace(name="D3.cds_o", prior=Normal(0.6, 0.1)),
              SimpleNamespace(name="D3.s1.eps", prior=Uniform(0.1, 0.9))]
    nowhere = _CountingModel(params, lambda theta: np.full(len(theta), -np.inf))
    # bad input, said as a refusal naming the bundle (exit status 2), not as an internal error
    with pytest.raises(InputError, match=r"^bundles/T1: no start with a finite log posterior .*not finite there "
                                         r"for D3\.s1\.eps.* Fix: check the priors"):
        find_map(nowhere, np.random.default_rng(0), starts=6, guesses=[np.array([0.6, 5.0])])
    assert nowhere.calls <= 100 * 6 + 1
    with pytest.raises(InputError, match="every prior is finite there, the likelihood is not"):
        find_map(nowhere, np.random.default_rng(0), starts=6, guesses=[np.array([0.6, 0.5])])
    # finite only within 1e-4 of the guess, where no jittered start lands: the search goes on from the guess
    def spike(theta):
        z = (theta - [0.6, 0.5]) / 1e-5
        return np.where((np.abs(theta - [0.6, 0.5]) < 1e-4).all(axis=1), -0.5 * (z * z).sum(axis=1), -np.inf)

    near = _CountingModel(params, spike)
    x, log_p = find_map(near, np.random.default_rng(0), starts=6, guesses=[np.array([0.6 + 2e-5, 0.5])])
    np.testing.assert_allclose(x, [0.6, 0.5], atol=1e-4)
    assert np.isfinite(log_p)


# ---------------------------------------------------------------------------
# a prior file that changes nothing for the bundle is refused, not silently ignored

def _file(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("text, place, problem", [
    ((PRIORS_DIR / "main.toml").read_text(encoding="utf-8"), "key 'kind'",
     "the file is for parachute kind 'main', and the test's parachutes are of kind 'drogue'"),
    (TEMPLATE.read_text(encoding="utf-8"), "key 'kind'", "for parachute kind 'rescue', and the test's parachutes "
     "are of kind 'drogue'"),
    ("", "", "the file sets no prior"),
    ('kind = "drogue"\ndescription = "nothing yet"\n[first]\n[nuisance]\n', "", "the file sets no prior"),
], ids=["main file", "template", "empty", "empty tables"])
def test_a_prior_file_that_changes_nothing_for_the_bundle_is_refused(example_dir, tmp_path, capsys, text, place,
                                                                     problem):
    from cpas_bayes.data.bundle import read_bundle

    bundle = example_dir("drogue-clean")
    path = _file(tmp_path, "mine.toml", text)
    test = read_bundle(bundle)
    priors_of_test(test, path)     # loads: the file itself is sound
    with pytest.raises(InputError) as info:
        check_override_applies(path, [p.kind for p in test.parachutes])
    message = str(info.value)
    assert message.startswith(f"{path}{', ' + place if place else ''}: "), message
    assert problem in message and 'Fix: give a file with kind = "drogue"' in message
    assert message.endswith("or leave out --priors")
    code, err = _run(capsys, "validate", bundle, "--priors", path)
    assert code == 2 and problem in err


def test_a_bundles_own_prior_file_that_changes_nothing_is_refused(example_dir, bundle_files):
    from cpas_bayes.data.bundle import read_bundle

    bundle = example_dir("drogue-clean")
    _file(bundle, "main.toml", (PRIORS_DIR / "main.toml").read_text(encoding="utf-8"))
    bundle_files(bundle).set_key("priors", value="main.toml")
    with pytest.raises(InputError) as info:
        priors_of_test(read_bundle(bundle))
    assert str(info.value).startswith(f"{(bundle / 'main.toml').resolve()}, key 'kind': the file is for parachute "
                                      "kind 'main'")
    assert str(info.value).endswith("or remove it from test.toml's key 'priors'")


def test_a_prior_file_for_one_kind_of_the_cluster_or_of_nuisances_only_applies(example_dir, bundle_files, tmp_path):
    from cpas_bayes.data.bundle import read_bundle

    bundle = example_dir("drogue-clean")
    drogues = read_bundle(bundle)
    nuisance = _file(tmp_path, "nuisance.toml", '[nuisance]\nnoise_acc = { family = "uniform", low = 0.5, '
                     'high = 3.0 }\n')
    assert priors_of_test(drogues, nuisance)[1]["noise_acc"] == Uniform(0.5, 3.0)
    kindless = _file(tmp_path, "any.toml", '[parachute]\ncd_o = { family = "uniform", low = 0.4, high = 0.8 }\n')
    assert priors_of_test(drogues, kindless)[0]["drogue"].parachute["cd_o"] == Uniform(0.4, 0.8)
    bundle_files(bundle).set_key("parachute", 1, "kind", value="main")   # a cluster of two kinds
    mixed = read_bundle(bundle)
    main_file = _file(tmp_path, "main.toml", 'kind = "main"\n[first]\nn_p = { family = "normal", mu = 12.0, '
                      'sigma = 1.0 }\n')
    kinds, _ = priors_of_test(mixed, main_file)
    assert kinds["main"].stage["first"]["n_p"] == Normal(12.0, 1.0)
    assert kinds["drogue"].stage["first"]["n_p"] == load_kind_priors("drogue").stage["first"]["n_p"]
    pilot = _file(tmp_path, "pilot.toml", main_file.read_text().replace('"main"', '"pilot"'))
    with pytest.raises(InputError, match="kind 'pilot', and the test's parachutes are of kind 'drogue', 'main'"):
        check_override_applies(pilot, [p.kind for p in mixed.parachutes])
    # a campaign's file serves every test: one for Mains applies to a campaign of Drogue and Main tests
    check_override_applies(main_file, ["drogue", "drogue", "main"], "remove 'priors' from the campaign's configuration")
    with pytest.raises(InputError, match="or remove 'priors' from the campaign's configuration$"):
        check_override_applies(main_file, ["drogue"], "remove 'priors' from the campaign's configuration")
