"""The ``mbst`` command: the same code paths the Snakemake rules call.

Every sub-command validates its input before it writes anything and turns
bad input into one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import traceback
from pathlib import Path
from typing import TypeAlias

from mbst import __version__


class UsageError(Exception):
    """Bad input that the user can fix; printed as one line."""


def _cmd_check(args: argparse.Namespace) -> int:
    from mbst.io.campaign import read_campaign, summarize_campaign

    camp = read_campaign(args.campaign)
    camp.model()  # the family's reading of it (assist curves, speeds), as identify reads it
    print(summarize_campaign(camp))
    print(f"ok: campaign '{camp.name}' is valid")
    return 0


# mbst bench's realism flags → BenchRealism fields
_REALISM_FLAGS = ("draw_rig", "known_error", "known_sigma", "draw_sizes", "noise_ar1",
                  "quantise", "torque_lag_s", "offset_drift", "friction_drift", "cogging_nm",
                  "cogging_order", "rack_ratio_variation", "angle_eccentricity_deg",
                  "oversample", "smoothing", "plan_jitter")


def _bench_realism(args: argparse.Namespace):
    from mbst.systems.eps.realism import BenchRealism

    given = {f: getattr(args, f) for f in _REALISM_FLAGS if getattr(args, f) is not None}
    try:
        return BenchRealism.realistic(**given) if args.realistic else BenchRealism(**given)
    except ValueError as exc:  # a flag outside what it means: said before anything runs
        raise UsageError(str(exc)) from None


def _cmd_bench(args: argparse.Namespace) -> int:
    from mbst.systems.eps.bench import (
        DEFAULT_SENSORS,
        DEMO_EFFECTS,
        PLANS,
        BenchRecipe,
        parse_effect,
        plan_from_campaign,
        run_bench,
    )

    effects = list(DEMO_EFFECTS) if args.effect is None else [e for e in args.effect if e != "none"]
    for e in effects:
        try:
            parse_effect(e)
        except (KeyError, ValueError) as exc:
            raise UsageError(str(exc).strip("'\"")) from None
    if not (math.isfinite(args.noise_scale) and args.noise_scale >= 0):
        raise UsageError(f"--noise-scale must be a finite factor ≥ 0, got {args.noise_scale}")
    if not (math.isfinite(args.sample_rate_hz) and args.sample_rate_hz > 0):
        raise UsageError(f"--sample-rate-hz must be a finite rate > 0 Hz, got "
                         f"{args.sample_rate_hz}")
    sensors = tuple(DEFAULT_SENSORS)
    if args.sensors:
        sensors = tuple(s.strip() for s in args.sensors.split(",") if s.strip())
    try:
        plan = plan_from_campaign(args.tests_from) if args.tests_from else PLANS[args.plan]()
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    recipe = BenchRecipe(effects=effects, seed=args.seed, noise_scale=args.noise_scale,
                         sensors=sensors, sample_rate_hz=args.sample_rate_hz, name=args.name,
                         plan=plan, assist_characteristic=args.assist_characteristic,
                         realism=_bench_realism(args))
    try:
        camp = run_bench(args.out, recipe)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not args.quiet:
        hidden = ", ".join(effects) or "none"
        print(f"wrote {camp} (hidden effects: {hidden}); truth in {Path(args.out) / 'truth.json'}")
    return 0


def _check_tau(tau_s: float) -> None:
    """The filter's time constant: finite and ≥ 0 (NaN or inf reached the optimiser's
    bounds as a bare ValueError)."""
    if not (math.isfinite(tau_s) and tau_s >= 0):
        raise UsageError(f"--tau must be a finite time constant ≥ 0 s, got {tau_s}")


def _cmd_preprocess(args: argparse.Namespace) -> int:
    from mbst.io.campaign import read_campaign
    from mbst.report.preprocess import write_preprocessed

    camp = read_campaign(args.campaign)
    _check_tau(args.tau)
    _check_out(args.out, camp.path)
    out = write_preprocessed(camp, args.out, args.tau)
    if not args.quiet:
        print(f"wrote {out}: filtered campaign, noise table, figure (τ = {args.tau * 1e3:g} ms)")
    return 0


def _cmd_identify(args: argparse.Namespace) -> int:
    from mbst.identify.cascade import IdentifySettings
    from mbst.io.campaign import read_campaign
    from mbst.report.identify import run_identify

    camp = read_campaign(args.campaign)
    if args.multistart < 1:
        raise UsageError(f"--multistart must be at least 1, got {args.multistart}")
    _check_tau(args.tau)
    settings = IdentifySettings(tau_s=args.tau, seed=args.seed, multistart=args.multistart,
                                joint_refinement=args.joint, progress=not args.quiet)
    _check_out(args.out, camp.path)
    result = run_identify(camp, args.out, settings)
    if not args.quiet:
        print(result.summary())
    return 0


def _cmd_discover(args: argparse.Namespace) -> int:
    from mbst.discovery.pipeline import DiscoverSettings
    from mbst.identify.cascade import IdentifySettings
    from mbst.io.campaign import read_campaign
    from mbst.report.discovery import run_discover

    camp = read_campaign(args.campaign)
    _check_tau(args.tau)
    if args.multistart < 1:
        raise UsageError(f"--multistart must be at least 1, got {args.multistart}")
    if args.max_effects < 0:
        raise UsageError(f"--max-effects must be ≥ 0, got {args.max_effects}")
    if not 0 < args.min_gain < 1:
        raise UsageError(f"--min-gain must be in (0, 1), got {args.min_gain}")
    if args.min_aic_drop is not None and not (math.isfinite(args.min_aic_drop)
                                              and args.min_aic_drop >= 0):
        raise UsageError(f"--min-aic-drop must be ≥ 0, got {args.min_aic_drop}")
    settings = DiscoverSettings(
        identify=IdentifySettings(tau_s=args.tau, seed=args.seed, multistart=args.multistart,
                                  joint_refinement=args.joint),
        max_effects=args.max_effects, min_relative_gain=args.min_gain,
        min_aic_drop=args.min_aic_drop,
        sparse=not args.no_sparse, neural=not args.no_neural,
        stick_slip=not args.no_stick_slip, equation_error=not args.no_equation_error,
        progress=not args.quiet,
    )
    _check_out(args.out, camp.path)
    result = run_discover(camp, args.out, settings, _read_base_fit(args.base_fit))
    if not args.quiet:
        print(result.summary())
    return 0


def _check_out(out: str, campaign_dir: str | Path | None) -> None:
    """Refuse an output folder the results cannot replace safely, before the work starts."""
    from mbst.io.outputs import output_dir_problem

    problem = output_dir_problem(out, campaign_dir)
    if problem:
        raise UsageError(problem)


def _read_base_fit(path: str | None) -> dict | None:
    if path is None:
        return None
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise UsageError(f"--base-fit {path}: cannot be read as JSON ({exc})") from None


def _cmd_plan(args: argparse.Namespace) -> int:
    from mbst.plan.config import PlanError, load_plan
    from mbst.plan.run import run_plan

    if args.resolve:
        return _cmd_resolve(args)
    if not args.plan:
        raise UsageError("give a planning config (e.g. config/plan.yaml) or --resolve DISCOVERY")
    try:
        cfg = load_plan(args.plan)
    except PlanError as exc:
        raise UsageError(str(exc)) from None
    _check_out(args.out, args.plan)
    proof = False if args.no_proof else (True if args.proof else None)
    result = run_plan(cfg, args.out, progress=not args.quiet, proof=proof)
    if not args.quiet:
        print(result.summary())
        print(f"wrote {args.out}/campaign.yaml, plan.md, tables and figures")
    return 0


def _cmd_resolve(args: argparse.Namespace) -> int:
    from mbst.io.campaign import CampaignError
    from mbst.io.outputs import atomic_output_dir
    from mbst.plan.resolve import ResolveError, resolve, write_resolve

    if args.plan:
        raise UsageError("--resolve designs from the discovery record and its campaign; "
                         "leave out the planning config")
    _check_out(args.out, args.resolve)
    try:
        result = resolve(args.resolve, targets=args.target, campaign_dir=args.campaign,
                         budget_share=args.budget_share, seed=args.seed)
    except (ResolveError, CampaignError) as exc:
        raise UsageError(str(exc)) from None
    with atomic_output_dir(args.out) as tmp:
        write_resolve(tmp, result, str(args.resolve))
    if not args.quiet:
        print(result.summary())
        print(f"wrote {args.out}/campaign.yaml (the campaign with the tests added), resolve.md, "
              "resolve.json, candidates.csv, figures/")
    return 0


def _cmd_import(args: argparse.Namespace) -> int:
    if Path(args.out).exists() and not args.overwrite:
        raise UsageError(f"{args.out} already exists; pass --overwrite to replace it")
    if args.format == "emps":
        from mbst.systems.prismatic.importer import import_emps

        if args.control is not None:
            raise UsageError("--control applies to friction-damper; EMPS has one control run")
        camp = import_emps(args.data_dir, args.out, overwrite=args.overwrite)
        what = ("system prismatic-axis; DATA_EMPS for identification, DATA_EMPS_PULSES as "
                "the held-out control")
    else:
        from mbst.systems.friction_damper.importer import import_friction_damper

        camp = import_friction_damper(args.data_dir, args.out, control=args.control,
                                      overwrite=args.overwrite)
        what = ("system friction-damper; " + (f"tests matching {args.control!r}" if args.control
                else "the recorded histories (earthquake folders)") + " as the held-out controls")
    if not args.quiet:
        print(f"wrote {camp} ({what})")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from mbst.report.summary import write_summary

    try:
        out = write_summary([Path(p) for p in args.inputs], Path(args.out))
    except (FileNotFoundError, ValueError) as exc:
        raise UsageError(str(exc)) from None
    if not args.quiet:
        print(f"wrote {out}")
    return 0


def _add_realism_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("a bench that is not the model (each flag overrides --realistic)")
    g.add_argument("--realistic", action="store_true",
                   help="every reality below at production size: drawn rig, known inertias "
                   "up to 10%% off, drawn effect sizes, AR(1) 0.9 noise, quantised channels, "
                   "3 ms torque-sensor lag, offset warm-up drift, 3x finer integration with "
                   "sharper friction, test inputs up to 15%% off the plan")
    g.add_argument("--draw-rig", action=argparse.BooleanOptionalAction, default=None,
                   help="rig parameters drawn per seed across eps-model.md's typical ranges")
    g.add_argument("--known-error", type=float, metavar="FRACTION",
                   help="known inertias written up to ± this fraction off (geometry 10x less)")
    g.add_argument("--known-sigma", type=float, metavar="FRACTION",
                   help="known values written as priors {value, sigma}, sigma this fraction "
                   "of the value (fitted with a prior term instead of held fixed)")
    g.add_argument("--draw-sizes", action=argparse.BooleanOptionalAction, default=None,
                   help="effect sizes not given on --effect drawn from production to worn")
    g.add_argument("--noise-ar1", type=float, metavar="A",
                   help="noise that wanders: AR(1) coefficient per sample (0 = white)")
    g.add_argument("--quantise", action=argparse.BooleanOptionalAction, default=None,
                   help="channels in the steps of a 13-bit encoder and 12-bit ADCs")
    g.add_argument("--torque-lag-s", type=float, metavar="S",
                   help="first-order lag of the torque sensor's own filter")
    g.add_argument("--offset-drift", type=float, metavar="RMS",
                   help="sensor offsets drift over the campaign by this many noise rms")
    g.add_argument("--friction-drift", type=float, metavar="FRACTION",
                   help="Coulomb levels fall by this fraction as the rig warms up (not a "
                   "catalogue effect)")
    g.add_argument("--cogging-nm", type=float, metavar="NM",
                   help="motor cogging: a torque ripple of this amplitude in N·m at the "
                   "motor, e.g. 0.004 (production motors show a few mN·m; not a catalogue "
                   "effect)")
    g.add_argument("--cogging-order", type=int, metavar="N",
                   help="the cogging's periods per motor revolution (default 18)")
    g.add_argument("--rack-ratio-variation", type=float, metavar="A",
                   help="a variable-ratio rack: travel per pinion radian r·(1 + A·θ²), θ the "
                   "pinion angle in rad (not a catalogue effect)")
    g.add_argument("--angle-eccentricity-deg", type=float, metavar="DEG",
                   help="the steering-angle encoder reads off by this much once per "
                   "revolution (not a catalogue effect)")
    g.add_argument("--oversample", type=int, metavar="K",
                   help="the bench integrates K times finer than it samples")
    g.add_argument("--smoothing", type=float, metavar="F",
                   help="the bench's friction regularisation velocities times F")
    g.add_argument("--plan-jitter", type=float, metavar="FRACTION",
                   help="test amplitudes and frequencies drawn up to ± this fraction off")


# what ``ArgumentParser.add_subparsers`` returns: each sub-command is added to it
_Subcommands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


def _add_command(sub: _Subcommands, name: str, help_: str) -> argparse.ArgumentParser:
    """A sub-command with ``help_`` as its help and description, and its ``--quiet``."""
    p = sub.add_parser(name, help=help_, description=help_)
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing but errors")
    return p


def _add_check(sub: _Subcommands) -> None:
    """``mbst check``: validate a campaign."""
    p = _add_command(sub, "check", "validate a campaign and print what it holds")
    p.add_argument("campaign", help="campaign directory (or its campaign.yaml)")
    p.set_defaults(func=_cmd_check)


def _add_bench(sub: _Subcommands) -> None:
    """``mbst bench``: a campaign from the virtual test bench, with its realism flags."""
    p = _add_command(sub, "bench",
                     "write a campaign from the virtual test bench (truth.json beside it)")
    p.add_argument("--out", required=True, help="output folder: DIR/campaign and DIR/truth.json")
    p.add_argument("--effect", action="append", metavar="EFFECT:COMPONENT[:param=value,...]",
                   help="hidden effect (repeatable); default: worm-gear backlash as in seed 000; "
                   "'none' for a clean rig")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--noise-scale", type=float, default=1.0, help="multiplies the spec's noise")
    p.add_argument("--sensors", help="comma-separated channels (default: seed 000's: angle, "
                   "torque, rack position, tie-rod forces; add motor_angle_rad on request)")
    p.add_argument("--sample-rate-hz", type=float, default=500.0)
    p.add_argument("--name", default="demo-eps", help="campaign name")
    p.add_argument("--plan", default="demo", choices=["demo", "compact", "assist", "compact-assist"],
                   help="test plan: seed 000's demo (default), a short passive one, seed 001's "
                   "powered layout (engine off/on, free/loaded wheels, 0.01/0.5/1 Hz, modes "
                   "normal and city, 60/100/120 km/h) or its short version")
    p.add_argument("--tests-from", metavar="CAMPAIGN", help="run the tests of this "
                   "campaign.yaml instead of --plan (e.g. the one `mbst plan --resolve` writes: "
                   "the campaign's tests in their order, then the added ones)")
    p.add_argument("--assist-characteristic", default="eps", choices=["eps", "hps"],
                   help="power-steer curve of the powered tests: EPS c1·T + c2·sign(T)·|T|^c3 "
                   "or HPS c1·sign(T)·(e^|T| − 1)")
    _add_realism_flags(p)
    p.set_defaults(func=_cmd_bench)


def _add_preprocess(sub: _Subcommands) -> None:
    """``mbst preprocess``: the filtered channels and model input, to inspect."""
    p = _add_command(sub, "preprocess", "write the filtered channels and the model input a fit "
                     "compares (a campaign to inspect), with a sensor-noise table and a "
                     "raw-vs-filtered figure")
    p.add_argument("campaign")
    p.add_argument("--out", required=True,
                   help="output folder: campaign/, noise.csv, preprocess.md, figures/filter.png")
    p.add_argument("--tau", type=float, default=0.005, help="exponential filter τ in s")
    p.set_defaults(func=_cmd_preprocess)


def _add_identify(sub: _Subcommands) -> None:
    """``mbst identify``: the cascaded identification of the physics model."""
    p = _add_command(sub, "identify",
                     "fit the physics model by cascaded identification; correlate on controls")
    p.add_argument("campaign")
    p.add_argument("--out", required=True)
    p.add_argument("--tau", type=float, default=0.005, help="exponential filter τ in s")
    p.add_argument("--seed", type=int, default=0, help="seed of the multi-start")
    p.add_argument("--multistart", type=int, default=2,
                   help="optimiser starts per cascade stage (default 2)")
    p.add_argument("--joint", action="store_true",
                   help="after the cascade, refit everything it found on all identification "
                        "tests together (slower; tells confounded terms apart, e.g. a small "
                        "active damping from the column's viscous friction)")
    p.set_defaults(func=_cmd_identify)


def _add_discover(sub: _Subcommands) -> None:
    """``mbst discover``: find, name and add what the base model lacks."""
    p = _add_command(sub, "discover", "find what the base model lacks, name it, extend the "
                     "model and compare model families on the control tests")
    p.add_argument("campaign")
    p.add_argument("--out", required=True)
    p.add_argument("--tau", type=float, default=0.005, help="exponential filter τ in s")
    p.add_argument("--seed", type=int, default=0, help="seed of multi-starts and training")
    p.add_argument("--joint", action="store_true",
                   help="the base model's cascade ends with a joint refit, as `identify --joint`")
    p.add_argument("--multistart", type=int, default=2, help="starts per cascade stage")
    p.add_argument("--max-effects", type=int, default=4,
                   help="most effects to add (default 4); rounds stop earlier when the best "
                   "candidate left does not clear the margins")
    p.add_argument("--min-gain", type=float, default=0.10,
                   help="share of a stage's residual cost an effect must remove (default 0.10)")
    p.add_argument("--min-aic-drop", type=float, default=None,
                   help="ΔAIC an effect must reach, as −value (default: from the campaign, "
                   "the likelihood-ratio test with its effective samples at a 1 %% "
                   "false-alarm rate over the catalogue)")
    p.add_argument("--base-fit", metavar="BASE_FIT_JSON", default=None,
                   help="start from the base cascade `mbst identify` wrote (its "
                   "base_fit.json) instead of fitting it again; used only where it was made "
                   "from this campaign's data with these settings by this code")
    _add_discover_skips(p)
    p.set_defaults(func=_cmd_discover)


def _add_discover_skips(p: argparse.ArgumentParser) -> None:
    """``mbst discover``'s ``--no-…`` flags: the evidence rounds it can leave out."""
    p.add_argument("--no-sparse", action="store_true", help="skip the sparse regression")
    p.add_argument("--no-neural", action="store_true", help="skip the neural residual")
    p.add_argument("--no-stick-slip", action="store_true",
                   help="skip the phase-free stick-slip test for Stribeck friction")
    p.add_argument("--no-equation-error", action="store_true",
                   help="skip the inverse-model (equation-error) round of rigs that define one "
                        "(the prismatic axis: on EMPS it names the drive lag the output-error "
                        "rounds cannot tell from the real-data misfit)")


