# Helpers shared by the workflow: which campaigns there are, where each one's
# data lives, and the code version that every result depends on. Only helpers
# live in this file (Snakemake's linter wants functions apart from the steps).

import re
import shlex
from pathlib import Path

import yaml

from mbst.io.provenance import source_hash

# --------------------------------------------------------------------------- campaigns

CAMPAIGNS = list(config["campaigns"])
BENCH_CAMPAIGNS = [c for c, entry in config["campaigns"].items() if "bench" in entry]
PATH_CAMPAIGNS = [c for c, entry in config["campaigns"].items() if "path" in entry]
IMPORT_CAMPAIGNS = [c for c, entry in config["campaigns"].items() if "import" in entry]

# Snakemake does not track Python code imported by a command. This hash of
# src/mbst/**/*.py is a param of every job (params.code): edit the package and
# every result made by the old code is out of date (rerun trigger "params").
CODE_VERSION = source_hash()


def alternation(names):
    """Regex matching exactly one of ``names`` (never matching when there are none)."""
    return "|".join(re.escape(n) for n in names) or "(?!x)x"


wildcard_constraints:
    campaign=alternation(CAMPAIGNS),


def campaign_entry(wildcards):
    return config["campaigns"][wildcards.campaign]


def import_control_args(wildcards):
    """``--control GLOB`` where the config names the held-out tests of an import."""
    glob = campaign_entry(wildcards)["import"].get("control")
    return "" if glob is None else f"--control {shlex.quote(glob)}"


def bench_recipe(wildcards):
    return campaign_entry(wildcards)["bench"]


def campaign_dir(wildcards):
    """The campaign folder: the user's ``path:`` or the virtual bench's output."""
    entry = campaign_entry(wildcards)
    if "path" in entry:
        return str(entry["path"])
    if "import" in entry:
        return f"results/{wildcards.campaign}/import/campaign"
    return f"results/{wildcards.campaign}/bench/campaign"


def campaign_inputs(wildcards):
    """Input files of a campaign, so that Snakemake sees a change in any of them.

    A bench campaign is the directory written by the bench step. For a user campaign
    this is its campaign.yaml plus every test file it lists (a folder's own
    timestamp does not change when a file inside it is edited). If the yaml
    cannot be read, only the yaml is listed and ``mbst identify`` reports the
    problem in its own words.
    """
    folder = campaign_dir(wildcards)
    if "path" not in campaign_entry(wildcards):
        return [folder]
    yaml_path = Path(folder) / "campaign.yaml"
    files = [str(yaml_path)]
    try:
        doc = yaml.safe_load(yaml_path.read_text())
        tests = doc.get("tests") or []
        files += [str(Path(folder) / t["file"]) for t in tests if t.get("file")]
    except (OSError, yaml.YAMLError, AttributeError, TypeError):
        pass
    return files


def bench_effect_args(wildcards):
    """``--effect E:C[:k=v]`` per hidden effect; ``--effect none`` for a clean rig.

    (``mbst bench`` without ``--effect`` would plant the demo's backlash.)
    """
    effects = bench_recipe(wildcards)["effects"] or ["none"]
    return " ".join(f"--effect {shlex.quote(str(e))}" for e in effects)


def bench_sensor_arg(wildcards):
    return shlex.quote(",".join(bench_recipe(wildcards)["sensors"]))


def discover_skip_args(wildcards):
    """Flags that switch off the optional evidence families of discovery."""
    flags = []
    if not config["discover"]["sparse_regression"]:
        flags.append("--no-sparse")
    if not config["discover"]["stick_slip"]:
        flags.append("--no-stick-slip")
    if not config["discover"].get("equation_error", True):
        flags.append("--no-equation-error")
    if not config["discover"]["neural_residual"]:
        flags.append("--no-neural")
    return " ".join(flags)


def discover_setting(name):
    """A discover setting: the campaign's own (max_effects only), else the global value."""

    def get(wildcards):
        own = campaign_entry(wildcards).get("discover", {})
        return own.get(name, config["discover"].get(name))

    return get


def aic_margin_arg(wildcards):
    """``--min-aic-drop`` when the config sets one; else discovery derives it per campaign."""
    drop = config["discover"].get("min_aic_drop")
    return "" if drop is None else f"--min-aic-drop {drop}"


def discover_outputs():
    """Discovery results requested by ``rule all`` (none when discovery is off)."""
    if not config["discover"]["enabled"]:
        return []
    return expand("results/{campaign}/discover/{f}", campaign=CAMPAIGNS,
                  f=["discovery.json", "comparison.csv", "discovery.md", "figures"])
