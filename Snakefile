# mbst workflow: virtual bench (demo campaigns) -> preprocessing -> identification ->
# discovery -> summary.
#
#   snakemake --cores 2                   # everything in config/config.yaml
#   snakemake --cores 2 --configfile my.yaml --replace-workflow-config
#   snakemake --report results/report.html
#
# A run that was killed leaves its outputs marked incomplete; the profile in
# profiles/default (used automatically) sets rerun-incomplete so they are redone.

from snakemake.utils import min_version, validate

min_version("9.0")


configfile: "config/config.yaml"


# Stops the run before anything is built, naming a misspelt or unknown key.
validate(config, "workflow/schemas/config.schema.yaml")


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/bench.smk"
include: "workflow/rules/import.smk"
include: "workflow/rules/preprocess.smk"
include: "workflow/rules/identify.smk"
include: "workflow/rules/discover.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/plan.smk"
include: "workflow/rules/resolve.smk"


rule all:
    default_target: True
    input:
        expand("results/{campaign}/preprocess/preprocess.md", campaign=CAMPAIGNS),
        expand("results/{campaign}/identify/params.json", campaign=CAMPAIGNS),
        expand("results/{campaign}/identify/correlation.csv", campaign=CAMPAIGNS),
        expand("results/{campaign}/identify/identify.md", campaign=CAMPAIGNS),
        expand("results/{campaign}/identify/figures", campaign=CAMPAIGNS),
        discover_outputs(),
        "results/summary.csv",
        # campaign planning (workflow/rules/plan.smk), only when `plan: enabled: true`
        ["results/plan/plan.json"] if config.get("plan", {}).get("enabled", False) else [],
        # the next tests that decide what discovery left open (workflow/rules/resolve.smk)
        expand("results/{campaign}/resolve/resolve.json", campaign=CAMPAIGNS)
        if config.get("resolve", {}).get("enabled", False) and config["discover"]["enabled"]
        else [],
