"""Priors: densities against scipy, batched evaluation, TOML files and their refusals."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from cpas_bayes.core.errors import InputError
from cpas_bayes.stats.distributions import Beta, LogNormal, Normal, TruncNormal, Uniform, from_table
from cpas_bayes.stats.priors import (PRIOR_FAMILIES, PRIORS_DIR, PriorSet, load_kind_priors, load_nuisance_priors,
                                     load_test_priors, prior_from_table)
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
