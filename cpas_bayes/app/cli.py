"""The ``cpas-bayes`` command line.

Each command is a thin face over a library function: parse options, call,
print where the outputs are. Bad input ends with one message naming the file,
the place and the fix (exit status 2); an unexpected fault ends with a short
message (exit status 1) and the traceback only when ``CPAS_BAYES_DEBUG=1``.

Every ``--out`` is checked while the command line is parsed (``app.options.out_option``, the rule of
:func:`cpas_bayes.core.ownership.check_output`: new, empty, or written by cpas-bayes); an output that cannot
be written (no permission, disk full, a name too long) ends like bad input, naming the path.
SIGTERM is handled like Ctrl-C: temporary files removed, workers stopped,
exit status 130.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from cpas_bayes import __version__
from cpas_bayes.data.bundle import KINDS, read_bundle, summary
from cpas_bayes.core.errors import InputError
from cpas_bayes.app.campaign_config import CONFIG_EXAMPLE as CAMPAIGN_EXAMPLE
from cpas_bayes.app.cli_runtime import on_interrupt, run_cli
from cpas_bayes.physics.inflation import BELOW_PREVIOUS_RULES, DECAY_SHAPES
from cpas_bayes.inference.coordinates import COORDINATES
from cpas_bayes.inference.fit import PROPOSALS
from cpas_bayes.inference.stopping import ESS_TARGET
from cpas_bayes.app.options import (BATCH, ENSEMBLES, ESS_TARGETS, RUNS, SEED, STEP_CAPS, STOP, WORKERS,
                                    check_fit_folders, check_scheduler, out_option, priors_option, seed_option,
                                    stop_problem, term_names, terms_problem)

CANDIDATE_NAMES = ("added_mass", "friction_drift", "sensor_lag", "canopy_breathing")

def parallel_options(default_workers=2, what="tasks", note=""):
    """``--workers`` and ``--scheduler`` for a command that runs independent tasks."""
    def decorate(fn):
        fn = click.option("--scheduler", default=None, metavar="ADDRESS|local", callback=check_scheduler,
                          help="Run the tasks on Dask: a scheduler address (tcp://HOST:PORT) or 'local' for a "
                               "LocalCluster of --workers processes. Results are identical to the local pool.")(fn)
        return click.option("--workers", type=WORKERS, default=default_workers,
                            show_default=default_workers is not None,
                            help=f"Processes running {what} at once (one BLAS thread each){note}.")(fn)
    return decorate


def _executor(workers, scheduler):
    from cpas_bayes.core.executor import make_executor

    executor = make_executor(workers, scheduler)
    if executor.kind != "serial":
        click.echo(f"running on {executor.describe()}")
    return executor


def _format_summary(s):
    lines = [f"{s['name']}  ({s['phase']}, {s['units']} units)",
             f"  {s['samples']} samples over {s['duration_s']:.2f} s at {s['sample_rate_hz']:.1f} Hz"]
    for p in s["parachutes"]:
        extras = [x for x, on in (("load cell", p["load_cell"]), ("fly-out angle", p["flyout_angle"])) if on]
        stages = ", ".join(f"{st['label']} @ {st['start']:.3f} s" for st in p["stages"])
        lines.append(f"  {p['id']}: {p['kind']}, {p['inflation']} mass, D_o {p['diameter']:g}"
                     f"{'; ' + ', '.join(extras) if extras else ''}")
        lines.append(f"      stages: {stages}")
    lines.append(f"  channels: {', '.join(s['channels'])}")
    if "air_data" in s:
        lines.append(f"  air data: {s['air_data']}")
    lines += [f"  warning: {w}" for w in s.get("warnings", ())]
    return "\n".join(lines)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="cpas-bayes")
def cli():
    """Parachute flight-test reduction, Bayesian inflation reconstruction and Monte Carlo loads."""


def _check_priors(priors, test=None):
    """Load every prior ``test`` needs (its own prior files and the override ``priors``, each checked whole)
    before any work starts; without a test, the override for every package kind."""
    from cpas_bayes.stats.priors import check_override_applies, load_test_priors, priors_of_test

    if test is None:
        load_test_priors(KINDS, priors)
    else:   # and a --priors file that changes none of its priors (it would be silently ignored) refused
        priors_of_test(test, priors)
        check_override_applies(priors, [p.kind for p in test.parachutes])


@cli.command()
@click.argument("bundles", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the summaries as JSON.")
@click.option("--priors", type=click.Path(path_type=Path), default=None,
              help="Also check this prior file (what fit and diagnose take as --priors).")
def validate(bundles, as_json, priors):
    """Check flight-test bundle folders (and a prior file) and summarise them.

    Exit status is non-zero if any bundle or the prior file is refused; every refusal is printed.
    """
    from cpas_bayes.data.reduction import check_reducible

    failures, summaries = 0, []
    if priors is not None:
        try:
            _check_priors(priors)
        except InputError as exc:
            failures += 1
            priors = None   # refused once; the bundles are checked with their own prior files
            click.secho(f"refused: {exc}", fg="red", err=True)
    for path in bundles:
        try:
            test = read_bundle(path)
            _check_priors(priors, test)
            check_reducible(test)   # what every later step needs of the load cells and the record
            summaries.append(summary(test))
        except InputError as exc:
            failures += 1
            click.secho(f"refused: {exc}", fg="red", err=True)
    if as_json:
        click.echo(json.dumps(summaries, indent=2))
    else:
        for s in summaries:
            click.echo(_format_summary(s))
    if failures:
        raise SystemExit(2)


@cli.command()
@out_option("Folder for the demo report.", default=Path("reports/demo"), show_default=True)
def demo(out):
    """Run the main job on the bundled data and write its report."""
    from cpas_bayes.app.demo import run_demo

    run_demo(out, echo=click.echo)   # the campaign's last line names the report


@cli.command("reduce")
@click.argument("bundle", type=click.Path(path_type=Path))
@out_option("Folder for reduced.csv, reduction.json and reduction.png.", inputs="bundle", required=True)
@click.option("--scale", type=click.Choice(["constant", "linear"]), default="constant", show_default=True,
              help="Load-cell friction scale factor: one constant, or a linear trend through the windows.")
@click.option("--window", "windows", multiple=True, metavar="T0:T1",
              help="Steady-state calibration window in seconds (repeat for several); replaces the automatic ones.")
def reduce_command(bundle, out, scale, windows):
    """Reduce a flight test: parachute loads and drag areas with 1-sigma, friction scale factor, peaks."""
    from cpas_bayes.data.reduction import parse_window, reduce_test
    from cpas_bayes.outputs.reduction import write_reduction

    test = read_bundle(bundle)
    _check_priors(None, test)   # a kind the priors know
    chosen = [parse_window(w, test.label) for w in windows] or None
    red = reduce_test(test, scale=scale, windows=chosen)
    paths = write_reduction(red, out)
    u = test.units
    force = u.label("force")
    click.echo(f"reduced {test.name} ({u.name} units, {len(test.parachutes)} parachutes)")
    if red.scale is not None:
        sc = red.scale
        per_window = ", ".join(f"{v:.4f} ± {s:.4f} [{a:.2f}–{b:.2f} s]"
                               for v, s, (a, b) in zip(sc.values, sc.sigma, sc.windows))
        click.echo(f"  friction scale factor by window ({sc.source}): {per_window}")
        click.echo(f"  applied constant scale factor: {sc.factor:.4f} ± {sc.factor_sigma:.4f}" if sc.mode == "constant"
                   else "  applied linear scale factor through the window midpoints")
    for pk in red.peaks:
        acc = pk.accelerometer
        line = (f"  {pk.stage.label}: peak load accelerometer {u.from_si(acc.load, 'force'):,.0f} ± "
                f"{u.from_si(acc.sigma, 'force'):,.0f} {force} at {acc.time:.2f} s")
        if pk.load_cells is not None:
            lc = pk.load_cells
            line += (f"; load cells {u.from_si(lc.load, 'force'):,.0f} ± {u.from_si(lc.sigma, 'force'):,.0f} "
                     f"{force} at {lc.time:.2f} s")
        click.echo(line)
    for share in red.load_share:
        click.echo(f"  {share.stage.label}: mean load share "
                   + ", ".join(f"{pid} {100 * v:.0f}%" for pid, v in share.mean.items()))
    for warning in red.warnings:
        click.secho(f"warning: {warning}", fg="yellow", err=True)
    for path in paths.values():
        click.echo(f"wrote {path}")


def _effect_name(ctx, param, value):
    """--effect: one name of ALL_EFFECTS or two joined by '+', checked here."""
    from cpas_bayes.data.synth_effects import effect_components

    try:
        effect_components(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    return value


@cli.command("synth")
@click.option("--scenario", type=click.Choice(["drogue", "main", "logger-drop", "logger-attitude", "logger-drogue",
                                                "logger-main"]), required=True,
              help="Scenario library entry: two Drogues (infinite mass) or three Mains (finite mass), with q̄ and "
                   "load cells; or a logger test without q̄ (accelerometer and GNSS): one unreefed canopy "
                   "(logger-drop; logger-attitude: three body axes and quaternions of a swinging vehicle), two "
                   "reefed Drogues, three reefed Mains.")
@click.option("--effect", default="none", show_default=True, callback=_effect_name,
              help="Hidden effect to put in the data: none; catalogued: added_mass, friction_drift, sensor_lag, "
                   "canopy_breathing; outside the catalogue: pitot_lag, accelerometer_clipping, riser_ringing, "
                   "load_cell_tare_shift; form variants: added_mass_form, friction_drift_form, sensor_lag_form; or two "
                   "joined by '+' (e.g. sensor_lag+canopy_breathing).")
@click.option("--magnitude", type=float, multiple=True,
              help="Effect size (k_a; friction drop; lag in s; breathing amplitude; see cpas_bayes.data.synth_effects "
                   "for the others). Drawn from the seed if omitted; a pair takes it twice, in the pair's order.")
@click.option("--seed", type=SEED, required=True, help="Seed of the truth, the effect size and the noise.")
@out_option("Bundle folder to write.", required=True)
def synth_command(scenario, effect, magnitude, seed, out):
    """Simulate a synthetic flight test with known truth and write it as a bundle with truth.json."""
    from cpas_bayes.data.synth import magnitude_problem, write_synthetic
    from cpas_bayes.data.synth_effects import is_pair

    if magnitude and effect == "none":
        raise click.BadParameter("a magnitude needs an effect other than 'none'", param_hint="--magnitude")
    if scenario.startswith("logger-"):
        from cpas_bayes.data.synth_logger import write_logger_synthetic
        from cpas_bayes.data.synth_logger_effects import LOGGER_EFFECTS
        if effect not in LOGGER_EFFECTS:
            raise click.BadParameter(f"logger scenarios take the effects {', '.join(LOGGER_EFFECTS)}; "
                                     f"drop --effect {effect} or choose one of those", param_hint="--effect")
        if len(magnitude) > 1:
            raise click.BadParameter(f"one effect takes one --magnitude, got {len(magnitude)}",
                                     param_hint="--magnitude")
        try:
            folder = write_logger_synthetic(scenario, seed, out, effect=effect,
                                            magnitude=magnitude[0] if magnitude else None)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--magnitude") from None
        click.echo(f"wrote {folder} ({scenario}, effect {effect}, seed {seed}) with truth.json")
        return
    if not magnitude:
        magnitude = None
    elif is_pair(effect):
        if len(magnitude) != 2:
            raise click.BadParameter(f"a pair takes --magnitude twice or not at all, got {len(magnitude)}",
                                     param_hint="--magnitude")
    elif len(magnitude) != 1:
        raise click.BadParameter(f"one effect takes one --magnitude, got {len(magnitude)}", param_hint="--magnitude")
    else:
        magnitude = magnitude[0]
    if magnitude is not None and magnitude_problem(effect, magnitude):
        raise click.BadParameter(magnitude_problem(effect, magnitude), param_hint="--magnitude")
    try:
        folder = write_synthetic(scenario, effect, seed, out, magnitude=magnitude)
    except ValueError as exc:  # an impossible effect size, said plainly
        raise click.BadParameter(str(exc), param_hint="--magnitude") from None
    click.echo(f"wrote {folder} ({scenario}, effect {effect}, seed {seed}) with truth.json")


@cli.command("fit")
@click.argument("bundle", type=click.Path(path_type=Path))
@out_option("Folder for the fit's outputs.", inputs="bundle", required=True)
@seed_option("Seed of the MAP starts and the sampler.")
@priors_option()
@click.option("--decay", type=click.Choice(DECAY_SHAPES), default="linear", show_default=True,
              help="Shape of the drag-area decay after the over-inflation peak; cml_linear is NASA CML's linear "
                   "mode (growth stops at t_f, jumps to the peak there, ramps down over t_k).")
@click.option("--below-previous", type=click.Choice(BELOW_PREVIOUS_RULES), default="drop", show_default=True,
              help="A stage whose drag area is below the one held when it starts: drop to its own value, or hold "
                   "the held one (NASA CML).")
@parallel_options(what="ensembles")
@click.option("--ensembles", type=ENSEMBLES, default=4, show_default=True,
              help="Independent emcee ensembles (R-hat).")
@click.option("--stop", type=STOP, default="ess", show_default=True,
              help="When sampling stops: 'ess' when every parameter's bulk and tail ESS reach --ess-target and "
                   "R-hat across ensembles is at most 1.01; 'tau' when each ensemble is longer than 50 "
                   "autocorrelation times.")
@click.option("--ess-target", type=ESS_TARGETS, default=None,
              help=f"With --stop ess: the bulk and tail ESS every parameter needs [default: {ESS_TARGET}].")
@click.option("--max-steps", type=STEP_CAPS, default=20000, show_default=True,
              help="Steps per ensemble at most: a fit that reaches it stops and says NOT converged (a cluster "
                   "without load cells can need hours to mix between pairings).")
@click.option("--proposal", type=click.Choice(PROPOSALS), default="adaptive", show_default=True,
              help="With --stop ess: 'adaptive' mixes in an independence move fitted to each ensemble's draws "
                   "after a warm-up (τ ~15× shorter); 'pooled' the same move fitted to all ensembles' warm-up "
                   "draws (the diagnosis' fits: faster across a slow direction); 'de' differential evolution alone.")
@click.option("--coordinates", type=click.Choice(COORDINATES), default="grown", show_default=True,
              help="Where the walkers move (same posterior): 'grown' drag areas ε·CDS_o, times to peak (drag area "
                   "grown if cut short); 'drag_area', 'peak_time' one of these; 'model' θ as written (README).")
@click.option("--with", "terms", default=None, metavar="TERMS",
              help="Comma-separated terms fitted beside the stage law: a cause 'diagnose' named, or 'discrepancy' "
                   "for a misfit it left unexplained (which then does not pull the weights and air-data terms).")
def fit_command(bundle, out, seed, priors, decay, below_previous, workers, scheduler, ensembles, stop, ess_target,
                max_steps, proposal, coordinates, terms):
    """Posterior of every inflation parameter of one flight test (emcee).

    Writes OUT/posterior.nc (ArviZ DataTree), OUT/summary.json, figures, and
    resumable checkpoints in OUT/checkpoint/ (rerun the same command to resume).
    """
    from cpas_bayes.core.ownership import claim_folder
    from cpas_bayes.data.bundle import read_bundle
    from cpas_bayes.data.reduction import reduce_test
    from cpas_bayes.inference.fit import SamplerOptions, fit_model, prepare_model
    from cpas_bayes.inference.fit_folder import fill_time_table, pairing_note, record_checks, write_fit_files
    from cpas_bayes.inference.predictive_checks import run_checks
    from cpas_bayes.outputs.fit_figures import start_corner_figures, write_fit_figures
    from cpas_bayes.stats.model_terms import make_extension

    if problem := stop_problem(stop, ess_target, ensembles):
        raise click.BadParameter(problem[1], param_hint=problem[0])
    terms = term_names(terms, "--with") if terms is not None else ()
    test = read_bundle(bundle)
    if problem := terms_problem(terms, test):
        raise click.BadParameter(problem, param_hint="--with")
    _check_priors(priors, test)
    options = SamplerOptions(seed=seed, workers=workers, n_ensembles=ensembles, stop=stop,
                             ess_target=ess_target or ESS_TARGET, proposal=proposal, coordinates=coordinates,
                             max_steps=max_steps)
    click.echo(f"fitting {test.name}: {len(test.parachutes)} parachutes, decay {decay}, "
               f"stage below previous: {below_previous}{', with ' + ', '.join(terms) if terms else ''}")
    reduction = reduce_test(test)
    for warning in reduction.warnings:   # before the sampling, which a unit off or a dead channel makes long and wrong
        click.secho(f"warning: {warning}", fg="yellow", err=True)
    model = prepare_model(test, reduction, priors=priors, decay=decay, below_previous=below_previous,
                          extensions=tuple(make_extension(n) for n in terms))
    on_interrupt(f"each ensemble's last complete chunk is in {out / 'checkpoint'}; "
                  "rerun the same command to resume from it")
    out = claim_folder(out)
    with _executor(min(workers, ensembles), scheduler) as executor:
        corners, warnings = [], []   # the corners start on the workers while the DataTree is assembled
        fit = fit_model(model, options, checkpoint_dir=out / "checkpoint", echo=click.echo, executor=executor,
                        on_sampled=lambda s: corners.append(start_corner_figures(model, s, out, executor)))

        def checks():   # run while the workers draw the figures that need none; the files while they draw the rest
            found = run_checks(fit, rng=0)
            warnings.extend(record_checks(fit, found))
            return found

        figures = write_fit_figures(fit, out, checks=checks, executor=executor, started=corners[0],
                                    meanwhile=lambda: write_fit_files(fit, out))
    d = fit.summary["diagnostics"]
    click.echo(f"{'converged' if d['converged'] else 'NOT converged'}: R-hat max {d['rhat_max']:.4f}, "
               f"ESS bulk min {d['ess_bulk_min']:.0f}, tail min {d['ess_tail_min']:.0f}, tau max "
               f"{d['tau_max']:.0f} steps, {max(d['steps'])} steps per ensemble (stop rule {stop}), "
               f"acceptance {d['acceptance']:.2f}")
    click.echo("\n".join(filter(None, (fill_time_table(fit.summary), pairing_note(fit.summary)))))
    for w in warnings:
        click.echo(f"WARNING [{w['code']}] {w['message']}")
    click.echo(f"{len(warnings) or 'no'} fit health warning{'s' if len(warnings) != 1 else ''}; wrote "
               f"{out / 'summary.json'}, {out / 'posterior.nc'} and {len(figures)} figures")


@cli.command("montecarlo")
@click.option("--memo", "memo_path", type=click.Path(path_type=Path), required=True,
              help="memo.toml (or its folder) with the population distributions.")
@click.option("--like", "like", type=click.Path(path_type=Path), required=True,
              help="Bundle whose configuration (parachutes, vehicle, initial state, cutter times) is flown.")
@click.option("--runs", type=RUNS, default=10000, show_default=True,
              help="Monte Carlo runs (at most 10,000,000 and what fits in half the available memory).")
@out_option("Folder for runs.csv, summary.json, peak_loads.png and fill_times.png.", inputs="like", required=True)
@seed_option("Seed of every draw.")
@click.option("--mode", type=click.Choice(["n_p", "n"]), default="n_p", show_default=True,
              help="Disperse n_p and derive n per run (Eq. 18), or disperse n itself (the old way).")
@click.option("--independent", is_flag=True,
              help="Draw every parameter independently from its memo distribution instead of resampling the "
                   "joint population draws.")
@click.option("--compare-np", "compare_np", is_flag=True,
              help="Also run both modes with independent parameters and write np_vs_n.json and "
                   "fill_time_np_vs_n.png (peak fill times outside the tested range).")
@click.option("--batch", type=BATCH, default=None, help="Runs simulated at once (default 1000).")
@parallel_options(default_workers=1, what="batches of runs")
def montecarlo_command(memo_path, like, runs, out, seed, mode, independent, compare_np, batch, workers, scheduler):
    """Monte Carlo peak loads and fill times of a test's cluster with parameters from the model memo."""
    import numpy as np

    from cpas_bayes.population.memo import load_memo
    from cpas_bayes.loads.budget import check_runs
    from cpas_bayes.loads.fill_time import compare_fill_time_dispersion
    from cpas_bayes.loads.montecarlo import ClusterLayout, run_monte_carlo
    from cpas_bayes.outputs.montecarlo import write_fill_time_comparison, write_monte_carlo

    memo = load_memo(memo_path)
    test = read_bundle(like)
    check_runs(ClusterLayout.from_test(test), runs, results=3 if compare_np else 1, table=True,
               source="command line", where=f"option --runs {runs}")
    rng = np.random.default_rng(seed)
    with _executor(workers, scheduler) as executor:
        result = run_monte_carlo(memo, test, runs, rng, mode=mode, joint=not independent, batch=batch,
                                 executor=executor)
        comparison = (compare_fill_time_dispersion(memo, test, runs, rng, batch=batch, executor=executor)
                      if compare_np else None)
    extra = {"seed": seed, "memo_path": str(memo_path), "like_path": str(like)}
    paths = write_monte_carlo(result, out, memo=memo, extra=extra)
    force = test.units.label("force")
    click.echo(f"{runs:,} runs of {test.name} ({mode} dispersed, "
               f"{'independent parameters' if independent else 'joint population draws'}) in "
               f"{result.runtime_s:.1f} s ({result.runs_per_second:,.0f} runs/s, {result.engine} engine)")
    for stage in result.summary()["stages"]:
        q = stage["peak_load"]
        if q:
            click.echo(f"  {stage['stage']}: peak load median {q['q50']:,.0f} {force}, "
                       f"99 % {q['q99']:,.0f} {force}")
    if comparison is not None:
        paths.update({f"np_vs_n {k}": v for k, v in write_fill_time_comparison(comparison, out, extra).items()})
        for g in comparison.groups:
            click.echo(f"  {g.kind} {g.stage}: t_fp outside the tested range {100 * g.fraction_outside('n_p'):.1f} % "
                       f"(n_p dispersed) vs {100 * g.fraction_outside('n'):.1f} % (n dispersed)")
    for path in paths.values():
        click.echo(f"wrote {path}")