def _add_plan(sub: _Subcommands) -> None:
    """``mbst plan``: plan a campaign, or the tests that resolve a discovery."""
    p = _add_command(sub, "plan", "plan a campaign before running it: sensors, cut-outs and "
                     "inputs that identify every unknown at the lowest cost (seed 000 "
                     "'simulation for testing')")
    p.add_argument("plan", nargs="?", help="planning config (mbst-plan/1), e.g. "
                   "config/plan.yaml (not with --resolve)")
    p.add_argument("--out", required=True, help="output folder: campaign.yaml skeleton, "
                   "plan.md, ranking tables, figures")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--proof", action="store_true",
                   help="run the planned-vs-naive bench proof (default: the config's proof.enabled)")
    g.add_argument("--no-proof", action="store_true", help="skip the bench proof")
    _add_resolve_flags(p)
    p.set_defaults(func=_cmd_plan)


def _add_resolve_flags(p: argparse.ArgumentParser) -> None:
    """``mbst plan``'s group for the next tests when discovery could not decide."""
    r = p.add_argument_group("the next tests when discovery could not decide (docs/loop.md)")
    r.add_argument("--resolve", metavar="DISCOVERY", help="discovery.json (or its folder): "
                   "design the tests that decide what it left open — the pairs its resolution "
                   "step marked below resolution, and any --target")
    r.add_argument("--target", action="append", default=[],
                   metavar="EFFECT:COMPONENT[:param=value,...]", help="a pair and size to "
                   "decide as well (repeatable), e.g. backlash:worm_gear:width_rad=0.005")
    r.add_argument("--campaign", help="the campaign discovery ran on (default: the folder "
                   "discovery.json names)")
    r.add_argument("--budget-share", type=float, default=0.5, metavar="FRACTION",
                   help="most test time to add, as a share of the campaign's identification "
                   "test time (default 0.5)")
    r.add_argument("--seed", type=int, default=0, help="noise of the predicted tests")


