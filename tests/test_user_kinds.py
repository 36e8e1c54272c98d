"""Any parachute (issue 17): a kind of the user's own with its priors file, C_k on finite-mass stages where
the prior allows, and a nominal diameter fitted within its stated sigma."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cpas_bayes.app.cli import main
from cpas_bayes.core.errors import InputError
from cpas_bayes.data.bundle import read_bundle
from cpas_bayes.data.bundle_write import write_bundle
from cpas_bayes.data.reduction import reduce_test
from cpas_bayes.inference.fit import prepare_model
from cpas_bayes.stats.priors import load_test_priors

TEMPLATE = Path(__file__).parent.parent / "priors" / "template.toml"


def run(capsys, *args):
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def rescue_bundle(example_dir, bundle_files):
    """The two-Drogue example with its canopies declared as kind 'rescue' and the template beside it."""
    folder = example_dir("drogue-clean")
    shutil.copy(TEMPLATE, folder / "rescue.toml")
    files = bundle_files(folder)
    for i in (0, 1):
        files.set_key("parachute", i, "kind", value="rescue")
    files.set_key("priors", value="rescue.toml")
    return folder


def test_a_new_kind_with_its_own_priors_file_validates_and_fits(rescue_bundle, capsys):
    from cpas_bayes.inference.candidate_fits import DIAGNOSIS_SAMPLER
    from cpas_bayes.inference.fit import fit_model

    code, out, err = run(capsys, "validate", rescue_bundle)
    assert code == 0, err
    test = read_bundle(rescue_bundle)
    assert test.priors_files == ((rescue_bundle / "rescue.toml").resolve(),)
    model = prepare_model(test, reduce_test(test))
    cd = model.parameters[model.index["D3.cds_o"]].prior
    s_o = np.pi / 4 * test.parachutes[0].diameter ** 2
    assert cd.support[1] == pytest.approx(2.0 * s_o)          # the template's bound, not the Drogue's 1.0
    fit = fit_model(model, replace(DIAGNOSIS_SAMPLER, workers=1, progress=False))
    assert fit.summary["diagnostics"]["rhat_max"] < 1.05
    cds = fit.summary["parachutes"]["D3"]["cds_o"]
    assert 0.3 * s_o < cds["q50"] < 1.0 * s_o                 # a Drogue-like C_D recovered through new priors
    assert fit.summary["parachutes"]["D3"]["kind"] == "rescue"


def test_a_new_kind_without_priors_is_refused_naming_kind_and_fix(rescue_bundle, bundle_files, capsys):
    bundle_files(rescue_bundle).delete_key("priors")
    code, _, err = run(capsys, "validate", rescue_bundle)
    assert code == 2
    assert "no priors for parachute kind 'rescue'" in err and "priors/template.toml" in err
    assert "--priors FILE" in err
    # the refusal points at where the bundle asks for the kind; the reduction refuses the unknown kind alike
    assert f"{rescue_bundle / 'test.toml'}, key 'parachute 'D3'.kind'" in err
    code, _, err = run(capsys, "reduce", rescue_bundle, "--out", rescue_bundle.parent / "reduced")
    assert code == 2 and "no priors for parachute kind 'rescue'" in err
    assert not (rescue_bundle.parent / "reduced").exists()
    # the same file given on the command line instead works
    assert run(capsys, "validate", "--priors", rescue_bundle / "rescue.toml", rescue_bundle)[0] == 0


@pytest.mark.parametrize("value, problem", [
    ("/etc/rescue.toml", "is an absolute path"),
    ("../../rescue.toml", "leads outside the bundle's folder and its parent"),
    ("rescue.txt", "is not a .toml file"),
    ("missing.toml", "not found"),
    (3, "must be a file name or a list of them"),
])
def test_a_bad_priors_key_is_refused_naming_the_key(rescue_bundle, bundle_files, value, problem):
    bundle_files(rescue_bundle).set_key("priors", value=value)
    with pytest.raises(InputError) as exc:
        read_bundle(rescue_bundle)
    assert "key 'priors'" in str(exc.value) and problem in str(exc.value)


def test_a_shared_priors_file_in_the_campaign_folder_is_found_and_copied_on_write(rescue_bundle, bundle_files,
                                                                                   tmp_path):
    shared = rescue_bundle.parent / "shared.toml"
    (rescue_bundle / "rescue.toml").rename(shared)
    bundle_files(rescue_bundle).set_key("priors", value="../shared.toml")
    test = read_bundle(rescue_bundle)
    assert test.priors_files == (shared.resolve(),)
    copy = read_bundle(write_bundle(test, tmp_path / "copy"))
    assert [f.name for f in copy.priors_files] == ["shared.toml"] and copy.priors_files[0].parent == tmp_path / "copy"


def test_the_command_line_priors_win_over_the_bundles(tmp_path):
    own = tmp_path / "own.toml"
    own.write_text(TEMPLATE.read_text())
    cli = tmp_path / "cli.toml"
    cli.write_text('kind = "rescue"\n[parachute]\ncd_o = { family = "uniform", low = 0.5, high = 0.7 }\n')
    kinds, _ = load_test_priors(["rescue"], cli, (own,))
    assert kinds["rescue"].parachute["cd_o"].support == (0.5, 0.7)
    assert kinds["rescue"].stage["first"]["n_p"].support[1] == 60.0     # the rest from the bundle's file
    assert kinds["rescue"].source == (str(own), str(cli))


def test_finite_mass_stages_overinflate_only_where_the_prior_allows(rescue_bundle, bundle_files):
    files = bundle_files(rescue_bundle)
    for i in (0, 1):
        files.set_key("parachute", i, "inflation", value="finite")
    test = read_bundle(rescue_bundle)
    allowed = prepare_model(test, reduce_test(test))
    assert {"D3.s1.ck", "D3.s1.tk", "D6.s2.ck"} <= set(allowed.names)
    text = TEMPLATE.read_text().replace("finite_mass_ck = true", "finite_mass_ck = false")
    (rescue_bundle / "rescue.toml").write_text(text)
    fixed = prepare_model(read_bundle(rescue_bundle), reduce_test(test))
    assert not [n for n in fixed.names if n.endswith((".ck", ".tk"))]
    # with C_k free, an overshoot on a finite-mass stage changes the prediction; C_k = 1 is the old model
    rng = np.random.default_rng(2)
    theta = allowed.sample_prior(rng, 8)
    keep = [allowed.index[n] for n in fixed.names]
    for name in allowed.names:
        if name.endswith(".ck"):
            theta[:, allowed.index[name]] = 1.0
    np.testing.assert_allclose(allowed.predict(theta).acc, fixed.predict(theta[:, keep]).acc, rtol=1e-12)
    (rescue_bundle / "rescue.toml").write_text(text.replace("finite_mass_ck = false", "finite_mass_ck = 3"))
    with pytest.raises(InputError, match="must be true or false"):
        load_test_priors(["rescue"], rescue_bundle / "rescue.toml")


def test_a_stated_diameter_sigma_makes_the_diameter_a_fitted_parameter(example_dir, bundle_files):
    folder = example_dir("drogue-clean")
    bundle_files(folder).set_key("parachute", 0, "diameter_sigma", value=0.5)   # ft, US bundle
    test = read_bundle(folder)
    assert test.parachutes[0].diameter_sigma == pytest.approx(0.5 * 0.3048)
    model = prepare_model(test, reduce_test(test))
    assert "D3.d_o" in model.names and "D6.d_o" not in model.names
    prior = model.parameters[model.index["D3.d_o"]].prior
    assert prior.mu == pytest.approx(test.parachutes[0].diameter)
    # D_o enters only as n_p·D_o: a 10 % larger canopy with 10 % smaller n_p fills the same way ...
    theta = model.sample_prior(np.random.default_rng(4), 16)
    theta[:, model.index["D3.d_o"]] = test.parachutes[0].diameter
    other = theta.copy()
    other[:, model.index["D3.d_o"]] *= 1.1
    for name in ("D3.s1.n_p", "D3.s2.n_p"):
        other[:, model.index[name]] /= 1.1
    np.testing.assert_allclose(model.predict(other).acc, model.predict(theta).acc, rtol=1e-10)
    # ... its n (fill distance in its own diameters) is 1/1.1 of the nominal one's, t_fp unchanged
    a, b = model.derived(other), model.derived(theta)
    np.testing.assert_allclose(a["D3.s1.n"] * 1.1, b["D3.s1.n"], rtol=1e-10)
    np.testing.assert_allclose(a["D3.s1.t_fp"], b["D3.s1.t_fp"], rtol=1e-10)
    # the fused likelihood (the sampler's path) agrees with the numpy pipeline off the nominal diameter
    fused = model.log_likelihood(other)
    ok = np.isfinite(fused)
    np.testing.assert_allclose(fused[ok], model.pointwise_log_likelihood(other[ok]).sum(axis=1), rtol=1e-9)
    bundle_files(folder).set_key("parachute", 0, "diameter_sigma", value=10.0)
    with pytest.raises(InputError, match="more than a quarter of the diameter"):
        read_bundle(folder)


def test_the_monte_carlo_takes_ck_of_finite_mass_stages_only_when_the_memo_has_it(rescue_bundle, bundle_files):
    from cpas_bayes.loads.montecarlo import ClusterLayout, _needed_columns

    bundle_files(rescue_bundle).set_key("parachute", 0, "inflation", value="finite")
    layout = ClusterLayout.from_test(read_bundle(rescue_bundle))
    key = layout.stage_key(0, 0)
    without = {c for c, _, _ in _needed_columns(layout, 0, "n_p")}
    assert f"{key}.ck" not in without                                  # C_k = 1: the seed's finite mass
    with_ck = {c for c, _, _ in _needed_columns(layout, 0, "n_p", [f"{key}.ck", f"{key}.tk"])}
    assert {f"{key}.ck", f"{key}.tk"} <= with_ck


def test_a_kind_named_like_the_memos_own_table_is_refused(rescue_bundle, bundle_files):
    bundle_files(rescue_bundle).set_key("parachute", 0, "kind", value="provenance")
    with pytest.raises(InputError, match="the model memo uses the name"):
        read_bundle(rescue_bundle)


def test_every_catalogued_term_builds_for_a_kind_of_the_users(rescue_bundle):
    from cpas_bayes.stats.model_terms import EXTENSIONS, make_extension

    test = read_bundle(rescue_bundle)
    reduction = reduce_test(test)
    for name in EXTENSIONS:
        model = prepare_model(test, reduction, extensions=(make_extension(name),))
        assert np.isfinite(model.log_prior(model.sample_prior(np.random.default_rng(0), 4))).any(), name
    breathing = prepare_model(test, reduction, extensions=(make_extension("canopy_breathing"),))
    prior = breathing.parameters[breathing.index["breathing_frequency"]].prior
    assert prior.median == pytest.approx(10.0 / test.parachutes[0].diameter)   # 1/D_o scaling: 1.4 Hz at 7 m