@cli.command("compare")
@click.argument("bundle", type=click.Path(path_type=Path))
@click.option("--memo", "memo_path", type=click.Path(path_type=Path), default=None,
              help="memo.toml: compare with the population predictive (Monte Carlo of this configuration).")
@click.option("--fit", "fit_path", type=click.Path(path_type=Path), default=None,
              help="Fit folder of this test: compare with its posterior predictive.")
@out_option("Folder for compare.json and compare.png.", inputs="bundle", required=True)
@click.option("--runs", type=RUNS, default=2000, show_default=True, help="Predicted runs per source.")
@seed_option("Seed of every draw.")
@click.option("--mode", type=click.Choice(["n_p", "n"]), default="n_p", show_default=True,
              help="Fill constant dispersed in the memo Monte Carlo.")
@click.option("--independent", is_flag=True, help="Memo Monte Carlo with independently drawn parameters.")
def compare_command(bundle, memo_path, fit_path, out, runs, seed, mode, independent):
    """Measured peak loads against predicted distributions, with the measurement's sigma."""
    import numpy as np

    from cpas_bayes.loads.budget import check_runs
    from cpas_bayes.loads.compare import compare_loads
    from cpas_bayes.loads.montecarlo import ClusterLayout
    from cpas_bayes.outputs.compare import write_comparison
    from cpas_bayes.population.memo import load_memo
    from cpas_bayes.inference.fit_folder import load_fit

    if memo_path is None and fit_path is None:
        raise click.UsageError("give --memo, --fit or both")
    test = read_bundle(bundle)
    memo = load_memo(memo_path) if memo_path is not None else None
    fit = load_fit(fit_path) if fit_path is not None else None
    check_runs(ClusterLayout.from_test(test), runs, results=(memo is not None) + (fit is not None),
               source="command line", where=f"option --runs {runs}", what="load comparison")
    comparison = compare_loads(test, memo=memo, fit=fit, runs=runs, rng=np.random.default_rng(seed), mode=mode,
                               joint=not independent)
    paths = write_comparison(comparison, out, extra={"seed": seed})
    u = test.units
    for c in comparison.comparisons:
        click.echo(f"  {c.stage_label} {c.channel} vs {c.source}: measured {u.from_si(c.measured, 'force'):,.0f} ± "
                   f"{u.from_si(c.sigma, 'force'):,.0f} {u.label('force')}, percentile {c.percentile:.1f}, "
                   f"P(prediction > measurement) {c.p_exceed:.2f}")
    for path in paths.values():
        click.echo(f"wrote {path}")


