# Identification: fit the base physics model to the identification tests of a
# campaign and correlate it on the held-out control tests.
#
# Atomic outputs: the old results/{campaign}/identify is removed first (also
# any file in it that is not a declared output), mbst writes into
# results/{campaign}/identify.tmp, and that folder is renamed to
# results/{campaign}/identify only after mbst succeeded. A killed or failed
# run therefore leaves either no identify/ folder or a complete one, never a
# half-written one (a stale identify.tmp is removed by the next run). In addition,
# Snakemake marks the outputs of an interrupted job as incomplete;
# `snakemake --rerun-incomplete` (default in profiles/) then redoes that job.
# The benchmark and log files live outside identify/ so the rename cannot
# clobber them.


rule identify:
    input:
        campaign_inputs,
    output:
        params="results/{campaign}/identify/params.json",
        # the cascade as a record: the discover rule starts from it (no second fit)
        base_fit="results/{campaign}/identify/base_fit.json",
        correlation=report(
            "results/{campaign}/identify/correlation.csv",
            caption="../report/correlation.rst",
            category="Identification",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "FIT table"},
        ),
        summary="results/{campaign}/identify/identify.md",
        summary_html=report(
            "results/{campaign}/identify/identify.html",
            caption="../report/identify_md.rst",
            category="Identification",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "summary"},
        ),
        figures=report(
            directory("results/{campaign}/identify/figures"),
            patterns=["{name}.png"],
            caption="../report/figures.rst",
            category="Identification",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "figure: {name}"},
        ),
    log:
        "logs/identify/{campaign}.log",
    benchmark:
        "results/{campaign}/benchmarks/identify.tsv"
    threads: 2
    params:
        campaign_dir=campaign_dir,
        outdir=lambda wildcards, output: os.path.dirname(output.params),
        tmpdir=lambda wildcards, output: f"{os.path.dirname(output.params)}.tmp",
        tau_s=config["preprocess"]["tau_s"],
        seed=config["identify"]["seed"],
        multistart=config["identify"]["multistart"],
        joint="--joint" if config["identify"].get("joint_refinement") else "",
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "rm -rf {params.tmpdir:q} {params.outdir:q}"
        " && OMP_NUM_THREADS={threads} MKL_NUM_THREADS={threads}"
        " OPENBLAS_NUM_THREADS={threads} NUMBA_NUM_THREADS={threads}"
        " mbst identify {params.campaign_dir:q} --out {params.tmpdir:q}"
        " --tau {params.tau_s} --seed {params.seed} --multistart {params.multistart}"
        " {params.joint} > {log:q} 2>&1"
        " && rm -rf {params.outdir:q}"
        " && mv {params.tmpdir:q} {params.outdir:q}"
