# Campaign planning (seed 000, "simulation for testing"): before a campaign, choose the
# sensors, cut-outs and inputs that identify every unknown at the lowest cost, and prove on
# the virtual bench that the plan beats a naive campaign of equal cost.
#
# Optional target: `snakemake --cores 2 plan`, or set `plan: {enabled: true}` in the config
# to make it part of `all`. `mbst plan` writes results/plan/ atomically (a temporary sibling
# folder renamed into place), so a killed run leaves the old folder or none.


rule plan:
    input:
        config.get("plan", {}).get("file", "config/plan.yaml"),
    output:
        campaign="results/plan/campaign.yaml",
        record="results/plan/plan.json",
        summary="results/plan/plan.md",
        summary_html=report(
            "results/plan/plan.html",
            caption="../report/plan_md.rst",
            category="Planning",
            labels={"result": "plan"},
        ),
        figures=report(
            directory("results/plan/figures"),
            patterns=["{name}.png"],
            caption="../report/plan_figures.rst",
            category="Planning",
            labels={"result": "figure: {name}"},
        ),
    log:
        "logs/plan/plan.log",
    benchmark:
        "results/benchmarks/plan.tsv"
    threads: 2
    params:
        outdir=lambda wildcards, output: os.path.dirname(output.record),
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "OMP_NUM_THREADS={threads} MKL_NUM_THREADS={threads}"
        " OPENBLAS_NUM_THREADS={threads} NUMBA_NUM_THREADS={threads}"
        " mbst plan {input:q} --out {params.outdir:q} --quiet > {log:q} 2>&1"