@cli.command("pool")
@click.argument("fitdirs", nargs=-1, required=True, type=click.Path(path_type=Path), callback=check_fit_folders)
@out_option("Memo folder: memo.toml, memo_draws.csv, memo.md and figures.", required=True)
@seed_option("Seed of the subsampling, hyper-posterior and population-predictive draws.")
@parallel_options(what="fit-folder loads, kind/stage/parameter selections and figures")
def pool_command(fitdirs, out, seed, workers, scheduler):
    """Pool fitted tests into population dispersions: the model memo.

    Per parachute kind and stage: n_p, n, expopen, ck, tk, eps and cd_o get a
    family chosen by leave-one-test-out predictive density, a hyper-posterior
    and population-predictive draws; n_p and expopen keep their correlation
    when it predicts better. Fit folders are those written by 'cpas-bayes fit'.
    """
    import warnings

    from cpas_bayes.outputs.memo import write_pool
    from cpas_bayes.population.pool import pool_folders
    from cpas_bayes.population.reweighting import PoolWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PoolWarning)
        with _executor(workers, scheduler) as executor:
            result = pool_folders(fitdirs, seed=seed, executor=executor)
            paths = write_pool(result, out, executor=executor)
    for w in caught:
        if issubclass(w.category, PoolWarning):
            click.secho(f"warning: {w.message}", fg="yellow", err=True)
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    click.echo(f"pooled {len(result.tests)} tests ({', '.join(result.tests)}) into {len(result.entries)} entries")
    for (kind, stage), pair in sorted(result.pairs.items()):
        click.echo(f"  {kind} {stage}: rho(n_p, expopen) {pair.rho_median:.2f} "
                   f"[{pair.rho_interval[0]:.2f}, {pair.rho_interval[1]:.2f}], "
                   f"{'kept' if pair.keep else 'not kept'} (delta elpd {pair.elpd_diff:+.2f})")
    click.echo(f"wrote {paths['memo']}, {paths['draws']}, {paths['markdown']} and {len(paths['figures'])} figures")