def _add_import(sub: _Subcommands) -> None:
    """``mbst import``: a public benchmark's files as a campaign."""
    p = _add_command(sub, "import", "convert a public benchmark's files into a campaign")
    p.add_argument("format", choices=["emps", "friction-damper"],
                   help="emps: the EMPS prismatic-axis benchmark; friction-damper: the banded "
                   "rotary friction damper data set")
    p.add_argument("data_dir", help="emps: folder with DATA_EMPS.mat and DATA_EMPS_PULSES.mat; "
                   "friction-damper: folder with characterization/, earthquake/, published/")
    p.add_argument("--control", default=None, metavar="GLOB",
                   help="friction-damper: file names (glob, e.g. '1Hz*') of the held-out "
                   "control tests (default: the earthquake tests)")
    p.add_argument("--out", required=True, help="campaign folder to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing campaign")
    p.set_defaults(func=_cmd_import)


def _add_report(sub: _Subcommands) -> None:
    """``mbst report``: per-campaign results in one table."""
    p = _add_command(sub, "report",
                     "collect per-campaign results into one table (results/summary.csv)")
    p.add_argument("kind", choices=["summary"], help="what to write")
    p.add_argument("inputs", nargs="+", help="per-campaign result folders (results/<campaign>)")
    p.add_argument("--out", required=True, help="CSV to write")
    p.set_defaults(func=_cmd_report)


# the sub-commands in the order ``mbst --help`` lists them
_SUBCOMMANDS = (_add_check, _add_bench, _add_preprocess, _add_identify, _add_discover,
                _add_plan, _add_import, _add_report)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="mbst",
        description="Model-based system testing: identify a steering rig's physics from its "
        "test logs, find what the model lacks, extend it and measure the gain.",
    )
    ap.add_argument("--version", action="version", version=f"mbst {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in _SUBCOMMANDS:
        add(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    from mbst.io.campaign import CampaignError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (CampaignError, UsageError) as exc:
        print(f"mbst {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mbst {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader went away (`mbst check … | head`): what was asked is already on disk
        # or was only printed; quiet, as a Unix filter ends
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as exc:  # a disk full or a folder that went away: said, not a traceback
        print(f"mbst {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # a fault of mbst's, not of the input: said first, then traced
        print(f"mbst {args.command}: internal error: {type(exc).__name__}: {exc}\n"
              "This is a fault in mbst, not in your data. The traceback below is for a "
              "bug report:", file=sys.stderr)
        traceback.print_exc()
        return 3


if __name__ == "__main__":
    sys.exit(main())