@cli.command("diagnose")
@click.argument("bundle", type=click.Path(path_type=Path))
@out_option("Folder for diagnosis.json, diagnosis.md, candidates.csv and the figures.", inputs="bundle", required=True)
@seed_option("Seed of every fit of the comparison.")
@priors_option()
@click.option("--candidates", default=",".join(CANDIDATE_NAMES), show_default=True,
              help="Comma-separated extensions to try against the baseline.")
@parallel_options(what="candidate fits (or one fit's ensembles)")
def diagnose_command(bundle, out, seed, priors, candidates, workers, scheduler):
    """Find what the baseline simulation gets wrong in one test and name the cause.

    Fits the baseline and the baseline plus each candidate term, compares them
    by PSIS-LOO and names the physical term that wins clearly (or none); see
    OUT/diagnosis.md.
    """
    from dataclasses import replace

    from cpas_bayes.inference.candidate_fits import DIAGNOSIS_SAMPLER, DiagnoseOptions
    from cpas_bayes.inference.diagnose import diagnose_test
    from cpas_bayes.outputs.diagnosis import write_diagnosis

    names = term_names(candidates, "--candidates")
    test = read_bundle(bundle)
    _check_priors(priors, test)
    options = DiagnoseOptions(seed=seed, candidates=names, priors=priors,
                              sampler=replace(DIAGNOSIS_SAMPLER, workers=workers))
    on_interrupt(f"nothing was written to {out} (a diagnosis writes its files at the end); rerun the command")
    with _executor(workers, scheduler) as executor:
        diagnosis = diagnose_test(test, options, echo=click.echo, executor=executor)
    path = write_diagnosis(diagnosis, out)
    table = diagnosis.versus_baseline.sort_values("elpd_diff", ascending=False)
    for r in table.to_dict("records"):
        click.echo(f"  {r['name']:<40} elpd gain over the baseline {r['elpd_diff']:+9.1f} ± {r['elpd_diff_se']:.1f}")
    for form in diagnosis.model_forms:
        click.echo(f"  model form ({form['comparison']}): {form['in_words']}")
    click.echo(f"verdict: {diagnosis.verdict}; causes: {', '.join(diagnosis.causes) or 'none'}")
    for reason in diagnosis.reasons:
        click.echo(f"  - {reason}")
    for warning in diagnosis.warnings:
        click.echo(f"  ! {warning}")
    click.echo(f"wrote {path}, {out / 'diagnosis.md'} and the figures")


@cli.command("campaign", epilog="A campaign TOML (--config), every key optional:\n\n"
             + "\n\n".join("\b\n" + part for part in CAMPAIGN_EXAMPLE.strip().split("\n\n")))
@click.argument("folder", type=click.Path(path_type=Path))
@out_option("Folder for every step's outputs and the report (index.html, report.md).", inputs="folder", required=True)
@click.option("--config", "config_path", type=click.Path(path_type=Path, exists=True, dir_okay=False), default=None,
              help="Campaign TOML with the options (see below).")
@parallel_options(default_workers=None, what="tests", note="; overrides --config, default 2")
@click.option("--diagnose", "diagnose_mode", type=click.Choice(["screen", "full", "off"]), default=None,
              help="Diagnosis of each test (overrides --config; default screen).")
def campaign_command(folder, out, config_path, workers, scheduler, diagnose_mode):
    """From a folder of flight-test bundles to a model memo, Monte Carlo, load comparisons and a report.

    Validates every bundle in FOLDER, reduces, fits, diagnoses and pools them,
    runs the Monte Carlo of each cluster configuration and the load
    comparisons, and writes OUT/index.html. A rerun skips every step whose
    inputs (bundle bytes, priors, options) have not changed.
    """
    from dataclasses import replace

    from cpas_bayes.app.campaign import run_campaign
    from cpas_bayes.app.campaign_config import CampaignConfig, load_config

    config = load_config(config_path) if config_path else CampaignConfig()
    if workers is not None:
        config = replace(config, workers=workers)
    if diagnose_mode is not None:
        config = replace(config, diagnose=diagnose_mode)
    on_interrupt(f"finished steps are kept in {out} and running fits' checkpoints in {out / '.checkpoints'}; "
                  "rerun the same command to resume")
    with _executor(config.workers, scheduler) as executor:
        result = run_campaign(folder, out, config, echo=click.echo, executor=executor)
    ran = sum(s.status == "ran" for s in result.steps)
    click.echo(f"{len(result.tests)} tests, {ran} steps run, {len(result.steps) - ran} kept, "
               f"{result.seconds:.0f} s; causes: "
               + (", ".join(f"{t} {' + '.join(c)}" for t, c in result.causes.items() if c) or "none"))


@cli.command("import")
@click.argument("map_path", metavar="MAP.toml", type=click.Path(path_type=Path))
@out_option("Bundle folder to write (test.toml, data.csv, import.json).", required=True)
def import_command(map_path, out):
    """Turn drop-test logger CSV files into a flight-test bundle (docs/import.md).

    MAP.toml says which file, column and unit feeds each channel, each
    logger's clock offset ("auto": cross-correlation with the reference
    logger) and the test's metadata. Release and line stretch are found in the
    sensed acceleration; time 0 of the bundle is the release. The bundle is
    read back and checked before it is put in place.
    """
    from cpas_bayes.data.import_map import read_import_map
    from cpas_bayes.data.importer import describe, import_loggers, write_import

    import_map = read_import_map(map_path, out)  # the whole map, and that every file exists, before any reading
    result = import_loggers(import_map, out)
    folder = write_import(result, out)   # a bundle refused on read-back prints only the refusal
    for line in describe(result):
        click.echo(f"  {line}")
    test = result.test
    click.echo(f"wrote {folder}: {test.name}, {len(test.data):,} rows, {test.time[0]:.3f} … {test.time[-1]:.3f} s "
               f"after release at {test.sample_rate:.1f} Hz, channels {', '.join(test.channels)}")


# -- commands added by later capabilities go above this line --


def main(argv=None):
    """Entry point: run the CLI, turning bad input into one clear message (:func:`run_cli`)."""
    return run_cli(cli, argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
